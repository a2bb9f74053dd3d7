//! Maps as robots get them: AMCL's map built by a simulated survey of the site, the way SLAM builds
//! maps, instead of the site itself. A robot with the TiM551's beams stands on a lattice over the
//! site's free space, looks both ways, and its scans (with range noise) go into
//! [`amr_core::map::Survey`] at poses that err a little (SLAM's residue): endpoint cells occupied,
//! traversed cells free, never-seen space unknown. So the localiser never sees the world it is
//! simulated in: walls are as thick as the endpoints' scatter and sit where the noisy survey put
//! them, and faces no survey pose saw are not in the map.

use amr_core::geometry::Polygon;
use amr_core::map::{OccupancyGrid, Survey};
use amr_core::rng::Rng;
use amr_core::se2::Se2;
use hil_mocks::world::{Noise, RobotSpec, Site, World, tim551_beams};

/// How the survey is made.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SurveyOptions {
    /// Distance between survey positions, m.
    pub spacing_m: f64,
    /// Clearance of a survey position from every wall, m (a robot stands there).
    pub clearance_m: f64,
    /// Range noise of the survey scans, m (1σ).
    pub range_sigma_m: f64,
    /// Error of each survey pose, m and rad (1σ): what SLAM leaves.
    pub pose_sigma_m: f64,
    pub pose_sigma_rad: f64,
    /// A cell is occupied when at least this share of the beams that reached it ended in it.
    pub occ_ratio: f64,
}

impl SurveyOptions {
    /// A careful survey: every 0.4 m, 25 cm clear of walls, 1 cm range noise, poses off by 2 cm
    /// and 0.3° (the residue `core/src/amcl/surveyed.rs` uses for its SLAM-style map); a cell is
    /// occupied at a quarter of hits, the default of the tool that turned the public Radish CARMEN logs
    /// (stored in the GitHub repository `acschaefer/ple`) into raw-odometry logs and references, and
    /// built the real-data maps.
    pub const TYPICAL: SurveyOptions = SurveyOptions {
        spacing_m: 0.4,
        clearance_m: 0.25,
        range_sigma_m: 0.01,
        pose_sigma_m: 0.02,
        pose_sigma_rad: 0.3 * std::f64::consts::PI / 180.0,
        occ_ratio: 0.25,
    };
}

/// The map a survey of `site` gives, on the grid geometry of `like` (its resolution, and its extent
/// with half a metre around). Deterministic from `seed`.
#[must_use]
pub fn surveyed_map(site: &Site, like: &OccupancyGrid, options: &SurveyOptions, seed: u64) -> OccupancyGrid {
    let res = like.resolution_m;
    let (x0, y0, x1, y1) = like.extent();
    let margin = 0.5;
    let mut rng = Rng::seed(seed ^ 0x5eed_5a7e);
    // SLAM lays its grid from where the mapping run started, not from the building's walls: the
    // grid stands at a random sub-cell offset from the site. (On the truth map's own grid every
    // wall face of our round-numbered sites lies on a cell boundary, so the endpoints' scatter
    // occupies the cell in front of every face: each wall sat half a cell inside the room, all
    // at once, and the map was a shrunken site.)
    let (ox, oy) = (x0 - margin - rng.uniform() * res, y0 - margin - rng.uniform() * res);
    let width = ((x1 - x0 + 2.0 * margin) / res).ceil() as usize + 1;
    let height = ((y1 - y0 + 2.0 * margin) / res).ceil() as usize + 1;
    let mut survey = Survey::new([ox, oy], width, height, res);
    let noise = Noise { range_sigma_m: options.range_sigma_m, ..Noise::NONE };
    let mut world = World::new(site.clone(), noise, seed);
    // The surveyor: a point-sized body (it sees no robot), its LiDAR at its centre.
    let Ok(dot) = Polygon::centered_rectangle(0.01, 0.01) else { return survey.grid(options.occ_ratio, 1) };
    let spec = RobotSpec {
        chassis: dot,
        wheel_radius_m: 0.05,
        track_width_m: 0.3,
        lidar_mount: Se2::IDENTITY,
        max_accel_mps2: 1.0,
    };
    let me = world.add_robot(spec, Se2::IDENTITY);
    let beams = tim551_beams();
    let step = options.spacing_m.max(res);
    let (nx, ny) = (((x1 - x0) / step).floor() as usize, ((y1 - y0) / step).floor() as usize);
    // Bounded: (nx + 1) · (ny + 1) positions, two scans each.
    for j in 0..=ny {
        for i in 0..=nx {
            let p = [x0 + (i as f64 + 0.5) * step, y0 + (j as f64 + 0.5) * step];
            if !site.is_clear(p, options.clearance_m) {
                continue;
            }
            // The TiM551 sees 270°: two opposite headings see all round.
            for k in 0..2 {
                let truth = Se2::new(p[0], p[1], f64::from(k) * std::f64::consts::PI);
                world.set_pose(me, truth);
                let Some(scan) = world.scan(me, &beams) else { continue };
                let believed = truth
                    * Se2::new(
                        rng.gaussian(options.pose_sigma_m),
                        rng.gaussian(options.pose_sigma_m),
                        rng.gaussian(options.pose_sigma_rad),
                    );
                survey.add_scan(&believed, &scan);
            }
        }
    }
    survey.grid(options.occ_ratio, 1)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "tests")]

    use amr_core::map::{FREE, UNKNOWN};
    use hil_mocks::world::paper_site;

    use super::*;

    #[test]
    fn a_survey_of_the_paper_site_is_like_it_but_not_it() {
        let config = amr_actors::config::load(&amr_actors::config::ConfigSource::Embedded).unwrap();
        let truth = &config.maps["paper-site"];
        let site: Site = paper_site().unwrap().into();
        let map = surveyed_map(&site, truth, &SurveyOptions::TYPICAL, 1);
        assert_eq!(map, surveyed_map(&site, truth, &SurveyOptions::TYPICAL, 1), "deterministic");
        assert_ne!(map, surveyed_map(&site, truth, &SurveyOptions::TYPICAL, 2), "the seed matters");
        // All but 1 % of the survey's occupied cells are near a wall of the site (within 15 cm: a 0.3° pose
        // error is 5 cm at 10 m, plus 2 cm and half a cell's diagonal), and most of
        // the site's wall cells have a surveyed wall cell within a cell.
        let near_wall = |p: [f64; 2], d: f64| site.polygons.iter().any(|w| w.distance_to_boundary(p) <= d);
        let occupied: Vec<[f64; 2]> = (0..map.height)
            .flat_map(|j| (0..map.width).map(move |i| (i, j)))
            .filter(|(i, j)| map.is_occupied(*i, *j))
            .map(|(i, j)| map.cell_center(i, j))
            .collect();
        assert!(occupied.len() > 300, "{} occupied cells", occupied.len());
        let stray = occupied.iter().filter(|p| !near_wall(**p, 0.15)).count();
        assert!(stray * 100 <= occupied.len(), "{stray} surveyed wall cells away from any wall");
        let mut walls = 0;
        let mut found = 0;
        for j in 0..truth.height {
            for i in 0..truth.width {
                if truth.is_occupied(i, j) {
                    walls += 1;
                    let c = truth.cell_center(i, j);
                    if occupied.iter().any(|o| (o[0] - c[0]).hypot(o[1] - c[1]) <= 0.075) {
                        found += 1;
                    }
                }
            }
        }
        assert!(f64::from(found) > 0.8 * f64::from(walls), "{found} of {walls} wall cells surveyed");
        // Not the true map: cells differ, and the inside is free, the outside unknown.
        let differ = truth.cells.iter().zip(&map.cells).filter(|(a, b)| a != b).count();
        assert!(differ > 100, "{differ} cells differ");
        assert_eq!(
            map.get(map.cell_of([0.0, 0.0]).unwrap().0, map.cell_of([0.0, 0.0]).unwrap().1),
            Some(FREE)
        );
        let (i, j) = map.cell_of([0.0, 2.5]).unwrap();
        assert_eq!(map.get(i, j), Some(UNKNOWN));
    }

    /// A survey stands only where a robot could, never inside a rack: what lies inside a rack's
    /// outline stays unknown to the map. Were a position inside a rack's outline taken as clear,
    /// the survey would stand four positions inside each rack of the hall and map the racks' inner
    /// faces behind their outer ones. Here a 10 m × 6 m room with two racks 2 m × 1.2 m against a
    /// wall, deep enough to hold positions of the survey's 0.4 m lattice (a survey of the
    /// 40 m × 20 m hall took a minute in a debug build).
    #[test]
    fn no_surveyor_stands_inside_a_rack() {
        let rect = |x0: f64, y0: f64, x1: f64, y1: f64| {
            Polygon::new(vec![[x0, y0], [x1, y0], [x1, y1], [x0, y1]]).unwrap()
        };
        let polygons = vec![rect(-5.0, -3.0, 5.0, 3.0), rect(-3.0, 1.8, -1.0, 3.0), rect(1.5, 1.8, 3.5, 3.0)];
        let site: Site = polygons.clone().into();
        assert!(!site.is_clear([-2.0, 2.4], 0.25), "0.6 m inside a rack");
        assert!(site.is_clear([-2.0, 1.4], 0.25), "0.4 m in front of it");
        let truth = amr_core::map::rasterize_outlines(
            &polygons,
            &polygons[0],
            0.05,
            Se2::new(-5.275, -3.275, 0.0),
            211,
            131,
        );
        let map = surveyed_map(&site, &truth, &SurveyOptions::TYPICAL, 3);
        // Cells deeper inside a rack than the survey's scatter (its poses err by 2 cm and 0.3°,
        // 5 cm at 10 m): no ray reaches them.
        let deep =
            |c: [f64; 2]| polygons[1..].iter().any(|r| r.contains(c) && r.distance_to_boundary(c) > 0.2);
        let (mut cells, mut occupied, mut free) = (0, 0, 0);
        for j in 0..map.height {
            for i in 0..map.width {
                if deep(map.cell_center(i, j)) {
                    cells += 1;
                    occupied += usize::from(map.is_occupied(i, j));
                    free += usize::from(map.is_free(i, j));
                }
            }
        }
        assert!(cells > 500, "{cells} cells deep inside the racks");
        // A stray endpoint of a pose 3σ off may land there.
        assert!(
            occupied <= 5 && free <= 5,
            "{occupied} occupied and {free} free cells deep inside the racks"
        );
    }

    /// The room as AMCL's likelihood field sees it across the paper's site, on the column through
    /// x = `x`: from the innermost occupied cell centre below the middle to the innermost above.
    fn surveyed_width(map: &OccupancyGrid, x: f64) -> Option<f64> {
        let (i, mid) = map.cell_of([x, 0.0])?;
        let below = (0..mid).rev().find(|j| map.is_occupied(i, *j))?;
        let above = (mid..map.height).find(|j| map.is_occupied(i, *j))?;
        Some(map.cell_center(i, above)[1] - map.cell_center(i, below)[1])
    }

    /// The survey's grid does not stand on the site's walls. On the truth map's grid every face of
    /// the paper's site lies on a cell boundary, the endpoints' scatter occupies the cell in front
    /// of each face, and the 3.10 m site measured 3.05 m in every survey: every robot was pulled
    /// towards the wall nearest it. At a random sub-cell offset a wall's cell is sometimes in
    /// front of its face and sometimes behind it; over surveys the site keeps its width.
    #[test]
    fn a_surveyed_site_keeps_its_width_over_surveys() {
        let config = amr_actors::config::load(&amr_actors::config::ConfigSource::Embedded).unwrap();
        let truth = &config.maps["paper-site"];
        let site: Site = paper_site().unwrap().into();
        let widths: Vec<f64> = (1..=12)
            .map(|seed| {
                let map = surveyed_map(&site, truth, &SurveyOptions::TYPICAL, seed);
                surveyed_width(&map, 0.0).unwrap()
            })
            .collect();
        let mean = widths.iter().sum::<f64>() / widths.len() as f64;
        assert!((mean - 3.10).abs() < 0.015, "mean surveyed width {mean:.3} m: {widths:?}");
        let spread = widths.iter().fold(0.0f64, |m, w| m.max((w - mean).abs()));
        assert!(spread > 0.01, "every survey measures the same width: {widths:?}");
    }
}
