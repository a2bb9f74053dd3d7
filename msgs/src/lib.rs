//! `amr-msgs`: the fleet's one message vocabulary. Every message that crosses an actor, network or
//! recording boundary is defined here once, with serde: the robot's uplink ([`Uplink`]), the
//! server's downlink ([`Downlink`]) and what the server makes of them (fused frames, estimates,
//! fusion status, particle clouds, its status for operators). The network link (`amr-net`,
//! postcard) and the recordings (`amr-record`, JSON) encode these very types, under
//! [`SCHEMA_VERSION`]; there are no mirrors to keep in step.
//!
//! Stamps are seconds on the fleet clock: one process shares one epoch; across processes it is the
//! hosts' synchronised wall clock.

use std::fmt;
use std::sync::Arc;

pub use amr_core::amcl::IntegrityState;
use amr_core::config::Configuration;
use amr_core::scan::Scan;
use amr_core::se2::Se2;
use serde::{Deserialize, Serialize};

/// The version of these types' encoding, on the network and in recordings. Any change to a type
/// here that changes its encoding must bump it (a test pins the encoding of a sample of every
/// message: it fails on such a change and says so).
pub const SCHEMA_VERSION: u16 = 8;

/// Most beams in a scan the fleet accepts (on the wire and at the server): far above any 2D LiDAR
/// a robot of ours could carry (a TiM551 has 271, the densest common scanners a few thousand).
pub const MAX_BEAMS: usize = 4096;

/// Device or service whose health is reported.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Device {
    Lidar,
    CanBus,
    Drives,
    Imu,
    Odometry,
    Safety,
    Link,
}

/// Health of one device actor.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
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
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HealthReport {
    pub device: Device,
    pub health: Health,
    /// Why, for people: the error or the state that caused it.
    pub detail: String,
}

/// A scan as it leaves the LiDAR actor and reaches the server: the one scan type between the
/// driver and AMCL.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ScanMsg {
    pub robot: String,
    /// Counts the robot's scans.
    pub seq: u64,
    /// When the scan was taken (the device clock mapped to the fleet clock).
    pub stamp_s: f64,
    /// When the robot received it from the device.
    pub received_s: f64,
    pub scan: Arc<Scan>,
    /// The robot's wheel/gyro odometry pose at `stamp_s`, in its odometry frame: filled in by the
    /// uplink (a scan goes up only with it); `None` on the robot before that.
    pub odom: Option<Se2>,
    /// Which odometry frame `odom` is in ([`OdomMsg::frame`]; 0 while `odom` is `None`).
    pub odom_frame: u64,
}

/// Odometry of one robot.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct OdomMsg {
    pub seq: u64,
    /// The odometry frame: a new number whenever the robot's odometry starts again at the origin
    /// (the odometry actor or the whole robot restarted), so that a receiver never mixes poses of
    /// two frames; `seq` starts again with it.
    pub frame: u64,
    pub stamp_s: f64,
    /// Pose in the robot's odometry frame.
    pub pose: Se2,
    /// Body twist `(v, ω)`.
    pub twist: (f64, f64),
    /// The heading came from the gyro (false: from the wheels, the IMU being unavailable).
    pub gyro: bool,
}

/// Robot → server.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
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
    /// The robot's safety state changed (armed, disarmed by the watchdog, e-stop, fault), or
    /// its stop counter did.
    Safety {
        robot: String,
        seq: u64,
        stamp_s: f64,
        state: SafetyState,
        /// Counts the robot's stops (start-up, disarm of any cause, halt, e-stop, its reset,
        /// fault, its reset); kept across restarts. An arm must carry the current value.
        stops: u64,
        /// The robot drives mock devices (a simulated world), not hardware: a server arms such a
        /// formation by itself when told to (`--auto-arm`), a real one only when the operator says.
        mock: bool,
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

    /// The message's own stamp.
    #[must_use]
    pub fn stamp_s(&self) -> f64 {
        match self {
            Uplink::Scan(m) => m.stamp_s,
            Uplink::Odom { msg, .. } => msg.stamp_s,
            Uplink::Health { stamp_s, .. } | Uplink::Safety { stamp_s, .. } => *stamp_s,
        }
    }
}

/// A velocity command for one robot.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Command {
    /// Increases with every command the server sends this robot.
    pub seq: u64,
    /// When the server computed it.
    pub stamp_s: f64,
    pub v_mps: f64,
    pub w_radps: f64,
}

/// Server → robot.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Downlink {
    Command(Command),
    /// Accept commands again after the watchdog, a start-up or an e-stop reset disarmed the robot.
    /// Carries the sequence number of the first command it allows (anything older stays refused),
    /// the robot's stop counter the sender last heard ([`Uplink::Safety`]) and when it was sent:
    /// the robot takes it only if no stop happened since (the counters match; no clocks are
    /// compared) and its stamp is within the command timeout of the robot's clock, either way.
    Arm {
        seq: u64,
        stops: u64,
        stamp_s: f64,
    },
    /// Stop and refuse commands until armed again.
    Disarm,
    /// Emergency stop: the drives quick-stop at once and the robot latches `EStop` (it survives a
    /// restart of the safety layer) until a [`Downlink::ResetEStop`] or a local reset.
    EStop,
    /// Clear a latched e-stop: the robot is disarmed until armed again.
    ResetEStop,
}

/// The robot's safety layer state.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SafetyState {
    /// Not accepting commands: wheels held at zero. Needs an [`Downlink::Arm`].
    Disarmed(DisarmReason),
    /// Following commands, within the limits.
    Armed,
    /// Emergency stop latched: quick stop, refuses everything until an explicit reset.
    EStop,
    /// A supervisor escalated: the robot is stopped and stays so, across restarts, until a
    /// reset on the robot itself.
    Fault,
}

/// Why the robot is disarmed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
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
    /// The safety layer's inbox overflowed (it stopped keeping up): halted, since an input was
    /// refused.
    QueueFull,
    /// A latched fault was reset on the robot.
    FaultReset,
}

/// Times of one fused update's stages, seconds (the paper's Table 4 rows). Wall-clock
/// measurements, not results: recordings leave them out.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct StageTimes {
    /// From the oldest scan's stamp to passing the sync gate.
    pub acquisition_sync_s: f64,
    pub preprocess_s: f64,
    pub tracking_s: f64,
    pub heading_s: f64,
    pub virtual_scan_s: f64,
    /// AMCL's update; `None` when the filter skipped it (moved less than `update_min_d`/`update_min_a`).
    pub amcl_s: Option<f64>,
    /// From the oldest scan's stamp to the published estimate.
    pub end_to_end_s: f64,
}

/// One fused measurement of the Virtual-AMR pipeline.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FusedFrame {
    pub seq: u64,
    pub configuration: Configuration,
    /// The reference robot's scan stamp.
    pub stamp_s: f64,
    /// The oldest stamp of the set (latency is counted from it).
    pub oldest_stamp_s: f64,
    /// V's pose in the reference robot's odometry frame at `stamp_s`.
    pub v_odom: Se2,
    /// The virtual scan's points in V's frame (T2–T4); `None` for T1.
    pub points: Option<Arc<Vec<[f64; 2]>>>,
    /// Per robot: its base in V, and its odometry pose at its scan.
    pub robots: Vec<(Se2, Se2)>,
    pub times: StageTimes,
}

/// Where one estimate came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EstimateSource {
    /// AMCL on the virtual scan (T2–T4), or V from the reference robot's own AMCL (T1).
    Fused(Configuration),
    /// One robot's own AMCL (the per-robot filters; the fallback when fusion is impossible).
    Robot(usize),
}

/// A robot's pose in the map with the odometry pose it corresponds to, so it can be carried
/// forward with odometry.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Anchored {
    pub map: Se2,
    pub odom: Se2,
    pub stamp_s: f64,
}

/// A localisation result.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Estimate {
    pub source: EstimateSource,
    pub stamp_s: f64,
    /// V in the map (fused estimates only).
    pub v: Option<Se2>,
    /// Per robot (formation order), where this estimate places it.
    pub robots: Vec<Option<Anchored>>,
    /// How far it can be trusted.
    pub integrity: EstimateIntegrity,
    /// The filter's covariance of its pose (V's for a fused estimate, the robot's for its own):
    /// x, y (m²) and heading (rad²), from the particles of its heaviest cluster. What the spread
    /// of particles says, not whether they are right (that is `integrity`).
    #[serde(default)]
    pub covariance: Option<[[f64; 3]; 3]>,
}

/// How far an estimate can be trusted: its filter's own judgement (`amr_core::amcl::integrity`)
/// and, for fused estimates, the server's cross-check against the robots' own estimates.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct EstimateIntegrity {
    /// `Uncertain` until the filter has judged an update.
    pub state: IntegrityState,
    /// Share of the scan the map explains at the estimate, and where the sensor is tracked.
    pub explained: f64,
    pub level: f64,
    /// A robot whose own tracking estimate is farther from where this estimate places it than
    /// `server.toml`'s `[integrity]` bound (the first such robot, formation order).
    pub disagrees: Option<u32>,
    /// Another place explains the filter's scans about as well as the estimate (a rival the scans
    /// have not told apart yet): why a filter whose estimate explains its scan well is not tracking.
    #[serde(default)]
    pub ambiguous: bool,
}

impl EstimateIntegrity {
    /// From a filter's judgement (`None`: not judged yet, uncertain).
    #[must_use]
    pub fn of(i: Option<amr_core::amcl::Integrity>) -> Self {
        match i {
            Some(i) => EstimateIntegrity {
                state: i.state,
                explained: i.explained,
                level: i.level,
                disagrees: None,
                ambiguous: i.ambiguous,
            },
            None => EstimateIntegrity { state: IntegrityState::Uncertain, ..EstimateIntegrity::default() },
        }
    }

    /// Tracking, and no robot disagrees: the estimate may be driven on.
    #[must_use]
    pub fn verified(&self) -> bool {
        self.state == IntegrityState::Tracking && self.disagrees.is_none()
    }
}

/// The fusion's state as seen from outside.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FusionStatus {
    Fusing,
    /// Robot `i`'s scans stopped; the others are localised on their own.
    RobotLost(usize),
}

/// A filter's particles after an update that ran (for recording and the live view).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ParticleCloud {
    pub source: EstimateSource,
    pub stamp_s: f64,
    pub poses: Arc<Vec<Se2>>,
}

/// The formation as the server sees it, for operators (`fleet/server/status`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ServerStatus {
    /// `Waiting`, `Arming`, `Running`, `Holding`, `Stopped` or `Finished`, with the reason if any.
    pub phase: String,
    pub plan_s: f64,
    pub plan_len_s: f64,
    /// Robots whose liveliness token the server sees.
    pub alive: Vec<String>,
    /// The integrity of the latest fresh estimate of V (`None`: none fresh).
    pub integrity: Option<EstimateIntegrity>,
}

impl fmt::Display for Device {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Device::Lidar => "lidar",
            Device::CanBus => "can_bus",
            Device::Drives => "drives",
            Device::Imu => "imu",
            Device::Odometry => "odometry",
            Device::Safety => "safety",
            Device::Link => "link",
        })
    }
}

impl fmt::Display for Health {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Health::Starting => "starting",
            Health::Ok => "ok",
            Health::Degraded => "degraded",
            Health::Lost => "lost",
            Health::Fault => "fault",
        })
    }
}

impl fmt::Display for SafetyState {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            SafetyState::Armed => f.write_str("armed"),
            SafetyState::EStop => f.write_str("estop"),
            SafetyState::Fault => f.write_str("fault"),
            SafetyState::Disarmed(r) => write!(f, "disarmed:{r}"),
        }
    }
}

impl fmt::Display for DisarmReason {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            DisarmReason::Startup => "startup",
            DisarmReason::Watchdog => "watchdog",
            DisarmReason::Requested => "requested",
            DisarmReason::EStopReset => "estop_reset",
            DisarmReason::DeviceLost => "device_lost",
            DisarmReason::QueueFull => "queue_full",
            DisarmReason::FaultReset => "fault_reset",
        })
    }
}

impl fmt::Display for EstimateSource {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            EstimateSource::Fused(c) => write!(f, "fused:{c:?}"),
            EstimateSource::Robot(i) => write!(f, "robot:{i}"),
        }
    }
}

#[cfg(test)]
mod tests;
