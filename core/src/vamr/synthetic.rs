//! Synthetic scenes by ray casting: a room with a few features and robots with the configured
//! outline, seen by TiM-like scanners. Noise-free: for tests and benchmarks of the pipeline (the
//! simulated world with noise lives in `hil-mocks`).

use crate::geometry::{Polygon, PolygonError, cast_ray};
use crate::scan::Scan;
use crate::se2::Se2;

/// A static scene, the robots' outline and the scanner's mount and beam layout.
#[derive(Debug, Clone)]
pub struct Site {
    pub static_parts: Vec<Polygon>,
    pub chassis: Polygon,
    pub mount: Se2,
    /// Beam layout (ranges unused).
    pub beams: Scan,
}

impl Site {
    /// The paper's 10 m × 3.1 m site with a few small features along the walls, 0.40 m × 0.40 m
    /// robots with the LiDAR at (0.175 m, 0, 0°), and `beams` beams over 270° (271: TiM551; 655: the
    /// paper's count; 811: TiM561/571).
    pub fn paper(beams: usize) -> Result<Self, PolygonError> {
        let square = |x0: f64, y0: f64, x1: f64, y1: f64| vec![[x0, y0], [x1, y0], [x1, y1], [x0, y1]];
        let parts = [
            square(-5.0, -1.55, 5.0, 1.55),
            vec![[2.0, 1.55], [2.3, 1.1], [2.6, 1.55]],
            square(-3.0, -1.55, -1.8, -1.35),
            vec![[-1.2, 1.55], [-0.8, 1.25], [-0.4, 1.55]],
        ];
        let step = 270f64.to_radians() / (beams.max(2) - 1) as f64;
        Ok(Site {
            static_parts: parts.into_iter().map(Polygon::new).collect::<Result<_, _>>()?,
            chassis: Polygon::new(square(-0.2, -0.2, 0.2, 0.2))?,
            mount: Se2::from_degrees(0.175, 0.0, 0.0),
            beams: Scan::new(-135f64.to_radians(), step, 0.05, 10.0, vec![f64::NAN; beams]),
        })
    }

    /// Robot `i`'s scan with every robot at `poses`. Its own body is not in its scan plane.
    #[must_use]
    pub fn scan(&self, poses: &[Se2], i: usize) -> Scan {
        let mut scene: Vec<(Se2, &Polygon)> = self.static_parts.iter().map(|p| (Se2::IDENTITY, p)).collect();
        scene.extend(poses.iter().enumerate().filter(|(j, _)| *j != i).map(|(_, p)| (*p, &self.chassis)));
        let Some(pose) = poses.get(i) else { return self.beams.clone() };
        let lidar = *pose * self.mount;
        let ranges = (0..self.beams.len())
            .map(|b| {
                cast_ray(
                    [lidar.x, lidar.y],
                    lidar.theta + self.beams.angle(b),
                    self.beams.range_max_m,
                    &scene,
                )
                .unwrap_or(f64::NAN)
            })
            .collect();
        self.beams.with_ranges(ranges)
    }
}

/// Two robots on a [`Site`] and what each one's scanner sees.
#[derive(Debug, Clone)]
pub struct Pair {
    pub site: Site,
    pub poses: [Se2; 2],
    pub scans: [Scan; 2],
}

impl Pair {
    /// The paper's straight-line layout: side by side, 0.9 m between centres, on [`Site::paper`].
    pub fn straight(beams: usize) -> Result<Self, PolygonError> {
        let site = Site::paper(beams)?;
        let poses = [Se2::new(0.0, 0.45, 0.0), Se2::new(0.0, -0.45, 0.0)];
        let scans = [site.scan(&poses, 0), site.scan(&poses, 1)];
        Ok(Pair { site, poses, scans })
    }

    /// `T_{B_1}^{B_0}`: robot 1 in robot 0's base frame.
    #[must_use]
    pub fn truth(&self) -> Se2 {
        self.poses[0].inverse() * self.poses[1]
    }

    /// Both scans as one synchronised set of packets, without AMCL poses.
    #[must_use]
    pub fn packets(&self) -> Vec<super::pipeline::RobotPacket<'_>> {
        self.scans
            .iter()
            .map(|s| super::pipeline::RobotPacket {
                scan: s,
                times: super::frame::PacketTimes { stamp_s: 0.0, received_s: 0.01 },
                lidar_to_base: self.site.mount,
                chassis: &self.site.chassis,
                weight: 1.0,
                amcl_pose: None,
            })
            .collect()
    }
}
