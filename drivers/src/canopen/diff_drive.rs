//! The differential-drive layer: (v, ω) → the two wheels' target velocities in drive units, and
//! wheel odometry by exact arc integration of encoder deltas (wrapping 32-bit counters). Every
//! drive-specific number is configuration (devices.md §2; ros2_canopen PR #74: scaling per drive).

use std::f64::consts::TAU;

pub use super::config::{DrivesConfig, WheelDriveConfig};

use super::config::BusConfig;
use super::frame::NodeId;
use super::master::{DriveSetup, MasterConfig};

/// Wheel geometry, from a robot file's `[kinematics]` (amr-core's type; this crate takes plain numbers).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Geometry {
    /// Wheel radius.
    pub wheel_radius_m: f64,
    /// Distance between the wheel contact points.
    pub track_width_m: f64,
}

/// Converts between body motion and drive units.
#[derive(Debug, Clone, PartialEq)]
pub struct DiffDrive {
    drives: DrivesConfig,
    geometry: Geometry,
}

impl DiffDrive {
    /// From the configuration.
    pub fn new(drives: DrivesConfig, geometry: Geometry) -> Self {
        Self { drives, geometry }
    }

    /// The drives' configuration.
    pub fn drives(&self) -> &DrivesConfig {
        &self.drives
    }

    fn sign(w: WheelDriveConfig) -> f64 {
        if w.inverted { -1.0 } else { 1.0 }
    }

    /// Wheel angular speed (rad/s, forward positive) → drive velocity units.
    fn wheel_units(&self, w: WheelDriveConfig, wheel_radps: f64) -> i32 {
        let motor_rps = wheel_radps / TAU * self.drives.gear_ratio;
        let units = (Self::sign(w) * motor_rps * self.drives.velocity_units_per_rps).round();
        // `as` saturates at the i32 range (and maps NaN to 0).
        units as i32
    }

    /// Target velocities for forward speed `v_mps` and yaw rate `omega_radps`:
    /// `[(left node, units), (right node, units)]`, sent together before one SYNC.
    pub fn wheel_targets(&self, v_mps: f64, omega_radps: f64) -> [(NodeId, i32); 2] {
        let half = self.geometry.track_width_m / 2.0;
        let r = self.geometry.wheel_radius_m;
        let left = (v_mps - omega_radps * half) / r;
        let right = (v_mps + omega_radps * half) / r;
        [
            (self.drives.left.node_id, self.wheel_units(self.drives.left, left)),
            (self.drives.right.node_id, self.wheel_units(self.drives.right, right)),
        ]
    }

    /// Encoder counts (motor side, drive sign) → wheel travel in metres (forward positive).
    pub fn counts_to_m(&self, w: WheelDriveConfig, counts: i64) -> f64 {
        let motor_rev = counts as f64 / f64::from(self.drives.encoder_counts_per_rev.max(1));
        Self::sign(w) * motor_rev / self.drives.gear_ratio * TAU * self.geometry.wheel_radius_m
    }

    /// Drive velocity units → wheel surface speed in m/s (forward positive).
    pub fn units_to_mps(&self, w: WheelDriveConfig, units: i32) -> f64 {
        Self::sign(w) * f64::from(units) / self.drives.velocity_units_per_rps / self.drives.gear_ratio
            * TAU
            * self.geometry.wheel_radius_m
    }

    /// The master for these drives on `bus`: profile acceleration `accel_mps2` (0x6083), profile
    /// deceleration `decel_mps2` (0x6084), the quick stop from `quick_stop_decel_mps2` (0x6085).
    /// Each target set holds for `target_hold_ms`.
    pub fn master_config(
        &self,
        bus: &BusConfig,
        accel_mps2: f64,
        decel_mps2: f64,
        target_hold_ms: u32,
    ) -> MasterConfig {
        MasterConfig {
            can: bus.clone(),
            drives: self.drive_setups(accel_mps2, decel_mps2, self.drives.quick_stop_decel_mps2),
            enable_timeout_ms: self.drives.enable_timeout_ms,
            mode_confirm_attempts: self.drives.mode_confirm_attempts,
            target_hold_ms,
        }
    }

    /// The start-up settings of both drives: profile acceleration, profile deceleration and quick-stop
    /// deceleration as wheel-surface m/s².
    pub fn drive_setups(
        &self,
        accel_mps2: f64,
        decel_mps2: f64,
        quick_stop_decel_mps2: f64,
    ) -> Vec<DriveSetup> {
        let to_units = |a_mps2: f64| {
            let motor_rps2 = a_mps2 / self.geometry.wheel_radius_m / TAU * self.drives.gear_ratio;
            (motor_rps2 * self.drives.velocity_units_per_rps).round().clamp(1.0, f64::from(u32::MAX)) as u32
        };
        [self.drives.left, self.drives.right]
            .iter()
            .map(|w| DriveSetup {
                node_id: w.node_id,
                // Both fit 16 bits in a validated file (`DrivesConfig::validate`).
                heartbeat_producer_ms: u16::try_from(self.drives.heartbeat_producer_ms).unwrap_or(u16::MAX),
                heartbeat_consumer_ms: self.drives.heartbeat_consumer_ms,
                master_consumer_ms: u16::try_from(self.drives.master_consumer_ms).unwrap_or(u16::MAX),
                comm_loss_reaction: self.drives.comm_loss_reaction,
                profile_acceleration: to_units(accel_mps2),
                profile_deceleration: to_units(decel_mps2),
                quick_stop_deceleration: to_units(quick_stop_decel_mps2),
                digital_inputs: self.drives.estop_input_bit.is_some(),
            })
            .collect()
    }
}

/// A planar pose (x, y, heading).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Pose2 {
    /// x in the odometry frame.
    pub x_m: f64,
    /// y in the odometry frame.
    pub y_m: f64,
    /// Heading.
    pub yaw_rad: f64,
}

/// Wheel odometry from absolute encoder positions.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct WheelOdometry {
    last: Option<(i32, i32)>,
    pose: Pose2,
    distance_m: f64,
}

impl WheelOdometry {
    /// Start at the origin; the first reading only sets the reference.
    pub fn new() -> Self {
        Self::default()
    }

    /// The integrated pose.
    pub fn pose(&self) -> Pose2 {
        self.pose
    }

    /// Path length travelled by the base centre.
    pub fn distance_m(&self) -> f64 {
        self.distance_m
    }

    /// Forget the reference (after a drive reboot its counter may restart).
    pub fn rereference(&mut self) {
        self.last = None;
    }

    /// New absolute positions (counts) of both wheels; returns the (left, right) travel in metres.
    /// Deltas are taken modulo 2³², so a counter wrap between readings is a small step.
    pub fn update(&mut self, dd: &DiffDrive, left_counts: i32, right_counts: i32) -> (f64, f64) {
        let Some((l0, r0)) = self.last.replace((left_counts, right_counts)) else { return (0.0, 0.0) };
        let dl = dd.counts_to_m(dd.drives.left, i64::from(left_counts.wrapping_sub(l0)));
        let dr = dd.counts_to_m(dd.drives.right, i64::from(right_counts.wrapping_sub(r0)));
        self.integrate(dl, dr, dd.geometry.track_width_m);
        (dl, dr)
    }

    /// Exact arc integration: the base moves on a circle of radius ds/dθ (a line when dθ ≈ 0).
    fn integrate(&mut self, dl_m: f64, dr_m: f64, track_m: f64) {
        let ds = (dl_m + dr_m) / 2.0;
        let dth = (dr_m - dl_m) / track_m;
        let th = self.pose.yaw_rad;
        if dth.abs() < 1e-9 {
            let mid = th + dth / 2.0;
            self.pose.x_m += ds * mid.cos();
            self.pose.y_m += ds * mid.sin();
        } else {
            let r = ds / dth;
            self.pose.x_m += r * ((th + dth).sin() - th.sin());
            self.pose.y_m -= r * ((th + dth).cos() - th.cos());
        }
        self.pose.yaw_rad = (th + dth + std::f64::consts::PI).rem_euclid(TAU) - std::f64::consts::PI;
        self.distance_m += ds.abs();
    }
}

#[cfg(test)]
mod tests {
    use super::super::config::CommLossReaction;
    use super::*;

    fn dd() -> DiffDrive {
        DiffDrive::new(
            DrivesConfig {
                left: WheelDriveConfig { node_id: 1, inverted: false },
                right: WheelDriveConfig { node_id: 2, inverted: true },
                encoder_counts_per_rev: 10_000,
                gear_ratio: 20.0,
                velocity_units_per_rps: 10_000.0,
                heartbeat_producer_ms: 100,
                heartbeat_consumer_ms: 300,
                master_consumer_ms: 300,
                comm_loss_reaction: CommLossReaction::QuickStop,
                enable_timeout_ms: 1000,
                mode_confirm_attempts: 5,
                quick_stop_decel_mps2: 0.5,
                estop_input_bit: None,
                estop_input_active_low: true,
            },
            Geometry { wheel_radius_m: 0.065, track_width_m: 0.33 },
        )
    }

    #[test]
    fn canopen_diff_drive_targets_in_drive_units() {
        let d = dd();
        // 0.2 m/s straight: wheel 0.2/0.065 rad/s, ×20/2π motor rps, ×10000 units.
        let expected = (0.2 / 0.065 / TAU * 20.0 * 10_000.0f64).round() as i32;
        assert_eq!(d.wheel_targets(0.2, 0.0), [(1, expected), (2, -expected)]);
        // Turning in place left: left wheel backwards, right forwards (right is inverted).
        let [(_, l), (_, r)] = d.wheel_targets(0.0, 0.5);
        assert!(l < 0 && r < 0, "{l} {r}");
        assert_eq!(l, r);
        assert!((d.units_to_mps(d.drives.left, expected) - 0.2).abs() < 1e-5);
        assert_eq!(d.wheel_targets(f64::NAN, 0.0), [(1, 0), (2, 0)]);
    }

    #[test]
    fn canopen_odometry_arc_and_counter_wrap() {
        let d = dd();
        let per_m = 10_000.0 * 20.0 / (TAU * 0.065); // counts per metre of wheel travel
        // A quarter circle of radius 1 m to the left: left travels (1 - b/2)·π/2, right (1 + b/2)·π/2.
        let b = 0.33;
        let (sl, sr) = ((1.0 - b / 2.0) * TAU / 4.0, (1.0 + b / 2.0) * TAU / 4.0);
        let mut odo = WheelOdometry::new();
        // Start near the wrap so both counters cross ±2³¹ on the way.
        let (l0, r0) = (i32::MAX - 1000, i32::MIN + 1000);
        odo.update(&d, l0, r0);
        let steps = 7; // exact arcs: the step count must not matter
        for k in 1..=steps {
            let f = f64::from(k) / f64::from(steps);
            let l = l0.wrapping_add((sl * f * per_m).round() as i32);
            let r = r0.wrapping_sub((sr * f * per_m).round() as i32);
            odo.update(&d, l, r);
        }
        let p = odo.pose();
        assert!((p.x_m - 1.0).abs() < 1e-4, "{p:?}");
        assert!((p.y_m - 1.0).abs() < 1e-4, "{p:?}");
        assert!((p.yaw_rad - TAU / 4.0).abs() < 1e-4, "{p:?}");
        assert!((odo.distance_m() - TAU / 4.0).abs() < 1e-4);
    }
}
