//! Drills on the whole fleet: the link and the server (`link`), a slow consumer (`slow`), a robot's
//! odometry restarting and scans no sensor can produce (`scans`), a flood of scans (`flood`). The
//! helpers they share are here.
//!
//! Each runs a whole simulation ([`Sim`]: both robots, their mock devices, the server) on one
//! straight 4 m leg of the shipped `straight` scenario, waits until the formation runs and the
//! robots move, injects the fault and checks, with deadlines, what the robots and the server do.
//! The times are measured from the injection.
//!
//! Safe state: a robot whose commands stop disarms itself (its 200 ms command watchdog) and brakes
//! its wheels to zero at its stop deceleration, 0.5 m/s² — from the formation's 0.22 m/s that takes
//! 0.44 s. Two times are measured: the braking *started* (every drive's commanded target below its
//! value at the injection; counter `ramp_started_ms`, within 350 ms) and the wheels *commanded to
//! zero* (every target 0; the outcome's safe-state time, at most 0.6 s after the last watchdog).

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use amr_actors::config::Config;
use amr_actors::server::formation::Phase;
use amr_actors::server::localizer::LocalizerMsg;
use amr_actors::server::ports::ServerStats;
use amr_actors::supervisor::EventKind;
use amr_core::config::ScenarioConfig;
use amr_msgs::{DisarmReason, SafetyState};
use hil_mocks::world::Noise;
use ractor::{Actor, ActorProcessingErr, ActorRef};
use tokio::time::Instant;

use super::Check;
use crate::{Sim, SimCan, SimOptions};

mod flood;
mod link;
mod scans;
mod slow;

pub(crate) use flood::{FLOOD_FULL, scan_flood};
pub(crate) use link::{late_scans, link_lost, server_restart};
pub(crate) use scans::{bad_scan, robot_restart_odometry};
pub(crate) use slow::slow_consumer;

/// The command watchdog fires 200 ms after the last command, which came up to one formation period
/// (50 ms) before the fault, and acts at the next 20 ms cycle: 270 ms, and some scheduling slack.
const WATCHDOG_DEADLINE: Duration = Duration::from_millis(350);
/// A stop brakes at the robot's stop deceleration (0.5 m/s²), not at the 0.05 m/s² motion limit:
/// from the formation's top speed (0.22 m/s) every target is zero 0.44 s after the watchdog fires,
/// and the drill requires it within 0.6 s of detection.
const STOP_AFTER_DETECTION: Duration = Duration::from_millis(600);
const ZERO_DEADLINE: Duration = Duration::from_millis(350 + 600);

/// One straight 4 m leg of the `straight` scenario (the drills need the plan to go on after the
/// fault, not to come back over the same ground).
fn one_leg(config: &Config) -> Option<ScenarioConfig> {
    let mut sc = config.scenarios.get("straight")?.clone();
    sc.segments.truncate(1);
    Some(sc)
}

/// A drill's simulation of `scenario`: typical noise, CAN in process (or, on virtual time, every
/// device in memory), no time limit.
fn drill_options(scenario: ScenarioConfig, seed: u64, c: &Check) -> SimOptions {
    SimOptions {
        scenario_name: "drill".into(),
        scenario,
        seed,
        noise: Noise::TYPICAL,
        can: c.can(SimCan::InProcess),
        configuration: None,
        max_duration: None,
        map: None,
        surveyed_map: false,
    }
}

/// The simulation, running its plan with the robots moving.
pub(super) async fn moving_sim(
    config: &Config,
    seed: u64,
    scenario: ScenarioConfig,
    c: &mut Check,
) -> Option<Sim> {
    let options = drill_options(scenario, seed, c);
    let sim = match Sim::start(config, options).await {
        Ok(s) => s,
        Err(e) => {
            c.fail(format!("setup: {e}"));
            return None;
        }
    };
    let ok = c
        .within(
            "setup: the formation running 6 s into its plan, the wheels turning",
            Duration::from_secs(40),
            || {
                sim.formation().is_some_and(|f| f.phase == Phase::Running && f.plan_s > 6.0)
                    && all_turning(&sim)
            },
        )
        .await;
    if ok.is_none() {
        sim.shutdown().await;
        return None;
    }
    Some(sim)
}

/// Every robot's wheels turning.
pub(super) fn all_turning(sim: &Sim) -> bool {
    sim.mocks.iter().all(|m| m.drives.iter().all(|d| d.now().velocity_cps.abs() > 1000.0))
}

/// Every drive of every robot commanded to zero.
pub(super) fn all_targets_zero(sim: &Sim) -> bool {
    sim.mocks.iter().all(|m| m.drives.iter().all(|d| d.now().target_velocity == 0))
}

/// Every drive at rest.
pub(super) fn all_still(sim: &Sim) -> bool {
    sim.mocks.iter().all(|m| m.drives.iter().all(|d| d.now().velocity_cps.abs() < 1.0))
}

/// The commanded targets of the drives of `robots`, robot by robot.
pub(super) fn targets(sim: &Sim, robots: &[usize]) -> Vec<i32> {
    robots.iter().flat_map(|i| sim.mocks[*i].drives.iter().map(|d| d.now().target_velocity)).collect()
}

/// Robot `i`'s safety state.
pub(super) fn safety(sim: &Sim, i: usize) -> Option<SafetyState> {
    *sim.robots[i].ports.safety_now.borrow()
}

/// No robot armed.
fn none_armed(sim: &Sim) -> bool {
    (0..sim.robots.len()).all(|i| safety(sim, i) != Some(SafetyState::Armed))
}

fn phase(sim: &Sim) -> Option<Phase> {
    sim.formation().map(|f| f.phase)
}

/// A phase's name without its details.
pub(super) fn phase_name(p: &Phase) -> &'static str {
    match p {
        Phase::Waiting => "Waiting",
        Phase::Arming { .. } => "Arming",
        Phase::Running => "Running",
        Phase::Holding { .. } => "Holding",
        Phase::Stopped { .. } => "Stopped",
        Phase::Finished => "Finished",
    }
}

/// Where each supervision log of the simulation is (robots, then the server).
fn marks(sim: &Sim) -> Vec<usize> {
    sim.robots.iter().map(|r| r.events.len()).chain([sim.server.events.len()]).collect()
}

/// The robots' supervision events since `marks`, as `supervisor: kind` lines.
fn robot_events(sim: &Sim, marks: &[usize]) -> Vec<String> {
    sim.robots
        .iter()
        .zip(marks)
        .flat_map(|(r, from)| {
            r.events.snapshot().into_iter().skip(*from).map(|e| format!("{}: {:?}", e.supervisor, e.kind))
        })
        .collect()
}

/// The formation phases from index `from` as `formation: Name` lines, then every supervision event.
fn event_lines(sim: &Sim, phases_from: usize, marks: &[usize], server_from: usize) -> Vec<String> {
    let mut lines: Vec<String> =
        sim.phases().iter().skip(phases_from).map(|p| format!("formation: {}", phase_name(p))).collect();
    lines.extend(robot_events(sim, marks));
    lines.extend(
        sim.server
            .events
            .snapshot()
            .into_iter()
            .skip(server_from)
            .map(|e| format!("{}: {:?}", e.supervisor, e.kind)),
    );
    lines
}

/// The phases seen from index `from`, by name.
fn phases_from(sim: &Sim, from: usize) -> Vec<&'static str> {
    sim.phases().iter().skip(from).map(phase_name).collect()
}

/// Every robot's counters into the outcome, prefixed with the robot's id.
fn keep_counters(sim: &Sim, c: &mut Check) {
    for r in &sim.robots {
        for (k, v) in r.counters.snapshot() {
            c.counters.insert(format!("{}.{k}", r.id), v);
        }
    }
    c.counters.insert("link.lost".into(), sim.link.lost());
    c.counters.insert("link.late".into(), sim.link.late());
}

/// Commands refused by robot `i` so far (any reason).
fn refused(sim: &Sim, i: usize) -> u64 {
    sim.robots[i]
        .counters
        .snapshot()
        .iter()
        .filter(|(k, _)| k.starts_with("safety.refused."))
        .map(|(_, v)| v)
        .sum()
}

fn ms(d: Duration) -> u64 {
    u64::try_from(d.as_millis()).unwrap_or(u64::MAX)
}

/// After a loss of commands to `robots`: (a) each disarmed by its watchdog, the ramp started, (b)
/// their every target zero — with the per-robot watchdog times and the ramp start in the counters. While it
/// waits it checks that no commanded target ever grows (nothing but the ramp down is applied).
async fn watchdog_stop(sim: &Sim, c: &mut Check, robots: &[usize]) {
    let start = targets(sim, robots);
    let owner: Vec<usize> =
        robots.iter().flat_map(|i| sim.mocks[*i].drives.iter().map(move |_| *i)).collect();
    let mut last: Vec<i32> = start.iter().map(|t| t.abs()).collect();
    let mut seen: BTreeMap<usize, Duration> = BTreeMap::new();
    let mut ramp = None;
    let mut stopped = None;
    let until = Instant::now() + ZERO_DEADLINE;
    // Bounded by the deadline.
    loop {
        for &i in robots {
            if !seen.contains_key(&i) && safety(sim, i) == Some(SafetyState::Disarmed(DisarmReason::Watchdog))
            {
                seen.insert(i, c.since_injection());
            }
        }
        if stopped.is_none() && matches!(phase(sim), Some(Phase::Stopped { .. })) {
            stopped = Some(c.since_injection());
        }
        let now = targets(sim, robots);
        if ramp.is_none() && now.iter().zip(&start).all(|(n, s)| *s == 0 || n.abs() < s.abs()) {
            ramp = Some(c.since_injection());
        }
        for (k, (n, l)) in now.iter().zip(last.iter_mut()).enumerate() {
            // Once its robot is disarmed (before, a command in flight may still arrive); ±1 unit of
            // rounding.
            if seen.contains_key(&owner[k]) && n.abs() > *l + 1 {
                c.fail(format!("drive {k}'s commanded target grew from {l} to {n} after the watchdog"));
            }
            *l = n.abs();
        }
        if now.iter().all(|t| *t == 0) {
            c.safe_state = Some(c.since_injection());
            break;
        }
        if Instant::now() >= until {
            c.fail(format!("every target zero: not within {ZERO_DEADLINE:?} ({now:?})"));
            break;
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    for &i in robots {
        let id = &sim.robots[i].id;
        match seen.get(&i) {
            Some(t) => {
                c.that(
                    *t <= WATCHDOG_DEADLINE,
                    format!("{id} disarmed by its watchdog after {t:?} (> {WATCHDOG_DEADLINE:?})"),
                );
                c.counters.insert(format!("watchdog_ms.{id}"), ms(*t));
            }
            None => c.fail(format!("{id} never Disarmed(Watchdog)")),
        }
    }
    c.detection = seen.values().max().copied();
    if let (Some(detected), Some(zero)) = (c.detection, c.safe_state) {
        c.that(
            zero.saturating_sub(detected) <= STOP_AFTER_DETECTION,
            format!(
                "every target zero {:?} after the last watchdog (> {STOP_AFTER_DETECTION:?})",
                zero.saturating_sub(detected)
            ),
        );
    }
    if let Some(t) = stopped {
        c.counters.insert("formation_stopped_ms".into(), ms(t));
    }
    match ramp {
        Some(t) => {
            c.that(
                t <= WATCHDOG_DEADLINE,
                format!("the ramp to zero started after {t:?} (> {WATCHDOG_DEADLINE:?})"),
            );
            c.counters.insert("ramp_started_ms".into(), ms(t));
        }
        None => c.fail("the ramp to zero never started"),
    }
}

/// The operator re-arms: recovery is the time from the re-arm to the formation running with every
/// wheel turning.
async fn rearm_and_run(sim: &Sim, c: &mut Check) {
    let rearm = c.since_injection();
    c.that(sim.server.rearm().await, "re-arm accepted");
    c.recovery = c
        .within("the formation running again, the wheels turning", Duration::from_secs(15), || {
            phase(sim) == Some(Phase::Running) && all_turning(sim)
        })
        .await
        .map(|t| t.saturating_sub(rearm));
}
