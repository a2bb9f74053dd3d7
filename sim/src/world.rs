//! The simulated world: the robots' bodies as the world models them, V from their poses, the site
//! the world ray-casts, the check that a scenario keeps every robot clear of the walls, and the
//! world with the formation's robots at their start.

use std::sync::Arc;

use amr_actors::config::{Config, RobotConfig};
use amr_core::config::ScenarioConfig;
use amr_core::map::OccupancyGrid;
use amr_core::se2::Se2;
use amr_core::vamr::frame::virtual_frame;
use hil_mocks::world::{Noise, RobotSpec, SharedWorld, Site, World};

use crate::eval;
use crate::options::SimError;

/// The world's model of robot `c`'s body: chassis, wheels, LiDAR mount and acceleration limit.
#[must_use]
pub fn robot_spec(c: &RobotConfig) -> RobotSpec {
    RobotSpec {
        chassis: c.chassis.outline_m.clone(),
        wheel_radius_m: c.kinematics.wheel_radius_m.get(),
        track_width_m: c.kinematics.track_width_m.get(),
        lidar_mount: c.lidar_mount.to_se2(),
        max_accel_mps2: c.limits.max_accel_mps2.get(),
    }
}

/// V in the map from the robots' poses, Eq. 16 with equal weights.
#[must_use]
pub fn v_of(poses: &[Se2]) -> Option<Se2> {
    let first = poses.first()?;
    let rel: Vec<(Se2, f64)> = poses.iter().map(|p| (first.inverse() * *p, 1.0)).collect();
    Some(*first * virtual_frame(&rel))
}

/// What the world ray-casts for a scenario on map `map_name`: a shipped site as its polygons (its
/// map is their rendering, `hil_mocks::world::shipped_site`), any other map (a site of one's own)
/// as its occupied cells.
///
/// A rendering marks both cells that touch a face, so its occupied cells reach a cell in front of
/// every face. Ray-cast as a grid, each face stood a cell nearer the robots than on the map AMCL
/// uses with `--map true`, whose likelihood field puts a two-cell band's surface between its
/// layers: on `short-racks` (2 robots 0.5 m apart, 10 trials, seed 7) every configuration was
/// placed 5.0 cm towards the racks, and T4 erred by 6.3 cm on the site's own map against 2.9 on a
/// survey. As polygons: 0.9 cm. A map given by path has no polygons; there `--map true` keeps
/// that offset (README). A configuration's own map that only shares a name with one of ours (a
/// `maps/corridor.yaml` of another building) is not our rendering, and is ray-cast as its cells.
pub fn site_for(map_name: &str, map: &OccupancyGrid) -> Result<Site, SimError> {
    let Some(polygons) = hil_mocks::world::shipped_site(map_name) else { return Ok(map.clone().into()) };
    let polygons = polygons.map_err(|e| SimError::Site(format!("{e:?}")))?;
    let Some(room) = polygons.first() else { return Ok(map.clone().into()) };
    let rendering = amr_core::map::rasterize_outlines(
        &polygons,
        room,
        map.resolution_m,
        map.origin,
        map.width,
        map.height,
    );
    let same = (0..map.height).all(|j| {
        (0..map.width).all(|i| {
            rendering.is_occupied(i, j) == map.is_occupied(i, j)
                && rendering.is_free(i, j) == map.is_free(i, j)
        })
    });
    Ok(if same { polygons.into() } else { map.clone().into() })
}

/// The site of the configuration's map named by `sc`.
pub fn site_of(config: &Config, sc: &ScenarioConfig) -> Result<Site, SimError> {
    site_for(&sc.map, config.maps.get(&sc.map).ok_or_else(|| SimError::NoMap(sc.map.clone()))?)
}

/// The world does not model collisions: refuse a scenario that drives a robot of the formation
/// into a wall (its chassis' reach from its centre must stay clear, every 10 cm of V's path).
pub fn check_formation(site: &Site, sc: &ScenarioConfig, robots: &[RobotConfig]) -> Result<(), SimError> {
    let Some(first) = robots.first() else { return Ok(()) };
    let (x0, y0, x1, y1) = robot_spec(first).chassis.bounds();
    let reach = x0.abs().max(x1.abs()).hypot(y0.abs().max(y1.abs()));
    let slots = amr_core::formation::slots(robots.len(), sc.spacing_m.get());
    for r in eval::reference(sc, robots.len(), 0.1) {
        for y in &slots {
            let c = (r.pose * Se2::new(0.0, *y, 0.0)).transform_point([0.0, 0.0]);
            if !site.is_clear(c, reach) {
                return Err(SimError::Site(format!(
                    "with {} robots {} m apart the scenario drives a robot into a wall (or off the map) near ({:.2}, {:.2})",
                    robots.len(),
                    sc.spacing_m.get(),
                    c[0],
                    c[1]
                )));
            }
        }
    }
    Ok(())
}

/// The world with the formation's robots at their slots around the scenario's start.
pub fn build_world(
    robots: &[RobotConfig],
    sc: &ScenarioConfig,
    site: Site,
    noise: &Noise,
    seed: u64,
) -> Result<SharedWorld, SimError> {
    let mut world = World::new(site, *noise, seed);
    let slots = amr_core::formation::slots(robots.len(), sc.spacing_m.get());
    let start_v = sc.start_pose();
    for (r, y) in robots.iter().zip(&slots) {
        let mut spec = robot_spec(r);
        // The drives ramp (and quick-stop) the wheels; the world only must not be slower.
        spec.max_accel_mps2 = spec.max_accel_mps2.max(r.devices.drives.quick_stop_decel_mps2);
        world.add_robot(spec, start_v * Se2::new(0.0, *y, 0.0));
    }
    Ok(Arc::new(std::sync::Mutex::new(world)))
}
