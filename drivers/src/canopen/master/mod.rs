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

mod boot;
mod types;

pub use types::{DriveSetup, DriveStatus, MODE_PROFILE_VELOCITY, MasterConfig, MasterEvent, Phase};

/// Retries of a configuration SDO request after a timeout, before the drive is reset.
const SDO_RETRIES: u32 = 2;

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
}
