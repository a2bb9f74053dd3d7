//! `robot-<id>.toml`: one robot's body (amr-core's types) and its devices, each section
//! deserialised straight into its driver's own configuration type (amr-drivers). What the drivers
//! are given is what the file says; nothing is copied in between.

use serde::Deserialize;

use amr_core::config::{
    ChassisConfig, ConfigFileType, KinematicsConfig, MotionLimits, MountConfig, RobotId, SafetyConfig,
    Violation, rule,
};
use amr_drivers::canopen::config::BusConfig;
use amr_drivers::canopen::diff_drive::{DiffDrive, DrivesConfig, Geometry};
use amr_drivers::canopen::master::MasterConfig;
use amr_drivers::lpms::LpmsConfig;
use amr_drivers::sopas::tcp::LidarConfig;

/// One robot (paper Table 3 for the values of the paper's platform).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RobotConfig {
    pub id: RobotId,
    pub chassis: ChassisConfig,
    pub kinematics: KinematicsConfig,
    /// `T_L^B`: the LiDAR frame in the base frame.
    pub lidar_mount: MountConfig,
    pub limits: MotionLimits,
    pub safety: SafetyConfig,
    pub devices: Devices,
}

/// `[devices.*]`: each section is its driver's configuration type.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Devices {
    /// The SICK TiM551 on TCP (SOPAS).
    pub lidar: LidarConfig,
    /// The CAN bus and the CANopen master.
    pub can: BusConfig,
    /// The two TECO wheel drives (CiA 402).
    pub drives: DrivesConfig,
    /// The LPMS-B2 IMU on a serial port (LPBUS).
    pub imu: LpmsConfig,
}

impl ConfigFileType for RobotConfig {
    fn validate(&self) -> Result<(), Violation> {
        let d = &self.devices;
        d.lidar.validate("devices.lidar")?;
        d.can.validate("devices.can")?;
        d.drives.validate("devices.drives", &d.can, "devices.can")?;
        rule(
            d.drives.quick_stop_decel_mps2 >= self.limits.max_accel_mps2.get(),
            "devices.drives.quick_stop_decel_mps2",
            format!(
                "must be at least limits.max_accel_mps2: a quick stop must not brake more gently than normal driving \
                 ({} < {} m/s²)",
                d.drives.quick_stop_decel_mps2,
                self.limits.max_accel_mps2.get()
            ),
        )?;
        if let Some(stop) = self.safety.stop_decel_mps2 {
            rule(
                stop >= self.limits.max_accel_mps2,
                "safety.stop_decel_mps2",
                format!(
                    "must be at least limits.max_accel_mps2: a stop must not brake more gently than normal driving \
                     ({} < {} m/s²)",
                    stop.get(),
                    self.limits.max_accel_mps2.get()
                ),
            )?;
            rule(
                stop.get() <= d.drives.quick_stop_decel_mps2,
                "safety.stop_decel_mps2",
                format!(
                    "must not exceed devices.drives.quick_stop_decel_mps2: the e-stop brakes hardest ({} > {} m/s²)",
                    stop.get(),
                    d.drives.quick_stop_decel_mps2
                ),
            )?;
        }
        d.imu.validate("devices.imu")?;
        self.safety.validate("safety")
    }
}

impl RobotConfig {
    /// The differential-drive layer: the drives on this robot's wheels.
    #[must_use]
    pub fn diff_drive(&self) -> DiffDrive {
        DiffDrive::new(
            self.devices.drives.clone(),
            Geometry {
                wheel_radius_m: self.kinematics.wheel_radius_m.get(),
                track_width_m: self.kinematics.track_width_m.get(),
            },
        )
    }

    /// The deceleration of the safety layer's stops: `safety.stop_decel_mps2`, else the drives'
    /// quick stop.
    #[must_use]
    pub fn stop_decel_mps2(&self) -> f64 {
        self.safety.stop_decel_mps2.map_or(self.devices.drives.quick_stop_decel_mps2, |d| d.get())
    }

    /// The CANopen master's settings: the bus from `[devices.can]`, each drive's start-up from
    /// `[devices.drives]`; the drives' profile acceleration is the robot's acceleration limit, their
    /// profile deceleration the stop deceleration, so that they can follow the safety layer's stops
    /// (it ramps ordinary slowing-down at the acceleration limit itself). A target holds for the
    /// command timeout: if the safety layer stops sending (stalled, restarting), the master sends
    /// zero by itself.
    #[must_use]
    pub fn master(&self) -> MasterConfig {
        self.diff_drive().master_config(
            &self.devices.can,
            self.limits.max_accel_mps2.get(),
            self.stop_decel_mps2(),
            self.safety.command_timeout_ms.ms(),
        )
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used, reason = "tests")]

    use std::time::Duration;

    use amr_drivers::canopen::master::CommLossReaction;
    use amr_drivers::sopas::session::{DialectChoice, Profile};

    use super::*;
    use crate::config::{ConfigSource, load};

    fn robot_a() -> RobotConfig {
        let cfg = load(&ConfigSource::Embedded).unwrap();
        cfg.robots.into_iter().find(|r| r.id.as_str() == "robot-a").unwrap()
    }

    #[test]
    fn the_shipped_robot_file_is_what_each_driver_gets() {
        let c = robot_a();
        let l = &c.devices.lidar;
        assert_eq!((l.host.as_str(), l.port), ("192.168.0.1", 2112));
        assert_eq!((l.dialect, l.startup), (DialectChoice::Auto, Profile::Minimal));
        assert_eq!((l.reply_timeout, l.scan_timeout), (Duration::from_secs(1), Duration::from_millis(500)));
        assert_eq!(
            (l.reconnect.initial, l.reconnect.max),
            (Duration::from_millis(100), Duration::from_secs(5))
        );
        let i = &c.devices.imu;
        assert_eq!((i.path.as_str(), i.baud, i.stream_hz, i.imu_id), ("/dev/rfcomm0", 115_200, 100, 1));
        assert_eq!(i.data_timeout, Duration::from_millis(250));
        assert_eq!(i.validate("devices.imu"), Ok(()));
        let m = c.master();
        assert_eq!((m.can.master_node_id, m.can.sync_period_ms, m.enable_timeout_ms), (127, 20, 1000));
        assert_eq!(m.mode_confirm_attempts, 5);
        assert_eq!(m.drives.len(), 2);
        assert_eq!((m.drives[0].node_id, m.drives[1].node_id), (1, 2));
        assert_eq!(m.drives[0].comm_loss_reaction, CommLossReaction::QuickStop);
        assert_eq!((m.drives[0].heartbeat_producer_ms, m.drives[0].heartbeat_consumer_ms), (100, 300));
        // 0.05 m/s² at the wheel: 0.05 / 0.065 / 2π rev/s² at the wheel, ×20 at the motor, ×10000.
        let expect = (0.05 / 0.065 / std::f64::consts::TAU * 20.0 * 10_000.0).round() as u32;
        assert_eq!(m.drives[0].profile_acceleration, expect);
        // The quick stop decelerates ten times harder than driving.
        assert_eq!(
            m.drives[0].quick_stop_deceleration,
            (0.5 / 0.065 / std::f64::consts::TAU * 20.0 * 10_000.0).round() as u32
        );
        // The right motor is mirrored: driving straight gives opposite signs.
        let [(_, left), (_, right)] = c.diff_drive().wheel_targets(0.1, 0.0);
        assert!(left > 0 && right == -left, "{left} {right}");
    }
}
