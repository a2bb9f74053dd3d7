//! What crosses the link between a robot and the server, and what the actors tell each other about
//! their health. Every link message names its robot and carries a sequence number and stamps
//! (issue 9 §5), so the server can gate by time and a robot can refuse stale commands.
//!
//! Stamps are seconds on the fleet clock ([`crate::clock::FleetClock`]): one process shares one
//! epoch; across processes it is the hosts' synchronised wall clock.

use std::sync::Arc;

use amr_core::scan::Scan;
use amr_core::se2::Se2;

/// Device or service whose health is reported.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Device {
    Lidar,
    CanBus,
    Drives,
    Imu,
    Odometry,
    Safety,
    Link,
}

/// Health of one device actor (ARCHITECTURE.md).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Health {
    /// Connecting or configuring.
    Starting,
    /// Working.
    Ok,
    /// Working with reduced quality (e.g. odometry without the gyro), or retrying after a loss.
    Degraded,
    /// No data: the link is down and being re-established.
    Lost,
    /// Latched failure: needs an explicit reset or a restart.
    Fault,
}

/// A health change, as published on the robot's health port and sent up the link.
#[derive(Debug, Clone, PartialEq)]
pub struct HealthReport {
    pub device: Device,
    pub health: Health,
    /// Why, for people: the error or the state that caused it.
    pub detail: String,
}

/// A scan with the robot's odometry at its stamp.
#[derive(Debug, Clone)]
pub struct ScanMsg {
    pub robot: String,
    pub seq: u64,
    /// When the scan was taken (the device clock mapped to the fleet clock).
    pub stamp_s: f64,
    /// When the robot sent it.
    pub sent_s: f64,
    pub scan: Arc<Scan>,
    /// The robot's wheel/gyro odometry pose at `stamp_s`, in its odometry frame.
    pub odom: Se2,
}

/// Odometry of one robot.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OdomMsg {
    pub seq: u64,
    pub stamp_s: f64,
    /// Pose in the robot's odometry frame.
    pub pose: Se2,
    /// Body twist `(v, ω)`.
    pub twist: (f64, f64),
    /// The heading came from the gyro (false: from the wheels, the IMU being unavailable).
    pub gyro: bool,
}

/// Robot → server.
#[derive(Debug, Clone)]
pub enum Uplink {
    Scan(ScanMsg),
    Odom {
        robot: String,
        msg: OdomMsg,
    },
    Health {
        robot: String,
        seq: u64,
        stamp_s: f64,
        report: HealthReport,
    },
    /// The robot's safety state changed (armed, disarmed by the watchdog, e-stop, fault).
    Safety {
        robot: String,
        seq: u64,
        stamp_s: f64,
        state: SafetyState,
    },
}

impl Uplink {
    /// The robot the message is from.
    #[must_use]
    pub fn robot(&self) -> &str {
        match self {
            Uplink::Scan(m) => &m.robot,
            Uplink::Odom { robot, .. } | Uplink::Health { robot, .. } | Uplink::Safety { robot, .. } => robot,
        }
    }
}

/// A velocity command for one robot.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Command {
    /// Increases with every command the server sends this robot.
    pub seq: u64,
    /// When the server computed it.
    pub stamp_s: f64,
    pub v_mps: f64,
    pub w_radps: f64,
}

/// Server → robot.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Downlink {
    Command(Command),
    /// Accept commands again after the watchdog, a start-up or an e-stop reset disarmed the robot.
    /// Carries the sequence number of the first command it allows: anything older stays refused.
    Arm {
        seq: u64,
    },
    /// Stop and refuse commands until armed again.
    Disarm,
}

/// The robot's safety layer state.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum SafetyState {
    /// Not accepting commands: wheels held at zero. Needs an [`Downlink::Arm`].
    Disarmed(DisarmReason),
    /// Following commands, within the limits.
    Armed,
    /// Emergency stop latched: quick stop, refuses everything until an explicit reset.
    EStop,
    /// A supervisor escalated: the robot is stopped and stays so until restarted.
    Fault,
}

/// Why the robot is disarmed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum DisarmReason {
    /// Never armed since start.
    Startup,
    /// No fresh command within the command timeout.
    Watchdog,
    /// The server asked.
    Requested,
    /// The e-stop was reset.
    EStopReset,
    /// The drives or their bus were lost: they stopped (the master zeroes every target, a deaf
    /// drive quick-stops by itself), so the output is zero too.
    DeviceLost,
}
