//! Fuzz a robot's whole downlink path, as its bridge and safety layer run it on Zenoh samples:
//! `Envelope::decode`, the bridge's checks (`DownlinkGate::on_cmd` on `fleet/robot-a/cmd`,
//! `DownlinkGate::on_estop` on `fleet/robot-a/estop/<sender>`), then the safety layer
//! (`SafetyHarness`: the core with robot-a's embedded configuration, the e-stop and fault latches,
//! the actor's dispatch), ticked every control cycle. Each input is one run of a fresh robot: a
//! sequence of operations, read until the input ends. The robot's clock (the fleet clock, Unix
//! seconds) starts at 2026-12-01T00:00:00Z and moves only in ticks; the wall clock (what sessions
//! compare with) is the fleet clock plus a skew the input may set.
//!
//! Each operation starts with one byte:
//! - `0x00..=0x5f`: a tick after a time step (one control period unless the next byte says
//!   otherwise);
//! - `0x60..=0xaf`: an envelope on the `cmd` key, built field by field: session and sequence number
//!   (the sender's next, a repeat, an older or newer session, one from the future, any), origin,
//!   robot, stamp (near now, seconds away, extreme), and body: what the server would send now (an
//!   arm carrying the robot's stop counter while it is disarmed, else a command), or a command, arm
//!   (right or wrong stop counter), disarm, e-stop, reset or an uplink message; then it may be
//!   corrupted by one byte;
//! - `0xb0..=0xcf`: the same on `fleet/robot-a/estop/<sender>`, the sender (server, operator, an
//!   unknown name, the other robot) from the next byte, an e-stop by default;
//! - `0xd0..=0xe7`: raw bytes (length from the next byte) on the `cmd` key or an e-stop key;
//! - `0xe8..=0xff`: an event on the robot: a drive halt (faulted, lost, rebooted drives, a lost
//!   bus), a report that does not halt, a local e-stop or reset, the e-stop input pressed or
//!   released, a supervisor escalation, a restart of the safety actor, a safety message lost on
//!   the link, a clock skew.
//!
//! A zero byte (and every byte read past the end is zero) takes the realistic default, so a run of
//! `0x60` followed by zeros arms the robot and drives it.
//!
//! Asserted: the bridge never refuses a stop (a disarm on `cmd` from the server, an e-stop on a
//! sender's key naming that sender), never passes an arm or reset stamped beyond its age limits,
//! nor anything for another robot or from another origin; the safety layer accepts a command only
//! while armed and an arm only with its current stop counter, within the command timeout; and
//! every wheel command is finite, within the limits, zero (with a quick stop) in e-stop and fault,
//! grows no faster than the acceleration limit, and after any stop (disarm, e-stop, halt, fault,
//! watchdog, lost message, restart) grows on no wheel until an arm was accepted after the stop.
//!
//! `DOWNLINK_PATH_SEEDS=<dir>` writes a few seeds into `<dir>` at start-up; `DOWNLINK_PATH_STATS=1`
//! prints what the bridge refused and what the safety layer did every 2^k inputs.
//!
//! One file because a fuzz target is one binary: the decoder of its input, the model it checks
//! against and the checks belong together.
#![no_main]

#[path = "common/reader.rs"]
mod reader;
use reader::Reader;

use std::collections::BTreeMap;
use std::sync::OnceLock;

use amr_actors::config::{ConfigSource, RobotConfig, load};
use amr_actors::robot::ports::{SafetyControl, SafetyInput, WheelCommand};
use amr_actors::robot::safety::{Applied, SafetyHarness};
use amr_msgs::{Command, Device, Downlink, Health, HealthReport, SCHEMA_VERSION, SafetyState, Uplink};
use amr_net::wire::{Body, DownlinkGate, Envelope, MAX_ENABLING_AGE_S, MAX_ENABLING_AHEAD_S, Reject};
use libfuzzer_sys::fuzz_target;

/// The robot's clock at the start of every run: 2026-12-01T00:00:00Z.
const START_S: f64 = 1_796_083_200.0;
const ME: &str = "robot-a";
const SERVER: &str = "server";
/// Who may e-stop (config/network.toml: the server and its operators).
const OPERATOR: &str = "operator";
/// The senders an e-stop key can name: the two allowed, a stranger, the other robot.
const SENDERS: [&str; 4] = [SERVER, OPERATOR, "mallory", "robot-b"];
/// Slack for float rounding in the output checks.
const EPS: f64 = 1e-9;

/// Robot-a's limits and timings (the embedded configuration).
struct Limits {
    max_speed: f64,
    max_yaw: f64,
    max_accel: f64,
    half_track: f64,
    period: f64,
    timeout: f64,
}

fn robot_config() -> &'static (RobotConfig, Limits) {
    static CONFIG: OnceLock<(RobotConfig, Limits)> = OnceLock::new();
    CONFIG.get_or_init(|| {
        let config = load(&ConfigSource::Embedded).expect("the embedded configuration loads");
        let robot = config.robots.iter().find(|r| r.id.as_str() == ME).expect("robot-a").clone();
        let limits = Limits {
            max_speed: robot.limits.max_speed_mps.get(),
            max_yaw: robot.limits.max_yaw_rate_radps.get(),
            max_accel: robot.limits.max_accel_mps2.get(),
            half_track: robot.kinematics.track_width_m.get() / 2.0,
            period: f64::from(robot.devices.can.sync_period_ms) / 1000.0,
            timeout: f64::from(robot.safety.command_timeout_ms.ms()) / 1000.0,
        };
        (robot, limits)
    })
}

fn stats_on() -> bool {
    static ON: OnceLock<bool> = OnceLock::new();
    *ON.get_or_init(|| std::env::var_os("DOWNLINK_PATH_STATS").is_some())
}

/// Counts by what happened, printed every 2^k inputs.
#[derive(Default)]
struct Stats {
    inputs: u64,
    by: BTreeMap<String, u64>,
}

static STATS: std::sync::Mutex<Option<Stats>> = std::sync::Mutex::new(None);

fn count(k: &str) {
    if stats_on() {
        let mut s = STATS.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        *s.get_or_insert_with(Stats::default).by.entry(k.to_owned()).or_default() += 1;
    }
}

fn input_done() {
    if stats_on() {
        let mut s = STATS.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        let s = s.get_or_insert_with(Stats::default);
        s.inputs += 1;
        if s.inputs.is_power_of_two() {
            eprintln!("downlink_path: {} inputs: {:?}", s.inputs, s.by);
        }
    }
}

/// Which key a sample came on.
#[derive(Clone, Copy, PartialEq)]
enum Key {
    Cmd,
    /// `fleet/robot-a/estop/<SENDERS[i]>`.
    Estop(usize),
}

/// One sender as its bridge stamps envelopes: its session (ns) and, per key, its last sequence
/// number.
#[derive(Clone, Copy)]
struct Sender {
    session: u64,
    seq: u64,
}

struct Robot {
    gate: DownlinkGate,
    safety: SafetyHarness,
    senders: Vec<String>,
    /// The fleet clock, and the wall clock's offset from it.
    now: f64,
    skew: f64,
    /// Per key: `cmd` (the server), then each e-stop key.
    stampers: [Sender; 5],
    /// The server's message counter (commands' sequence numbers, arms' floors).
    msg_seq: u64,
    /// An arm was accepted since the last stop.
    armed_since_stop: bool,
    /// The last output, and when.
    prev: (f64, f64),
    prev_at: Option<f64>,
}

impl Robot {
    fn new() -> Robot {
        let session = ((START_S - 100.0) * 1e9) as u64;
        Robot {
            gate: DownlinkGate::default(),
            safety: SafetyHarness::new(&robot_config().0),
            senders: vec![SERVER.to_owned(), OPERATOR.to_owned()],
            now: START_S,
            skew: 0.0,
            stampers: [Sender { session, seq: 0 }; 5],
            msg_seq: 1000,
            armed_since_stop: false,
            prev: (0.0, 0.0),
            prev_at: None,
        }
    }

    fn wall(&self) -> f64 {
        self.now + self.skew
    }

    fn stamper(key: Key) -> usize {
        match key {
            Key::Cmd => 0,
            Key::Estop(i) => 1 + i,
        }
    }

    /// A structured envelope on `key`, as its sender's bridge (or a forger) would build it.
    fn structured(&mut self, key: Key, r: &mut Reader<'_>) -> Vec<u8> {
        let k = Self::stamper(key);
        let right = match key {
            Key::Cmd => SERVER,
            Key::Estop(i) => SENDERS[i],
        };
        // Session and sequence number.
        let mut st = self.stampers[k];
        match r.u8() {
            0..=191 => {}
            192..=207 => st.session = st.session.saturating_sub(1_000_000_000 * u64::from(1 + r.u8() % 100)),
            208..=223 => {
                // The sender restarted: a newer session, numbered afresh.
                st.session = st.session.saturating_add(1_000_000 * (1 + u64::from(r.u16())));
                st.seq = 0;
                self.stampers[k] = st;
            }
            224..=239 => st.session = ((self.wall() + 6.0 + f64::from(r.u8())) * 1e9) as u64,
            _ => st.session = r.u64(),
        }
        let seq = match r.u8() {
            0..=191 => {
                self.stampers[k].seq += 1;
                self.stampers[k].seq
            }
            192..=223 => self.stampers[k].seq,
            224..=239 => self.stampers[k].seq.saturating_sub(1 + u64::from(r.u8())),
            _ => r.u64(),
        };
        let origin = match r.u8() {
            0..=223 => right.to_owned(),
            s => ["server", "operator", "robot-a", "robot-b", "", "mallory", "Server", "server "]
                [usize::from(s % 8)]
            .to_owned(),
        };
        let robot = match r.u8() {
            0..=239 => ME.to_owned(),
            s => ["robot-b", "", "robot-a ", "ROBOT-A"][usize::from(s % 4)].to_owned(),
        };
        let stamp_s = self.now - r.real(0.003, -5.0, 5.0);
        let body = match key {
            Key::Cmd => self.cmd_body(stamp_s, r),
            Key::Estop(_) => match r.u8() {
                0..=127 => Downlink::EStop,
                128..=223 => Downlink::ResetEStop,
                _ => self.cmd_body(stamp_s, r),
            },
        };
        let body = match r.u8() {
            0..=247 => Body::Downlink(body),
            _ => Body::Uplink(Uplink::Safety {
                robot: ME.to_owned(),
                seq: 1,
                stamp_s,
                state: SafetyState::Armed,
                stops: self.safety.stops(),
                mock: false,
            }),
        };
        let env = Envelope {
            version: SCHEMA_VERSION,
            session: st.session,
            seq,
            origin,
            robot,
            stamp_s,
            sent_s: stamp_s + 0.001,
            body,
        };
        let bytes = env.encode().expect("an envelope always encodes (net/src/wire/mod.rs)");
        // What was encoded decodes to the same bytes (NaN stamps are refused).
        match Envelope::decode(&bytes) {
            Ok(back) => assert_eq!(back.encode().ok().as_ref(), Some(&bytes), "{env:?} changed on the wire"),
            Err(Reject::NotFinite(_)) => assert!(!(stamp_s.is_finite())),
            Err(e) => panic!("{env:?} does not decode: {e}"),
        }
        bytes
    }

    /// A downlink message: by default what the server would send now.
    fn cmd_body(&mut self, stamp_s: f64, r: &mut Reader<'_>) -> Downlink {
        let kind = match r.u8() {
            0..=127 => match self.safety.state() {
                SafetyState::Disarmed(_) => 1,
                _ => 0,
            },
            128..=175 => 0,
            176..=207 => 1,
            208..=223 => 2,
            224..=239 => 3,
            _ => 4,
        };
        match kind {
            0 => {
                let seq = match r.u8() {
                    0..=223 => {
                        self.msg_seq += 1;
                        self.msg_seq
                    }
                    224..=239 => self.msg_seq.saturating_sub(u64::from(r.u8())),
                    _ => r.u64(),
                };
                let stamp = match r.u8() {
                    0..=223 => stamp_s,
                    _ => self.now - r.real(0.0, -1.0, 1.0),
                };
                Downlink::Command(Command {
                    seq,
                    stamp_s: stamp,
                    v_mps: r.real(0.2, -1.0, 1.0),
                    w_radps: r.real(0.05, -1.0, 1.0),
                })
            }
            1 => {
                let floor = match r.u8() {
                    0..=223 => self.msg_seq + 1,
                    _ => r.u64(),
                };
                let stops = match r.u8() {
                    0..=191 => self.safety.stops(),
                    192..=223 => self.safety.stops().wrapping_sub(1 + u64::from(r.u8() % 4)),
                    224..=239 => self.safety.stops().wrapping_add(1),
                    _ => r.u64(),
                };
                let stamp = match r.u8() {
                    0..=223 => stamp_s,
                    _ => self.now - r.real(0.0, -1.0, 1.0),
                };
                Downlink::Arm { seq: floor, stops, stamp_s: stamp }
            }
            2 => Downlink::Disarm,
            3 => Downlink::EStop,
            _ => Downlink::ResetEStop,
        }
    }

    /// A sample on `key`: decoded, through the bridge's gate, into the safety layer.
    fn receive(&mut self, key: Key, bytes: &[u8]) {
        let env = match Envelope::decode(bytes) {
            Ok(env) => env,
            Err(e) => {
                count(&format!("decode:{}", e.kind()));
                return;
            }
        };
        let (now, wall) = (self.now, self.wall());
        let got = match key {
            Key::Cmd => self.gate.on_cmd(&env, ME, SERVER, now, wall),
            Key::Estop(i) => self.gate.on_estop(&env, ME, SENDERS[i], &self.senders, now, wall),
        };
        let sender = match key {
            Key::Cmd => SERVER,
            Key::Estop(i) => SENDERS[i],
        };
        let allowed = match key {
            Key::Cmd => true,
            Key::Estop(_) => self.senders.iter().any(|s| s == sender),
        };
        let legit = env.robot == ME && env.origin == sender && allowed;
        // A stop from whoever may send it is never refused.
        match (key, &env.body) {
            (Key::Cmd, Body::Downlink(Downlink::Disarm))
            | (Key::Estop(_), Body::Downlink(Downlink::EStop))
                if legit =>
            {
                assert!(got.is_ok(), "a stop on the {sender} key was refused: {got:?} ({env:?})");
            }
            _ => {}
        }
        let d = match got {
            Ok(d) => d,
            Err(e) => {
                count(&format!("gate:{}", e.kind()));
                return;
            }
        };
        assert!(legit, "{d:?} passed from {} about {} on the {sender} key", env.origin, env.robot);
        assert!(matches!(&env.body, Body::Downlink(x) if kind(x) == kind(&d)), "{d:?} from {env:?}");
        if matches!(key, Key::Estop(_)) {
            assert!(matches!(d, Downlink::EStop | Downlink::ResetEStop), "{d:?} on an e-stop key");
        }
        if matches!(d, Downlink::Arm { .. } | Downlink::ResetEStop) {
            let age = now - env.stamp_s;
            assert!(
                age <= MAX_ENABLING_AGE_S && -age <= MAX_ENABLING_AHEAD_S,
                "{d:?} stamped {age} s ago passed"
            );
        }
        count(&format!("gate:ok:{}", kind(&d)));
        self.feed(SafetyInput::Link(d));
    }

    /// One input to the safety layer at the current time.
    fn feed(&mut self, input: SafetyInput) {
        let (state, stops) = (self.safety.state(), self.safety.stops());
        let a: Applied = self.safety.apply(input.clone(), self.now);
        let what = match &input {
            SafetyInput::Link(d) => kind(d),
            SafetyInput::Control(SafetyControl::EStop) => "local-estop",
            SafetyInput::Control(SafetyControl::ResetEStop) => "local-reset",
            SafetyInput::Health(_) => "health",
            SafetyInput::EStopInput => "estop-input",
            SafetyInput::Missed => "missed",
        };
        count(&format!("safety:{what}:{}", if a.taken { "taken" } else { "refused" }));
        let stop = match &input {
            SafetyInput::Link(Downlink::Disarm | Downlink::EStop)
            | SafetyInput::Control(SafetyControl::EStop)
            | SafetyInput::EStopInput
            | SafetyInput::Missed => true,
            SafetyInput::Health(_) => a.taken,
            _ => false,
        };
        if stop || self.safety.stops() != stops {
            self.armed_since_stop = false;
        }
        match input {
            SafetyInput::Link(Downlink::Arm { stops: carried, stamp_s, .. }) if a.taken => {
                assert_eq!(carried, stops, "an arm with another stop counter was taken");
                assert!(!matches!(state, SafetyState::EStop | SafetyState::Fault), "armed from {state:?}");
                assert!((self.now - stamp_s).abs() <= self.limits().timeout, "an expired arm was taken");
                assert_eq!(self.safety.stops(), stops);
                self.armed_since_stop = true;
            }
            SafetyInput::Link(Downlink::Command(c)) if a.taken => {
                assert_eq!(state, SafetyState::Armed, "{c:?} taken while {state:?}");
                assert!(c.v_mps.is_finite() && c.w_radps.is_finite());
            }
            _ => {}
        }
        if let Some(out) = a.output {
            self.check(out);
        }
    }

    fn limits(&self) -> &'static Limits {
        &robot_config().1
    }

    /// A control cycle after `dt` s.
    fn tick(&mut self, dt: f64) {
        self.now += dt;
        let stops = self.safety.stops();
        let out = self.safety.tick(self.now);
        if self.safety.stops() != stops {
            count(&format!("tick:stopped:{:?}", self.safety.state()));
            self.armed_since_stop = false;
        }
        self.check(out);
    }

    /// The invariants of one wheel command applied now.
    fn check(&mut self, out: WheelCommand) {
        let l = self.limits();
        let (v, w) = (out.v_mps, out.w_radps);
        assert!(v.is_finite() && w.is_finite(), "output {out:?}");
        assert!(
            v.abs() <= l.max_speed + EPS && w.abs() <= l.max_yaw + EPS,
            "output {out:?} beyond the limits"
        );
        let state = self.safety.state();
        if matches!(state, SafetyState::EStop | SafetyState::Fault) {
            assert!(v == 0.0 && w == 0.0 && out.quick_stop, "{out:?} in {state:?}");
        }
        if state == SafetyState::Armed {
            assert!(self.armed_since_stop, "armed with no arm accepted since the last stop");
        }
        let wheels = |(v, w): (f64, f64)| [v - w * l.half_track, v + w * l.half_track];
        let (a, b) = (wheels(self.prev), wheels((v, w)));
        let dt = self.prev_at.map_or(10.0 * l.period, |t| (self.now - t).clamp(0.0, 10.0 * l.period));
        for k in 0..2 {
            assert!(
                b[k].abs() <= a[k].abs() + l.max_accel * dt + EPS,
                "wheel {k}: {} -> {} in {dt} s, faster than the acceleration limit",
                a[k],
                b[k]
            );
            if !self.armed_since_stop {
                assert!(
                    b[k].abs() <= a[k].abs() + EPS,
                    "wheel {k} sped up ({} -> {}) with no arm since the last stop ({state:?})",
                    a[k],
                    b[k]
                );
            }
        }
        if v != 0.0 || w != 0.0 {
            count("output:moving");
        }
        self.prev = (v, w);
        self.prev_at = Some(self.now);
    }

    /// An event on the robot.
    fn event(&mut self, e: u8, r: &mut Reader<'_>) {
        let report = |device, health| HealthReport { device, health, detail: String::new() };
        match e {
            0 => self.feed(SafetyInput::Health(report(Device::Drives, Health::Degraded))),
            1 => self.feed(SafetyInput::Health(report(Device::Drives, Health::Lost))),
            2 => self.feed(SafetyInput::Health(report(Device::Drives, Health::Starting))),
            3 => self.feed(SafetyInput::Health(report(Device::CanBus, Health::Lost))),
            4 | 5 => self.feed(SafetyInput::Control(SafetyControl::EStop)),
            6 | 7 => self.feed(SafetyInput::Control(SafetyControl::ResetEStop)),
            8 | 9 => {
                let stops = self.safety.stops();
                let a = self.safety.estop_input(e == 8, self.now);
                if e == 8 || self.safety.stops() != stops {
                    self.armed_since_stop = false;
                }
                if let Some(out) = a.output {
                    self.check(out);
                }
            }
            10 => {
                // Seen by the next cycle.
                self.safety.escalate();
                count("event:escalate");
            }
            11 => {
                self.armed_since_stop = false;
                // A new core outputs zero from the start.
                self.prev = (0.0, 0.0);
                self.prev_at = None;
                if let Some(out) = self.safety.restart(self.now) {
                    self.check(out);
                }
                count("event:restart");
            }
            12 => self.feed(SafetyInput::Missed),
            13 => {
                let device =
                    [Device::Lidar, Device::Imu, Device::Odometry, Device::CanBus][usize::from(r.u8() % 4)];
                let health = if device == Device::CanBus { Health::Degraded } else { Health::Lost };
                self.feed(SafetyInput::Health(report(device, health)));
            }
            14 => self.skew = r.real(0.0, -10.0, 10.0).clamp(-1e6, 1e6),
            _ => self.feed(SafetyInput::Health(report(Device::Drives, Health::Ok))),
        }
        if !self.skew.is_finite() {
            self.skew = 0.0;
        }
    }
}

fn kind(d: &Downlink) -> &'static str {
    match d {
        Downlink::Command(_) => "command",
        Downlink::Arm { .. } => "arm",
        Downlink::Disarm => "disarm",
        Downlink::EStop => "estop",
        Downlink::ResetEStop => "reset",
    }
}

impl Reader<'_> {
    /// Mostly `default`, else a value in `lo..=hi`, else one of the edge values.
    fn real(&mut self, default: f64, lo: f64, hi: f64) -> f64 {
        match self.u8() {
            0..=127 => default,
            128..=223 => lo + (hi - lo) * f64::from(self.u16()) / f64::from(u16::MAX),
            s => match s - 224 {
                0 => 0.0,
                1 => -0.0,
                2 => f64::NAN,
                3 => f64::INFINITY,
                4 => f64::NEG_INFINITY,
                5 => f64::MIN_POSITIVE,
                6 => 5e-324,
                7 => 1e-9,
                8 => -1e-9,
                9 => f64::MAX,
                10 => f64::MIN,
                11 => 0.2,
                12 => 0.200_000_000_1,
                13 => -0.2,
                14 => 0.5,
                15 => 0.500_000_000_1,
                16 => -0.5,
                17 => -0.500_000_000_1,
                18 => 2.0,
                19 => 2.000_000_001,
                20 => -2.0,
                21 => 1e6,
                22 => -1e6,
                23 => 1e300,
                24 => 0.22,
                25 => -0.22,
                26 => 100.0,
                27 => 1.0,
                28 => -default,
                29 => default * 2.0,
                30 => f64::EPSILON,
                _ => f64::from_bits(self.u64()),
            },
        }
    }
}

/// The time step of a tick: one control period by default.
fn step(r: &mut Reader<'_>, period: f64) -> f64 {
    match r.u8() {
        0..=191 => period,
        192..=223 => f64::from(r.u8()) / 255.0 * 0.3,
        224..=231 => 0.0,
        s => [0.001, 0.199, 0.2, 0.201, 0.5, 2.0, 10.0, 1000.0][usize::from(s - 232) % 8],
    }
}

fn run(data: &[u8]) {
    let mut robot = Robot::new();
    let mut r = Reader(data);
    let period = robot.limits().period;
    while !r.is_empty() {
        match r.u8() {
            0x00..=0x5f => {
                let dt = step(&mut r, period);
                robot.tick(dt);
            }
            0x60..=0xaf => {
                let bytes = robot.structured(Key::Cmd, &mut r);
                let bytes = corrupt(bytes, &mut r);
                robot.receive(Key::Cmd, &bytes);
            }
            0xb0..=0xcf => {
                let key = Key::Estop(usize::from(r.u8() % 4));
                let bytes = robot.structured(key, &mut r);
                let bytes = corrupt(bytes, &mut r);
                robot.receive(key, &bytes);
            }
            b @ 0xd0..=0xe7 => {
                let key = if b < 0xdc { Key::Cmd } else { Key::Estop(usize::from(r.u8() % 4)) };
                let n = usize::from(r.u8());
                let bytes = r.bytes(n);
                robot.receive(key, &bytes);
            }
            b => {
                let e = b - 0xe8;
                robot.event(e, &mut r);
            }
        }
    }
    input_done();
}

/// Maybe one byte of `bytes` replaced (position and value from the input).
fn corrupt(mut bytes: Vec<u8>, r: &mut Reader<'_>) -> Vec<u8> {
    if r.u8() >= 248 && !bytes.is_empty() {
        let i = usize::from(r.u16()) % bytes.len();
        bytes[i] = r.u8();
    }
    bytes
}

/// Seed inputs: arm and drive, then stop every way, arm again and drive; an e-stop reset by the
/// operator before the re-arm.
fn write_seeds(dir: &std::path::Path) {
    std::fs::create_dir_all(dir).expect("the seed directory");
    // An arm (what the server sends while the robot is disarmed): the op byte and 11 defaults; a
    // command: 12 defaults; a tick of one period: 2 bytes.
    let arm = || [&[0x60u8][..], &[0; 11]].concat();
    let drive =
        |n: usize| -> Vec<u8> { (0..n).flat_map(|_| [&[0x60u8][..], &[0; 12], &[0, 0]].concat()).collect() };
    let estop_key =
        |sender: u8, reset: bool| vec![0xb0, sender, 0, 0, 0, 0, 0, if reset { 128 } else { 0 }, 0, 0];
    let start = [arm(), drive(60)].concat();
    let mut seeds: Vec<(String, Vec<u8>)> = vec![("drive".into(), start.clone())];
    let stops: [(&str, Vec<u8>); 9] = [
        ("disarm", vec![0x60, 0, 0, 0, 0, 0, 208, 0, 0]),
        ("estop-server", estop_key(0, false)),
        ("estop-operator", estop_key(1, false)),
        ("local-estop", vec![0xec]),
        ("halt", vec![0xe8]),
        ("escalate", vec![0xf2, 0, 0]),
        ("restart", vec![0xf3]),
        ("missed", vec![0xf4]),
        ("watchdog", vec![0, 237]),
    ];
    for (name, stop) in stops {
        seeds.push((
            format!("drive-{name}-rearm"),
            [start.clone(), stop, drive(5), arm(), drive(30)].concat(),
        ));
    }
    let reset = [start.clone(), estop_key(1, false), drive(5), estop_key(1, true), arm(), drive(30)].concat();
    seeds.push(("estop-reset-rearm".into(), reset));
    for (name, bytes) in seeds {
        std::fs::write(dir.join(name), bytes).expect("a seed file");
    }
}

fuzz_target!(
    init: {
        if let Some(dir) = std::env::var_os("DOWNLINK_PATH_SEEDS") {
            write_seeds(std::path::Path::new(&dir));
        }
        robot_config();
    },
    |data: &[u8]| run(data)
);
