//! The CANopen master for the wheel drives, sans-IO (frames in, frames and events out, `now`
//! passed in, as quinn-proto): NMT, the SYNC producer, its own heartbeat, a heartbeat consumer per
//! drive, an SDO client per drive, the start-up configuration (0x1017, 0x1016, 0x6007, profile
//! ramps, PDO remap, mode 3 confirmed on 0x6061) after every boot-up, and the CiA 402 walk with
//! the controlword in the synchronous RPDO1. Behaviour asked for by users of drive stacks (notes
//! B5): verified fault reset, master heartbeat consumed by the drives, configurable timeouts.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

pub use super::config::CommLossReaction;

use super::cia402::{Goal, State402, controlword, next_controlword};
use super::config::BusConfig;
use super::emcy::{EMCY_HEARTBEAT, Emcy};
use super::error::{CanopenError, DeviceError, LinkError};
use super::frame::{CanFrame, Cob, NodeId};
use super::heartbeat::{ConsumerState, HeartbeatConsumer, HeartbeatProducer};
use super::nmt::{NmtCommand, NmtState, sync_frame};
use super::pdo::{
    self, PdoDirection, RPDO1_MAP, TPDO1_MAP, TPDO2_INPUTS_MAP, TPDO2_MAP, TRANSMISSION_SYNC_EVERY,
    decode_tpdo1, decode_tpdo2,
};
use super::sdo::{ObjectAddr, SdoClient, SdoFailure, SdoRequest, SdoResult, SdoStep};

/// Retries of a configuration SDO request after a timeout, before the drive is reset.
const SDO_RETRIES: u32 = 2;

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

#[derive(Debug, Clone, PartialEq, Eq)]
enum JobKind {
    /// Part of the start-up: a failure restarts the drive.
    Config,
    /// Part of the start-up, allowed to fail (e.g. 0x1008 may not exist).
    Optional,
    /// Read 0x1000.
    DeviceType,
    /// Read 0x6061 until it shows profile velocity.
    ConfirmMode,
    /// Asked for by the user.
    User(u64),
}

#[derive(Debug, Clone, PartialEq, Eq)]
enum Job {
    Sdo(SdoRequest, JobKind),
    Nmt(NmtCommand),
    /// The configuration is complete.
    Finish,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Recovery {
    Idle,
    /// Send 0x0000 so bit 7 is low.
    Low,
    /// Send 0x0080: the rising edge.
    Edge,
    /// Keep 0x0080 until the state leaves Fault or the deadline passes.
    Wait(Instant),
}

#[derive(Debug)]
struct Drive {
    setup: DriveSetup,
    phase: Phase,
    sdo: SdoClient,
    jobs: VecDeque<Job>,
    current: Option<(JobKind, SdoRequest)>,
    /// Timeouts of the configuration request in flight so far.
    retries: u32,
    consumer: HeartbeatConsumer,
    boot_deadline: Option<Instant>,
    state: Option<State402>,
    statusword: u16,
    velocity_actual: i32,
    position: Option<i32>,
    position_fresh: bool,
    /// The last digital inputs reported (0x60FD), when watched.
    inputs: Option<u32>,
    target: i32,
    last_emcy_code: u16,
    recovery: Recovery,
    enable_deadline: Option<Instant>,
    device_type: u32,
    mode_reads: u32,
    configurations: u32,
}

/// The master.
#[derive(Debug)]
pub struct Master {
    config: MasterConfig,
    drives: Vec<Drive>,
    tx: VecDeque<CanFrame>,
    events: VecDeque<MasterEvent>,
    heartbeat: HeartbeatProducer,
    next_sync: Instant,
    goal: Goal,
    halt: bool,
    /// When the targets last set stop applying.
    targets_until: Option<Instant>,
    next_user_id: u64,
}

fn ms(v: u32) -> Duration {
    Duration::from_millis(u64::from(v))
}

impl Master {
    /// A master that resets every drive's communication at `now` and configures each on its boot-up.
    pub fn new(config: MasterConfig, now: Instant) -> Self {
        let sdo_timeout = ms(config.can.sdo_timeout_ms);
        let drives = config
            .drives
            .iter()
            .map(|s| Drive {
                setup: s.clone(),
                phase: Phase::WaitingBoot,
                sdo: SdoClient::new(s.node_id, sdo_timeout),
                jobs: VecDeque::new(),
                current: None,
                retries: 0,
                consumer: HeartbeatConsumer::new(ms(s.heartbeat_consumer_ms)),
                boot_deadline: None,
                state: None,
                statusword: 0,
                velocity_actual: 0,
                position: None,
                position_fresh: false,
                inputs: None,
                target: 0,
                last_emcy_code: 0,
                recovery: Recovery::Idle,
                enable_deadline: None,
                device_type: 0,
                mode_reads: 0,
                configurations: 0,
            })
            .collect();
        let mut m = Self {
            heartbeat: HeartbeatProducer::new(ms(config.can.master_heartbeat_ms), now),
            next_sync: now + ms(config.can.sync_period_ms.max(1)),
            config,
            drives,
            tx: VecDeque::new(),
            events: VecDeque::new(),
            goal: Goal::Disabled,
            halt: false,
            next_user_id: 0,
            targets_until: None,
        };
        for i in 0..m.drives.len() {
            m.reset_drive(i, now);
        }
        m
    }

    /// The next frame to put on the bus.
    pub fn poll_transmit(&mut self) -> Option<CanFrame> {
        self.tx.pop_front()
    }

    /// The next event.
    pub fn poll_event(&mut self) -> Option<MasterEvent> {
        self.events.pop_front()
    }

    /// A snapshot of drive `node`.
    pub fn drive_status(&self, node: NodeId) -> Option<DriveStatus> {
        self.drives.iter().find(|d| d.setup.node_id == node).map(|d| DriveStatus {
            phase: d.phase,
            state: d.state,
            statusword: d.statusword,
            velocity_actual: d.velocity_actual,
            position_actual: d.position,
            target_velocity: d.target,
            configurations: d.configurations,
        })
    }

    /// Walk every drive to Operation enabled (confirmed by [`MasterEvent::Enabled`]).
    pub fn enable(&mut self, now: Instant) {
        self.goal = Goal::Enabled;
        let t = ms(self.config.enable_timeout_ms);
        // Drives still booting or configuring get their deadline when configured; those enabled
        // already are confirmed again (the user may have lost the first confirmation).
        for d in &mut self.drives {
            if d.phase == Phase::Operational && d.state != Some(State402::OperationEnabled) {
                d.enable_deadline = Some(now + t);
            } else if d.phase == Phase::Operational {
                self.events.push_back(MasterEvent::Enabled { node: d.setup.node_id });
            }
        }
    }

    /// Disable voltage on every drive.
    pub fn disable(&mut self) {
        self.goal = Goal::Disabled;
        self.clear_deadlines();
    }

    /// Quick stop every drive (they stay in Quick stop active until enabled again).
    pub fn quick_stop(&mut self) {
        self.goal = Goal::QuickStop;
        self.clear_deadlines();
    }

    fn clear_deadlines(&mut self) {
        for d in &mut self.drives {
            d.enable_deadline = None;
        }
    }

    /// Set or clear the halt bit (profile velocity: ramp to zero, stay enabled).
    pub fn set_halt(&mut self, halt: bool) {
        self.halt = halt;
    }

    /// Target velocities in drive units, set at `now`; they go out together in the next cycle,
    /// before one SYNC, while every drive is enabled, and for at most
    /// [`MasterConfig::target_hold_ms`]. A fault, a lost heartbeat or a boot-up of any drive sets
    /// every target to zero: motion needs a fresh command afterwards.
    pub fn set_targets(&mut self, now: Instant, targets: &[(NodeId, i32)]) {
        self.targets_until = Some(now + ms(self.config.target_hold_ms));
        for (node, v) in targets {
            if let Some(d) = self.drives.iter_mut().find(|d| d.setup.node_id == *node) {
                d.target = *v;
            }
        }
    }

    /// Start the verified fault reset of `node`: 0x0000, then 0x0080 (rising edge), then wait until
    /// the statusword has left Fault ([`MasterEvent::Recovered`]) or report
    /// [`DeviceError::FaultResetFailed`] after the enable timeout.
    pub fn recover(&mut self, node: NodeId) {
        if let Some(d) = self.drives.iter_mut().find(|d| d.setup.node_id == node)
            && d.state.is_some_and(State402::is_fault)
        {
            d.recovery = Recovery::Low;
        }
    }

    /// Queue an SDO request to `node`; the result comes as [`MasterEvent::SdoDone`] with the id.
    pub fn sdo(&mut self, now: Instant, node: NodeId, req: SdoRequest) -> Option<u64> {
        let i = self.drives.iter().position(|d| d.setup.node_id == node)?;
        let id = self.next_user_id;
        self.next_user_id += 1;
        self.drives[i].jobs.push_back(Job::Sdo(req, JobKind::User(id)));
        self.pump(i, now);
        Some(id)
    }

    /// The earliest time [`Master::handle_timeout`] has something to do.
    pub fn poll_timeout(&self) -> Option<Instant> {
        let mut t = Some(self.next_sync);
        let mut add = |x: Option<Instant>| {
            if let Some(x) = x {
                t = Some(t.map_or(x, |t: Instant| t.min(x)));
            }
        };
        add(self.heartbeat.poll_timeout());
        for d in &self.drives {
            add(d.consumer.poll_timeout());
            add(d.sdo.poll_timeout());
            add(d.boot_deadline);
            add(d.enable_deadline);
            if let Recovery::Wait(x) = d.recovery {
                add(Some(x));
            }
        }
        t
    }

    /// Do what is due at `now`: heartbeat, SYNC cycle, timeouts.
    pub fn handle_timeout(&mut self, now: Instant) {
        if self.heartbeat.due(now) {
            self.tx.push_back(NmtState::Operational.heartbeat(self.config.can.master_node_id));
        }
        for i in 0..self.drives.len() {
            let node = self.drives[i].setup.node_id;
            if self.drives[i].consumer.check(now) {
                tracing::warn!(node, "drive heartbeat lost");
                self.drives[i].sdo.cancel();
                self.drives[i].jobs.clear();
                self.drives[i].current = None;
                self.drives[i].enable_deadline = None;
                self.drives[i].recovery = Recovery::Idle;
                self.error(LinkError::HeartbeatLost { node }.into());
                self.zero_targets();
                // Any drive lost: every target is sent as zero (see `cycle`); ask it to restart.
                self.reset_drive(i, now);
            }
            if let Some(step) = self.drives[i].sdo.handle_timeout(now) {
                self.sdo_step(i, now, step);
            }
            if self.drives[i].boot_deadline.is_some_and(|t| now >= t) {
                tracing::warn!(node, "no boot-up");
                self.error(LinkError::BootTimeout { node }.into());
                self.reset_drive(i, now);
            }
            if self.drives[i].enable_deadline.is_some_and(|t| now >= t) {
                self.drives[i].enable_deadline = None;
                self.error(DeviceError::EnableTimeout { node }.into());
            }
            if let Recovery::Wait(t) = self.drives[i].recovery
                && now >= t
            {
                self.drives[i].recovery = Recovery::Idle;
                self.error(DeviceError::FaultResetFailed { node }.into());
            }
        }
        if now >= self.next_sync {
            self.cycle(now);
            let period = ms(self.config.can.sync_period_ms.max(1));
            self.next_sync += period;
            if self.next_sync <= now {
                self.next_sync = now + period;
            }
        }
    }

    /// Whether every drive is operational, enabled and not lost: only then are targets sent.
    fn zero_targets(&mut self) {
        for d in &mut self.drives {
            d.target = 0;
        }
    }

    fn all_enabled(&self) -> bool {
        self.drives
            .iter()
            .all(|d| d.phase == Phase::Operational && d.state == Some(State402::OperationEnabled))
    }

    /// One SYNC cycle: both RPDO1s (controlword + target), then one SYNC so both apply together.
    fn cycle(&mut self, now: Instant) {
        if self.targets_until.is_some_and(|t| now >= t) {
            self.targets_until = None;
            if self.drives.iter().any(|d| d.target != 0) {
                tracing::warn!(
                    hold_ms = self.config.target_hold_ms,
                    "no target set within the hold time: zero"
                );
                self.zero_targets();
                self.events.push_back(MasterEvent::TargetsExpired);
            }
        }
        let positions: Vec<(NodeId, i32)> = self
            .drives
            .iter_mut()
            .filter_map(|d| {
                if std::mem::take(&mut d.position_fresh) {
                    Some((d.setup.node_id, d.position?))
                } else {
                    None
                }
            })
            .collect();
        let inputs: Vec<(NodeId, u32)> = self
            .drives
            .iter()
            .filter(|d| d.phase == Phase::Operational)
            .filter_map(|d| Some((d.setup.node_id, d.inputs?)))
            .collect();
        if self.drives.iter().any(|d| d.phase == Phase::Operational) {
            self.events.push_back(MasterEvent::Cycle { positions, inputs });
        }
        let moving = self.all_enabled() && self.goal == Goal::Enabled;
        for d in &mut self.drives {
            if d.phase != Phase::Operational {
                continue;
            }
            let state = d.state.unwrap_or(State402::NotReadyToSwitchOn);
            let cw = match d.recovery {
                Recovery::Low => {
                    d.recovery = Recovery::Edge;
                    controlword::DISABLE_VOLTAGE
                }
                Recovery::Edge => {
                    d.recovery = Recovery::Wait(now + ms(self.config.enable_timeout_ms));
                    controlword::FAULT_RESET
                }
                Recovery::Wait(_) => controlword::FAULT_RESET,
                Recovery::Idle => {
                    let cw = next_controlword(state, self.goal);
                    if self.halt && cw == controlword::ENABLE_OPERATION { cw | controlword::HALT } else { cw }
                }
            };
            let target = if moving { d.target } else { 0 };
            self.tx.push_back(Cob::Rpdo(1, d.setup.node_id).frame(&pdo::encode_rpdo1(cw, target)));
        }
        if self.drives.iter().any(|d| d.phase == Phase::Operational) {
            self.tx.push_back(sync_frame());
        }
    }

    /// A frame from the bus at `now`.
    pub fn handle_frame(&mut self, now: Instant, frame: &CanFrame) {
        // What fell due before this frame is done first. After a stall (a frozen process, a
        // starved thread) frames have waited in the receive queue and are handled late: a drive's
        // heartbeat that waited there would otherwise count as heard at `now` and hide a consumer
        // time that ran out meanwhile (the shell's select takes ready branches in random order).
        if self.poll_timeout().is_some_and(|t| t <= now) {
            self.handle_timeout(now);
        }
        let cob = frame.cob();
        let node = match cob {
            Cob::Heartbeat(n) | Cob::SdoResponse(n) | Cob::Emcy(n) | Cob::Tpdo(_, n) => n,
            _ => return,
        };
        let Some(i) = self.drives.iter().position(|d| d.setup.node_id == node) else { return };
        match cob {
            Cob::Heartbeat(_) => match NmtState::decode(frame) {
                Some((_, NmtState::BootUp)) => self.on_boot(i, now),
                Some((_, state)) => {
                    let d = &mut self.drives[i];
                    if d.consumer.state() == ConsumerState::Waiting && d.phase == Phase::Operational {
                        tracing::debug!(node, ?state, "first heartbeat");
                    }
                    d.consumer.received(now);
                }
                None => {}
            },
            Cob::SdoResponse(_) => {
                if let Some(step) = self.drives[i].sdo.handle_response(now, frame.data()) {
                    self.sdo_step(i, now, step);
                }
            }
            Cob::Emcy(_) => {
                if let Some((_, emcy)) = Emcy::decode(frame) {
                    if emcy.is_reset() {
                        self.events.push_back(MasterEvent::EmcyReset { node });
                    } else {
                        self.drives[i].last_emcy_code = emcy.code;
                        if emcy.code == EMCY_HEARTBEAT {
                            // The drive lost our heartbeat and took its 0x6007 reaction (quick
                            // stop, disable or fault): what we last read of its state is stale.
                            // Unknown, it is walked from Switch on disabled and its next TPDO is
                            // reported as a change, instead of "Enable operation" taking it out
                            // of Quick stop active (transition 16) unseen.
                            self.drives[i].state = None;
                        }
                        tracing::warn!(node, code = emcy.code, class = emcy.class_name(), "EMCY");
                        self.error(
                            DeviceError::Emcy {
                                node,
                                code: emcy.code,
                                class: emcy.class_name(),
                                register: emcy.register,
                            }
                            .into(),
                        );
                    }
                }
            }
            // PDOs are valid only once the drive is started (CiA 301: none in PRE-OPERATIONAL).
            // One that arrives while the drive is reset or being configured was sent before the
            // reset: a stale "Operation enabled" must not re-enable a drive just found lost.
            Cob::Tpdo(..) if self.drives[i].phase != Phase::Operational => {}
            Cob::Tpdo(1, _) => {
                if let Some((sw, v)) = decode_tpdo1(frame.data()) {
                    self.on_status(i, now, sw, v);
                }
            }
            Cob::Tpdo(2, _) => {
                if let Some((p, inputs)) = decode_tpdo2(frame.data()) {
                    let d = &mut self.drives[i];
                    d.position = Some(p);
                    d.position_fresh = true;
                    if let Some(bits) = inputs.filter(|_| d.setup.digital_inputs)
                        && d.inputs != Some(bits)
                    {
                        d.inputs = Some(bits);
                        let node = d.setup.node_id;
                        self.events.push_back(MasterEvent::Inputs { node, bits });
                    }
                }
            }
            _ => {}
        }
    }

    fn on_status(&mut self, i: usize, now: Instant, sw: u16, velocity: i32) {
        let d = &mut self.drives[i];
        let node = d.setup.node_id;
        d.statusword = sw;
        d.velocity_actual = velocity;
        let Some(new) = State402::from_statusword(sw) else { return };
        let old = d.state.replace(new);
        if old == Some(new) {
            return;
        }
        self.events.push_back(MasterEvent::StateChanged { node, state: new });
        if old == Some(State402::OperationEnabled) || new == State402::OperationEnabled {
            // Leaving Operation enabled, and entering it again: the targets set before do not
            // apply; motion needs a target set after the drive is back.
            self.zero_targets();
        }
        let d = &mut self.drives[i];
        if new == State402::Fault {
            let error_code = d.last_emcy_code;
            self.error(DeviceError::Fault { node, error_code }.into());
            self.zero_targets();
            return;
        }
        if new.is_fault() {
            return;
        }
        match d.recovery {
            Recovery::Edge | Recovery::Wait(_) => {
                d.recovery = Recovery::Idle;
                d.last_emcy_code = 0;
                if self.goal == Goal::Enabled {
                    d.enable_deadline = Some(now + ms(self.config.enable_timeout_ms));
                }
                self.events.push_back(MasterEvent::Recovered { node });
            }
            Recovery::Low => d.recovery = Recovery::Idle,
            Recovery::Idle => {}
        }
        let d = &mut self.drives[i];
        if new == State402::OperationEnabled {
            d.enable_deadline = None;
            self.events.push_back(MasterEvent::Enabled { node });
        }
    }

    fn error(&mut self, e: CanopenError) {
        self.events.push_back(MasterEvent::Error(e));
    }

    /// Stop drive `i`, then send it a reset-communication and wait for its boot-up.
    ///
    /// Stop first: a reset of communication (CiA 301) leaves the drive's application running, in
    /// whatever state and at whatever target it had, and resets its watchdog of our heartbeat
    /// (0x1016) to off until it is configured again. So a quick stop (0x6040 = 0x0002) and a zero
    /// target (0x60FF = 0) go first, as expedited SDO writes, which a drive takes in
    /// PRE-OPERATIONAL and OPERATIONAL alike (PDOs only in the latter); their confirmations find
    /// no request in flight and are ignored.
    fn reset_drive(&mut self, i: usize, now: Instant) {
        let d = &mut self.drives[i];
        d.phase = Phase::WaitingBoot;
        d.state = None;
        d.enable_deadline = None;
        d.sdo.cancel();
        d.current = None;
        d.jobs.clear();
        d.boot_deadline = Some(now + ms(self.config.can.boot_timeout_ms));
        let node = d.setup.node_id;
        let stop = [
            (ObjectAddr::new(0x6040, 0), controlword::QUICK_STOP.to_le_bytes().to_vec()),
            (ObjectAddr::new(0x60FF, 0), 0i32.to_le_bytes().to_vec()),
        ];
        for (addr, data) in stop {
            if let Some(body) = super::sdo::expedited_download(addr, &data) {
                self.tx.push_back(Cob::SdoRequest(node).frame(&body));
            }
        }
        self.tx.push_back(NmtCommand::ResetCommunication.frame(node));
    }

    /// A boot-up: forget the drive's state and configure it again before it may be enabled.
    fn on_boot(&mut self, i: usize, now: Instant) {
        let node = self.drives[i].setup.node_id;
        tracing::info!(node, "boot-up: configuring");
        self.events.push_back(MasterEvent::BootUp { node });
        self.zero_targets();
        let jobs = self.config_jobs(i);
        let d = &mut self.drives[i];
        d.sdo.cancel();
        d.current = None;
        d.jobs = jobs;
        d.phase = Phase::Configuring;
        d.boot_deadline = None;
        d.state = None;
        d.position = None;
        d.position_fresh = false;
        d.inputs = None;
        d.recovery = Recovery::Idle;
        d.enable_deadline = None;
        d.mode_reads = 0;
        d.retries = 0;
        // Monitoring starts with the first heartbeat (CiA 301), which the drive sends only once
        // 0x1017 is written; a drive dying during configuration shows as SDO timeouts.
        d.consumer.reset(ms(d.setup.heartbeat_consumer_ms));
        self.pump(i, now);
    }

    fn config_jobs(&self, i: usize) -> VecDeque<Job> {
        let s = &self.drives[i].setup;
        let n = s.node_id;
        let w = |index: u16, sub: u8, data: Vec<u8>| {
            Job::Sdo(SdoRequest::Download(ObjectAddr::new(index, sub), data), JobKind::Config)
        };
        let mut jobs = VecDeque::new();
        jobs.push_back(Job::Nmt(NmtCommand::EnterPreOperational));
        jobs.push_back(Job::Sdo(SdoRequest::Upload(ObjectAddr::new(0x1000, 0)), JobKind::DeviceType));
        jobs.push_back(Job::Sdo(SdoRequest::Upload(ObjectAddr::new(0x1008, 0)), JobKind::Optional));
        jobs.push_back(w(0x1017, 0, s.heartbeat_producer_ms.to_le_bytes().to_vec()));
        let consumer = (u32::from(self.config.can.master_node_id) << 16) | u32::from(s.master_consumer_ms);
        jobs.push_back(w(0x1016, 1, consumer.to_le_bytes().to_vec()));
        jobs.push_back(w(0x6007, 0, s.comm_loss_reaction.code().to_le_bytes().to_vec()));
        jobs.push_back(w(0x6083, 0, s.profile_acceleration.to_le_bytes().to_vec()));
        jobs.push_back(w(0x6084, 0, s.profile_deceleration.to_le_bytes().to_vec()));
        jobs.push_back(w(0x6085, 0, s.quick_stop_deceleration.to_le_bytes().to_vec()));
        for (dir, k, map) in [
            (PdoDirection::Receive, 1, &RPDO1_MAP[..]),
            (PdoDirection::Transmit, 1, &TPDO1_MAP[..]),
            (
                PdoDirection::Transmit,
                2,
                if s.digital_inputs { &TPDO2_INPUTS_MAP[..] } else { &TPDO2_MAP[..] },
            ),
        ] {
            for req in pdo::remap_requests(dir, k, n, TRANSMISSION_SYNC_EVERY, map) {
                jobs.push_back(Job::Sdo(req, JobKind::Config));
            }
        }
        jobs.push_back(w(0x60FF, 0, 0i32.to_le_bytes().to_vec()));
        jobs.push_back(w(0x6060, 0, MODE_PROFILE_VELOCITY.to_le_bytes().to_vec()));
        jobs.push_back(Job::Sdo(SdoRequest::Upload(ObjectAddr::new(0x6061, 0)), JobKind::ConfirmMode));
        jobs.push_back(Job::Nmt(NmtCommand::Start));
        jobs.push_back(Job::Finish);
        jobs
    }

    /// Start queued jobs while the SDO client is free.
    fn pump(&mut self, i: usize, now: Instant) {
        // Bounded: every pass pops a job.
        while self.drives[i].sdo.is_idle() {
            let Some(job) = self.drives[i].jobs.pop_front() else { return };
            let node = self.drives[i].setup.node_id;
            match job {
                Job::Nmt(cmd) => self.tx.push_back(cmd.frame(node)),
                Job::Finish => {
                    let d = &mut self.drives[i];
                    d.phase = Phase::Operational;
                    d.configurations += 1;
                    if self.goal == Goal::Enabled {
                        d.enable_deadline = Some(now + ms(self.config.enable_timeout_ms));
                    }
                    let device_type = d.device_type;
                    tracing::info!(node, device_type, "drive configured");
                    self.events.push_back(MasterEvent::Configured { node, device_type });
                }
                Job::Sdo(req, kind) => {
                    let d = &mut self.drives[i];
                    let body = d.sdo.start(now, req.clone());
                    let frame = d.sdo.frame(body);
                    d.current = Some((kind, req));
                    self.tx.push_back(frame);
                }
            }
        }
    }

    fn sdo_step(&mut self, i: usize, now: Instant, step: SdoStep) {
        let node = self.drives[i].setup.node_id;
        let (result, abort) = match step {
            SdoStep::Send(body) => {
                let f = self.drives[i].sdo.frame(body);
                self.tx.push_back(f);
                return;
            }
            SdoStep::Done { result, abort } => (result, abort),
        };
        if let Some(body) = abort {
            let f = self.drives[i].sdo.frame(body);
            self.tx.push_back(f);
        }
        let Some((kind, req)) = self.drives[i].current.take() else { return };
        let addr = req.addr();
        let retry = matches!(kind, JobKind::Config | JobKind::DeviceType | JobKind::ConfirmMode)
            && result == Err(SdoFailure::Timeout)
            && self.drives[i].retries < SDO_RETRIES;
        if retry {
            // A lost frame costs one timeout, not a whole reconfiguration.
            tracing::debug!(node, %addr, "SDO timeout during configuration; retrying");
            let d = &mut self.drives[i];
            d.retries += 1;
            d.jobs.push_front(Job::Sdo(req, kind));
            self.pump(i, now);
            return;
        }
        self.drives[i].retries = 0;
        let to_error = |addr: ObjectAddr, f: SdoFailure| -> CanopenError {
            match f {
                SdoFailure::Aborted(code) => DeviceError::SdoAbort { node, addr, code }.into(),
                SdoFailure::Protocol(code) => LinkError::SdoProtocol { node, addr, code }.into(),
                SdoFailure::Timeout => LinkError::SdoTimeout { node, addr }.into(),
            }
        };
        match (kind, result) {
            (JobKind::User(id), result) => {
                let result = result.map_err(|f| to_error(addr, f));
                self.events.push_back(MasterEvent::SdoDone { id, node, result });
            }
            (JobKind::Optional, _) => {}
            (JobKind::DeviceType, Ok(SdoResult::Read(v))) => {
                let mut b = [0u8; 4];
                let n = v.len().min(4);
                b[..n].copy_from_slice(&v[..n]);
                self.drives[i].device_type = u32::from_le_bytes(b);
            }
            (JobKind::ConfirmMode, Ok(SdoResult::Read(v))) => {
                let displayed = v.first().map_or(0, |b| *b as i8);
                if displayed != MODE_PROFILE_VELOCITY {
                    let d = &mut self.drives[i];
                    d.mode_reads += 1;
                    if d.mode_reads < self.config.mode_confirm_attempts {
                        d.jobs.push_front(Job::Sdo(
                            SdoRequest::Upload(ObjectAddr::new(0x6061, 0)),
                            JobKind::ConfirmMode,
                        ));
                    } else {
                        self.error(
                            DeviceError::ModeNotConfirmed {
                                node,
                                requested: MODE_PROFILE_VELOCITY,
                                displayed,
                            }
                            .into(),
                        );
                        self.reset_drive(i, now);
                        return;
                    }
                }
            }
            (JobKind::Config | JobKind::DeviceType | JobKind::ConfirmMode, Ok(_)) => {}
            (JobKind::Config | JobKind::DeviceType | JobKind::ConfirmMode, Err(f)) => {
                tracing::warn!(node, ?f, "configuration step failed; resetting the drive");
                self.error(to_error(addr, f));
                let d = &mut self.drives[i];
                d.jobs.clear();
                self.reset_drive(i, now);
                return;
            }
        }
        self.pump(i, now);
    }
}
