//! The simulated world: a static site — polygon outlines, or any occupancy grid whose occupied
//! cells are solid — N robot bodies with the configured chassis, differential-drive kinematics with
//! acceleration limits, wheel slip and encoder resolution; a TiM551 model that ray-casts the map
//! and every other robot; an IMU model (true yaw rate + bias + noise). Deterministic from a seed:
//! all noise comes from one [`amr_core::rng::Rng`], forked per robot and per sensor.
//!
//! Time is the caller's: [`World::step`] advances it, the sensor models read the state at the current
//! time. The mock devices reach the world through [`WorldLidar`] and [`WorldImu`].

mod site;

use std::sync::{Arc, Mutex, PoisonError};

use amr_core::geometry::{Polygon, cast_ray};
use amr_core::map::OccupancyGrid;
use amr_core::rng::Rng;
use amr_core::scan::Scan;
use amr_core::se2::Se2;

pub use site::{
    PAPER_SITE_LENGTH_M, PAPER_SITE_WIDTH_M, corridor, one_sided_hall, paper_site, shipped_site, short_racks,
};

/// A robot's physical description (from its configuration).
#[derive(Debug, Clone)]
pub struct RobotSpec {
    pub chassis: Polygon,
    pub wheel_radius_m: f64,
    pub track_width_m: f64,
    pub lidar_mount: Se2,
    /// Largest wheel-surface acceleration the drives deliver, m/s².
    pub max_accel_mps2: f64,
}

/// Sensor and actuator imperfections.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Noise {
    /// Standard deviation of each LiDAR range, m.
    pub range_sigma_m: f64,
    /// Probability that a beam returns nothing.
    pub dropout_probability: f64,
    /// Standard deviation of the relative wheel slip per step (ground speed = wheel speed·(1 + s)).
    pub wheel_slip_sigma: f64,
    /// Encoder resolution: counts per wheel revolution (motor counts × gear ratio).
    pub encoder_counts_per_wheel_rev: f64,
    /// Standard deviation of each encoder reading, counts (electrical noise and backlash; it does
    /// not accumulate).
    pub encoder_sigma_counts: f64,
    /// Gyro bias range: each robot's bias is drawn once, uniform in ±this, rad/s.
    pub gyro_bias_max_radps: f64,
    /// Gyro white noise, rad/s.
    pub gyro_sigma_radps: f64,
    /// Systematic odometry errors (Borenstein & Feng, "Measurement and correction of systematic
    /// odometry errors in mobile robots", IEEE Trans. Robotics and Automation 12(6), 1996: the
    /// unequal wheel diameters `E_d` and the uncertain wheelbase `E_b` that their UMBmark test
    /// measures). Each wheel's effective radius is the nominal one times `1 + ε`, ε drawn once per
    /// robot with this relative standard deviation; the odometry keeps using the nominal radius.
    pub wheel_radius_sigma: f64,
    /// Likewise the effective track width (the tyres' contact patches), relative 1σ, drawn once
    /// per robot.
    pub track_width_sigma: f64,
}

impl Noise {
    /// No noise at all: exact sensors, no slip, continuous encoders.
    pub const NONE: Noise = Noise {
        range_sigma_m: 0.0,
        dropout_probability: 0.0,
        wheel_slip_sigma: 0.0,
        encoder_counts_per_wheel_rev: 0.0,
        encoder_sigma_counts: 0.0,
        gyro_bias_max_radps: 0.0,
        gyro_sigma_radps: 0.0,
        wheel_radius_sigma: 0.0,
        track_width_sigma: 0.0,
    };

    /// A TiM551 (statistical error ≈ 20 mm at 1σ in SICK's data sheet; we use 10 mm as the
    /// systematic part is calibrated), occasional dropouts, a good floor and an LPMS-class gyro.
    pub const TYPICAL: Noise = Noise {
        range_sigma_m: 0.01,
        dropout_probability: 0.01,
        wheel_slip_sigma: 0.002,
        encoder_counts_per_wheel_rev: 200_000.0,
        encoder_sigma_counts: 2.0,
        gyro_bias_max_radps: 0.002,
        gyro_sigma_radps: 0.005,
        // A calibrated robot, not a perfect one: 0.2 % per wheel radius (0.13 mm of a 65 mm wheel;
        // tyre wear and load change more than that) and 0.5 % of the track width (1.7 mm of
        // 0.33 m, less than a tyre's contact patch). Driving straight, a robot whose wheels differ
        // by 0.28 % (1σ of the difference) turns 0.5°/m that its odometry does not see.
        wheel_radius_sigma: 0.002,
        track_width_sigma: 0.005,
    };
}

/// The TiM551 beam layout: 271 beams over 270°, 0.05–10 m (devices.md §1), robot convention.
#[must_use]
pub fn tim551_beams() -> Scan {
    Scan::new(-135f64.to_radians(), 1f64.to_radians(), 0.05, 10.0, vec![f64::NAN; 271])
}

#[derive(Debug, Clone)]
struct SimRobot {
    spec: RobotSpec,
    pose: Se2,
    /// Commanded body twist.
    cmd_v_mps: f64,
    cmd_w_radps: f64,
    /// Actual wheel surface speeds (left, right), m/s.
    wheel_mps: [f64; 2],
    /// Integrated wheel rotation (left, right), rad — what the encoders measure.
    wheel_rad: [f64; 2],
    /// The body's true twist over the last step.
    twist: (f64, f64),
    gyro_bias_radps: f64,
    /// Effective wheel radii (left, right) and track width over the nominal ones
    /// ([`Noise::wheel_radius_sigma`], [`Noise::track_width_sigma`]).
    wheel_scale: [f64; 2],
    track_scale: f64,
    rng: Rng,
}

/// What one robot's LiDAR can see ([`World::visibility`]), in beams.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Visibility {
    pub beams: usize,
    /// Beams whose first return is another robot's body.
    pub on_robots: usize,
    /// Beams that return from the site with no other robot about.
    pub site_alone: usize,
    /// Of those, the ones that still do.
    pub site_left: usize,
}

/// What the LiDARs see besides the robots: walls as polygon edges (the paper's site), and the
/// occupied cells of a grid as solid squares (any ROS map).
#[derive(Debug, Clone, Default)]
pub struct Site {
    pub polygons: Vec<Polygon>,
    pub grid: Option<OccupancyGrid>,
}

impl Site {
    /// Everything solid as polygons, for drawing: the polygons, and a square per occupied cell.
    #[must_use]
    pub fn outlines(&self) -> Vec<Polygon> {
        let mut out = self.polygons.clone();
        if let Some(g) = &self.grid {
            let r = g.resolution_m;
            for j in 0..g.height {
                for i in 0..g.width {
                    if g.is_occupied(i, j) {
                        let c = [[0.0, 0.0], [r, 0.0], [r, r], [0.0, r]]
                            .map(|[a, b]| g.origin.transform_point([i as f64 * r + a, j as f64 * r + b]));
                        if let Ok(p) = Polygon::new(c.to_vec()) {
                            out.push(p);
                        }
                    }
                }
            }
        }
        out
    }

    /// Whether a disc of `radius_m` around `c` is clear of every wall: inside the first polygon
    /// (the room), outside every other (the obstacles: a rack is solid) and away from every
    /// polygon's edges; on a grid, on a free cell with no occupied or unknown cell within the
    /// radius. The world does not model collisions, so a scenario that drives a robot through a
    /// wall is refused with this, and a survey stands only where this holds.
    #[must_use]
    pub fn is_clear(&self, c: [f64; 2], radius_m: f64) -> bool {
        let polygons_ok = self.polygons.first().is_none_or(|room| room.contains(c))
            && self.polygons.iter().skip(1).all(|obstacle| !obstacle.contains(c))
            && self.polygons.iter().all(|p| p.distance_to_boundary(c) > radius_m);
        let grid_ok = self.grid.as_ref().is_none_or(|g| {
            let Some((ci, cj)) = g.cell_of(c) else { return false };
            if !g.is_free(ci, cj) {
                return false;
            }
            let n = (radius_m / g.resolution_m).ceil() as i64 + 1;
            let half = g.resolution_m / 2.0;
            // Bounded: (2n + 1)² cells.
            for dj in -n..=n {
                for di in -n..=n {
                    let (i, j) = (ci as i64 + di, cj as i64 + dj);
                    if i < 0 || j < 0 {
                        continue;
                    }
                    let (i, j) = (i as usize, j as usize);
                    let Some(v) = g.get(i, j) else { continue };
                    let m = g.cell_center(i, j);
                    // The cell's nearest point to `c` is within `radius_m` (a conservative test
                    // with the cell's circumscribed disc).
                    let near = (m[0] - c[0]).hypot(m[1] - c[1]) - half * std::f64::consts::SQRT_2 <= radius_m;
                    if near && v != amr_core::map::FREE {
                        return false;
                    }
                }
            }
            true
        });
        polygons_ok && grid_ok
    }
}

impl From<Vec<Polygon>> for Site {
    fn from(polygons: Vec<Polygon>) -> Site {
        Site { polygons, grid: None }
    }
}

impl From<OccupancyGrid> for Site {
    fn from(grid: OccupancyGrid) -> Site {
        Site { polygons: Vec::new(), grid: Some(grid) }
    }
}

/// The world.
#[derive(Debug, Clone)]
pub struct World {
    site: Site,
    robots: Vec<SimRobot>,
    noise: Noise,
    t_s: f64,
    rng: Rng,
}

impl World {
    #[must_use]
    pub fn new(site: impl Into<Site>, noise: Noise, seed: u64) -> Self {
        World { site: site.into(), robots: Vec::new(), noise, t_s: 0.0, rng: Rng::seed(seed) }
    }

    /// Add a robot at `pose`, standing still; returns its index.
    pub fn add_robot(&mut self, spec: RobotSpec, pose: Se2) -> usize {
        let mut rng = self.rng.fork(self.robots.len() as u64);
        let max_bias = self.noise.gyro_bias_max_radps;
        let bias = if max_bias > 0.0 { rng.range(-max_bias, max_bias) } else { 0.0 };
        let mut scale = |sigma: f64| if sigma > 0.0 { 1.0 + rng.gaussian(sigma) } else { 1.0 };
        let wheel_scale = [scale(self.noise.wheel_radius_sigma), scale(self.noise.wheel_radius_sigma)];
        let track_scale = scale(self.noise.track_width_sigma);
        self.robots.push(SimRobot {
            spec,
            pose,
            cmd_v_mps: 0.0,
            cmd_w_radps: 0.0,
            wheel_mps: [0.0; 2],
            wheel_rad: [0.0; 2],
            twist: (0.0, 0.0),
            gyro_bias_radps: bias,
            wheel_scale,
            track_scale,
            rng,
        });
        self.robots.len() - 1
    }

    #[must_use]
    pub fn time_s(&self) -> f64 {
        self.t_s
    }

    #[must_use]
    pub fn robot_count(&self) -> usize {
        self.robots.len()
    }

    /// The velocity the robot's drives are asked for (the drives' own acceleration limit applies).
    pub fn command(&mut self, robot: usize, v_mps: f64, w_radps: f64) {
        if let Some(r) = self.robots.get_mut(robot) {
            (r.cmd_v_mps, r.cmd_w_radps) = (finite_or_zero(v_mps), finite_or_zero(w_radps));
        }
    }

    /// Advance by `dt_s`: wheel speeds ramp towards the command at the acceleration limit, the ground
    /// speed differs from the wheel speed by the slip, and the pose follows the exact arc.
    pub fn step(&mut self, dt_s: f64) {
        if dt_s.is_nan() || dt_s <= 0.0 {
            return;
        }
        let slip_sigma = self.noise.wheel_slip_sigma;
        for r in &mut self.robots {
            let half_b = r.spec.track_width_m / 2.0;
            let target = [r.cmd_v_mps - r.cmd_w_radps * half_b, r.cmd_v_mps + r.cmd_w_radps * half_b];
            let dv_max = r.spec.max_accel_mps2 * dt_s;
            let mut ground = [0.0; 2];
            for k in 0..2 {
                let dv = (target[k] - r.wheel_mps[k]).clamp(-dv_max, dv_max);
                let before = r.wheel_mps[k];
                r.wheel_mps[k] += dv;
                let mean = 0.5 * (before + r.wheel_mps[k]);
                // The drive turns the wheel at the rate the nominal radius asks for; the ground
                // moves by the effective radius.
                r.wheel_rad[k] += mean * dt_s / r.spec.wheel_radius_m;
                ground[k] = mean * r.wheel_scale[k] * (1.0 + r.rng.gaussian(slip_sigma));
            }
            let v = 0.5 * (ground[0] + ground[1]);
            let w = (ground[1] - ground[0]) / (r.spec.track_width_m * r.track_scale);
            r.pose = r.pose * arc(v * dt_s, w * dt_s);
            r.twist = (v, w);
        }
        self.t_s += dt_s;
    }

    /// The true pose of a robot.
    #[must_use]
    pub fn pose(&self, robot: usize) -> Option<Se2> {
        self.robots.get(robot).map(|r| r.pose)
    }

    /// Place a robot (teleport), e.g. for a kidnapping drill.
    pub fn set_pose(&mut self, robot: usize, pose: Se2) {
        if let Some(r) = self.robots.get_mut(robot) {
            r.pose = pose;
        }
    }

    /// The true body twist `(v, ω)` over the last step.
    #[must_use]
    pub fn twist(&self, robot: usize) -> Option<(f64, f64)> {
        self.robots.get(robot).map(|r| r.twist)
    }

    /// Wheel rotations (left, right) as the encoders report them, rad: quantised to the encoder
    /// resolution, with reading noise.
    pub fn encoders_rad(&mut self, robot: usize) -> Option<[f64; 2]> {
        let (cpr, sigma) = (self.noise.encoder_counts_per_wheel_rev, self.noise.encoder_sigma_counts);
        let r = self.robots.get_mut(robot)?;
        let tau = std::f64::consts::TAU;
        let wheel = r.wheel_rad;
        Some(wheel.map(|a| {
            if cpr > 0.0 {
                let counts = (a / tau * cpr + r.rng.gaussian(sigma)).floor();
                counts / cpr * tau
            } else {
                a
            }
        }))
    }

    /// The gyro's yaw rate: true rate + the robot's bias + white noise.
    pub fn gyro_radps(&mut self, robot: usize) -> Option<f64> {
        let sigma = self.noise.gyro_sigma_radps;
        let r = self.robots.get_mut(robot)?;
        Some(r.twist.1 + r.gyro_bias_radps + r.rng.gaussian(sigma))
    }

    /// What robot `robot`'s LiDAR sees now on the beams of `beams`: the map and every other robot's
    /// body (its own body is below the scan plane), with range noise and dropouts.
    pub fn scan(&mut self, robot: usize, beams: &Scan) -> Option<Scan> {
        let ranges = self.ranges(
            robot,
            &(0..beams.len()).map(|i| beams.angle(i)).collect::<Vec<_>>(),
            beams.range_max_m,
        )?;
        Some(beams.with_ranges(ranges))
    }

    /// What robot `robot`'s LiDAR could see now on the beams of `beams`, noise-free: how many beams
    /// the other robots' bodies take, and how many of the site's returns it would have alone are
    /// left (what `amr eval --study occlusion` reports).
    #[must_use]
    pub fn visibility(&self, robot: usize, beams: &Scan) -> Option<Visibility> {
        let me = self.robots.get(robot)?;
        let lidar = me.pose * me.spec.lidar_mount;
        let statics: Vec<(Se2, &Polygon)> = self.site.polygons.iter().map(|p| (Se2::IDENTITY, p)).collect();
        let others: Vec<(Se2, &Polygon)> = self
            .robots
            .iter()
            .enumerate()
            .filter(|(j, _)| *j != robot)
            .map(|(_, r)| (r.pose, &r.spec.chassis))
            .collect();
        let at = [lidar.x, lidar.y];
        let max = beams.range_max_m;
        let mut v = Visibility { beams: beams.len(), ..Visibility::default() };
        for i in 0..beams.len() {
            let a = lidar.theta + beams.angle(i);
            let cells = self.site.grid.as_ref().and_then(|g| g.cast_ray(at, a, max));
            let site = match (cast_ray(at, a, max, &statics), cells) {
                (Some(p), Some(c)) => Some(p.min(c)),
                (p, c) => p.or(c),
            };
            let robot_hit = cast_ray(at, a, max, &others);
            let hidden = robot_hit.is_some_and(|r| site.is_none_or(|s| r < s));
            v.on_robots += usize::from(hidden);
            v.site_alone += usize::from(site.is_some());
            v.site_left += usize::from(site.is_some() && !hidden);
        }
        Some(v)
    }

    /// Ranges along `angles_rad` (robot frame) from robot `robot`'s LiDAR; NaN where nothing returns.
    pub fn ranges(&mut self, robot: usize, angles_rad: &[f64], range_max_m: f64) -> Option<Vec<f64>> {
        let lidar = self.robots.get(robot)?.pose * self.robots[robot].spec.lidar_mount;
        let mut scene: Vec<(Se2, &Polygon)> = self.site.polygons.iter().map(|p| (Se2::IDENTITY, p)).collect();
        scene.extend(
            self.robots
                .iter()
                .enumerate()
                .filter(|(j, _)| *j != robot)
                .map(|(_, r)| (r.pose, &r.spec.chassis)),
        );
        let grid = self.site.grid.as_ref();
        let exact: Vec<Option<f64>> = angles_rad
            .iter()
            .map(|a| {
                let at = [lidar.x, lidar.y];
                let polygons = cast_ray(at, lidar.theta + a, range_max_m, &scene);
                let cells = grid.and_then(|g| g.cast_ray(at, lidar.theta + a, range_max_m));
                match (polygons, cells) {
                    (Some(p), Some(c)) => Some(p.min(c)),
                    (p, c) => p.or(c),
                }
            })
            .collect();
        let (sigma, drop) = (self.noise.range_sigma_m, self.noise.dropout_probability);
        let rng = &mut self.robots[robot].rng;
        Some(
            exact
                .into_iter()
                .map(|r| match r {
                    Some(r) if !(drop > 0.0 && rng.uniform() < drop) => r + rng.gaussian(sigma),
                    _ => f64::NAN,
                })
                .collect(),
        )
    }
}

fn finite_or_zero(x: f64) -> f64 {
    if x.is_finite() { x } else { 0.0 }
}

/// The motion along an arc of length `ds` turning by `dtheta`, in the start frame.
fn arc(ds: f64, dtheta: f64) -> Se2 {
    if dtheta.abs() < 1e-9 {
        return Se2::new(ds * (0.5 * dtheta).cos(), ds * (0.5 * dtheta).sin(), dtheta);
    }
    let r = ds / dtheta;
    Se2::new(r * dtheta.sin(), r * (1.0 - dtheta.cos()), dtheta)
}

/// A world shared between the simulation loop and the mock devices.
pub type SharedWorld = Arc<Mutex<World>>;

fn lock(world: &SharedWorld) -> std::sync::MutexGuard<'_, World> {
    // A panic elsewhere while holding the lock leaves a consistent world (every mutation is
    // completed before the guard drops), so keep going with it.
    world.lock().unwrap_or_else(PoisonError::into_inner)
}

/// Robot `robot`'s LiDAR, for the mock TiM551: the world's state now, whatever time the mock asks
/// for (the simulation loop owns time).
#[derive(Debug, Clone)]
pub struct WorldLidar {
    pub world: SharedWorld,
    pub robot: usize,
}

impl crate::tim551::ScanSource for WorldLidar {
    fn scan(&self, _elapsed: std::time::Duration, angles_rad: &[f64]) -> crate::tim551::SourceScan {
        let ranges = lock(&self.world).ranges(self.robot, angles_rad, 10.0).unwrap_or_default();
        crate::tim551::SourceScan {
            ranges_m: ranges.iter().map(|r| if r.is_finite() { *r as f32 } else { 0.0 }).collect(),
            rssi: None,
        }
    }
}

/// Robot `robot`'s IMU, for the mock LPMS-B2.
#[derive(Debug, Clone)]
pub struct WorldImu {
    pub world: SharedWorld,
    pub robot: usize,
}

impl crate::lpms::MotionSource for WorldImu {
    fn motion_at(&mut self, _t_s: f64) -> crate::lpms::Motion {
        let mut w = lock(&self.world);
        let yaw_rate = w.gyro_radps(self.robot).unwrap_or(0.0);
        let yaw = w.pose(self.robot).map_or(0.0, |p| p.theta);
        crate::lpms::Motion {
            angular_velocity_radps: [0.0, 0.0, yaw_rate],
            orientation_wxyz: [(yaw / 2.0).cos(), 0.0, 0.0, (yaw / 2.0).sin()],
            linear_acc_mps2: [0.0; 3],
        }
    }
}

#[cfg(test)]
mod tests;
