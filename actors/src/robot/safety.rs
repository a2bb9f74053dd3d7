//! SafetyActor: the robot's own safety layer, whatever the server or the network does.
//!
//! - Commands are accepted only while armed, only newer than the last one accepted (sequence
//!   number) and not older than the command timeout (stamp); anything else is refused and counted.
//! - Velocity limits clamp every command; each wheel's speed changes by at most
//!   `max_accel · dt` per cycle, so turning obeys the acceleration limit as well as driving.
//! - Command watchdog: no fresh command for `command_timeout_ms` → disarm and stop. Only an
//!   explicit arm (with a new sequence floor) lets commands through again, so nothing queued during
//!   an outage is ever applied.
//! - The layer counts its stops (its start, a disarm of any cause, a halt, an e-stop or its reset, a
//!   fault or its reset) and reports the count; an arm counts only if it carries the current count
//!   and its stamp is within the command timeout of this clock, before or after: an arm sent
//!   before a drive fault, or one queued while this actor was being restarted, cannot start the
//!   robot again, whatever the two hosts' clocks say.
//! - Every input comes through [`RobotPorts::safety_inbox`](super::ports::SafetyInbox), in order,
//!   none dropped; if it ever overflows, the robot halts (`Disarmed(QueueFull)`).
//! - Every stop the layer makes (watchdog, disarm, lost drives) brakes at the stop deceleration,
//!   not at the acceleration limit, which only shapes driving while armed.
//! - E-stop latch: quick stop at once; only an explicit reset clears it (to disarmed). It comes
//!   from the operator's control port (a signal to `amr robot`) or the link (`Downlink::EStop`,
//!   e.g. `estop` on `amr server`'s stdin), and it survives a restart of this actor and, with a
//!   latch file ([`super::latches`]), of the robot: e-stop, fault and the stop count are on disk
//!   before the new state is reported.
//! - A supervisor escalation latches `Fault`, cleared only by a reset on the robot; a lost drive
//!   halts.
//!
//! The decisions live in `SafetyCore` (no IO, time passed in); the actor ticks it every cycle and
//! publishes the wheel command.

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use ractor::{Actor, ActorProcessingErr, ActorRef};

use super::latches::Latched;
use super::ports::{AbortOnDrop, EStopSource, RobotPorts, SafetyControl, SafetyInput, WheelCommand};
use super::status::{Counters, HealthCell};
use amr_msgs::{Command, Device, DisarmReason, Downlink, Health, HealthReport, SafetyState};

/// The limits and timings of the safety layer (from `[limits]` and `[safety]`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct SafetyParams {
    pub max_speed_mps: f64,
    pub max_yaw_rate_radps: f64,
    pub max_accel_mps2: f64,
    /// Wheel-surface deceleration of a stop (any state but armed).
    pub stop_decel_mps2: f64,
    pub track_width_m: f64,
    pub command_timeout_s: f64,
    /// Control cycle (the CAN SYNC period).
    pub period_s: f64,
}

/// Why a command was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Refusal {
    NotArmed,
    /// Its sequence number is not above the last accepted one (a replay or reordering), or below
    /// the floor set by the last arm.
    Stale,
    /// Its stamp is older than the command timeout.
    Expired,
    NotFinite,
}

/// Why an arm was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum ArmRefusal {
    /// E-stop or fault: only a reset clears them.
    Latched,
    /// It carries another stop counter: the robot stopped since the sender last heard of it (or
    /// it was sent before this robot started).
    BeforeStop,
    /// Stamped more than the command timeout before or after the robot's clock, or not finite.
    Expired,
}

/// The safety layer's decisions.
#[derive(Debug, Clone)]
pub(crate) struct SafetyCore {
    params: SafetyParams,
    state: SafetyState,
    /// The last accepted command and when it arrived.
    command: Option<(Command, f64)>,
    last_seq: Option<u64>,
    seq_floor: u64,
    /// The twist being output.
    output: (f64, f64),
    last_tick_s: Option<f64>,
    /// Counts the stops (this core's start, a disarm, a halt, an e-stop or its reset, a fault or
    /// its reset): only an arm that carries the current count starts the robot. Nothing here
    /// compares the sender's clock with this one to order an arm and a stop.
    stops: u64,
}

impl SafetyCore {
    #[must_use]
    /// A core started after `stops` earlier stops (disarmed: a start is a stop event).
    pub(crate) fn new(params: SafetyParams, stops: u64) -> Self {
        SafetyCore {
            params,
            state: SafetyState::Disarmed(DisarmReason::Startup),
            command: None,
            last_seq: None,
            seq_floor: 0,
            output: (0.0, 0.0),
            last_tick_s: None,
            stops: stops.wrapping_add(1),
        }
    }

    #[must_use]
    pub(crate) fn state(&self) -> SafetyState {
        self.state
    }

    /// The stop counter an arm must carry.
    #[must_use]
    pub(crate) fn stops(&self) -> u64 {
        self.stops
    }

    fn stopped(&mut self) {
        self.stops = self.stops.wrapping_add(1);
    }

    /// The twist currently output.
    #[cfg(test)]
    #[must_use]
    pub(crate) fn output(&self) -> (f64, f64) {
        self.output
    }

    /// Arm (carrying stop counter `stops`, stamped `stamp_s` by the sender): accept commands with
    /// `seq >= floor`, starting the watchdog now.
    pub(crate) fn arm(&mut self, floor: u64, stops: u64, stamp_s: f64, now_s: f64) -> Result<(), ArmRefusal> {
        if matches!(self.state, SafetyState::EStop | SafetyState::Fault) {
            return Err(ArmRefusal::Latched);
        }
        if !(stamp_s.is_finite() && (now_s - stamp_s).abs() <= self.params.command_timeout_s) {
            return Err(ArmRefusal::Expired);
        }
        if stops != self.stops {
            return Err(ArmRefusal::BeforeStop);
        }
        match self.state {
            SafetyState::Disarmed(_) => {
                self.state = SafetyState::Armed;
                self.seq_floor = floor;
                self.last_tick_s.get_or_insert(now_s);
                // The watchdog runs from the arm: a first command must come within the timeout.
                self.command = Some((Command { seq: 0, stamp_s: now_s, v_mps: 0.0, w_radps: 0.0 }, now_s));
            }
            SafetyState::Armed => self.seq_floor = self.seq_floor.max(floor),
            SafetyState::EStop | SafetyState::Fault => {}
        }
        Ok(())
    }

    /// Disarm (ramp to zero); kept if already e-stopped or faulted.
    pub(crate) fn disarm(&mut self, reason: DisarmReason) {
        self.stopped();
        if matches!(self.state, SafetyState::Armed | SafetyState::Disarmed(_)) {
            self.state = SafetyState::Disarmed(reason);
            self.command = None;
        }
    }

    /// Disarm with `reason` and drop the output to zero at once: the drives were lost, faulted or
    /// rebooted, so they have stopped already; ramping on from the old speed would make them move
    /// again, disarmed, when they return.
    pub(crate) fn halt(&mut self, reason: DisarmReason) {
        self.disarm(reason);
        self.output = (0.0, 0.0);
    }

    /// Latch the e-stop (a fault stays a fault).
    pub(crate) fn estop(&mut self) {
        self.stopped();
        if self.state != SafetyState::Fault {
            self.state = SafetyState::EStop;
            self.command = None;
            self.output = (0.0, 0.0);
        }
    }

    /// Clear the e-stop: the robot is disarmed until armed by an arm that knows of this reset.
    pub(crate) fn reset_estop(&mut self) -> bool {
        if self.state == SafetyState::EStop {
            self.state = SafetyState::Disarmed(DisarmReason::EStopReset);
            self.stopped();
            true
        } else {
            false
        }
    }

    /// Latch a fault (a supervisor escalated, now or before a restart).
    pub(crate) fn fault(&mut self) {
        self.stopped();
        self.state = SafetyState::Fault;
        self.command = None;
        self.output = (0.0, 0.0);
    }

    /// Clear a fault, by a reset on the robot: back in `EStop` if an e-stop still holds
    /// (`estop_held`), else disarmed until armed.
    pub(crate) fn reset_fault(&mut self, estop_held: bool) -> bool {
        if self.state != SafetyState::Fault {
            return false;
        }
        self.stopped();
        self.state =
            if estop_held { SafetyState::EStop } else { SafetyState::Disarmed(DisarmReason::FaultReset) };
        true
    }

    /// Offer a command that arrived at `now_s`.
    pub(crate) fn offer(&mut self, c: Command, now_s: f64) -> Result<(), Refusal> {
        if self.state != SafetyState::Armed {
            return Err(Refusal::NotArmed);
        }
        if !(c.v_mps.is_finite() && c.w_radps.is_finite() && c.stamp_s.is_finite()) {
            return Err(Refusal::NotFinite);
        }
        if c.seq < self.seq_floor || self.last_seq.is_some_and(|s| c.seq <= s) {
            return Err(Refusal::Stale);
        }
        if now_s - c.stamp_s > self.params.command_timeout_s {
            return Err(Refusal::Expired);
        }
        self.last_seq = Some(c.seq);
        self.command = Some((c, now_s));
        Ok(())
    }

    /// One control cycle at `now_s`: the wheel command to apply.
    pub(crate) fn tick(&mut self, now_s: f64) -> WheelCommand {
        let p = self.params;
        let dt = self.last_tick_s.map_or(p.period_s, |t| (now_s - t).clamp(0.0, 10.0 * p.period_s));
        self.last_tick_s = Some(now_s);
        if matches!(self.state, SafetyState::EStop | SafetyState::Fault) {
            self.output = (0.0, 0.0);
            return WheelCommand { v_mps: 0.0, w_radps: 0.0, quick_stop: true };
        }
        if self.state == SafetyState::Armed
            && self.command.is_none_or(|(_, at)| now_s - at > p.command_timeout_s)
        {
            tracing::warn!(timeout_s = p.command_timeout_s, "command watchdog: no fresh command, stopping");
            self.disarm(DisarmReason::Watchdog);
        }
        let target = match (self.state, self.command) {
            (SafetyState::Armed, Some((c, _))) => (
                c.v_mps.clamp(-p.max_speed_mps, p.max_speed_mps),
                c.w_radps.clamp(-p.max_yaw_rate_radps, p.max_yaw_rate_radps),
            ),
            _ => (0.0, 0.0),
        };
        // Driving (armed) is shaped by the comfort limit; a stop brakes at the stop deceleration.
        let rate = if self.state == SafetyState::Armed { p.max_accel_mps2 } else { p.stop_decel_mps2 };
        self.output = ramp_wheels(self.output, target, rate * dt, p.track_width_m);
        WheelCommand { v_mps: self.output.0, w_radps: self.output.1, quick_stop: false }
    }
}

/// Move from twist `from` towards `to`, changing each wheel's surface speed by at most `dv`.
fn ramp_wheels(from: (f64, f64), to: (f64, f64), dv: f64, track_m: f64) -> (f64, f64) {
    let half = track_m / 2.0;
    let wheels = |(v, w): (f64, f64)| [v - w * half, v + w * half];
    let (a, b) = (wheels(from), wheels(to));
    let l = a[0] + (b[0] - a[0]).clamp(-dv, dv);
    let r = a[1] + (b[1] - a[1]).clamp(-dv, dv);
    let out = (0.5 * (l + r), (r - l) / track_m);
    // Snap exact zeros so a stopped robot outputs exactly zero.
    (if out.0.abs() < 1e-12 { 0.0 } else { out.0 }, if out.1.abs() < 1e-12 { 0.0 } else { out.1 })
}

/// Whether a health report stops the robot until it is armed again: without working drives
/// commands cannot be followed. Drives that are anything but Ok halt it: a fault or reboot of one
/// (`Degraded`: it left Operation enabled), their loss, and their reconfiguration (`Starting`:
/// both rebooted or were reset, e.g. after the whole robot froze and the master found them silent).
/// The drive actor enables them again by itself; the halt has made the output zero by then, so
/// they never come back into motion without a new arm.
fn halts(h: &HealthReport) -> bool {
    match h.device {
        Device::Drives => h.health != Health::Ok,
        Device::CanBus => matches!(h.health, Health::Lost | Health::Fault | Health::Starting),
        _ => false,
    }
}

/// Messages of the safety actor.
#[derive(Debug)]
pub(crate) enum SafetyMsg {
    /// One control cycle (it takes the inbox first).
    Tick,
    /// Something was queued in the inbox.
    Inbox,
}

/// The safety actor.
#[derive(Debug, Clone)]
pub(crate) struct SafetyActor {
    pub ports: Arc<RobotPorts>,
    pub params: SafetyParams,
    pub counters: Counters,
}

#[derive(Debug)]
pub(crate) struct SafetyActorState {
    core: SafetyCore,
    published: Option<(SafetyState, u64)>,
    /// What the latch file holds (as last written or read).
    persisted: Option<Latched>,
    health: HealthCell,
    /// Wakes this actor when the inbox gets something.
    _waker: AbortOnDrop<()>,
}

impl SafetyActor {
    /// Report a change of state or stop counter, after the latches are on disk: a robot that has
    /// acknowledged an e-stop or a fault keeps it across a restart.
    fn publish(&self, s: &mut SafetyActorState) {
        let now = s.core.state();
        self.ports.stops.store(s.core.stops(), Ordering::SeqCst);
        self.ports.reserve_stops(s.core.stops());
        if now == SafetyState::Fault {
            // Lowered only by a reset on the robot (`apply`).
            self.ports.fault_latch.store(true, Ordering::SeqCst);
        }
        let latched = self.ports.latched();
        if s.persisted != Some(latched) {
            match self.ports.persist_latches() {
                Ok(()) => s.persisted = Some(latched),
                Err(e) => {
                    // The latches hold in memory; a reset that could not be written is still latched
                    // on the next start (fail safe).
                    tracing::error!(robot = %self.ports.robot, error = %e, "the latches are not on disk");
                    self.counters.count("safety.latch_file_errors");
                }
            }
        }
        if s.published != Some((now, s.core.stops())) {
            if s.published.map(|p| p.0) != Some(now) {
                tracing::info!(robot = %self.ports.robot, state = ?now, stops = s.core.stops(), "safety");
            }
            s.published = Some((now, s.core.stops()));
            self.ports.safety_now.send_replace(Some(now));
            self.ports.safety.send(now);
            let health = match now {
                SafetyState::Fault => Health::Fault,
                SafetyState::EStop => Health::Degraded,
                _ => Health::Ok,
            };
            s.health.set(&self.ports, health, format!("{now:?}"));
        }
    }

    fn output(&self, s: &mut SafetyActorState) {
        let cmd = s.core.tick(self.ports.clock.now_s());
        self.ports.wheel_cmd.send(cmd);
    }

    /// Apply everything in the inbox, oldest first.
    fn take_inbox(&self, s: &mut SafetyActorState) {
        let (inputs, overflowed) = self.ports.safety_inbox.take();
        for input in inputs {
            self.apply(s, input);
        }
        if overflowed {
            // The stated overflow policy: something was refused, so stop until armed again.
            tracing::error!(robot = %self.ports.robot, "safety inbox overflowed: halting");
            self.counters.count("safety.inbox_full");
            s.core.halt(DisarmReason::QueueFull);
        }
    }

    fn apply(&self, s: &mut SafetyActorState, input: SafetyInput) {
        let now = self.ports.clock.now_s();
        match input {
            SafetyInput::Link(Downlink::Command(c)) => {
                if let Err(why) = s.core.offer(c, now) {
                    self.counters.count(match why {
                        Refusal::NotArmed => "safety.refused.not_armed",
                        Refusal::Stale => "safety.refused.stale",
                        Refusal::Expired => "safety.refused.expired",
                        Refusal::NotFinite => "safety.refused.not_finite",
                    });
                }
            }
            SafetyInput::Link(Downlink::Arm { seq, stops, stamp_s }) => {
                if let Err(why) = s.core.arm(seq, stops, stamp_s, now) {
                    self.counters.count("safety.refused.arm");
                    self.counters.count(match why {
                        ArmRefusal::Latched => "safety.refused.arm.latched",
                        ArmRefusal::BeforeStop => "safety.refused.arm.before_stop",
                        ArmRefusal::Expired => "safety.refused.arm.expired",
                    });
                }
            }
            SafetyInput::Link(Downlink::Disarm) => s.core.disarm(DisarmReason::Requested),
            SafetyInput::Link(Downlink::EStop)
            | SafetyInput::Control(SafetyControl::EStop)
            | SafetyInput::EStopInput => {
                match input {
                    SafetyInput::Link(_) => self.ports.estop_latch.set(EStopSource::Network),
                    SafetyInput::Control(_) => self.ports.estop_latch.set(EStopSource::Local),
                    // Latched as such by the drive actor before it was queued.
                    _ => {}
                }
                s.core.estop();
                // Not waiting for the next cycle.
                self.output(s);
            }
            SafetyInput::Link(Downlink::ResetEStop) | SafetyInput::Control(SafetyControl::ResetEStop) => {
                let local = matches!(input, SafetyInput::Control(_));
                if s.core.state() == SafetyState::Fault && !local {
                    // A fault is reset only on the robot.
                    tracing::warn!(robot = %self.ports.robot, "a network reset refused: a fault is latched");
                    self.counters.count("safety.refused.reset");
                    return;
                }
                let clear = self.ports.estop_latch.reset(local);
                if s.core.state() == SafetyState::Fault {
                    tracing::warn!(robot = %self.ports.robot, "fault reset on the robot");
                    self.ports.fault_latch.store(false, Ordering::SeqCst);
                    s.core.reset_fault(!clear);
                } else if clear {
                    s.core.reset_estop();
                } else {
                    tracing::warn!(robot = %self.ports.robot, local, "e-stop reset refused: held by another source");
                    self.counters.count("safety.refused.reset");
                }
            }
            SafetyInput::Health(h) => {
                if halts(&h) {
                    s.core.halt(DisarmReason::DeviceLost);
                }
            }
            SafetyInput::Missed => {
                self.counters.count("safety.link_queue_full");
                s.core.halt(DisarmReason::QueueFull);
            }
        }
    }
}

impl Actor for SafetyActor {
    type Msg = SafetyMsg;
    type State = SafetyActorState;
    type Arguments = ();

    async fn pre_start(
        &self,
        myself: ActorRef<SafetyMsg>,
        (): (),
    ) -> Result<SafetyActorState, ActorProcessingErr> {
        let waker = super::ports::wake_on(
            Arc::clone(&self.ports),
            |p| &p.safety_inbox,
            myself.clone(),
            || SafetyMsg::Inbox,
        );
        let period = Duration::from_secs_f64(self.params.period_s.max(0.001));
        myself.send_interval(period, || SafetyMsg::Tick);
        let mut s = SafetyActorState {
            // A start is a stop: an arm sent before it carries an older counter.
            core: SafetyCore::new(self.params, self.ports.stops.load(Ordering::SeqCst)),
            published: None,
            persisted: None,
            health: HealthCell::new(Device::Safety),
            _waker: waker,
        };
        if self.ports.fault_latch.load(Ordering::SeqCst) {
            tracing::warn!(robot = %self.ports.robot, "safety started with a fault latched: reset it on the robot");
            s.core.fault();
            self.output(&mut s);
        } else if self.ports.estop_latch.is_set() {
            tracing::warn!(robot = %self.ports.robot, "safety started with the e-stop latched");
            s.core.estop();
            self.output(&mut s);
        }
        // What arrived while no safety actor ran (an arm from before this start is refused).
        self.take_inbox(&mut s);
        self.publish(&mut s);
        Ok(s)
    }

    async fn handle(
        &self,
        _myself: ActorRef<SafetyMsg>,
        msg: SafetyMsg,
        s: &mut SafetyActorState,
    ) -> Result<(), ActorProcessingErr> {
        self.take_inbox(s);
        if let SafetyMsg::Tick = msg {
            // The latch is the authority: an e-stop latched by a source that could not reach this
            // actor still stops the robot within a cycle.
            if self.ports.fault_latch.load(Ordering::SeqCst) && s.core.state() != SafetyState::Fault {
                tracing::warn!(robot = %self.ports.robot, "fault latched outside this actor: stopping");
                s.core.fault();
            } else if self.ports.estop_latch.is_set()
                && !matches!(s.core.state(), SafetyState::EStop | SafetyState::Fault)
            {
                tracing::warn!(robot = %self.ports.robot, "e-stop latched outside this actor: stopping");
                s.core.estop();
            }
            self.output(s);
        }
        self.publish(s);
        Ok(())
    }
}

/// What an input to [`SafetyHarness`] did.
#[doc(hidden)]
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Applied {
    /// It took effect: a command or an arm accepted, a stop made, a reset that cleared a latch.
    pub taken: bool,
    /// The output applied at once, without waiting for the next cycle (after an e-stop).
    pub output: Option<WheelCommand>,
}

/// The safety layer as [`SafetyActor`] runs it, with time passed in, for fuzzing: the core with a
/// robot's configured limits and timings, the e-stop and fault latches, the same dispatch of each
/// input as `SafetyActor::apply` and the same latch check before each cycle. Nothing is published.
#[doc(hidden)]
#[derive(Debug)]
pub struct SafetyHarness {
    core: SafetyCore,
    params: SafetyParams,
    estop_latch: super::ports::EStopLatch,
    fault_latch: bool,
}

impl SafetyHarness {
    /// A robot with `cfg`'s limits and timings, started with nothing latched.
    #[must_use]
    pub fn new(cfg: &crate::config::RobotConfig) -> Self {
        let params = super::safety_params(cfg);
        SafetyHarness {
            core: SafetyCore::new(params, 0),
            params,
            estop_latch: super::ports::EStopLatch::default(),
            fault_latch: false,
        }
    }

    #[must_use]
    pub fn state(&self) -> SafetyState {
        self.core.state()
    }

    /// The stop counter an arm must carry.
    #[must_use]
    pub fn stops(&self) -> u64 {
        self.core.stops()
    }

    /// One input, as the actor applies it at `now_s`. [`SafetyInput::EStopInput`] expects the
    /// latch set first ([`SafetyHarness::estop_input`]).
    pub fn apply(&mut self, input: SafetyInput, now_s: f64) -> Applied {
        let mut output = None;
        let taken = match input {
            SafetyInput::Link(Downlink::Command(c)) => self.core.offer(c, now_s).is_ok(),
            SafetyInput::Link(Downlink::Arm { seq, stops, stamp_s }) => {
                self.core.arm(seq, stops, stamp_s, now_s).is_ok()
            }
            SafetyInput::Link(Downlink::Disarm) => {
                self.core.disarm(DisarmReason::Requested);
                true
            }
            SafetyInput::Link(Downlink::EStop)
            | SafetyInput::Control(SafetyControl::EStop)
            | SafetyInput::EStopInput => {
                match input {
                    SafetyInput::Link(_) => self.estop_latch.set(EStopSource::Network),
                    SafetyInput::Control(_) => self.estop_latch.set(EStopSource::Local),
                    _ => {}
                }
                self.core.estop();
                output = Some(self.core.tick(now_s));
                true
            }
            SafetyInput::Link(Downlink::ResetEStop) | SafetyInput::Control(SafetyControl::ResetEStop) => {
                let local = matches!(input, SafetyInput::Control(_));
                if self.core.state() == SafetyState::Fault && !local {
                    false
                } else {
                    let clear = self.estop_latch.reset(local);
                    if self.core.state() == SafetyState::Fault {
                        self.fault_latch = false;
                        self.core.reset_fault(!clear)
                    } else {
                        clear && self.core.reset_estop()
                    }
                }
            }
            SafetyInput::Health(h) => {
                let halt = halts(&h);
                if halt {
                    self.core.halt(DisarmReason::DeviceLost);
                }
                halt
            }
            SafetyInput::Missed => {
                self.core.halt(DisarmReason::QueueFull);
                true
            }
        };
        self.latch_fault();
        Applied { taken, output }
    }

    /// The e-stop input of a drive changed; pressed, it latches and stops the robot.
    pub fn estop_input(&mut self, pressed: bool, now_s: f64) -> Applied {
        self.estop_latch.input(pressed);
        if pressed {
            self.apply(SafetyInput::EStopInput, now_s)
        } else {
            Applied { taken: false, output: None }
        }
    }

    /// A supervisor escalated: the fault is latched (the actor sees the latch before its next
    /// cycle).
    pub fn escalate(&mut self) {
        self.fault_latch = true;
    }

    /// The safety actor restarted: a new core from the stop counter and the latches.
    pub fn restart(&mut self, now_s: f64) -> Option<WheelCommand> {
        self.core = SafetyCore::new(self.params, self.core.stops());
        let out = if self.fault_latch {
            self.core.fault();
            Some(self.core.tick(now_s))
        } else if self.estop_latch.is_set() {
            self.core.estop();
            Some(self.core.tick(now_s))
        } else {
            None
        };
        self.latch_fault();
        out
    }

    /// One control cycle at `now_s`: the latches checked, then the wheel command.
    pub fn tick(&mut self, now_s: f64) -> WheelCommand {
        if self.fault_latch && self.core.state() != SafetyState::Fault {
            self.core.fault();
        } else if self.estop_latch.is_set()
            && !matches!(self.core.state(), SafetyState::EStop | SafetyState::Fault)
        {
            self.core.estop();
        }
        let out = self.core.tick(now_s);
        self.latch_fault();
        out
    }

    /// As `SafetyActor::publish`: a fault stays latched until a reset on the robot.
    fn latch_fault(&mut self) {
        if self.core.state() == SafetyState::Fault {
            self.fault_latch = true;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const P: SafetyParams = SafetyParams {
        max_speed_mps: 0.22,
        max_yaw_rate_radps: 0.2,
        max_accel_mps2: 0.05,
        stop_decel_mps2: 0.5,
        track_width_m: 0.33,
        command_timeout_s: 0.2,
        period_s: 0.02,
    };

    fn cmd(seq: u64, stamp_s: f64, v: f64, w: f64) -> Command {
        Command { seq, stamp_s, v_mps: v, w_radps: w }
    }

    /// Ticks every 20 ms from `t0` for `n` cycles, offering a command before each if `feed`.
    fn run(core: &mut SafetyCore, t0: f64, n: u32, feed: Option<(&mut u64, f64, f64)>) -> Vec<WheelCommand> {
        let mut out = Vec::new();
        let mut feed = feed;
        for k in 0..n {
            let t = t0 + f64::from(k) * 0.02;
            if let Some((seq, v, w)) = feed.as_mut() {
                **seq += 1;
                let _ = core.offer(cmd(**seq, t, *v, *w), t);
            }
            out.push(core.tick(t));
        }
        out
    }

    #[test]
    fn starts_disarmed_and_refuses_commands_until_armed() {
        let mut c = SafetyCore::new(P, 0);
        assert_eq!(c.state(), SafetyState::Disarmed(DisarmReason::Startup));
        assert_eq!(c.offer(cmd(1, 0.0, 0.1, 0.0), 0.0), Err(Refusal::NotArmed));
        assert_eq!(c.tick(0.0), WheelCommand { v_mps: 0.0, w_radps: 0.0, quick_stop: false });
        assert_eq!(c.arm(1, c.stops(), 0.0, 0.0), Ok(()));
        assert_eq!(c.offer(cmd(1, 0.0, 0.1, 0.0), 0.0), Ok(()));
    }

    #[test]
    fn limits_speed_and_ramps_each_wheel_at_the_acceleration_limit() {
        let mut c = SafetyCore::new(P, 0);
        assert_eq!(c.arm(0, c.stops(), 0.0, 0.0), Ok(()));
        let mut seq = 0;
        let out = run(&mut c, 0.0, 400, Some((&mut seq, 5.0, 0.0)));
        // 0.05 m/s² → 0.001 m/s per 20 ms cycle.
        for w in out.windows(2) {
            assert!((w[1].v_mps - w[0].v_mps).abs() <= 0.001 + 1e-12);
        }
        // The first tick is at the arm time (no time has passed), then 1 mm/s per cycle.
        assert_eq!(out[0].v_mps, 0.0);
        assert!((out[10].v_mps - 0.010).abs() < 1e-9, "{}", out[10].v_mps);
        assert!((out.last().map_or(0.0, |o| o.v_mps) - 0.22).abs() < 1e-12, "capped at max speed");
        // A turn on the spot: each wheel ramps at the limit, the yaw rate is capped.
        let mut c = SafetyCore::new(P, 0);
        assert_eq!(c.arm(0, c.stops(), 0.0, 0.0), Ok(()));
        let mut seq = 0;
        let out = run(&mut c, 0.0, 400, Some((&mut seq, 0.0, 9.0)));
        let dw = 0.001 / (P.track_width_m / 2.0);
        assert!((out[1].w_radps - dw).abs() < 1e-9);
        assert!((out.last().map_or(0.0, |o| o.w_radps) - 0.2).abs() < 1e-12);
    }

    #[test]
    fn watchdog_ramps_to_zero_and_needs_a_rearm() {
        let mut c = SafetyCore::new(P, 0);
        assert_eq!(c.arm(0, c.stops(), 0.0, 0.0), Ok(()));
        let mut seq = 0;
        let out = run(&mut c, 0.0, 300, Some((&mut seq, 0.2, 0.0)));
        let v0 = out.last().map_or(0.0, |o| o.v_mps);
        assert!(v0 > 0.19);
        // Commands stop at t = 5.98; the watchdog fires once 200 ms have passed.
        let after = run(&mut c, 6.0, 400, None);
        assert_eq!(c.state(), SafetyState::Disarmed(DisarmReason::Watchdog));
        // It braked at the stop deceleration (0.5 m/s²: 10 mm/s per cycle), not at the motion
        // limit, and reached zero exactly.
        for w in after.windows(2) {
            assert!(w[0].v_mps - w[1].v_mps <= 0.010 + 1e-12);
        }
        assert_eq!(after.last().map(|o| o.v_mps), Some(0.0));
        // Full speed for the first 10 cycles (the timeout), then down: zero 0.2 s / 0.5 m/s² = 0.4 s
        // (20 cycles) after the watchdog.
        assert!((after[8].v_mps - v0).abs() < 1e-12);
        assert!(after[12].v_mps < v0 - 0.015);
        let first_down = after.iter().position(|o| o.v_mps < v0).unwrap_or(usize::MAX);
        let zero = after.iter().position(|o| o.v_mps == 0.0).unwrap_or(usize::MAX);
        assert!(zero.saturating_sub(first_down) <= 20, "braking from cycle {first_down}, zero at {zero}");
        // A command that was queued during the outage (older seq, or stamped long ago) is refused
        // even after the re-arm.
        assert_eq!(c.offer(cmd(seq + 1, 6.0, 0.2, 0.0), 14.0), Err(Refusal::NotArmed));
        assert_eq!(c.arm(seq + 10, c.stops(), 14.0, 14.0), Ok(()));
        assert_eq!(c.offer(cmd(seq + 1, 13.9, 0.2, 0.0), 14.0), Err(Refusal::Stale));
        assert_eq!(c.offer(cmd(seq + 10, 13.0, 0.2, 0.0), 14.0), Err(Refusal::Expired));
        assert_eq!(c.offer(cmd(seq + 11, 14.0, 0.2, 0.0), 14.0), Ok(()));
        // Replays and reordering are refused.
        assert_eq!(c.offer(cmd(seq + 11, 14.0, 0.2, 0.0), 14.0), Err(Refusal::Stale));
        assert_eq!(c.offer(cmd(seq + 10, 14.0, 0.2, 0.0), 14.0), Err(Refusal::Stale));
        assert_eq!(c.offer(cmd(seq + 12, 14.0, f64::NAN, 0.0), 14.0), Err(Refusal::NotFinite));
    }

    #[test]
    fn slowing_down_while_armed_keeps_the_comfort_limit_a_disarm_brakes_at_the_stop_rate() {
        let mut c = SafetyCore::new(P, 0);
        assert_eq!(c.arm(0, c.stops(), 0.0, 0.0), Ok(()));
        let mut seq = 0;
        let out = run(&mut c, 0.0, 300, Some((&mut seq, 0.2, 0.0)));
        let v0 = out.last().map_or(0.0, |o| o.v_mps);
        // Commanded down to 0.1 m/s: 1 mm/s per cycle.
        let down = run(&mut c, 6.0, 10, Some((&mut seq, 0.1, 0.0)));
        assert!((down[9].v_mps - (v0 - 0.010)).abs() < 1e-9, "{} {v0}", down[9].v_mps);
        // A disarm: 10 mm/s per cycle to zero.
        c.disarm(DisarmReason::Requested);
        let stop = run(&mut c, 6.2, 30, None);
        let v1 = down[9].v_mps;
        assert!((stop[0].v_mps - (v1 - 0.010)).abs() < 1e-9, "{} {v1}", stop[0].v_mps);
        let zero_at = stop.iter().position(|o| o.v_mps == 0.0).unwrap_or(usize::MAX);
        assert_eq!(zero_at + 1, (v1 / 0.010).round() as usize, "{v1}");
    }

    #[test]
    fn an_armed_robot_that_never_hears_a_command_stops_at_the_timeout() {
        let mut c = SafetyCore::new(P, 0);
        assert_eq!(c.arm(0, c.stops(), 1.0, 1.0), Ok(()));
        c.tick(1.0);
        c.tick(1.19);
        assert_eq!(c.state(), SafetyState::Armed);
        c.tick(1.21);
        assert_eq!(c.state(), SafetyState::Disarmed(DisarmReason::Watchdog));
    }

    #[test]
    fn a_lost_drive_halts_the_output_so_nothing_moves_when_it_returns() {
        let mut c = SafetyCore::new(P, 0);
        assert_eq!(c.arm(0, c.stops(), 0.0, 0.0), Ok(()));
        let mut seq = 0;
        run(&mut c, 0.0, 300, Some((&mut seq, 0.2, 0.1)));
        assert!(c.output().0 > 0.19);
        c.halt(DisarmReason::DeviceLost);
        assert_eq!(c.state(), SafetyState::Disarmed(DisarmReason::DeviceLost));
        // From the next cycle on, exactly zero (not a ramp from 0.2 m/s).
        assert_eq!(c.tick(6.02), WheelCommand { v_mps: 0.0, w_radps: 0.0, quick_stop: false });
        assert_eq!(c.offer(cmd(seq + 1, 6.02, 0.2, 0.0), 6.02), Err(Refusal::NotArmed));
        // A latched e-stop stays one.
        c.estop();
        c.halt(DisarmReason::DeviceLost);
        assert_eq!(c.state(), SafetyState::EStop);
    }

    #[test]
    fn only_an_arm_that_knows_the_last_stop_and_is_fresh_starts_the_robot() {
        // Started after 6 stops (a restart): an arm that carries the count from before the start
        // (queued while this core's actor was being restarted, or sent to the robot's previous
        // run) is refused.
        let mut c = SafetyCore::new(P, 6);
        assert_eq!(c.stops(), 7, "a start is a stop");
        assert_eq!(c.arm(1, 6, 10.0, 10.01), Err(ArmRefusal::BeforeStop));
        // One stamped more than the command timeout before or after this clock, or not finite, is
        // refused whatever it carries.
        assert_eq!(c.arm(1, 7, 10.05, 10.3), Err(ArmRefusal::Expired));
        assert_eq!(c.arm(1, 7, 10.55, 10.3), Err(ArmRefusal::Expired), "from the future");
        assert_eq!(c.arm(1, 7, f64::NAN, 10.3), Err(ArmRefusal::Expired));
        assert_eq!(c.state(), SafetyState::Disarmed(DisarmReason::Startup));
        assert_eq!(c.arm(1, 7, 10.25, 10.3), Ok(()));
        let mut seq = 0;
        run(&mut c, 10.3, 100, Some((&mut seq, 0.1, 0.0)));
        // The server's clock runs 2 s ahead and the link is slow. It sends an arm (stamped 14.49 on
        // its clock, 12.49 on the robot's); a drive faults at 12.5 (robot clock); the arm arrives
        // at 12.51. Comparing stamps, it looked newer than the fault (and only the future check
        // refuses it); the counter refuses it whatever the clocks say.
        c.halt(DisarmReason::DeviceLost);
        assert_eq!(c.stops(), 8);
        assert_eq!(c.arm(seq + 1, 7, 12.51, 12.51), Err(ArmRefusal::BeforeStop), "with synchronised clocks");
        assert_eq!(c.arm(seq + 1, 7, 14.49, 12.51), Err(ArmRefusal::Expired), "with the server 2 s ahead");
        let out = run(&mut c, 12.52, 20, Some((&mut seq, 0.1, 0.0)));
        assert!(out.iter().all(|o| o.v_mps == 0.0 && o.w_radps == 0.0));
        // A disarm of any cause is a stop too: a reordered arm from before it is refused.
        assert_eq!(c.arm(seq + 1, 8, 12.95, 12.96), Ok(()));
        c.disarm(DisarmReason::Requested);
        assert_eq!(c.arm(seq + 1, 8, 13.01, 13.01), Err(ArmRefusal::BeforeStop));
        assert_eq!(c.arm(seq + 1, 9, 13.01, 13.02), Ok(()));
        // An e-stop's reset is one: the arm must know of the reset.
        c.estop();
        assert_eq!(c.arm(seq + 1, c.stops(), 14.1, 14.1), Err(ArmRefusal::Latched));
        let at_estop = c.stops();
        assert!(c.reset_estop());
        assert_eq!(c.arm(seq + 1, at_estop, 14.21, 14.21), Err(ArmRefusal::BeforeStop));
        assert_eq!(c.arm(seq + 1, at_estop + 1, 14.21, 14.22), Ok(()));
        // A fault is reset only by `reset_fault` (on the robot), back to the e-stop if one holds.
        c.fault();
        assert!(!c.reset_estop());
        assert!(c.reset_fault(true));
        assert_eq!(c.state(), SafetyState::EStop);
        c.fault();
        assert!(c.reset_fault(false));
        assert_eq!(c.state(), SafetyState::Disarmed(DisarmReason::FaultReset));
        assert_eq!(c.arm(seq + 1, c.stops(), 15.0, 15.0), Ok(()));
    }

    #[test]
    fn a_faulted_or_rebooted_drive_halts_other_devices_do_not() {
        let report = |device, health| HealthReport { device, health, detail: String::new() };
        assert!(halts(&report(Device::Drives, Health::Degraded)));
        assert!(halts(&report(Device::Drives, Health::Lost)));
        assert!(halts(&report(Device::Drives, Health::Fault)));
        assert!(halts(&report(Device::CanBus, Health::Lost)));
        assert!(!halts(&report(Device::Drives, Health::Ok)));
        assert!(halts(&report(Device::Drives, Health::Starting)), "reconfigured after a reset");
        assert!(halts(&report(Device::CanBus, Health::Starting)));
        assert!(!halts(&report(Device::CanBus, Health::Degraded)));
        assert!(!halts(&report(Device::Lidar, Health::Lost)));
        assert!(!halts(&report(Device::Imu, Health::Fault)));
    }

    #[test]
    fn estop_latches_until_reset_and_a_fault_never_clears() {
        let mut c = SafetyCore::new(P, 0);
        assert_eq!(c.arm(0, c.stops(), 0.0, 0.0), Ok(()));
        let mut seq = 0;
        run(&mut c, 0.0, 100, Some((&mut seq, 0.2, 0.0)));
        c.estop();
        assert_eq!(c.output(), (0.0, 0.0));
        assert_eq!(c.tick(2.0), WheelCommand { v_mps: 0.0, w_radps: 0.0, quick_stop: true });
        assert_eq!(
            c.arm(1000, c.stops(), 2.0, 2.0),
            Err(ArmRefusal::Latched),
            "arming does not clear an e-stop"
        );
        assert_eq!(c.offer(cmd(1001, 2.0, 0.1, 0.0), 2.0), Err(Refusal::NotArmed));
        assert!(c.reset_estop());
        assert_eq!(c.state(), SafetyState::Disarmed(DisarmReason::EStopReset));
        assert!(!c.tick(2.02).quick_stop);
        assert_eq!(c.arm(1000, c.stops(), 2.04, 2.04), Ok(()));
        c.fault();
        assert!(!c.reset_estop());
        assert_eq!(c.arm(2000, c.stops(), 3.0, 3.0), Err(ArmRefusal::Latched));
        c.estop();
        assert_eq!(c.state(), SafetyState::Fault);
        assert!(c.tick(3.0).quick_stop);
    }

    #[test]
    fn the_harness_applies_inputs_and_latches_as_the_actor_does() {
        use crate::config::{ConfigSource, load};
        let config = load(&ConfigSource::Embedded).unwrap();
        let robot = config.robots.iter().find(|r| r.id.as_str() == "robot-a").unwrap();
        let mut h = SafetyHarness::new(robot);
        assert_eq!((h.state(), h.stops()), (SafetyState::Disarmed(DisarmReason::Startup), 1));
        let link = |d: Downlink| SafetyInput::Link(d);
        assert!(!h.apply(link(Downlink::Arm { seq: 1, stops: 0, stamp_s: 10.0 }), 10.0).taken);
        assert!(h.apply(link(Downlink::Arm { seq: 1, stops: 1, stamp_s: 10.0 }), 10.0).taken);
        assert!(h.apply(link(Downlink::Command(cmd(1, 10.0, 0.2, 0.0))), 10.0).taken);
        assert!(h.tick(10.02).v_mps > 0.0);
        // A network e-stop stops at once; with a local one too, a network reset clears only its own.
        let stop = h.apply(link(Downlink::EStop), 10.03);
        assert_eq!(stop.output, Some(WheelCommand { v_mps: 0.0, w_radps: 0.0, quick_stop: true }));
        assert!(h.apply(SafetyInput::Control(SafetyControl::EStop), 10.04).taken);
        assert!(!h.apply(link(Downlink::ResetEStop), 10.05).taken);
        assert_eq!(h.state(), SafetyState::EStop);
        assert!(h.apply(SafetyInput::Control(SafetyControl::ResetEStop), 10.06).taken);
        assert_eq!(h.state(), SafetyState::Disarmed(DisarmReason::EStopReset));
        // An escalation faults before the next cycle; only a reset on the robot clears it, and a
        // restart keeps it.
        h.escalate();
        assert!(h.tick(10.08).quick_stop);
        assert_eq!(h.state(), SafetyState::Fault);
        assert!(!h.apply(link(Downlink::ResetEStop), 10.1).taken);
        assert!(h.restart(10.12).is_some_and(|o| o.quick_stop));
        assert_eq!(h.state(), SafetyState::Fault);
        assert!(h.apply(SafetyInput::Control(SafetyControl::ResetEStop), 10.14).taken);
        assert_eq!(h.state(), SafetyState::Disarmed(DisarmReason::FaultReset));
        assert_eq!(h.restart(10.16), None);
        // A pressed e-stop input holds until released, whatever the resets.
        assert!(h.estop_input(true, 10.2).taken);
        assert!(!h.apply(SafetyInput::Control(SafetyControl::ResetEStop), 10.22).taken);
        assert!(!h.estop_input(false, 10.24).taken);
        assert!(h.apply(SafetyInput::Control(SafetyControl::ResetEStop), 10.26).taken);
        // A lost drive halts; a lidar does not.
        let report = |device, health| HealthReport { device, health, detail: String::new() };
        assert!(h.apply(SafetyInput::Health(report(Device::Drives, Health::Lost)), 10.3).taken);
        assert!(!h.apply(SafetyInput::Health(report(Device::Lidar, Health::Lost)), 10.3).taken);
        assert_eq!(h.state(), SafetyState::Disarmed(DisarmReason::DeviceLost));
    }

    /// One input to the safety layer, as the state-machine property test draws them.
    #[derive(Debug, Clone)]
    enum Op {
        /// A command `ahead` numbers after the last one sent (0: a replay), stamped `age_s` ago.
        Command {
            ahead: u64,
            age_s: f64,
            v: f64,
            w: f64,
        },
        /// An arm whose floor is `ahead` numbers after the last command sent, stamped `age_s` ago
        /// (negative: ahead of the robot's clock), carrying a stop counter `behind` stops old.
        Arm {
            ahead: u64,
            age_s: f64,
            behind: u64,
        },
        Disarm,
        /// The drives lost or faulted.
        Halt,
        EStop,
        ResetEStop,
        Fault,
        /// A reset of a fault on the robot (`held`: an e-stop still holds).
        ResetFault {
            held: bool,
        },
        /// The safety actor restarted: a new core.
        Restart,
        Tick {
            dt_s: f64,
        },
    }

    fn op() -> impl Strategy<Value = Op> {
        prop_oneof![
            6 => (0u64..3, 0.0..0.4f64, -1.0..1.0f64, -1.0..1.0f64)
                .prop_map(|(ahead, age_s, v, w)| Op::Command { ahead, age_s, v, w }),
            3 => (0u64..3, -0.3..0.3f64, prop_oneof![3 => Just(0u64), 1 => 1u64..3])
                .prop_map(|(ahead, age_s, behind)| Op::Arm { ahead, age_s, behind }),
            1 => Just(Op::Disarm),
            1 => Just(Op::Halt),
            1 => Just(Op::EStop),
            1 => Just(Op::ResetEStop),
            1 => Just(Op::Fault),
            1 => any::<bool>().prop_map(|held| Op::ResetFault { held }),
            1 => Just(Op::Restart),
            12 => (0.0..0.1f64).prop_map(|dt_s| Op::Tick { dt_s }),
        ]
    }

    fn wheels((v, w): (f64, f64)) -> [f64; 2] {
        [v - w * P.track_width_m / 2.0, v + w * P.track_width_m / 2.0]
    }

    use proptest::prelude::*;

    proptest! {
        #![proptest_config(ProptestConfig { cases: 500, ..ProptestConfig::default() })]

        /// Whatever the sequence of commands, arms, e-stops, faults, restarts and time steps, the
        /// output stays within the limits, changes no faster than the ramp of the state it is in,
        /// never grows while the robot is not armed, is zero in e-stop and fault, and is zero once
        /// the watchdog and a stop have had their time after the last fresh command; the stop
        /// counter counts every stop, and only an arm carrying it starts the robot.
        #[test]
        fn safety_core_invariants_hold_for_any_input_sequence(ops in proptest::collection::vec(op(), 1..200)) {
            let mut core = SafetyCore::new(P, 0);
            let mut now = 0.0f64;
            // The stops counted (start, disarm, halt, e-stop or its reset, fault or its reset,
            // restart), and whether an arm that knew the last one was accepted since.
            let mut stops = 1u64;
            let mut armed_since_stop = false;
            let mut sent = 0u64;
            // When the robot last had something that lets it move: an accepted arm or command.
            let mut fresh_at = f64::NEG_INFINITY;
            let mut prev = (0.0f64, 0.0f64);
            // Whether the output may jump this cycle (a quick stop or dropped drives set it to zero).
            let mut jumped = false;
            for op in ops {
                let armed_before = core.state() == SafetyState::Armed;
                match op {
                    Op::Command { ahead, age_s, v, w } => {
                        sent += ahead;
                        let c = cmd(sent, now - age_s, v, w);
                        if core.offer(c, now).is_ok() {
                            prop_assert!(armed_before, "a command was accepted while not armed");
                            fresh_at = now;
                        }
                    }
                    Op::Arm { ahead, age_s, behind } => {
                        let was = core.state();
                        let stamp = now - age_s;
                        let ok = core.arm(sent + ahead, stops.wrapping_sub(behind), stamp, now).is_ok();
                        let may = matches!(was, SafetyState::Armed | SafetyState::Disarmed(_))
                            && age_s.abs() <= P.command_timeout_s
                            && behind == 0;
                        prop_assert_eq!(ok, may);
                        if ok && was != SafetyState::Armed {
                            fresh_at = now;
                            armed_since_stop = true;
                        }
                    }
                    Op::Disarm => {
                        core.disarm(DisarmReason::Requested);
                        stops += 1;
                        armed_since_stop = false;
                    }
                    Op::Halt => {
                        core.halt(DisarmReason::DeviceLost);
                        stops += 1;
                        armed_since_stop = false;
                        jumped = true;
                    }
                    Op::EStop => {
                        core.estop();
                        stops += 1;
                        armed_since_stop = false;
                        jumped = true;
                    }
                    Op::ResetEStop => {
                        let was = core.state();
                        prop_assert_eq!(core.reset_estop(), was == SafetyState::EStop);
                        if was == SafetyState::EStop {
                            stops += 1;
                        }
                    }
                    Op::Fault => {
                        core.fault();
                        stops += 1;
                        armed_since_stop = false;
                        jumped = true;
                    }
                    Op::ResetFault { held } => {
                        let was = core.state();
                        prop_assert_eq!(core.reset_fault(held), was == SafetyState::Fault);
                        if was == SafetyState::Fault {
                            stops += 1;
                            let want = if held { SafetyState::EStop } else { SafetyState::Disarmed(DisarmReason::FaultReset) };
                            prop_assert_eq!(core.state(), want);
                        }
                    }
                    Op::Restart => {
                        // A new core from the counter the ports keep.
                        core = SafetyCore::new(P, core.stops());
                        stops += 1;
                        armed_since_stop = false;
                        jumped = true;
                    }
                    Op::Tick { dt_s } => {
                        now += dt_s;
                        let state_before = core.state();
                        let out = core.tick(now);
                        if state_before == SafetyState::Armed && core.state() != SafetyState::Armed {
                            // The watchdog disarmed: a stop event.
                            stops += 1;
                        }
                        let (v, w) = (out.v_mps, out.w_radps);
                        prop_assert!(v.abs() <= P.max_speed_mps + 1e-9 && w.abs() <= P.max_yaw_rate_radps + 1e-9, "{v} {w}");
                        if matches!(core.state(), SafetyState::EStop | SafetyState::Fault) {
                            prop_assert!(out.quick_stop && v == 0.0 && w == 0.0);
                        }
                        let (a, b) = (wheels(prev), wheels((v, w)));
                        if !jumped {
                            // The tick clamps dt to ten periods.
                            let dt = dt_s.min(10.0 * P.period_s);
                            let rate = if core.state() == SafetyState::Armed { P.max_accel_mps2 } else { P.stop_decel_mps2 };
                            for k in 0..2 {
                                prop_assert!((b[k] - a[k]).abs() <= rate * dt + 1e-9, "wheel {k}: {} -> {} in {dt} s", a[k], b[k]);
                            }
                        }
                        if state_before != SafetyState::Armed && core.state() != SafetyState::Armed {
                            for k in 0..2 {
                                prop_assert!(b[k].abs() <= a[k].abs() + 1e-9, "wheel {k} sped up while not armed: {} -> {}", a[k], b[k]);
                            }
                        }
                        // Watchdog, then a stop from at most the top wheel speed, then one cycle.
                        let top_wheel = P.max_speed_mps + P.max_yaw_rate_radps * P.track_width_m / 2.0;
                        if now - fresh_at > P.command_timeout_s + top_wheel / P.stop_decel_mps2 + 11.0 * P.period_s {
                            prop_assert!(v == 0.0 && w == 0.0, "still moving {v} {w} {} s after the last fresh command", now - fresh_at);
                        }
                        // No motion after a fault, e-stop, halt or restart without a newer re-arm
                        // (a disarm or the watchdog only ramps down what was moving).
                        if !armed_since_stop && core.state() != SafetyState::Armed {
                            for k in 0..2 {
                                prop_assert!(b[k].abs() <= a[k].abs() + 1e-9, "wheel {k} sped up with no arm since the stop");
                            }
                        }
                        if jumped && !armed_since_stop {
                            prop_assert!(v == 0.0 && w == 0.0, "moving right after a halt, e-stop, fault or restart: {v} {w}");
                        }
                        prev = (v, w);
                        jumped = false;
                    }
                }
                prop_assert_eq!(core.stops(), stops, "the stop counter");
            }
        }
    }
}
