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
//!
//! It is one file because `SafetyHarness` must dispatch every input and check the latches exactly
//! as `SafetyActor` does, and both drive the same `SafetyCore`: side by side, the two stay in step.

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
mod tests;
