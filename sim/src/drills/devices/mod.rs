//! Drills on one robot and its devices: its supervision tree (`supervision`), the device links
//! (`links`), the drives (`drives`) and its stops (`stops`). The helpers they share are here.

use std::time::Duration;

use amr_actors::config::Config;
use amr_actors::robot::canbus::CanBusMsg;
use amr_actors::robot::lidar::LidarMsg;
use amr_actors::supervisor::{EventKind, SupervisorMsg};
use amr_drivers::canopen::cia402::State402;
use amr_msgs::{Command, Device, DisarmReason, Downlink, Health, SafetyState, Uplink};
use hil_mocks::teco_drive::Fault as DriveFault;
use hil_mocks::tim551::Fault as LidarFault;
use ractor::ActorRef;

use super::{
    Check, all_ok, child, drive, drive_from, events_from, health, keep_counters, rig, rig_on, rig_with,
    wheels_still, wheels_turning,
};
use crate::{RobotRig, SimCan};
use amr_actors::robot::RobotOptions;

mod drives;
mod links;
mod stops;
mod supervision;

pub(crate) use drives::{
    drive_bus_off, drive_fault_moving, drive_heartbeat, drive_reboot, drive_reboot_moving, new_master_moving,
};
pub(crate) use links::{absent_at_start, bad_data, can_link_reset, imu_unplug, lidar_reset, lidar_stall};
pub(crate) use stops::{
    command_burst, estop, estop_during_restart, estop_input, estop_restart, robot_freeze, safety_crash_moving,
};
pub(crate) use supervision::{can_bus_restart, fail_forever, lidar_panic};

fn kinds(rig: &RobotRig, supervisor: &str, from: usize) -> Vec<EventKind> {
    rig.tree
        .events
        .snapshot()
        .iter()
        .skip(from)
        .filter(|e| e.supervisor == supervisor)
        .map(|e| e.kind.clone())
        .collect()
}

fn started(rig: &RobotRig, supervisor: &str, child: &str, from: usize) -> bool {
    kinds(rig, supervisor, from).iter().any(|k| *k == EventKind::Started { child: child.into() })
}

fn targets_zero(rig: &RobotRig) -> bool {
    rig.mocks.drives.iter().all(|d| d.now().target_velocity == 0)
}

/// Every drive either commanded to zero or out of Operation enabled (a deaf drive stops by its own
/// communication-loss reaction, 0x6007).
fn drives_safe(rig: &RobotRig) -> bool {
    rig.mocks.drives.iter().all(|d| {
        let s = d.now();
        s.target_velocity == 0 || s.state != State402::OperationEnabled
    })
}

/// Arm the robot and drive it at `v_mps` until its wheels turn; the feed stops when dropped.
async fn drive_until_turning(rig: &RobotRig, v_mps: f64, c: &mut Check) -> Option<crate::AbortOnDrop<()>> {
    let feed = drive(rig, v_mps);
    c.within("the wheels turning", Duration::from_secs(10), || wheels_turning(rig, 1000.0)).await?;
    Some(feed)
}

/// The end of a drill in which nothing may restart: no supervision event after `n0`; keep the
/// counters; shut the robot down.
async fn end_without_restarts(rig: RobotRig, c: &mut Check, n0: usize) {
    c.eq("supervision events (no restart)", events_from(&rig, n0), vec![]);
    wrap_up(rig, c, n0).await;
}

/// The end of a drill: keep the supervision events after `n0` and the counters; shut the robot
/// down.
async fn wrap_up(rig: RobotRig, c: &mut Check, n0: usize) {
    c.events = events_from(&rig, n0);
    keep_counters(&rig, c);
    rig.tree.shutdown().await;
}

/// After a halt, the server goes on commanding (`feed`): for `hold` every target stays zero, the
/// robot is not armed and the commands are refused; then a new arm, numbered past everything sent,
/// drives it at `v_mps` again (the drill's recovery time).
async fn refused_until_rearmed(
    rig: &RobotRig,
    c: &mut Check,
    feed: crate::AbortOnDrop<()>,
    hold: Duration,
    v_mps: f64,
) {
    let refused_before = rig.tree.counters.get("safety.refused.not_armed");
    c.throughout("still commanded: every target zero, the robot not armed", hold, || {
        targets_zero(rig) && *rig.tree.ports.safety_now.borrow() != Some(SafetyState::Armed)
    })
    .await;
    c.that(
        rig.tree.counters.get("safety.refused.not_armed") > refused_before,
        "the commands that went on were refused (not armed)",
    );
    drop(feed);
    let _feed = drive_from(rig, v_mps, 100_000);
    c.recovery = c
        .within("turning again after a new arm", Duration::from_secs(10), || wheels_turning(rig, 1000.0))
        .await;
}
