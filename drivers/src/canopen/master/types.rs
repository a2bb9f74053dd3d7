//! What the master is configured with, and what it tells: each drive's setup, the bus's
//! configuration, a drive's phase and status, the master's events.

#[allow(clippy::wildcard_imports, reason = "the master's own types, beside it")]
use super::*;

/// Profile velocity mode (0x6060 value 3, python-canopen `OperationMode`).
pub const MODE_PROFILE_VELOCITY: i8 = 3;

/// What the master writes into one drive at start-up, and how it watches it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DriveSetup {
    /// The drive's node id.
    pub node_id: NodeId,
    /// The drive's heartbeat period, written to its 0x1017.
    pub heartbeat_producer_ms: u16,
    /// The master gives up on the drive after this long without a heartbeat.
    pub heartbeat_consumer_ms: u32,
    /// The drive's consumer time of the master's heartbeat, written to its 0x1016:01.
    pub master_consumer_ms: u16,
    /// Written to 0x6007.
    pub comm_loss_reaction: CommLossReaction,
    /// 0x6083, drive velocity units per second.
    pub profile_acceleration: u32,
    /// 0x6084, drive velocity units per second.
    pub profile_deceleration: u32,
    /// 0x6085, drive velocity units per second.
    pub quick_stop_deceleration: u32,
    /// Map the digital inputs (0x60FD) into TPDO2 and report their changes
    /// ([`MasterEvent::Inputs`]): an e-stop chain is wired to the drive.
    pub digital_inputs: bool,
}

/// Everything the master needs.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MasterConfig {
    /// Bus settings (`[devices.can]`); the master uses its node id and periods.
    pub can: BusConfig,
    /// The drives.
    pub drives: Vec<DriveSetup>,
    /// Time for a drive to reach Operation enabled, and for a fault reset to be confirmed.
    pub enable_timeout_ms: u32,
    /// Reads of 0x6061 before giving up on the mode (python-canopen #131: it may lag).
    pub mode_confirm_attempts: u32,
    /// A target applies for this long after it was set ([`Master::set_targets`]); then every
    /// target goes out as zero until the next set ([`MasterEvent::TargetsExpired`]). Defence below
    /// the robot's safety layer: a controller that stalls or restarts cannot leave the wheels
    /// turning. On a robot: its command timeout.
    pub target_hold_ms: u32,
}

/// Where a drive is in its life cycle, as the master sees it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Phase {
    /// Reset sent, waiting for its boot-up.
    WaitingBoot,
    /// Being configured by SDO (PRE-OPERATIONAL).
    Configuring,
    /// Configured and started: PDOs flow. (A drive whose heartbeat stops is reported and reset,
    /// so it goes back to `WaitingBoot`.)
    Operational,
}

/// A snapshot of one drive.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DriveStatus {
    /// Life-cycle phase.
    pub phase: Phase,
    /// Last CiA 402 state from the statusword.
    pub state: Option<State402>,
    /// Last statusword.
    pub statusword: u16,
    /// Last velocity actual (drive units).
    pub velocity_actual: i32,
    /// Last position actual (counts).
    pub position_actual: Option<i32>,
    /// Target velocity set by the user (drive units); sent only while every drive is enabled.
    pub target_velocity: i32,
    /// Times this drive was configured since the master started.
    pub configurations: u32,
}

/// What the master reports.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum MasterEvent {
    /// A drive sent its boot-up (first start or a reset): it is reconfigured before enabling.
    BootUp {
        /// The node.
        node: NodeId,
    },
    /// A drive finished its start-up configuration and was started (NMT OPERATIONAL).
    Configured {
        /// The node.
        node: NodeId,
        /// Its device type 0x1000 (0x00020192 for a CiA 402 servo drive).
        device_type: u32,
    },
    /// The CiA 402 state of a drive changed.
    StateChanged {
        /// The node.
        node: NodeId,
        /// The new state.
        state: State402,
    },
    /// A drive's digital inputs (0x60FD) changed, or were read for the first time since it was
    /// configured (only for drives set up with `digital_inputs`).
    Inputs {
        /// The node.
        node: NodeId,
        /// 0x60FD.
        bits: u32,
    },
    /// A drive reached Operation enabled (the enable sequence confirmed).
    Enabled {
        /// The node.
        node: NodeId,
    },
    /// A fault reset was confirmed: the drive left Fault.
    Recovered {
        /// The node.
        node: NodeId,
    },
    /// An EMCY with code 0x0000: the drive's errors were reset (not an error).
    EmcyReset {
        /// The node.
        node: NodeId,
    },
    /// A SYNC was sent; the positions received since the previous one (for odometry), and the
    /// digital inputs as last read (their level every cycle: a lost [`MasterEvent::Inputs`]
    /// cannot hide a pressed e-stop).
    Cycle {
        /// (node, position actual) of each drive whose TPDO2 arrived.
        positions: Vec<(NodeId, i32)>,
        /// (node, 0x60FD) of each operational drive whose inputs are watched and known.
        inputs: Vec<(NodeId, u32)>,
    },
    /// No target was set for [`MasterConfig::target_hold_ms`]: every target is zero from this
    /// cycle on, until the next [`Master::set_targets`].
    TargetsExpired,
    /// Events were dropped on their way to the user (its queue was full): what the drives did
    /// meanwhile is unknown (from the shell, not the master).
    EventsLost {
        /// How many.
        count: u64,
    },
    /// A user SDO request finished.
    SdoDone {
        /// The id returned when it was queued.
        id: u64,
        /// The node.
        node: NodeId,
        /// The outcome.
        result: Result<SdoResult, CanopenError>,
    },
    /// An error of a drive or of the link.
    Error(CanopenError),
    /// The CAN controller reported an error frame that did not end the connection (from the
    /// transport, not the master: SocketCAN error frames).
    BusError {
        /// The SocketCAN error class bits.
        class: u32,
        /// The controller's error state, when the frame gives it.
        state: Option<crate::canopen::error::BusState>,
    },
}
