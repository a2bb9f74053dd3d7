//! From the validated configuration (amr-core) to each driver's settings (amr-drivers, which does
//! not depend on core). One function per device; every key of `[devices.*]` lands somewhere.

use std::time::Duration;

use amr_core::config::{
    CommLossReaction as CfgReaction, ImuDataMode, LidarDialect, LidarStartup, RobotConfig,
};
use amr_core::scan::Scan;
use amr_drivers::canopen::diff_drive::{DiffDrive, DrivesConfig, Geometry, WheelDriveConfig};
use amr_drivers::canopen::master::{CanConfig, CommLossReaction, MasterConfig};
use amr_drivers::lpms::data::DataMode;
use amr_drivers::lpms::serial::LpmsConfig;
use amr_drivers::sopas::framing::Dialect;
use amr_drivers::sopas::session::{DialectChoice, Mode, Profile};
use amr_drivers::sopas::tcp::LidarConfig;

/// The TiM551's measuring range (devices.md §1: 0.05–10 m).
pub(crate) const TIM551_RANGE_M: (f64, f64) = (0.05, 10.0);

/// `[devices.lidar]` → the SOPAS TCP shell.
#[must_use]
pub fn lidar(c: &RobotConfig) -> LidarConfig {
    let l = &c.devices.lidar;
    LidarConfig {
        host: l.host.clone(),
        port: l.port,
        dialect: match l.dialect {
            LidarDialect::Auto => DialectChoice::Auto,
            LidarDialect::A => DialectChoice::Fixed(Dialect::ColaA),
            LidarDialect::B => DialectChoice::Fixed(Dialect::ColaB),
        },
        profile: match l.startup {
            LidarStartup::Minimal => Profile::Minimal,
            LidarStartup::Full => Profile::Full,
        },
        mode: Mode::Streaming,
        reply_timeout: l.reply_timeout_ms.duration(),
        scan_timeout: l.scan_timeout_ms.duration(),
        backoff_initial: l.reconnect.initial_ms.duration(),
        backoff_max: l.reconnect.max_ms.duration(),
        connect_timeout: Duration::from_secs(5),
    }
}

/// `[devices.imu]` → the LPBUS serial shell.
#[must_use]
pub fn imu(c: &RobotConfig) -> LpmsConfig {
    let i = &c.devices.imu;
    LpmsConfig {
        path: i.path.clone(),
        baud: i.baud,
        stream_hz: i.stream_hz,
        imu_id: i.imu_id,
        data_mode: match i.data_mode {
            ImuDataMode::Float => DataMode::Float32,
            ImuDataMode::Int16 => DataMode::Int16,
        },
        reply_timeout: i.reply_timeout_ms.duration(),
        data_timeout: i.data_timeout_ms.duration(),
        backoff_initial: i.reconnect.initial_ms.duration(),
        backoff_max: i.reconnect.max_ms.duration(),
        ..LpmsConfig::default()
    }
}

/// `[devices.drives]` + `[kinematics]` → the differential-drive layer.
#[must_use]
pub(crate) fn diff_drive(c: &RobotConfig) -> DiffDrive {
    let d = &c.devices.drives;
    let wheel = |w: &amr_core::config::DriveConfig| WheelDriveConfig {
        node_id: w.node_id.get(),
        inverted: w.inverted,
    };
    DiffDrive::new(
        DrivesConfig {
            left: wheel(&d.left),
            right: wheel(&d.right),
            encoder_counts_per_rev: d.encoder_counts_per_rev.get(),
            gear_ratio: d.gear_ratio.get(),
            velocity_units_per_rps: d.velocity_units_per_rps.get(),
            heartbeat_producer_ms: u16::try_from(d.heartbeat_producer_ms.ms()).unwrap_or(u16::MAX),
            heartbeat_consumer_ms: d.heartbeat_consumer_ms.ms(),
            master_consumer_ms: u16::try_from(d.master_consumer_ms.ms()).unwrap_or(u16::MAX),
            comm_loss_reaction: match d.comm_loss_reaction {
                CfgReaction::Fault => CommLossReaction::Fault,
                CfgReaction::DisableVoltage => CommLossReaction::DisableVoltage,
                CfgReaction::QuickStop => CommLossReaction::QuickStop,
            },
        },
        Geometry {
            wheel_radius_m: c.kinematics.wheel_radius_m.get(),
            track_width_m: c.kinematics.track_width_m.get(),
        },
    )
}

/// `[devices.can]` + `[devices.drives]` + `[limits]` → the CANopen master. The drives' profile
/// ramps come from the robot's acceleration limit, their quick stop from `quick_stop_decel_mps2`.
#[must_use]
pub fn master(c: &RobotConfig) -> MasterConfig {
    let can = &c.devices.can;
    let d = &c.devices.drives;
    MasterConfig {
        can: CanConfig {
            master_node_id: can.master_node_id.get(),
            master_heartbeat_ms: can.master_heartbeat_ms.ms(),
            sync_period_ms: can.sync_period_ms.ms(),
            sdo_timeout_ms: can.sdo_timeout_ms.ms(),
            boot_timeout_ms: can.boot_timeout_ms.ms(),
        },
        drives: diff_drive(c).drive_setups(c.limits.max_accel_mps2.get(), d.quick_stop_decel_mps2.get()),
        enable_timeout_ms: d.enable_timeout_ms.ms(),
        mode_confirm_attempts: d.mode_confirm_attempts.get(),
    }
}

/// A decoded TiM551 scan in the robot's units: ranges of 0 (no return) or outside the measuring
/// range become NaN (invalid beam).
#[must_use]
pub fn scan(s: &amr_drivers::sopas::scan::Scan) -> Scan {
    let (lo, hi) = TIM551_RANGE_M;
    let ranges = s
        .ranges_m
        .iter()
        .map(|r| {
            let r = f64::from(*r);
            if r.is_finite() && (lo..=hi).contains(&r) { r } else { f64::NAN }
        })
        .collect();
    Scan::new(s.angle_min_rad, s.angle_increment_rad, lo, hi, ranges)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used, reason = "tests")]

    use super::*;
    use crate::config::{ConfigSource, load};

    fn robot_a() -> RobotConfig {
        let cfg = load(&ConfigSource::Embedded).unwrap();
        cfg.robots.into_iter().find(|r| r.id.as_str() == "robot-a").unwrap()
    }

    #[test]
    fn shipped_robot_maps_onto_every_driver() {
        let c = robot_a();
        let l = lidar(&c);
        assert_eq!((l.host.as_str(), l.port), ("192.168.0.1", 2112));
        assert_eq!((l.dialect, l.profile), (DialectChoice::Auto, Profile::Minimal));
        assert_eq!((l.reply_timeout, l.scan_timeout), (Duration::from_secs(1), Duration::from_millis(500)));
        assert_eq!((l.backoff_initial, l.backoff_max), (Duration::from_millis(100), Duration::from_secs(5)));
        let i = imu(&c);
        assert_eq!((i.path.as_str(), i.baud, i.stream_hz, i.imu_id), ("/dev/rfcomm0", 115_200, 100, 1));
        assert_eq!(i.data_timeout, Duration::from_millis(250));
        assert_eq!(i.validate(), Ok(()));
        let m = master(&c);
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
        let [(_, left), (_, right)] = diff_drive(&c).wheel_targets(0.1, 0.0);
        assert!(left > 0 && right == -left, "{left} {right}");
    }

    #[test]
    fn zero_and_out_of_range_beams_become_invalid() {
        let s = amr_drivers::sopas::scan::Scan {
            serial: 0,
            device_status: [0; 2],
            telegram_counter: 0,
            scan_counter: 0,
            generation_tick_us: 0,
            transmission_tick_us: 0,
            scan_frequency_hz: 15.0,
            measurement_frequency_hz: 0.0,
            angle_min_rad: -1.0,
            angle_increment_rad: 0.5,
            angles_rad: vec![-1.0, -0.5, 0.0, 0.5],
            ranges_m: vec![0.0, 2.0, 12.0, f32::NAN],
            rssi: None,
        };
        let out = scan(&s);
        assert_eq!(out.len(), 4);
        let r = out.ranges_m();
        assert!(r[0].is_nan() && r[2].is_nan() && r[3].is_nan());
        assert_eq!(r[1], 2.0);
        assert_eq!((out.angle_min_rad, out.angle_increment_rad), (-1.0, 0.5));
    }
}
