//! Fault-recovery drills: each injects a fault through a mock device's fault plan (or kills an
//! actor) in a running system and checks, with deadlines, (a) detection, (b) the safe state where
//! the fault is safety-relevant, (c) recovery, (d) the exact ordered event log and (e) the
//! counters. Every wait is bounded. A drill runs in real time over real sockets and ptys, or on
//! virtual time over in-memory pipes ([`DrillClock`]).
//!
//! A drill never panics on a failed expectation: it records it, so `amr drill all` can print the
//! whole table; the tests assert that each drill passed and print what failed.

mod devices;
mod fleet;
mod soak;

pub use soak::SOAK_FULL;

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::time::Duration;

use amr_actors::config::Config;
use amr_actors::robot::RobotOptions;
use amr_actors::supervisor::{ChildInfo, SupervisorMsg};
use amr_msgs::{Command, Device, Downlink, Health};
use ractor::{ActorCell, ActorRef};
use serde::Serialize;
use tokio::time::Instant;

use crate::{RobotRig, SimCan};

/// One drill.
#[derive(Debug, Clone, Copy)]
pub struct Drill {
    pub name: &'static str,
    pub about: &'static str,
}

impl Drill {
    /// Why this drill needs the wall clock (`None`: it runs on [`DrillClock::Virtual`] as well).
    #[must_use]
    pub fn real_time_only(&self) -> Option<&'static str> {
        match self.name {
            "can-link-reset" => Some("it breaks the TCP connection to socketcand"),
            "absent-at-start" => Some("the LiDAR's address is a TCP port nobody listens on"),
            "command-burst" | "robot-freeze" | "estop-restart" => {
                Some("the robot runs on a runtime and thread of its own, frozen or killed")
            }
            "slow-consumer" => {
                Some("a blocked worker of the multi-thread runtime hands its tasks to the other")
            }
            _ => None,
        }
    }
}

/// The clock a drill runs on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DrillClock {
    /// Wall time: the devices over loopback TCP, a pty and (where the drill says) socketcand, as
    /// on a robot. What `amr drill` runs.
    Real,
    /// tokio's paused clock on a current-thread runtime (the caller's), the LiDAR and the IMU
    /// over in-memory pipes and CAN on the in-process bus ([`SimCan::VirtualTime`]): the
    /// machine's speed decides nothing, so a drill gives the same outcome, timings included,
    /// from the same seed (all but the scan flood's readings of the process's resident memory).
    /// Drills with [`Drill::real_time_only`] refuse it.
    Virtual,
}

/// Every drill, in the order `amr drill all` runs and lists them.
pub const DRILLS: &[Drill] = &[
    Drill { name: "lidar-panic", about: "the LiDAR actor panics: restarted alone, drives and IMU untouched" },
    Drill {
        name: "fail-forever",
        about: "a device actor that fails forever: escalation, Fault latched, robot stopped, no restart storm",
    },
    Drill {
        name: "can-bus-restart",
        about: "the CAN bus actor restarts: the drives restart after it (rest-for-one)",
    },
    Drill {
        name: "lidar-reset",
        about: "LiDAR TCP connection reset: reconnect with backoff, Lost → Ok, no restart",
    },
    Drill {
        name: "lidar-stall",
        about: "LiDAR half-open (connected, silent): detected by the scan watchdog, reconnect",
    },
    Drill {
        name: "imu-unplug",
        about: "IMU tty closed and back: reopened with backoff, odometry falls back to the wheels",
    },
    Drill {
        name: "can-link-reset",
        about: "the CAN link (socketcand TCP) breaks: drives stop by themselves, reconnect with backoff",
    },
    Drill {
        name: "drive-bus-off",
        about: "a drive goes bus-off: heartbeat lost, robot stopped, drive back and reconfigured",
    },
    Drill {
        name: "drive-heartbeat",
        about: "a drive's heartbeat stops: reported within the consumer time, the robot stops",
    },
    Drill { name: "drive-reboot", about: "a drive reboots: reconfigured before it is enabled again" },
    Drill {
        name: "bad-scan",
        about: "impossible scans reach the server: refused and counted, the server runs on, V stays localised",
    },
    Drill {
        name: "robot-restart-odometry",
        about: "a robot's odometry restarts at the origin mid-run: the server re-anchors it, V stays localised",
    },
    Drill {
        name: "safety-crash-moving",
        about: "the safety actor dies while the robot drives: targets zeroed, back disarmed, no motion until a new arm",
    },
    Drill {
        name: "estop-during-restart",
        about: "an e-stop over the link while the safety actor restarts: latched, drives zeroed by the master's hold, back in EStop",
    },
    Drill {
        name: "new-master-moving",
        about: "the CANopen master dies while the robot drives: the new one quick-stops every drive before resetting it",
    },
    Drill {
        name: "drive-fault-moving",
        about: "a drive faults while the robot drives: halted, the drive reset and enabled at zero, no motion until a new arm",
    },
    Drill {
        name: "drive-reboot-moving",
        about: "a drive reboots while the robot drives: halted, reconfigured and enabled at zero, no motion until a new arm",
    },
    Drill {
        name: "bad-data",
        about: "garbage, truncated frames, bad checksums, NaN: rejected and counted, nothing panics",
    },
    Drill {
        name: "absent-at-start",
        about: "the LiDAR is absent at start-up: the robot comes up without it and keeps retrying",
    },
    Drill {
        name: "link-lost",
        about: "robot ↔ server link lost: each robot stops within its watchdog; no stale command after; re-arm needed",
    },
    Drill {
        name: "server-restart",
        about: "the server crashes and restarts: robots stay stopped, reconnect, resume after re-arm",
    },
    Drill {
        name: "command-burst",
        about: "a stalled link flushes commands with a disarm among them: nothing dropped, the disarm holds",
    },
    Drill {
        name: "robot-freeze",
        about: "the whole robot process freezes: the drives quick-stop on the master's lost heartbeat",
    },
    Drill { name: "slow-consumer", about: "a stalled localisation does not delay the robot's safety loop" },
    Drill {
        name: "estop-input",
        about: "the e-stop chain on a drive's digital input (0x60FD) opens: latched, quick stop, reset needed",
    },
    Drill { name: "estop", about: "e-stop: wheels commanded to zero within 100 ms; orderly shutdown" },
    Drill {
        name: "estop-restart",
        about: "e-stop, kill -9 the robot, restart it, re-arm: still EStop, no wheel moves until reset and arm; the same for a fault",
    },
    Drill {
        name: "late-scans",
        about: "one LiDAR's scans reach the server late at the start: the formation waits for a verified V, then starts",
    },
    Drill {
        name: "scan-flood",
        about: "one robot sends scans at 10x its rate for 60 s: server memory bounded, the other's reports on time",
    },
    Drill {
        name: "soak",
        about: "seeded chaos: random faults from this list, invariants checked throughout",
    },
];

/// What a drill measured and found.
#[derive(Debug, Clone, Serialize)]
pub struct DrillOutcome {
    pub name: String,
    pub passed: bool,
    /// From the injection to the fault being noticed (health change, event, report).
    pub detection_ms: Option<f64>,
    /// From the injection to the safe state (wheels commanded to zero or quick stop).
    pub safe_state_ms: Option<f64>,
    /// From the injection (or the end of the fault) to working again.
    pub recovery_ms: Option<f64>,
    /// The supervision events after the injection, in order.
    pub events: Vec<String>,
    pub counters: BTreeMap<String, u64>,
    /// Every expectation that did not hold.
    pub failures: Vec<String>,
    pub duration_s: f64,
}

/// Records expectations and timings of one drill.
#[derive(Debug)]
pub struct Check {
    name: String,
    clock: DrillClock,
    started: Instant,
    injected: Option<Instant>,
    pub detection: Option<Duration>,
    pub safe_state: Option<Duration>,
    pub recovery: Option<Duration>,
    pub events: Vec<String>,
    pub counters: BTreeMap<String, u64>,
    failures: Vec<String>,
}

impl Check {
    #[must_use]
    pub fn new(name: &str) -> Self {
        Self::on(name, DrillClock::Real)
    }

    /// A check of a drill running on `clock`.
    #[must_use]
    pub fn on(name: &str, clock: DrillClock) -> Self {
        Check {
            name: name.to_owned(),
            clock,
            started: Instant::now(),
            injected: None,
            detection: None,
            safe_state: None,
            recovery: None,
            events: Vec::new(),
            counters: BTreeMap::new(),
            failures: Vec::new(),
        }
    }

    /// How the robots reach their devices: `wanted` in real time, in-memory pipes on virtual time.
    #[must_use]
    pub fn can(&self, wanted: SimCan) -> SimCan {
        match self.clock {
            DrillClock::Real => wanted,
            DrillClock::Virtual => SimCan::VirtualTime,
        }
    }

    /// Mark the injection: later timings count from here.
    pub fn inject(&mut self) {
        self.injected = Some(Instant::now());
    }

    /// Time since the injection (or the start).
    #[must_use]
    pub fn since_injection(&self) -> Duration {
        self.injected.unwrap_or(self.started).elapsed()
    }

    /// Record `what` as failed unless `ok`.
    pub fn that(&mut self, ok: bool, what: impl Into<String>) -> bool {
        if !ok {
            let what = what.into();
            tracing::warn!(drill = %self.name, %what, "drill expectation failed");
            self.failures.push(what);
        }
        ok
    }

    /// Record a failure.
    pub fn fail(&mut self, what: impl Into<String>) {
        self.that(false, what);
    }

    /// `got == want`, or a failure showing both.
    pub fn eq<T: PartialEq + std::fmt::Debug>(&mut self, what: &str, got: T, want: T) -> bool {
        let ok = got == want;
        self.that(ok, format!("{what}: got {got:?}, want {want:?}"))
    }

    /// Wait (polling every 10 ms) until `cond` holds, at most `deadline` from now; the time since the
    /// injection when it held, or a failure.
    pub async fn within(
        &mut self,
        what: &str,
        deadline: Duration,
        mut cond: impl FnMut() -> bool,
    ) -> Option<Duration> {
        let until = Instant::now() + deadline;
        // Bounded by the deadline.
        loop {
            if cond() {
                return Some(self.since_injection());
            }
            if Instant::now() >= until {
                self.that(false, format!("{what}: not within {deadline:?}"));
                return None;
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    }

    /// Check that `cond` holds throughout the next `period` (polling every 10 ms).
    pub async fn throughout(&mut self, what: &str, period: Duration, mut cond: impl FnMut() -> bool) -> bool {
        let until = Instant::now() + period;
        while Instant::now() < until {
            if !cond() {
                return self.that(false, format!("{what}: broken after {:?}", self.since_injection()));
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        true
    }

    #[must_use]
    pub fn finish(self) -> DrillOutcome {
        let ms = |d: Option<Duration>| d.map(|d| d.as_secs_f64() * 1000.0);
        DrillOutcome {
            name: self.name,
            passed: self.failures.is_empty(),
            detection_ms: ms(self.detection),
            safe_state_ms: ms(self.safe_state),
            recovery_ms: ms(self.recovery),
            events: self.events,
            counters: self.counters,
            failures: self.failures,
            duration_s: self.started.elapsed().as_secs_f64(),
        }
    }

    /// A drill that could not even set up.
    #[must_use]
    pub fn aborted(mut self, why: impl Into<String>) -> DrillOutcome {
        self.that(false, why);
        self.finish()
    }
}

/// Run drill `name` in real time (`None` for an unknown name).
pub async fn run(name: &str, config: &Config, seed: u64) -> Option<DrillOutcome> {
    run_on(name, config, seed, DrillClock::Real).await
}

/// Run drill `name` on `clock` (`None` for an unknown name). On [`DrillClock::Virtual`] the
/// caller's runtime must be a current-thread one with its clock paused; a drill that needs real
/// time fails saying why.
pub async fn run_on(name: &str, config: &Config, seed: u64, clock: DrillClock) -> Option<DrillOutcome> {
    let drill = DRILLS.iter().find(|d| d.name == name)?;
    let mut c = Check::on(name, clock);
    if let (DrillClock::Virtual, Some(why)) = (clock, drill.real_time_only()) {
        return Some(c.aborted(format!("runs in real time only: {why}")));
    }
    match name {
        "lidar-panic" => devices::lidar_panic(config, seed, &mut c).await,
        "fail-forever" => devices::fail_forever(config, seed, &mut c).await,
        "can-bus-restart" => devices::can_bus_restart(config, seed, &mut c).await,
        "lidar-reset" => devices::lidar_reset(config, seed, &mut c).await,
        "lidar-stall" => devices::lidar_stall(config, seed, &mut c).await,
        "imu-unplug" => devices::imu_unplug(config, seed, &mut c).await,
        "can-link-reset" => devices::can_link_reset(config, seed, &mut c).await,
        "drive-bus-off" => devices::drive_bus_off(config, seed, &mut c).await,
        "drive-heartbeat" => devices::drive_heartbeat(config, seed, &mut c).await,
        "drive-reboot" => devices::drive_reboot(config, seed, &mut c).await,
        "drive-fault-moving" => devices::drive_fault_moving(config, seed, &mut c).await,
        "new-master-moving" => devices::new_master_moving(config, seed, &mut c).await,
        "estop-during-restart" => devices::estop_during_restart(config, seed, &mut c).await,
        "safety-crash-moving" => devices::safety_crash_moving(config, seed, &mut c).await,
        "robot-restart-odometry" => fleet::robot_restart_odometry(config, seed, &mut c).await,
        "bad-scan" => fleet::bad_scan(config, seed, &mut c).await,
        "command-burst" => devices::command_burst(config, seed, &mut c).await,
        "robot-freeze" => devices::robot_freeze(config, seed, &mut c).await,
        "drive-reboot-moving" => devices::drive_reboot_moving(config, seed, &mut c).await,
        "bad-data" => devices::bad_data(config, seed, &mut c).await,
        "absent-at-start" => devices::absent_at_start(config, seed, &mut c).await,
        "link-lost" => fleet::link_lost(config, seed, &mut c).await,
        "server-restart" => fleet::server_restart(config, seed, &mut c).await,
        "slow-consumer" => fleet::slow_consumer(config, seed, &mut c).await,
        "estop" => devices::estop(config, seed, &mut c).await,
        "estop-input" => devices::estop_input(config, seed, &mut c).await,
        "estop-restart" => devices::estop_restart(config, seed, &mut c).await,
        "late-scans" => fleet::late_scans(config, seed, &mut c).await,
        "scan-flood" => fleet::scan_flood(config, seed, fleet::FLOOD_FULL, &mut c).await,
        "soak" => soak::soak(config, seed, soak::SOAK_FULL, &mut c).await,
        _ => return None,
    }
    Some(c.finish())
}

pub use soak::SOAK_MIN;

/// The scan-flood drill on `clock`, flooding for `length` (CI runs a shortened one).
pub async fn scan_flood(config: &Config, seed: u64, length: Duration, clock: DrillClock) -> DrillOutcome {
    let mut c = Check::on("scan-flood", clock);
    fleet::scan_flood(config, seed, length, &mut c).await;
    c.finish()
}

/// The soak drill on `clock` for `length` (CI runs a shortened one; at least [`SOAK_MIN`] to mean
/// anything).
pub async fn soak(config: &Config, seed: u64, length: Duration, clock: DrillClock) -> DrillOutcome {
    let mut c = Check::on("soak", clock);
    soak::soak(config, seed, length, &mut c).await;
    c.finish()
}

/// The results as a Markdown table.
#[must_use]
pub fn table(outcomes: &[DrillOutcome]) -> String {
    let ms = |v: Option<f64>| v.map_or("–".to_owned(), |v| format!("{v:.0}"));
    let mut s = String::from(
        "| drill | result | detection ms | safe state ms | recovery ms | time s |\n|---|---|---:|---:|---:|---:|\n",
    );
    for o in outcomes {
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} | {} | {:.1} |",
            o.name,
            if o.passed { "pass" } else { "FAIL" },
            ms(o.detection_ms),
            ms(o.safe_state_ms),
            ms(o.recovery_ms),
            o.duration_s
        );
    }
    for o in outcomes.iter().filter(|o| !o.passed) {
        let _ = writeln!(s, "\n{} failed:", o.name);
        for f in &o.failures {
            let _ = writeln!(s, "- {f}");
        }
    }
    s
}

// ---- helpers shared by the drills ----

/// A robot alone with its mocks, every device Ok.
pub(crate) async fn rig(config: &Config, seed: u64, can: SimCan, c: &mut Check) -> Option<RobotRig> {
    rig_on(config, seed, can, false, c).await
}

/// [`rig`], with the robot on a runtime of its own if `apart` (so that it can be frozen).
pub(crate) async fn rig_on(
    config: &Config,
    seed: u64,
    can: SimCan,
    apart: bool,
    c: &mut Check,
) -> Option<RobotRig> {
    rig_with(config, seed, can, apart, RobotOptions::default(), c).await
}

/// [`rig_on`] with the robot's `options`.
pub(crate) async fn rig_with(
    config: &Config,
    seed: u64,
    can: SimCan,
    apart: bool,
    options: RobotOptions,
    c: &mut Check,
) -> Option<RobotRig> {
    let Some(scenario) = config.scenarios.get("straight").cloned() else {
        c.fail("setup: the configuration has no `straight` scenario");
        return None;
    };
    let can = c.can(can);
    let started = if apart {
        RobotRig::start_apart(config, &scenario, seed, can, options).await
    } else {
        RobotRig::start(config, &scenario, seed, can, options).await
    };
    let rig = match started {
        Ok(r) => r,
        Err(e) => {
            c.that(false, format!("setup: {e}"));
            return None;
        }
    };
    c.within("setup: every device Ok", Duration::from_secs(15), || all_ok(&rig)).await?;
    Some(rig)
}

/// LiDAR, IMU, bus and drives all Ok.
pub(crate) fn all_ok(rig: &RobotRig) -> bool {
    [Device::Lidar, Device::Imu, Device::CanBus, Device::Drives]
        .iter()
        .all(|d| health(rig, *d) == Some(Health::Ok))
}

/// A device's health now.
pub(crate) fn health(rig: &RobotRig, d: Device) -> Option<Health> {
    rig.tree.ports.health_board.borrow().get(&d).map(|r| r.health)
}

/// The current child `name` of `sup`.
pub(crate) async fn child(sup: &ActorRef<SupervisorMsg>, name: &str) -> Option<ActorCell> {
    let children: Vec<ChildInfo> = ractor::call!(sup, SupervisorMsg::Children).ok()?;
    children.into_iter().find(|c| c.name == name).and_then(|c| c.cell)
}

/// The supervision events from index `from`, as `supervisor: kind` lines.
pub(crate) fn events_from(rig: &RobotRig, from: usize) -> Vec<String> {
    rig.tree.events.snapshot().iter().skip(from).map(|e| format!("{}: {:?}", e.supervisor, e.kind)).collect()
}

/// Arm the robot and feed it `v` at 20 Hz until the returned guard is dropped.
pub(crate) fn drive(rig: &RobotRig, v_mps: f64) -> crate::AbortOnDrop<()> {
    drive_from(rig, v_mps, 1)
}

/// [`drive`] with an arm and commands numbered from `first_seq` (a re-arm after an earlier feed).
pub(crate) fn drive_from(rig: &RobotRig, v_mps: f64, first_seq: u64) -> crate::AbortOnDrop<()> {
    let id = rig.tree.id.clone();
    let down = rig.server.down.clone();
    let clock = rig.clock;
    down.send(&id, Downlink::Arm { seq: first_seq, stops: rig.stops(), stamp_s: clock.now_s() });
    crate::AbortOnDrop(tokio::spawn(async move {
        // Bounded: at most 10 minutes of commands.
        for seq in first_seq..first_seq + 12_000 {
            down.send(&id, Downlink::Command(Command { seq, stamp_s: clock.now_s(), v_mps, w_radps: 0.0 }));
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }))
}

/// Both mock drives turning faster than `cps` counts/s.
pub(crate) fn wheels_turning(rig: &RobotRig, cps: f64) -> bool {
    rig.mocks.drives.iter().all(|d| d.now().velocity_cps.abs() > cps)
}

/// Both mock drives at rest.
pub(crate) fn wheels_still(rig: &RobotRig) -> bool {
    rig.mocks.drives.iter().all(|d| d.now().velocity_cps.abs() < 1.0)
}

/// The robot's counters into the outcome.
pub(crate) fn keep_counters(rig: &RobotRig, c: &mut Check) {
    c.counters = rig.tree.counters.snapshot();
}
