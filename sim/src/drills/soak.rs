//! Drill 12: a seeded chaos soak.
//!
//! The whole simulation runs the `turning` scenario (30 laps, about 25 minutes: the plan does not
//! end within the soak). Every 3–6 s (after the previous fault has ended) a fault is drawn, seeded,
//! from the drills' list and injected into a random robot: LiDAR connection drop, LiDAR stall and
//! resume, LiDAR garbage and corrupt telegrams, a LiDAR actor panic (at most one per robot in any
//! 12 s, so the restart intensity of 3 in 10 s is never reached by design), IMU unplug and replug,
//! a drive's heartbeat lost for a second, a drive reboot, the robot's link cut for a second,
//! an e-stop reset a second later, and the server crashed and restarted a second later (the new
//! one does not arm by itself: the soak re-arms it as any stopped formation). Between faults the formation is re-armed whenever it stopped.
//!
//! A watcher, every 10 ms, checks the invariants throughout:
//! 1. never actuate while Fault or EStop: a robot in either state has every drive target at zero
//!    after at most 100 ms (the e-stop's deadline; its first cycles may still be in flight);
//! 2. no restart loop: no supervisor escalated, and no child failed more than the restart
//!    intensity allows (3) within its window (10 s);
//! 3. the safe state within its deadline after every safety-relevant fault: link cut → the robot
//!    not armed within 350 ms (its watchdog); server crash → every robot armed at the crash not
//!    armed within 350 ms; drive heartbeat lost → every drive of the robot
//!    commanded to zero or out of Operation enabled within 700 ms; e-stop → every target zero within
//!    100 ms.
//!
//! At the end every device must be Ok again and the formation must run after a last re-arm. The
//! counters hold the faults injected per kind, the re-arms, the violations and the worst
//! safe-state time per kind.

use std::collections::BTreeMap;
use std::time::Duration;

use amr_actors::config::Config;
use amr_actors::robot::lidar::LidarMsg;
use amr_actors::supervisor::EventKind;
use amr_core::rng::Rng;
use amr_drivers::canopen::cia402::State402;
use amr_msgs::{Device, Health, SafetyState};
use hil_mocks::teco_drive::Fault as DriveFault;
use hil_mocks::tim551::Fault as LidarFault;
use ractor::ActorRef;
use tokio::time::Instant;

use super::Check;
use super::fleet::{all_turning, moving_sim, phase_name, safety};
use crate::Sim;
use amr_actors::server::formation::Phase;

/// The full soak: 10 minutes.
pub const SOAK_FULL: Duration = Duration::from_secs(600);

/// The shortest soak that means something: the first fault comes after 2 s, each lasts 1 s and
/// the next follows 3–6 s later, so 30 s injects at least four, and the check wants three of
/// three kinds. `amr drill` refuses a shorter one.
pub const SOAK_MIN: Duration = Duration::from_secs(30);

/// After Fault or EStop, every target zero within this.
const ACTUATE_GRACE: Duration = Duration::from_millis(100);
const LINK_DEADLINE: Duration = Duration::from_millis(350);
const HEARTBEAT_DEADLINE: Duration = Duration::from_millis(700);
const ESTOP_DEADLINE: Duration = Duration::from_millis(100);
/// How long a fault lasts before it is undone.
const FAULT_LENGTH: Duration = Duration::from_secs(1);
/// Violations quoted in the failures (all are counted).
const QUOTED: usize = 5;

#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
enum Kind {
    LidarDrop,
    LidarStall,
    LidarGarbage,
    LidarPanic,
    ImuUnplug,
    DriveHeartbeat,
    DriveReboot,
    LinkCut,
    EStop,
    ServerCrash,
}

const KINDS: [Kind; 10] = [
    Kind::LidarDrop,
    Kind::LidarStall,
    Kind::LidarGarbage,
    Kind::LidarPanic,
    Kind::ImuUnplug,
    Kind::DriveHeartbeat,
    Kind::DriveReboot,
    Kind::LinkCut,
    Kind::EStop,
    Kind::ServerCrash,
];

impl Kind {
    fn name(self) -> &'static str {
        match self {
            Kind::LidarDrop => "lidar-drop",
            Kind::LidarStall => "lidar-stall",
            Kind::LidarGarbage => "lidar-garbage",
            Kind::LidarPanic => "lidar-panic",
            Kind::ImuUnplug => "imu-unplug",
            Kind::DriveHeartbeat => "drive-heartbeat",
            Kind::DriveReboot => "drive-reboot",
            Kind::LinkCut => "link-cut",
            Kind::EStop => "estop",
            Kind::ServerCrash => "server-crash",
        }
    }
}

/// A safe state owed by a robot after a fault.
#[derive(Debug)]
struct Owed {
    kind: Kind,
    robot: usize,
    injected: Instant,
    deadline: Duration,
}

/// The fault being undone later.
#[derive(Debug)]
struct Active {
    kind: Kind,
    robot: usize,
    drive: usize,
    until: Instant,
}

struct Soak {
    counters: BTreeMap<String, u64>,
    violations: Vec<String>,
    /// Per robot: since when it has been in Fault or EStop.
    stopped_since: Vec<Option<Instant>>,
    start: Instant,
    /// When the next fault is due (once the active one is undone).
    next_at: Instant,
    active: Option<Active>,
    owed: Vec<Owed>,
    /// Per robot: its last LiDAR panic (at most one in any 12 s).
    last_panic: Vec<Option<Instant>>,
    last_rearm: Instant,
    worst_safe: Duration,
    /// Recovery: from a fault's injection to the formation running again, for the faults that
    /// stopped it (whether it has left Running since).
    since_fault: Option<(Instant, bool)>,
    worst_recovery: Option<Duration>,
}

impl Soak {
    fn new(robots: usize, start: Instant) -> Self {
        Soak {
            counters: BTreeMap::new(),
            violations: Vec::new(),
            stopped_since: vec![None; robots],
            start,
            next_at: start + Duration::from_secs(2),
            active: None,
            owed: Vec::new(),
            last_panic: vec![None; robots],
            last_rearm: start,
            worst_safe: Duration::ZERO,
            since_fault: None,
            worst_recovery: None,
        }
    }

    fn count(&mut self, key: String, by: u64) {
        *self.counters.entry(key).or_default() += by;
    }

    fn max(&mut self, key: String, v: u64) {
        let e = self.counters.entry(key).or_default();
        *e = (*e).max(v);
    }

    fn violation(&mut self, what: String) {
        self.count("violations".into(), 1);
        if self.violations.len() < QUOTED {
            self.violations.push(what);
        }
    }

    fn targets_zero(sim: &Sim, robot: usize) -> bool {
        sim.mocks[robot].drives.iter().all(|d| d.now().target_velocity == 0)
    }

    fn drives_safe(sim: &Sim, robot: usize) -> bool {
        sim.mocks[robot].drives.iter().all(|d| {
            let s = d.now();
            s.target_velocity == 0 || s.state != State402::OperationEnabled
        })
    }

    /// Invariant 1, every tick.
    fn never_actuate_while_stopped(&mut self, sim: &Sim, at: Duration) {
        for i in 0..sim.robots.len() {
            let stopped = matches!(safety(sim, i), Some(SafetyState::EStop | SafetyState::Fault));
            match (stopped, self.stopped_since[i]) {
                (false, _) => self.stopped_since[i] = None,
                (true, None) => self.stopped_since[i] = Some(Instant::now()),
                (true, Some(since)) => {
                    if since.elapsed() > ACTUATE_GRACE && !Self::targets_zero(sim, i) {
                        let state = safety(sim, i);
                        self.violation(format!(
                            "{} actuated while {state:?} at {:.2} s: targets {:?}",
                            sim.robots[i].id,
                            at.as_secs_f64(),
                            sim.mocks[i].drives.iter().map(|d| d.now().target_velocity).collect::<Vec<_>>()
                        ));
                        // Once per episode.
                        self.stopped_since[i] = Some(Instant::now() + Duration::from_secs(3600));
                    }
                }
            }
        }
    }

    /// Invariant 3: whether the owed safe state holds now.
    fn safe(sim: &Sim, o: &Owed) -> bool {
        match o.kind {
            Kind::LinkCut | Kind::ServerCrash => safety(sim, o.robot) != Some(SafetyState::Armed),
            Kind::DriveHeartbeat => Self::drives_safe(sim, o.robot),
            Kind::EStop => Self::targets_zero(sim, o.robot),
            _ => true,
        }
    }
    /// Invariant 3: every owed safe state reached (its time counted) or past its deadline.
    fn settle_owed(&mut self, sim: &Sim) {
        let mut k = 0;
        while k < self.owed.len() {
            let o = &self.owed[k];
            let took = o.injected.elapsed();
            if Self::safe(sim, o) {
                let kind = o.kind;
                self.worst_safe = self.worst_safe.max(took);
                self.max(
                    format!("safe_ms.max.{}", kind.name()),
                    u64::try_from(took.as_millis()).unwrap_or(u64::MAX),
                );
                self.owed.swap_remove(k);
            } else if took > o.deadline {
                let msg = format!(
                    "{} after {} at {:.2} s: no safe state within {:?}",
                    sim.robots[o.robot].id,
                    o.kind.name(),
                    (o.injected - self.start).as_secs_f64(),
                    o.deadline
                );
                self.violation(msg);
                self.owed.swap_remove(k);
            } else {
                k += 1;
            }
        }
    }

    /// Undo the active fault when its time is up; the next one is drawn 3–6 s later.
    async fn undo_due(&mut self, sim: &mut Sim, rng: &mut Rng, now: Instant, c: &mut Check) {
        let Some(a) = self.active.as_ref().filter(|a| now >= a.until) else { return };
        if a.kind == Kind::ServerCrash {
            // Its supervision log goes with it: check it first (invariant 2).
            for v in restart_loops(&sim.server.events, 3, Duration::from_secs(5)) {
                self.violation(v);
            }
            if let Err(e) = sim.restart_server().await {
                c.fail(format!("server restart: {e}"));
            }
        } else if let Err(e) = undo(sim, a).await {
            c.fail(format!("undo {}: {e}", a.kind.name()));
        }
        self.active = None;
        self.next_at = Instant::now() + Duration::from_secs_f64(rng.range(3.0, 6.0));
    }

    /// The formation's phase now: recovery times, driving time, and a re-arm (as an operator
    /// would once the fault is gone) of a stopped formation or a restarted server's waiting one,
    /// so that the robots drive most of the soak.
    async fn follow_formation(&mut self, sim: &Sim) {
        let ph = sim.formation().map(|f| f.phase);
        match (&ph, self.since_fault.as_mut()) {
            (Some(Phase::Running), Some((t, true))) => {
                let d = t.elapsed();
                self.worst_recovery = Some(self.worst_recovery.map_or(d, |w: Duration| w.max(d)));
                self.since_fault = None;
            }
            (Some(Phase::Running), Some((_, false))) | (_, None) => {}
            (_, Some((_, left))) => *left = true,
        }
        if ph == Some(Phase::Running) && all_turning(sim) {
            self.count("moving_ms".into(), 10);
        }
        if self.active.is_none()
            && matches!(ph, Some(Phase::Stopped { .. } | Phase::Waiting))
            && self.last_rearm.elapsed() > Duration::from_secs(3)
        {
            self.last_rearm = Instant::now();
            self.count("rearms".into(), 1);
            let _ = sim.server.rearm().await;
        }
    }

    /// Draw and inject the next fault when it is due, with the safe states it owes.
    async fn inject_due(&mut self, sim: &Sim, rng: &mut Rng, now: Instant, c: &mut Check) {
        if self.active.is_some() || now < self.next_at {
            return;
        }
        let n = sim.robots.len();
        let robot = rng.below(n);
        let drive = rng.below(sim.mocks[robot].drives.len().max(1));
        let mut kind = KINDS[rng.below(KINDS.len())];
        if kind == Kind::LidarPanic
            && self.last_panic[robot].is_some_and(|t| t.elapsed() < Duration::from_secs(12))
        {
            kind = Kind::LidarGarbage;
        }
        if kind == Kind::LidarPanic {
            self.last_panic[robot] = Some(now);
        }
        let armed = safety(sim, robot) == Some(SafetyState::Armed);
        let armed_all: Vec<bool> = (0..n).map(|i| safety(sim, i) == Some(SafetyState::Armed)).collect();
        let at_s = (now - self.start).as_secs_f64();
        tracing::info!(fault = kind.name(), robot = %sim.robots[robot].id, at_s, "soak: fault");
        match inject(sim, kind, robot, drive).await {
            Ok(()) => self.count(format!("injected.{}", kind.name()), 1),
            Err(e) => c.fail(format!("inject {}: {e}", kind.name())),
        }
        let deadline = match kind {
            Kind::LinkCut if armed => Some(LINK_DEADLINE),
            Kind::DriveHeartbeat => Some(HEARTBEAT_DEADLINE),
            Kind::EStop => Some(ESTOP_DEADLINE),
            _ => None,
        };
        if let Some(deadline) = deadline {
            self.owed.push(Owed { kind, robot, injected: now, deadline });
        }
        if kind == Kind::ServerCrash {
            // Every armed robot loses its commands.
            for (i, was) in armed_all.iter().enumerate() {
                if *was {
                    self.owed.push(Owed { kind, robot: i, injected: now, deadline: LINK_DEADLINE });
                }
            }
        }
        if self.since_fault.is_none_or(|(_, left)| !left) {
            self.since_fault = Some((now, false));
        }
        let lasts = match kind {
            Kind::LidarStall
            | Kind::ImuUnplug
            | Kind::DriveHeartbeat
            | Kind::LinkCut
            | Kind::EStop
            | Kind::ServerCrash => FAULT_LENGTH,
            _ => Duration::ZERO,
        };
        self.active = Some(Active { kind, robot, drive, until: now + lasts });
    }

    /// After the soak: the active fault undone, invariant 2 over the whole run, every robot tree
    /// running.
    async fn wind_down(&mut self, sim: &mut Sim, c: &mut Check) {
        if let Some(a) = self.active.take() {
            let undone = if a.kind == Kind::ServerCrash {
                sim.restart_server().await.map_err(|e| e.to_string())
            } else {
                undo(sim, &a).await
            };
            if let Err(e) = undone {
                c.fail(format!("undo {}: {e}", a.kind.name()));
            }
        }
        let policy = amr_actors::robot::RobotOptions::default().policy;
        let max_restarts = usize::try_from(policy.max_restarts).unwrap_or(usize::MAX);
        for r in &sim.robots {
            for v in restart_loops(&r.events, max_restarts, policy.window) {
                self.violation(v);
            }
        }
        for v in restart_loops(&sim.server.events, 3, Duration::from_secs(5)) {
            self.violation(v);
        }
        c.that(
            sim.robots.iter().all(amr_actors::robot::RobotTree::is_running),
            "every robot tree still running",
        );
    }

    /// The end: every device Ok again, and the formation running after a last re-arm.
    async fn run_again(&mut self, sim: &Sim, c: &mut Check) {
        c.within("every device Ok after the soak", Duration::from_secs(15), || all_devices_ok(sim)).await;
        let rearm_deadline = Instant::now() + Duration::from_secs(20);
        let mut ran = false;
        // Bounded by the deadline; re-arms every 3 s while stopped.
        while Instant::now() < rearm_deadline {
            let ph = sim.formation().map(|f| f.phase);
            if ph == Some(Phase::Running) && all_turning(sim) {
                ran = true;
                break;
            }
            if !matches!(ph, Some(Phase::Running | Phase::Arming { .. }))
                && self.last_rearm.elapsed() > Duration::from_secs(3)
            {
                self.last_rearm = Instant::now();
                let _ = sim.server.rearm().await;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        c.that(ran, "the formation running after the soak and a re-arm");
    }

    /// The verdicts on the whole soak and what the outcome reports.
    fn conclude(mut self, length: Duration, ended: Duration, c: &mut Check) {
        c.recovery = self.worst_recovery;
        c.safe_state = (self.worst_safe > Duration::ZERO).then_some(self.worst_safe);
        // Enough chaos to mean something: several faults of several kinds.
        let injected: u64 =
            self.counters.iter().filter(|(k, _)| k.starts_with("injected.")).map(|(_, v)| v).sum();
        let kinds = self.counters.keys().filter(|k| k.starts_with("injected.")).count();
        let want = (length.as_secs() / 10).max(3);
        c.that(
            injected >= want && kinds >= 3,
            format!("{injected} faults of {kinds} kinds injected (≥ {want}, ≥ 3 kinds)"),
        );
        // The faults met moving robots: the formation drove for a good part of the soak.
        let moving = self.counters.get("moving_ms").copied().unwrap_or(0);
        c.that(
            moving as f64 >= 0.25 * length.as_millis() as f64,
            format!(
                "the robots drove {:.0} s of the {:.0} s soak (≥ 25 %)",
                moving as f64 / 1000.0,
                length.as_secs_f64()
            ),
        );
        for v in std::mem::take(&mut self.violations) {
            c.fail(format!("invariant: {v}"));
        }
        let violations = self.counters.get("violations").copied().unwrap_or(0);
        c.eq("invariant violations", violations, 0);
        self.counters.insert("soak_ms".into(), u64::try_from(ended.as_millis()).unwrap_or(u64::MAX));
        c.counters = self.counters;
    }
}

/// Invariant 2 over a whole supervision log: escalations, and failures per child beyond the
/// intensity within its window.
fn restart_loops(
    log: &amr_actors::supervisor::EventLog,
    max_restarts: usize,
    window: Duration,
) -> Vec<String> {
    let mut out = Vec::new();
    let mut failures: BTreeMap<(String, String), Vec<Instant>> = BTreeMap::new();
    for (t, e) in log.timed_snapshot() {
        match e.kind {
            EventKind::Escalated { reason } => out.push(format!("{} escalated: {reason}", e.supervisor)),
            EventKind::Failed { child, .. } | EventKind::StartFailed { child, .. } => {
                failures.entry((e.supervisor.clone(), child)).or_default().push(t);
            }
            _ => {}
        }
    }
    for ((sup, child), times) in failures {
        for (k, t) in times.iter().enumerate() {
            let within = times[k..].iter().take_while(|u| u.duration_since(*t) <= window).count();
            if within > max_restarts {
                out.push(format!("{sup}/{child}: {within} failures within {window:?}"));
                break;
            }
        }
    }
    out
}

async fn inject(sim: &Sim, kind: Kind, robot: usize, drive: usize) -> Result<(), String> {
    let m = &sim.mocks[robot];
    let id = &sim.robots[robot].id;
    match kind {
        Kind::LidarDrop => m.lidar.handle.inject(LidarFault::Drop { refuse_for: FAULT_LENGTH }),
        Kind::LidarStall => m.lidar.handle.inject(LidarFault::Stall),
        Kind::LidarGarbage => {
            m.lidar.handle.inject(LidarFault::Garbage(b"\x02sSN LMDscandata \xff\xfe soak\x03".to_vec()));
            m.lidar.handle.inject(LidarFault::CorruptNext);
        }
        Kind::LidarPanic => {
            let lidar = super::child(&sim.robots[robot].supervisor, "lidar").await.ok_or("no lidar actor")?;
            ActorRef::<LidarMsg>::from(lidar)
                .cast(LidarMsg::InjectPanic("soak: lidar panic".into()))
                .map_err(|e| e.to_string())?;
        }
        Kind::ImuUnplug => m.imu.unplug().await.map_err(|e| e.to_string())?,
        Kind::DriveHeartbeat => m.drives[drive].inject(DriveFault::HeartbeatLoss(true)),
        Kind::DriveReboot => m.drives[drive].inject(DriveFault::Reboot),
        Kind::LinkCut => sim.link.set_cut(id, true),
        Kind::EStop => sim.robots[robot].estop(),
        Kind::ServerCrash => sim.crash_server(),
    }
    Ok(())
}

async fn undo(sim: &Sim, a: &Active) -> Result<(), String> {
    let m = &sim.mocks[a.robot];
    match a.kind {
        Kind::LidarStall => m.lidar.handle.inject(LidarFault::Resume),
        Kind::ImuUnplug => {
            m.imu.replug().await.map_err(|e| e.to_string())?;
        }
        Kind::DriveHeartbeat => m.drives[a.drive].inject(DriveFault::HeartbeatLoss(false)),
        Kind::LinkCut => sim.link.set_cut(&sim.robots[a.robot].id, false),
        Kind::EStop => sim.robots[a.robot].reset_estop(),
        // The server is restarted by the soak's loop (it needs the simulation mutably).
        Kind::LidarDrop | Kind::LidarGarbage | Kind::LidarPanic | Kind::DriveReboot | Kind::ServerCrash => {}
    }
    Ok(())
}

/// Every device of every robot Ok.
fn all_devices_ok(sim: &Sim) -> bool {
    sim.robots.iter().all(|r| {
        let board = r.ports.health_board.borrow();
        [Device::Lidar, Device::Imu, Device::CanBus, Device::Drives]
            .iter()
            .all(|d| board.get(d).is_some_and(|h| h.health == Health::Ok))
    })
}

/// Random faults over `length`, invariants checked throughout.
pub(crate) async fn soak(config: &Config, seed: u64, length: Duration, c: &mut Check) {
    let Some(scenario) = config.scenarios.get("turning").cloned() else {
        return c.fail("no turning scenario");
    };
    let Some(mut sim) = moving_sim(config, seed, scenario, c).await else { return };
    let mut rng = Rng::seed(seed ^ 0x50a4);
    let p0 = sim.phases().len();
    let marks: Vec<usize> = sim.robots.iter().map(|r| r.events.len()).collect();
    c.inject();
    let start = Instant::now();
    let end = start + length;
    let mut s = Soak::new(sim.robots.len(), start);
    let mut every = tokio::time::interval(Duration::from_millis(10));
    every.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    // Bounded by `length`.
    while Instant::now() < end {
        every.tick().await;
        let now = Instant::now();
        s.never_actuate_while_stopped(&sim, now - start);
        s.settle_owed(&sim);
        s.undo_due(&mut sim, &mut rng, now, c).await;
        s.follow_formation(&sim).await;
        s.inject_due(&sim, &mut rng, now, c).await;
    }
    s.wind_down(&mut sim, c).await;
    let ended = c.since_injection();
    s.run_again(&sim, c).await;
    s.conclude(length, ended, c);
    for r in &sim.robots {
        for (k, v) in r.counters.snapshot() {
            if k.starts_with("safety.") {
                c.counters.insert(format!("{}.{k}", r.id), v);
            }
        }
    }
    c.events = sim.phases().iter().skip(p0).map(|p| format!("formation: {}", phase_name(p))).collect();
    for (r, from) in sim.robots.iter().zip(&marks) {
        c.events.extend(
            r.events.snapshot().iter().skip(*from).map(|e| format!("{}: {:?}", e.supervisor, e.kind)),
        );
    }
    sim.shutdown().await;
}
