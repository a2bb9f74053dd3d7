//! Fuzz the server formation's handling of what the robots report and the localizer estimates:
//! each input starts a fresh formation (`FormationHarness`: the actor built as `start_server`
//! builds it from the embedded configuration, robot-a and robot-b, started by its own `pre_start`)
//! on a link whose robot ends the target holds, in a current-thread tokio runtime whose clock is
//! paused, and gives the actor's own handler odometry, health and safety reports, estimates, fusion
//! status, the operator's rearm and stop, and a tick every formation period as the clock advances
//! (the 20 Hz timer of a running actor). After each tick (and stop) the target reads every message
//! the formation sent down the link and checks it against what the robots last reported.
//!
//! The first byte chooses the scenario (straight, or one lap of turning, hall-turning or corridor),
//! what a lost robot does (stop or hold), the auto-arm mode (off, mock, hardware) and whether an
//! earlier formation on the plan left a progress record. Then each operation starts with one byte:
//! - `0x00..=0x3f`: the clock advances one formation period (a tick), or as the next byte says;
//! - `0x40..=0x5f`: every robot reports as a robot of the target's model would (odometry, its
//!   safety state and stop counter, mock devices, devices Ok); the model arms on an arm carrying its
//!   stop counter, follows commands while armed, drives its odometry, disarms on a disarm and on
//!   its watchdog;
//! - `0x60..=0x7f`: odometry of a robot (or an unknown one), field by field: sequence numbers that
//!   go back or repeat, new frames, stamps, NaN, infinite or huge poses and twists;
//! - `0x80..=0x8f`: a health report (any device, any health);
//! - `0x90..=0xaf`: a safety report (any state, right or wrong stop counter, mock or not), which the
//!   model takes on;
//! - `0xb0..=0xcf`: an estimate: fused with the model's poses by default, else any source, stamps,
//!   anchors (none, shifted, huge), integrity and disagreement;
//! - `0xd0..=0xdf`: the fusion's status (fusing, or a robot lost);
//! - `0xe0..=0xe7`: the operator's rearm; `0xe8..=0xef`: the operator's stop;
//! - `0xf0..=0xff`: the clock jumps (up to seconds).
//!
//! A zero byte (and every byte read past the end is zero) takes the realistic default.
//!
//! Asserted for every message the formation sends: a command is finite, stamped, within the
//! scenario's limits, numbered above the robot's last message and at or above its last arm's
//! floor; a command that is not zero goes out only while every robot's last safety report is
//! `Armed`; no arm and no moving command after a disarm until the operator's rearm; an arm carries
//! the robot's last reported stop counter, goes to no robot while any robot's last report is
//! `EStop` or `Fault`, and without the operator's rearm only under auto-arm (on mock robots only
//! unless auto-arm covers hardware). And nothing panics.
//!
//! `FORMATION_INPUTS_SEEDS=<dir>` writes seeds into `<dir>` at start-up;
//! `FORMATION_INPUTS_STATS=1` prints the phases reached and the messages sent every 2^k inputs.
//!
//! One file because a fuzz target is one binary: the decoder of its input, the model it checks
//! against and the checks belong together.
#![no_main]

#[path = "common/reader.rs"]
mod reader;
use reader::Reader;

use std::collections::BTreeMap;
use std::sync::{Arc, OnceLock};
use std::time::Duration;

use amr_actors::clock::FleetClock;
use amr_actors::config::{ConfigSource, load};
use amr_actors::link::DownlinkSender;
use amr_actors::server::formation::{FormationHarness, FormationMsg, Phase};
use amr_actors::server::progress::{PlanProgress, plan_id};
use amr_actors::server::{AutoArm, ServerSetup, formation_robots};
use amr_actors::supervisor::RestartPolicy;
use amr_core::amcl::IntegrityState;
use amr_core::config::value::Count;
use amr_core::config::{Configuration, OnRobotLost, ScenarioConfig};
use amr_core::map::OccupancyGrid;
use amr_core::se2::Se2;
use amr_msgs::{
    Anchored, Device, DisarmReason, Downlink, Estimate, EstimateIntegrity, EstimateSource, FusionStatus,
    Health, HealthReport, OdomMsg, SafetyState, Uplink,
};
use libfuzzer_sys::fuzz_target;
use tokio::sync::mpsc;

/// The formation's control period (`FORMATION_PERIOD_S` in actors/src/server/mod.rs), s.
const PERIOD_S: f64 = 0.05;
/// The robots' command timeout (config/robot-*.toml), s.
const COMMAND_TIMEOUT_S: f64 = 0.2;
const EPS: f64 = 1e-9;

/// What every input starts from.
struct Base {
    setup: ServerSetup,
    robots: Vec<String>,
    /// The scenarios (one lap each), with their plan's identity and length, s.
    scenarios: Vec<(ScenarioConfig, String, f64)>,
    runtime: tokio::runtime::Runtime,
}

fn base() -> &'static Base {
    static BASE: OnceLock<Base> = OnceLock::new();
    BASE.get_or_init(|| {
        let config = load(&ConfigSource::Embedded).expect("the embedded configuration loads");
        let robots = formation_robots(&config.server, &config.robots).expect("the formation's robots");
        let ids = robots.iter().map(|r| r.id.as_str().to_owned()).collect();
        let scenarios = ["straight", "turning", "hall-turning", "corridor"]
            .iter()
            .map(|name| {
                let mut sc = config.scenarios[*name].clone();
                sc.laps = Count::new(1).expect("one lap");
                let plan = amr_core::plan::reference(&sc, robots.len(), PERIOD_S);
                let id = plan_id(&plan);
                let len = plan.len() as f64 * PERIOD_S;
                (sc, id, len)
            })
            .collect();
        // No localizer runs here: its settings are never used.
        let mut amcl = config.amcl.clone();
        amcl.min_particles = Count::new(10).expect("a count");
        amcl.max_particles = Count::new(10).expect("a count");
        let map = OccupancyGrid::filled(8, 8, 0.5, Se2::new(-2.0, -2.0, 0.0), 0);
        let setup = ServerSetup {
            server: config.server.clone(),
            vamr: config.vamr.clone(),
            amcl,
            map,
            robots,
            scenario: config.scenarios["straight"].clone(),
            seed: 1,
            auto_arm: AutoArm::Off,
            policy: RestartPolicy::default(),
            progress: Arc::new(PlanProgress::in_memory()),
        };
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_time()
            .start_paused(true)
            .build()
            .expect("a runtime");
        Base { setup, robots: ids, scenarios, runtime }
    })
}

fn stats_on() -> bool {
    static ON: OnceLock<bool> = OnceLock::new();
    *ON.get_or_init(|| std::env::var_os("FORMATION_INPUTS_STATS").is_some())
}

static STATS: std::sync::Mutex<(u64, BTreeMap<String, u64>)> = std::sync::Mutex::new((0, BTreeMap::new()));

fn count(k: String) {
    if stats_on() {
        *STATS.lock().unwrap_or_else(std::sync::PoisonError::into_inner).1.entry(k).or_default() += 1;
    }
}

/// One robot as the target models it: what it would report.
#[derive(Debug, Clone)]
struct Model {
    /// Where it started, in the map (its slot around V's start).
    start: Se2,
    odom: OdomMsg,
    state: SafetyState,
    stops: u64,
    floor: u64,
    cmd: (f64, f64),
    cmd_at: f64,
}

impl Model {
    fn map_pose(&self) -> Se2 {
        self.start * self.odom.pose
    }

    /// What the formation sent it.
    fn receive(&mut self, d: Downlink, now: f64) {
        match d {
            Downlink::Arm { seq, stops, .. } => {
                if matches!(self.state, SafetyState::Disarmed(_)) && stops == self.stops {
                    self.state = SafetyState::Armed;
                    self.floor = seq;
                    self.cmd = (0.0, 0.0);
                    self.cmd_at = now;
                }
            }
            Downlink::Disarm => {
                self.stops = self.stops.wrapping_add(1);
                if matches!(self.state, SafetyState::Armed | SafetyState::Disarmed(_)) {
                    self.state = SafetyState::Disarmed(DisarmReason::Requested);
                }
                self.cmd = (0.0, 0.0);
            }
            Downlink::Command(c) => {
                if self.state == SafetyState::Armed
                    && c.seq >= self.floor
                    && c.v_mps.is_finite()
                    && c.w_radps.is_finite()
                {
                    self.cmd = (c.v_mps, c.w_radps);
                    self.cmd_at = now;
                }
            }
            Downlink::EStop | Downlink::ResetEStop => {}
        }
    }

    /// `dt` s pass.
    fn advance(&mut self, dt: f64, now: f64) {
        if self.state != SafetyState::Armed {
            return;
        }
        if now - self.cmd_at > COMMAND_TIMEOUT_S {
            self.state = SafetyState::Disarmed(DisarmReason::Watchdog);
            self.stops = self.stops.wrapping_add(1);
            self.cmd = (0.0, 0.0);
            return;
        }
        let (v, w) = self.cmd;
        self.odom.pose = self.odom.pose * amr_core::odometry::arc(v * dt, w * dt);
        self.odom.twist = (v, w);
    }
}

/// Everything one input runs with.
struct Run<'a> {
    formation: FormationHarness,
    downs: Vec<mpsc::Receiver<Downlink>>,
    clock: FleetClock,
    robots: &'a [String],
    models: Vec<Model>,
    configuration: Configuration,
    auto_arm: AutoArm,
    limits: (f64, f64),
    /// Per robot: its last safety report, stop counter and mock flag as reported.
    reported: Vec<(Option<SafetyState>, u64, bool)>,
    /// Per robot: the last message number and the last arm's floor.
    seq: Vec<(u64, u64)>,
    /// A disarm went out and the operator has not re-armed since.
    needs_rearm: bool,
    /// The operator re-armed in this run.
    operator_rearmed: bool,
    /// Per robot: its devices were last reported Ok by the model.
    healthy: Vec<bool>,
    phase: Phase,
}

impl Run<'_> {
    fn now(&self) -> f64 {
        self.clock.now_s()
    }

    fn cast(&mut self, msg: FormationMsg) {
        self.formation.handle(msg).expect("the formation handles it");
    }

    /// Check what the formation sent.
    fn drain(&mut self) {
        if stats_on() {
            let phase = self.formation.status().phase;
            if phase != self.phase {
                count(format!("phase:{}", phase_name(&phase)));
            }
            self.phase = phase;
        }
        let now = self.now();
        for i in 0..self.downs.len() {
            while let Ok(d) = self.downs[i].try_recv() {
                self.check(i, d, now);
                self.models[i].receive(d, now);
            }
        }
    }

    /// The invariants of message `d` to robot `i`, sent by now.
    fn check(&mut self, i: usize, d: Downlink, now: f64) {
        let robot = &self.robots[i];
        let (last, floor) = self.seq[i];
        let all_armed = self.reported.iter().all(|r| r.0 == Some(SafetyState::Armed));
        match d {
            Downlink::Command(c) => {
                let (v_max, w_max) = self.limits;
                assert!(
                    c.v_mps.is_finite() && c.w_radps.is_finite() && c.stamp_s.is_finite(),
                    "a command that is not finite to {robot}: {c:?}"
                );
                assert!(
                    c.v_mps.abs() <= v_max + EPS && c.w_radps.abs() <= w_max + EPS,
                    "a command beyond the limits to {robot}: {c:?}"
                );
                assert!(c.stamp_s <= now + EPS, "a command stamped in the future: {c:?} at {now}");
                assert!(
                    c.seq > last && c.seq >= floor,
                    "{c:?} to {robot} after message {last}, floor {floor}"
                );
                self.seq[i].0 = c.seq;
                if c.v_mps != 0.0 || c.w_radps != 0.0 {
                    assert!(all_armed, "{c:?} to {robot} while the robots report {:?}", self.reported);
                    assert!(!self.needs_rearm, "{c:?} to {robot} after a disarm, with no rearm since");
                    count("sent:moving".into());
                } else {
                    count("sent:zero".into());
                }
            }
            Downlink::Arm { seq, stops, stamp_s } => {
                assert!(!self.needs_rearm, "an arm to {robot} after a disarm, with no rearm since");
                assert!(
                    !self
                        .reported
                        .iter()
                        .any(|r| matches!(r.0, Some(SafetyState::EStop | SafetyState::Fault))),
                    "an arm to {robot} while the robots report {:?}",
                    self.reported
                );
                assert_eq!(stops, self.reported[i].1, "an arm to {robot} with another stop counter");
                assert!(stamp_s.is_finite() && stamp_s <= now + EPS);
                if !self.operator_rearmed {
                    match self.auto_arm {
                        AutoArm::Off => panic!("an arm to {robot} with auto-arm off and no rearm"),
                        AutoArm::Mock => assert!(
                            self.reported.iter().all(|r| r.2),
                            "auto-arm of robots on hardware: {:?}",
                            self.reported
                        ),
                        AutoArm::Hardware => {}
                    }
                }
                assert!(seq > last, "an arm numbered {seq} after message {last}");
                self.seq[i] = (seq - 1, seq);
                count("sent:arm".into());
            }
            Downlink::Disarm => {
                self.needs_rearm = true;
                count("sent:disarm".into());
            }
            Downlink::EStop | Downlink::ResetEStop => panic!("the formation sent {d:?}"),
        }
    }

    /// The clock advances `dt` s, a formation period at a time, the formation ticking at each.
    async fn advance(&mut self, dt: f64) {
        let mut left = dt;
        while left > 0.0 {
            let step = left.min(PERIOD_S);
            left -= step;
            tokio::time::advance(Duration::from_secs_f64(step)).await;
            let now = self.now();
            for m in &mut self.models {
                m.advance(step, now);
            }
            self.cast(FormationMsg::Tick);
            self.drain();
        }
    }

    fn robot(&self, r: &mut Reader<'_>) -> (Option<usize>, String) {
        let b = r.u8();
        if b >= 240 {
            return (None, ["robot-x", "", "robot-a "][usize::from(b % 3)].to_owned());
        }
        let i = usize::from(b) % self.robots.len();
        (Some(i), self.robots[i].clone())
    }

    fn uplink(&mut self, u: Uplink) {
        if let Uplink::Safety { robot, state, stops, mock, .. } = &u
            && let Some(i) = self.robots.iter().position(|r| r == robot)
        {
            self.reported[i] = (Some(*state), *stops, *mock);
        }
        self.cast(FormationMsg::Uplink(Box::new(u)));
    }

    /// Every robot reports as the model says.
    fn report_all(&mut self) {
        let now = self.now();
        for i in 0..self.robots.len() {
            let robot = self.robots[i].clone();
            let m = &mut self.models[i];
            m.odom.seq = m.odom.seq.wrapping_add(1);
            m.odom.stamp_s = now;
            let (odom, state, stops) = (m.odom, m.state, m.stops);
            self.uplink(Uplink::Odom { robot: robot.clone(), msg: odom });
            self.uplink(Uplink::Safety {
                robot: robot.clone(),
                seq: 0,
                stamp_s: now,
                state,
                stops,
                mock: true,
            });
            // Devices Ok, said again only after another report.
            if !std::mem::replace(&mut self.healthy[i], true) {
                for device in [Device::Lidar, Device::CanBus, Device::Drives] {
                    let report = HealthReport { device, health: Health::Ok, detail: String::new() };
                    self.uplink(Uplink::Health { robot: robot.clone(), seq: 0, stamp_s: now, report });
                }
            }
        }
    }

    fn odom(&mut self, r: &mut Reader<'_>) {
        let now = self.now();
        let (i, robot) = self.robot(r);
        let mut msg = i.map_or(
            OdomMsg { seq: 1, frame: 1, stamp_s: now, pose: Se2::IDENTITY, twist: (0.0, 0.0), gyro: true },
            |i| self.models[i].odom,
        );
        msg.seq = match r.u8() {
            0..=191 => msg.seq.wrapping_add(1),
            192..=207 => msg.seq,
            208..=223 => msg.seq.saturating_sub(1 + u64::from(r.u8())),
            _ => r.u64(),
        };
        match r.u8() {
            0..=223 => {}
            224..=239 => {
                // The robot's odometry restarted: a new frame from the origin.
                msg.frame = msg.frame.wrapping_add(1);
                msg.seq = 1;
                msg.pose = Se2::IDENTITY;
            }
            _ => msg.frame = r.u64(),
        }
        msg.stamp_s = now - r.real(0.0, -2.0, 2.0);
        if r.u8() >= 128 {
            msg.pose = Se2 {
                x: r.real(msg.pose.x, -50.0, 50.0),
                y: r.real(msg.pose.y, -50.0, 50.0),
                theta: r.real(msg.pose.theta, -7.0, 7.0),
            };
            msg.twist = (r.real(msg.twist.0, -1.0, 1.0), r.real(msg.twist.1, -1.0, 1.0));
            msg.gyro = r.u8() < 128;
        }
        if let Some(i) = i {
            // The model's robot drives on from there.
            self.models[i].odom = msg;
        }
        self.uplink(Uplink::Odom { robot, msg });
    }

    fn health(&mut self, r: &mut Reader<'_>) {
        let (i, robot) = self.robot(r);
        if let Some(i) = i {
            self.healthy[i] = false;
        }
        let b = r.u8();
        let device = [
            Device::Lidar,
            Device::CanBus,
            Device::Drives,
            Device::Imu,
            Device::Odometry,
            Device::Safety,
            Device::Link,
        ][usize::from(b % 7)];
        let health = [Health::Ok, Health::Starting, Health::Degraded, Health::Lost, Health::Fault]
            [usize::from(r.u8() % 5)];
        let report = HealthReport { device, health, detail: String::new() };
        self.uplink(Uplink::Health { robot, seq: 0, stamp_s: self.now(), report });
    }

    fn safety(&mut self, r: &mut Reader<'_>) {
        let (i, robot) = self.robot(r);
        let state = match r.u8() % 10 {
            0 => SafetyState::Armed,
            1 => SafetyState::EStop,
            2 => SafetyState::Fault,
            k => SafetyState::Disarmed(
                [
                    DisarmReason::Startup,
                    DisarmReason::Watchdog,
                    DisarmReason::Requested,
                    DisarmReason::EStopReset,
                    DisarmReason::DeviceLost,
                    DisarmReason::QueueFull,
                    DisarmReason::FaultReset,
                ][usize::from(k - 3)],
            ),
        };
        let known = i.map_or(0, |i| self.models[i].stops);
        let stops = match r.u8() {
            0..=127 => known,
            128..=223 => known.wrapping_add(1),
            224..=239 => known.saturating_sub(1),
            _ => r.u64(),
        };
        let mock = r.u8() < 192;
        if let Some(i) = i {
            let m = &mut self.models[i];
            if state == SafetyState::Armed && m.state != SafetyState::Armed {
                m.cmd_at = self.clock.now_s();
            }
            m.state = state;
            m.stops = stops;
        }
        self.uplink(Uplink::Safety { robot, seq: 0, stamp_s: self.now(), state, stops, mock });
    }

    /// The model's poses as the configured fusion (or a robot's own filter) would place them.
    fn estimate(&mut self, r: &mut Reader<'_>) {
        let now = self.now();
        let anchored =
            |m: &Model| Anchored { map: m.map_pose(), odom: m.odom.pose, stamp_s: m.odom.stamp_s.min(now) };
        let mut e = Estimate {
            source: EstimateSource::Fused(self.configuration),
            stamp_s: now,
            v: None,
            robots: self.models.iter().map(|m| Some(anchored(m))).collect(),
            integrity: EstimateIntegrity {
                state: IntegrityState::Tracking,
                explained: 0.9,
                level: 0.9,
                disagrees: None,
            },
            // The formation does not read it; any value, NaN included, must change nothing.
            covariance: (r.u8() >= 192).then(|| [[r.real(0.01, -1.0, 1.0); 3]; 3]),
        };
        if r.u8() >= 128 {
            e.source = match r.u8() {
                0..=127 => EstimateSource::Fused(self.configuration),
                128..=191 => {
                    let i = usize::from(r.u8()) % (self.robots.len() + 1);
                    // A robot's own estimate places only that robot.
                    for (k, a) in e.robots.iter_mut().enumerate() {
                        if k != i {
                            *a = None;
                        }
                    }
                    EstimateSource::Robot(i)
                }
                b => EstimateSource::Fused(
                    [Configuration::T1, Configuration::T2, Configuration::T3, Configuration::T4]
                        [usize::from(b % 4)],
                ),
            };
            e.stamp_s = now - r.real(0.0, -1.0, 2.0);
            match r.u8() {
                0..=223 => {}
                b => e.robots.resize(usize::from(b % 4), None),
            }
            for a in e.robots.iter_mut().flatten() {
                match r.u8() {
                    0..=127 => {}
                    128..=191 => {
                        let d =
                            Se2::new(r.real(0.0, -2.0, 2.0), r.real(0.0, -2.0, 2.0), r.real(0.0, -3.2, 3.2));
                        a.map = a.map * d;
                        a.stamp_s = now - r.real(0.0, -1.0, 2.0);
                    }
                    192..=239 => {
                        // Finite, as from a filter, but anywhere.
                        a.map = Se2::new(
                            finite(r.real(1e6, -1e9, 1e9)),
                            finite(r.real(-1e6, -1e9, 1e9)),
                            finite(r.real(0.0, -1e3, 1e3)),
                        );
                        a.odom = Se2::new(
                            finite(r.real(-1e6, -1e9, 1e9)),
                            finite(r.real(1e6, -1e9, 1e9)),
                            finite(r.real(0.0, -1e3, 1e3)),
                        );
                    }
                    _ => {}
                }
            }
            let state = [IntegrityState::Tracking, IntegrityState::Uncertain, IntegrityState::Lost]
                [usize::from(r.u8() % 3)];
            let disagrees = match r.u8() {
                0..=191 => None,
                b => Some(u32::from(b % 4)),
            };
            e.integrity = EstimateIntegrity { state, explained: 0.5, level: 0.5, disagrees };
        }
        count(format!("estimate:{:?}", e.source));
        self.cast(FormationMsg::Estimate(Box::new(e)));
    }
}

/// A finite value: a filter's output never is anything else.
fn finite(x: f64) -> f64 {
    if x.is_finite() { x } else { 0.0 }
}

fn phase_name(p: &Phase) -> &'static str {
    match p {
        Phase::Waiting => "waiting",
        Phase::Arming { .. } => "arming",
        Phase::Running => "running",
        Phase::Holding { .. } => "holding",
        Phase::Stopped { .. } => "stopped",
        Phase::Finished => "finished",
    }
}

async fn run(data: &[u8]) {
    let b = base();
    let mut r = Reader(data);
    let b0 = r.u8();
    let (scenario, id, len) = &b.scenarios[usize::from(b0 & 3)];
    let mut setup = b.setup.clone();
    setup.scenario = scenario.clone();
    setup.server.on_robot_lost = if b0 & 4 == 0 { OnRobotLost::Stop } else { OnRobotLost::Hold };
    setup.auto_arm =
        [AutoArm::Off, AutoArm::Mock, AutoArm::Hardware, AutoArm::Mock][usize::from((b0 >> 3) & 3)];
    let progress = PlanProgress::in_memory();
    if b0 & 0x20 != 0 {
        progress.note(id, r.real(len / 2.0, -5.0, len + 5.0).clamp(-1e9, 1e9));
    }
    setup.progress = Arc::new(progress);

    let mut senders = BTreeMap::new();
    let mut downs = Vec::new();
    for robot in &b.robots {
        let (tx, rx) = mpsc::channel(4096);
        senders.insert(robot.clone(), tx);
        downs.push(rx);
    }
    let clock = FleetClock::start();
    let start_v = scenario.start_pose();
    let slots = amr_core::formation::slots(b.robots.len(), scenario.spacing_m.get());
    let models = slots
        .iter()
        .map(|y| Model {
            start: start_v * Se2::new(0.0, *y, 0.0),
            odom: OdomMsg {
                seq: 0,
                frame: 1,
                stamp_s: 0.0,
                pose: Se2::IDENTITY,
                twist: (0.0, 0.0),
                gyro: true,
            },
            state: SafetyState::Disarmed(DisarmReason::Startup),
            stops: 1,
            floor: 0,
            cmd: (0.0, 0.0),
            cmd_at: 0.0,
        })
        .collect();
    let lim = &scenario.limits;
    let auto_arm = setup.auto_arm;
    let configuration = setup.server.configuration;
    let formation = FormationHarness::new(&setup, DownlinkSender::new(senders), clock)
        .await
        .expect("the formation starts");
    let mut run = Run {
        formation,
        downs,
        clock,
        robots: &b.robots,
        models,
        configuration,
        auto_arm,
        limits: (lim.max_speed_mps.get(), lim.max_yaw_rate_radps.get()),
        reported: vec![(None, 0, false); b.robots.len()],
        seq: vec![(0, 0); b.robots.len()],
        needs_rearm: false,
        operator_rearmed: false,
        healthy: vec![false; b.robots.len()],
        phase: Phase::Waiting,
    };
    while !r.is_empty() {
        match r.u8() {
            0x00..=0x3f => {
                let dt = match r.u8() {
                    0..=223 => PERIOD_S,
                    b => PERIOD_S * f64::from(b - 223) / 8.0,
                };
                run.advance(dt).await;
            }
            0x40..=0x5f => run.report_all(),
            0x60..=0x7f => run.odom(&mut r),
            0x80..=0x8f => run.health(&mut r),
            0x90..=0xaf => run.safety(&mut r),
            0xb0..=0xcf => run.estimate(&mut r),
            0xd0..=0xdf => {
                let s = match r.u8() {
                    0..=127 => FusionStatus::Fusing,
                    k => FusionStatus::RobotLost(usize::from(k) % b.robots.len()),
                };
                run.cast(FormationMsg::Fusion(s));
            }
            0xe0..=0xe7 => {
                run.needs_rearm = false;
                run.operator_rearmed = true;
                run.cast(FormationMsg::Rearm);
            }
            0xe8..=0xef => {
                // It sends its disarms at once: they are read before anything else happens.
                run.cast(FormationMsg::Stop);
                run.drain();
            }
            0xf0..=0xf7 => {
                // A twist for V (a teleop on /cmd_vel): any values, NaN and huge ones included.
                let (v_mps, w_radps) = (r.real(0.2, -5.0, 5.0), r.real(0.0, -5.0, 5.0));
                run.cast(FormationMsg::Twist { v_mps, w_radps });
            }
            _ => {
                let dt = [0.1, 0.25, 0.5, 0.55, 1.0, 2.0, 2.1, 5.0][usize::from(r.u8() % 8)];
                run.advance(dt).await;
            }
        }
    }
    run.drain();
    if stats_on() {
        let mut s = STATS.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        s.0 += 1;
        if s.0.is_power_of_two() {
            eprintln!("formation_inputs: {} inputs: {:?}", s.0, s.1);
        }
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
                11 => 1e300,
                12 => -1e300,
                13 => 1e154,
                14 => 0.5,
                15 => 0.500_000_000_1,
                16 => -0.5,
                17 => std::f64::consts::PI,
                18 => -std::f64::consts::PI,
                19 => std::f64::consts::TAU,
                20 => 1e6,
                21 => -1e6,
                22 => 100.0,
                23 => 1.0,
                24 => -1.0,
                25 => 0.22,
                26 => 0.2,
                27 => f64::EPSILON,
                28 => -default,
                29 => default * 2.0,
                30 => default + 1e-9,
                _ => f64::from_bits(self.u64()),
            },
        }
    }
}

/// Seeds: a formation armed by the operator (or by auto-arm on mock robots) that runs, then stops
/// by a robot's e-stop, a lost robot, an unverified estimate or the operator.
fn write_seeds(dir: &std::path::Path) {
    std::fs::create_dir_all(dir).expect("the seed directory");
    // Report, estimate, tick: one period of a formation whose robots behave.
    let period = || vec![0x40u8, 0xb0, 0x00, 0x00, 0x00];
    let periods = |n: usize| -> Vec<u8> { (0..n).flat_map(|_| period()).collect() };
    let mut seeds: Vec<(String, Vec<u8>)> = Vec::new();
    for (name, head) in [
        ("rearm-straight", vec![0x00u8, 0xe0]),
        ("auto-mock-turning", vec![0x09]),
        ("hold-turning", vec![0x05, 0xe0]),
    ] {
        let run = [head, periods(120)].concat();
        seeds.push((name.to_owned(), run.clone()));
        seeds.push((
            format!("{name}-estop"),
            [run.clone(), vec![0x90, 0, 1, 0, 0], periods(20), vec![0xe0], periods(20)].concat(),
        ));
        seeds.push((
            format!("{name}-lost"),
            [run.clone(), vec![0xd0, 0x80], periods(20), vec![0xd0, 0x00], periods(20)].concat(),
        ));
        seeds.push((
            format!("{name}-stop"),
            [run.clone(), vec![0xe8], periods(20), vec![0xe0], periods(40)].concat(),
        ));
        seeds
            .push((format!("{name}-restart-odom"), [run, vec![0x60, 0, 0, 230, 0, 0], periods(40)].concat()));
    }
    // A record of earlier progress: the fresh formation resumes where V is.
    seeds.push(("record".into(), [vec![0x20u8, 0, 0xe0], periods(60)].concat()));
    for (name, bytes) in seeds {
        std::fs::write(dir.join(name), bytes).expect("a seed file");
    }
}

fuzz_target!(
    init: {
        if let Some(dir) = std::env::var_os("FORMATION_INPUTS_SEEDS") {
            write_seeds(std::path::Path::new(&dir));
        }
        base();
    },
    |data: &[u8]| {
        let b = base();
        b.runtime.block_on(run(data));
    }
);
