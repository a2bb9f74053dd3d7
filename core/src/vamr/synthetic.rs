//! Synthetic scenes by ray casting: a room with a few features and robots with the configured
//! outline (a [`Pair`], or a [`Team`] of any size), seen by TiM-like scanners. Noise-free: for tests and benchmarks of the pipeline (the
//! simulated world with noise lives in `hil-mocks`).

use super::frame::PacketTimes;
use super::heading::{AngleGrid, HeadingProblem, TargetScan};
use super::pipeline::{Pipeline, RobotPacket, UpdateError};
use super::preprocess::{Preprocessed, preprocess};
use crate::config::{Configuration, HeadingParams, VamrParams};
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
        let parts = vec![
            rectangle(-5.0, -1.55, 5.0, 1.55),
            vec![[2.0, 1.55], [2.3, 1.1], [2.6, 1.55]],
            rectangle(-3.0, -1.55, -1.8, -1.35),
            vec![[-1.2, 1.55], [-0.8, 1.25], [-0.4, 1.55]],
        ];
        Site::with_parts(beams, parts)
    }

    /// A `width_m` × `height_m` hall centred on the origin, with the paper's robots and scanner. Six
    /// features stand on its walls, none placed symmetrically to another, so that no rotation of
    /// the hall maps it onto itself: the heading search has one answer.
    pub fn hall(beams: usize, width_m: f64, height_m: f64) -> Result<Self, PolygonError> {
        let (a, b) = (width_m / 2.0, height_m / 2.0);
        let (top, bottom, right, left) = (0.4 * a, 0.2 * a, 0.3 * b, -0.4 * b);
        let parts = vec![
            rectangle(-a, -b, a, b),
            // On the top wall: two wedges of different sizes.
            vec![[top - 0.3, b], [top, b - 0.45], [top + 0.3, b]],
            vec![[-0.25 * a - 0.4, b], [-0.25 * a, b - 0.3], [-0.25 * a + 0.4, b]],
            // On the bottom wall: a low box and a wedge.
            rectangle(-0.6 * a, -b, -0.6 * a + 1.2, -b + 0.2),
            vec![[bottom + 0.3, -b], [bottom, -b + 0.4], [bottom - 0.3, -b]],
            // A box on the right wall, a wedge on the left one.
            rectangle(a - 0.3, right - 0.4, a, right + 0.4),
            vec![[-a, left - 0.35], [-a + 0.4, left], [-a, left + 0.35]],
        ];
        Site::with_parts(beams, parts)
    }

    /// `parts` with 0.40 m × 0.40 m robots, the LiDAR at (0.175 m, 0, 0°) and `beams` beams over
    /// 270° out to 10 m.
    fn with_parts(beams: usize, parts: Vec<Vec<[f64; 2]>>) -> Result<Self, PolygonError> {
        let step = 270f64.to_radians() / (beams.max(2) - 1) as f64;
        Ok(Site {
            static_parts: parts.into_iter().map(Polygon::new).collect::<Result<_, _>>()?,
            chassis: Polygon::new(rectangle(-0.2, -0.2, 0.2, 0.2))?,
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
    pub fn packets(&self) -> Vec<RobotPacket<'_>> {
        packets(&self.site, &self.scans)
    }
}

/// The stages of the pipeline prepared on a [`Pair::straight`] scene, for timing them one by one:
/// both scans preprocessed, robot 0's as the heading search's target (with its surface), and the
/// full and the refined angle grids (the refined one around the true heading). The criterion
/// benchmark of amr-core and `amr bench vamr` both time this scene.
#[derive(Debug, Clone)]
pub struct PairStages {
    pub pair: Pair,
    /// Robot 0's and robot 1's scans, preprocessed.
    pub preprocessed: [Preprocessed; 2],
    /// Robot 0's smoothed points with the surface between them.
    pub target: TargetScan,
    /// All headings (initialisation and recovery).
    pub full: AngleGrid,
    /// The refinement window around the true heading (normal operation).
    pub refined: AngleGrid,
}

impl PairStages {
    /// The straight pair with `beams` beams per scan, prepared with `params`.
    pub fn new(beams: usize, params: &VamrParams) -> Result<Self, PolygonError> {
        let pair = Pair::straight(beams)?;
        let (site, scans, truth) = (&pair.site, &pair.scans, pair.truth());
        let preprocessed = [0, 1].map(|i| preprocess(&scans[i], &site.mount, &params.preprocess));
        let h = &params.heading;
        let target = TargetScan::new(&scans[0], &site.mount, &preprocessed[0].smoothed_points)
            .with_surface(h.surface_jump_m());
        let full = AngleGrid::full(h.step_deg.get());
        let refined = AngleGrid::around(truth.theta, h.refine_window_deg.get(), h.step_deg.get());
        Ok(PairStages { pair, preprocessed, target, full, refined })
    }

    /// Robot 1's smoothed points against [`PairStages::target`], at the true translation.
    #[must_use]
    pub fn problem<'a>(&'a self, params: &HeadingParams) -> HeadingProblem<'a> {
        let truth = self.pair.truth();
        HeadingProblem::new(&self.preprocessed[1].smoothed_points, &self.target, [truth.x, truth.y], params)
    }

    /// Robot 0's smoothed points alone: the KD-tree baseline's target.
    #[must_use]
    pub fn target_points(&self) -> Vec<[f64; 2]> {
        self.preprocessed[0].smoothed_points.iter().map(|b| b.p).collect()
    }

    /// A T4 pipeline (50 ms sync spread, 100 ms age) that has run one update on the pair's packets:
    /// it already has a heading, so its next updates refine.
    pub fn primed_pipeline(&self, params: &VamrParams) -> Result<Pipeline, UpdateError> {
        let mut pipeline = Pipeline::new(2, params.clone(), Configuration::T4, 0.05, 0.1);
        pipeline.update(&self.pair.packets())?;
        Ok(pipeline)
    }
}

/// Why a [`Team`] cannot be built.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TeamError {
    #[error("a team needs at least 2 robots (got {0})")]
    TooFewRobots(usize),
    #[error(transparent)]
    Site(#[from] PolygonError),
}

/// N robots on a [`Site`], robot 0 the reference, and what each one's scanner sees.
#[derive(Debug, Clone)]
pub struct Team {
    pub site: Site,
    pub poses: Vec<Se2>,
    pub scans: Vec<Scan>,
}

impl Team {
    /// The hall's size for [`Team::fan`]: room for eight robots, every wall within the 10 m range.
    pub const HALL_M: [f64; 2] = [10.0, 7.0];
    /// Distances of the others from robot 0 on the fan, alternating so that neighbours on the fan
    /// stand apart and a near robot does not hide a far one.
    const FAN_RANGES_M: [f64; 2] = [1.1, 1.9];
    /// Bearings of the fan's ends from robot 0's heading: from abeam on one side to abeam on the
    /// other.
    const FAN_HALF_WIDTH_DEG: f64 = 90.0;
    /// The others' headings relative to robot 0, in turn: within ±15°, as in a formation that
    /// drives one way, and all different, so that no two heading searches are the same problem.
    const HEADINGS_DEG: [f64; 7] = [8.0, -12.0, 15.0, -5.0, 10.0, -15.0, 4.0];

    /// `robots` robots on [`Site::hall`] ([`Team::HALL_M`]): robot 0 near the left wall facing
    /// into the hall, the others on a fan in front of it, evenly spread over ±90° of bearing at
    /// 1.1 m and 1.9 m in turn. Robot 0 sees every other robot's body unobstructed for up to eight
    /// robots (tested); with more the fan gets crowded.
    pub fn fan(robots: usize, beams: usize) -> Result<Self, TeamError> {
        if robots < 2 {
            return Err(TeamError::TooFewRobots(robots));
        }
        let site = Site::hall(beams, Self::HALL_M[0], Self::HALL_M[1])?;
        let reference = Se2::from_degrees(-3.0, -0.3, 6.0);
        let others = robots - 1;
        let mut poses = vec![reference];
        for k in 0..others {
            let bearing_deg = if others == 1 {
                0.0
            } else {
                -Self::FAN_HALF_WIDTH_DEG + 2.0 * Self::FAN_HALF_WIDTH_DEG * k as f64 / (others - 1) as f64
            };
            let range_m = Self::FAN_RANGES_M[k % 2];
            let (s, c) = bearing_deg.to_radians().sin_cos();
            let heading_deg = Self::HEADINGS_DEG[k % Self::HEADINGS_DEG.len()];
            poses.push(reference * Se2::from_degrees(range_m * c, range_m * s, heading_deg));
        }
        let scans = (0..robots).map(|i| site.scan(&poses, i)).collect();
        Ok(Team { site, poses, scans })
    }

    /// `T_{B_i}^{B_0}`: robot `i` in robot 0's base frame (`None` past the last robot).
    #[must_use]
    pub fn truth(&self, i: usize) -> Option<Se2> {
        Some(self.poses[0].inverse() * *self.poses.get(i)?)
    }

    /// Every robot's scan as one synchronised set of packets, robot 0 first, without AMCL poses.
    #[must_use]
    pub fn packets(&self) -> Vec<RobotPacket<'_>> {
        packets(&self.site, &self.scans)
    }
}

/// `scans` as packets stamped at 0 and received 10 ms later, with the site's mount and chassis.
fn packets<'a>(site: &'a Site, scans: &'a [Scan]) -> Vec<RobotPacket<'a>> {
    scans
        .iter()
        .map(|s| RobotPacket {
            scan: s,
            times: PacketTimes { stamp_s: 0.0, received_s: 0.01 },
            lidar_to_base: site.mount,
            chassis: &site.chassis,
            weight: 1.0,
            amcl_pose: None,
            truth: None,
            odom: None,
        })
        .collect()
}

fn rectangle(x0: f64, y0: f64, x1: f64, y1: f64) -> Vec<[f64; 2]> {
    vec![[x0, y0], [x1, y0], [x1, y1], [x0, y1]]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Robot 0's beams that end on robot `i`'s body.
    fn beams_on(site: &Site, poses: &[Se2], scan: &Scan, i: usize) -> usize {
        let body = poses[i].inverse();
        scan.points_in(&(poses[0] * site.mount))
            .iter()
            .filter(|b| site.chassis.distance_to_boundary(body.transform_point(b.p)) < 1e-9)
            .count()
    }

    #[test]
    fn robot_0_sees_every_other_robot_whole() {
        for beams in [271, 655] {
            for robots in [2, 3, 4, 8] {
                let team = Team::fan(robots, beams).unwrap();
                assert_eq!(
                    (team.poses.len(), team.scans.len(), team.packets().len()),
                    (robots, robots, robots)
                );
                for i in 1..robots {
                    let seen = beams_on(&team.site, &team.poses, &team.scans[0], i);
                    // The same robot with no other robot in the scene: nothing may hide any of it.
                    let alone = [team.poses[0], team.poses[i]];
                    let unobstructed = beams_on(&team.site, &alone, &team.site.scan(&alone, 0), 1);
                    assert_eq!(seen, unobstructed, "{robots} robots, {beams} beams: robot {i} partly hidden");
                    // Enough beams for the contour's line fits (10 points) at the TiM551's 1°.
                    assert!(seen >= 10, "{robots} robots, {beams} beams: robot {i} on {seen} beams");
                    let t = team.truth(i).unwrap();
                    let d = t.x.hypot(t.y);
                    assert!((0.9..=2.5).contains(&d), "robot {i} at {d:.2} m");
                }
                // Bodies apart from each other and from every wall and feature.
                for (i, a) in team.poses.iter().enumerate() {
                    for b in &team.poses[i + 1..] {
                        assert!((a.x - b.x).hypot(a.y - b.y) > 0.9, "{robots} robots: {a:?} and {b:?}");
                    }
                    let corners = team.site.chassis.vertices().iter().map(|v| a.transform_point(*v));
                    for (c, part) in corners.flat_map(|c| team.site.static_parts.iter().map(move |p| (c, p)))
                    {
                        assert!(
                            part.distance_to_boundary(c) > 0.3,
                            "{robots} robots: robot at {a:?} touches {part:?}"
                        );
                    }
                }
                assert!(team.truth(robots).is_none());
            }
        }
    }

    #[test]
    fn a_team_needs_two_robots() {
        assert_eq!(Team::fan(1, 271).unwrap_err(), TeamError::TooFewRobots(1));
    }
}
