//! The drives' shaft speeds, read from their snapshots without holding the handles.

use amr_actors::config::RobotConfig;
use hil_mocks::teco_drive::{DriveHandle, DriveSnapshot};
use tokio::sync::watch;

#[derive(Debug, Clone)]
pub(crate) struct Snapshot {
    pub(crate) node: u8,
    pub(crate) rx: watch::Receiver<DriveSnapshot>,
}

impl Snapshot {
    pub(crate) fn of(h: &DriveHandle) -> Self {
        Snapshot { node: h.node_id, rx: h.snapshot.clone() }
    }
}

/// Wheel surface speeds (left, right), m/s.
pub(crate) fn wheel_speeds(robot: &RobotConfig, drives: &[Snapshot]) -> (f64, f64) {
    let d = &robot.devices.drives;
    let r = robot.kinematics.wheel_radius_m.get();
    let speed = |node: u8, inverted: bool| {
        let cps = drives.iter().find(|h| h.node == node).map_or(0.0, |h| h.rx.borrow().velocity_cps);
        let sign = if inverted { -1.0 } else { 1.0 };
        sign * cps / f64::from(d.encoder_counts_per_rev) / d.gear_ratio * std::f64::consts::TAU * r
    };
    (speed(d.left.node_id, d.left.inverted), speed(d.right.node_id, d.right.inverted))
}
