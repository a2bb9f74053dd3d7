//! Supervisor tests: tokio paused time, exact ordered event logs, exact restart delays.
//!
//! One file because the tests share one set-up: the toy child actors with their failure switches,
//! the supervisors built from them and the helpers that read the exact event log.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "tests fail loudly on a broken set-up")]

use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use ractor::{Actor, ActorCell, ActorProcessingErr, ActorRef, ActorStatus, call_t};
use tokio::time::Instant;

use super::{
    ChildInfo, ChildSpec, EventKind, EventLog, RestartPolicy, Strategy, Supervisor, SupervisorEvent,
    SupervisorMsg, SupervisorSpec,
};

/// Start and stop records of the test actors, shared with the test.
type Journal = Arc<Mutex<Vec<String>>>;

/// Generous bound for waits: with paused time it only matters when something is broken.
const WAIT: Duration = Duration::from_secs(120);

const POLICY: RestartPolicy = RestartPolicy {
    max_restarts: 3,
    window: Duration::from_secs(10),
    backoff_initial: Duration::from_millis(100),
    backoff_max: Duration::from_secs(1),
};

/// A test child: records its start (end of `pre_start`) and its orderly stop (`post_stop`), fails
/// on request, and optionally fails its first starts.
struct Worker;

struct WorkerArgs {
    label: String,
    journal: Journal,
    /// Start attempts so far and how many of the first ones fail.
    flaky: Option<(Arc<AtomicU32>, u32)>,
}

#[derive(Debug)]
enum WorkerMsg {
    /// `handle` returns an error.
    Fail,
    /// `handle` panics.
    Panic,
    /// The worker stops itself (a normal exit we did not ask for).
    Exit,
}

impl Actor for Worker {
    type Msg = WorkerMsg;
    type State = WorkerArgs;
    type Arguments = WorkerArgs;

    async fn pre_start(
        &self,
        _myself: ActorRef<WorkerMsg>,
        args: WorkerArgs,
    ) -> Result<WorkerArgs, ActorProcessingErr> {
        if let Some((attempts, failing)) = &args.flaky
            && attempts.fetch_add(1, Ordering::SeqCst) < *failing
        {
            return Err(format!("{} not reachable", args.label).into());
        }
        args.journal.lock().unwrap().push(format!("start {}", args.label));
        Ok(args)
    }

    async fn handle(
        &self,
        myself: ActorRef<WorkerMsg>,
        message: WorkerMsg,
        _state: &mut WorkerArgs,
    ) -> Result<(), ActorProcessingErr> {
        match message {
            WorkerMsg::Fail => Err("injected failure".into()),
            WorkerMsg::Panic => panic!("injected panic"),
            WorkerMsg::Exit => {
                myself.stop(Some("done".to_owned()));
                Ok(())
            }
        }
    }

    async fn post_stop(
        &self,
        _myself: ActorRef<WorkerMsg>,
        state: &mut WorkerArgs,
    ) -> Result<(), ActorProcessingErr> {
        state.journal.lock().unwrap().push(format!("stop {}", state.label));
        Ok(())
    }
}

fn worker(name: &str, journal: &Journal) -> ChildSpec {
    flaky_worker(name, journal, 0)
}

/// A worker whose first `failing` starts fail in `pre_start`.
fn flaky_worker(name: &str, journal: &Journal, failing: u32) -> ChildSpec {
    let label = name.to_owned();
    let journal = Arc::clone(journal);
    let attempts = Arc::new(AtomicU32::new(0));
    ChildSpec::new(name, move || {
        let flaky = (failing > 0).then(|| (Arc::clone(&attempts), failing));
        (Worker, WorkerArgs { label: label.clone(), journal: Arc::clone(&journal), flaky })
    })
}

fn spec(
    name: &str,
    strategy: Strategy,
    policy: RestartPolicy,
    children: Vec<ChildSpec>,
    events: &EventLog,
) -> SupervisorSpec {
    SupervisorSpec { name: name.to_owned(), strategy, policy, children, events: events.clone() }
}

async fn spawn(spec: SupervisorSpec) -> (ActorRef<SupervisorMsg>, ractor::concurrency::JoinHandle<()>) {
    Actor::spawn(None, Supervisor, spec).await.unwrap()
}

async fn children(supervisor: &ActorRef<SupervisorMsg>) -> Vec<ChildInfo> {
    call_t!(supervisor, SupervisorMsg::Children, 10_000).unwrap()
}

fn info<'a>(infos: &'a [ChildInfo], name: &str) -> &'a ChildInfo {
    infos.iter().find(|info| info.name == name).unwrap()
}

fn cell(infos: &[ChildInfo], name: &str) -> ActorCell {
    info(infos, name).cell.clone().unwrap()
}

/// Sends `message` to the running child `name` of `supervisor`.
async fn send(supervisor: &ActorRef<SupervisorMsg>, name: &str, message: WorkerMsg) {
    cell(&children(supervisor).await, name).send_message(message).unwrap();
}

fn started(child: &str) -> EventKind {
    EventKind::Started { child: child.to_owned() }
}

fn stopped(child: &str) -> EventKind {
    EventKind::Stopped { child: child.to_owned() }
}

fn failed(child: &str, reason: &str) -> EventKind {
    EventKind::Failed { child: child.to_owned(), reason: reason.to_owned() }
}

fn start_failed(child: &str, reason: &str) -> EventKind {
    EventKind::StartFailed { child: child.to_owned(), reason: reason.to_owned() }
}

fn scheduled(child: &str, attempt: u32, delay_ms: u64) -> EventKind {
    EventKind::RestartScheduled { child: child.to_owned(), attempt, delay_ms }
}

fn event(supervisor: &str, kind: EventKind) -> SupervisorEvent {
    SupervisorEvent { supervisor: supervisor.to_owned(), kind }
}

/// Waits for the `n`-th (1-based) event of this kind recorded by any supervisor.
async fn wait_nth(log: &EventLog, kind: &EventKind, n: usize) {
    let found = log.wait_for_nth(|event| event.kind == *kind, n, WAIT).await;
    assert!(found.is_some(), "no {kind:?} #{n} in {:#?}", log.snapshot());
}

/// When the `n`-th (1-based) event of this kind was recorded.
fn at(log: &EventLog, kind: &EventKind, n: usize) -> Instant {
    log.timed_snapshot().into_iter().filter(|(_, event)| event.kind == *kind).nth(n - 1).unwrap().0
}

fn journal(journal: &Journal) -> Vec<String> {
    journal.lock().unwrap().clone()
}

fn strings(items: &[&str]) -> Vec<String> {
    items.iter().map(|&item| item.to_owned()).collect()
}

#[test]
fn backoff_doubles_from_the_initial_delay_and_is_capped() {
    let policy = RestartPolicy { backoff_max: Duration::from_millis(400), ..POLICY };
    let delays: Vec<_> = (0..=5).map(|attempt| policy.backoff(attempt).as_millis()).collect();
    assert_eq!(delays, vec![100, 100, 200, 400, 400, 400]);
    assert_eq!(policy.backoff(u32::MAX), Duration::from_millis(400));
    let huge =
        RestartPolicy { backoff_initial: Duration::MAX, backoff_max: Duration::from_secs(7), ..POLICY };
    assert_eq!(huge.backoff(3), Duration::from_secs(7));
}

#[tokio::test(start_paused = true)]
async fn one_for_one_restarts_only_the_failed_child() {
    let log = EventLog::new();
    let record = Journal::default();
    let children_specs = vec![worker("a", &record), worker("b", &record), worker("c", &record)];
    let (sup, handle) = spawn(spec("s", Strategy::OneForOne, POLICY, children_specs, &log)).await;
    let before = children(&sup).await;

    send(&sup, "b", WorkerMsg::Fail).await;
    wait_nth(&log, &started("b"), 2).await;

    assert_eq!(
        log.kinds("s"),
        vec![
            started("a"),
            started("b"),
            started("c"),
            failed("b", "injected failure"),
            scheduled("b", 1, 100),
            started("b"),
        ]
    );
    assert_eq!(
        at(&log, &started("b"), 2) - at(&log, &failed("b", "injected failure"), 1),
        POLICY.backoff_initial
    );
    let after = children(&sup).await;
    assert_eq!(cell(&after, "a").get_id(), cell(&before, "a").get_id());
    assert_eq!(cell(&after, "c").get_id(), cell(&before, "c").get_id());
    assert_ne!(cell(&after, "b").get_id(), cell(&before, "b").get_id());
    let restarts: Vec<_> = after.iter().map(|info| info.restarts).collect();
    assert_eq!(restarts, vec![0, 1, 0]);
    assert_eq!(journal(&record), strings(&["start a", "start b", "start c", "start b"]));

    sup.stop_and_wait(None, Some(WAIT)).await.unwrap();
    handle.await.unwrap();
}

#[tokio::test(start_paused = true)]
async fn a_panic_and_a_normal_exit_are_failures_too() {
    let log = EventLog::new();
    let record = Journal::default();
    let (sup, _handle) =
        spawn(spec("s", Strategy::OneForOne, POLICY, vec![worker("a", &record), worker("b", &record)], &log))
            .await;

    send(&sup, "a", WorkerMsg::Panic).await;
    wait_nth(&log, &started("a"), 2).await;
    send(&sup, "b", WorkerMsg::Exit).await;
    wait_nth(&log, &started("b"), 2).await;

    assert_eq!(
        log.kinds("s"),
        vec![
            started("a"),
            started("b"),
            failed("a", "injected panic"),
            scheduled("a", 1, 100),
            started("a"),
            failed("b", "exited: done"),
            scheduled("b", 1, 100),
            started("b"),
        ]
    );
    // The worker that exited on its own ran its post_stop; the one that panicked did not.
    assert_eq!(journal(&record), strings(&["start a", "start b", "start a", "stop b", "start b"]));
    sup.stop_and_wait(None, Some(WAIT)).await.unwrap();
}

#[tokio::test(start_paused = true)]
async fn backoff_doubles_caps_and_starts_over_after_a_stable_window() {
    let log = EventLog::new();
    let record = Journal::default();
    let policy = RestartPolicy { max_restarts: 10, backoff_max: Duration::from_millis(400), ..POLICY };
    let (sup, _handle) =
        spawn(spec("s", Strategy::OneForOne, policy, vec![worker("w", &record)], &log)).await;

    // Five failures in a row, each right after the restart.
    for n in 1..=5 {
        wait_nth(&log, &started("w"), n).await;
        send(&sup, "w", WorkerMsg::Fail).await;
    }
    wait_nth(&log, &started("w"), 6).await;
    // Then it runs for a whole window before failing again: the backoff starts over.
    tokio::time::sleep(policy.window).await;
    send(&sup, "w", WorkerMsg::Fail).await;
    wait_nth(&log, &started("w"), 7).await;

    let fail = failed("w", "injected failure");
    let mut expected = vec![started("w")];
    for (attempt, delay_ms) in [(1, 100), (2, 200), (3, 400), (4, 400), (5, 400), (1, 100)] {
        expected.extend([fail.clone(), scheduled("w", attempt, delay_ms), started("w")]);
    }
    assert_eq!(log.kinds("s"), expected);
    let delays: Vec<_> =
        (1..=6).map(|n| (at(&log, &started("w"), n + 1) - at(&log, &fail, n)).as_millis()).collect();
    assert_eq!(delays, vec![100, 200, 400, 400, 400, 100]);
    sup.stop_and_wait(None, Some(WAIT)).await.unwrap();
}

#[tokio::test(start_paused = true)]
async fn intensity_exceeded_stops_the_children_in_reverse_and_escalates_without_a_restart_storm() {
    let log = EventLog::new();
    let record = Journal::default();
    let policy = RestartPolicy { max_restarts: 2, ..POLICY };
    let children_specs = vec![worker("a", &record), worker("b", &record), worker("c", &record)];
    let (sup, handle) = spawn(spec("s", Strategy::OneForOne, policy, children_specs, &log)).await;

    for n in 1..=3 {
        wait_nth(&log, &started("b"), n).await;
        send(&sup, "b", WorkerMsg::Fail).await;
    }
    tokio::time::timeout(WAIT, handle).await.unwrap().unwrap();
    assert_eq!(sup.get_status(), ActorStatus::Stopped);

    let fail = failed("b", "injected failure");
    let expected = vec![
        started("a"),
        started("b"),
        started("c"),
        fail.clone(),
        scheduled("b", 1, 100),
        started("b"),
        fail.clone(),
        scheduled("b", 2, 200),
        started("b"),
        fail,
        stopped("c"),
        stopped("a"),
        EventKind::Escalated { reason: "child b: 3 failures within 10s exceed max_restarts 2".to_owned() },
    ];
    assert_eq!(log.kinds("s"), expected);
    let stops = strings(&["start a", "start b", "start c", "start b", "start b", "stop c", "stop a"]);
    assert_eq!(journal(&record), stops);

    // Long after any backoff: nothing restarts.
    tokio::time::sleep(Duration::from_secs(60)).await;
    assert_eq!(log.kinds("s"), expected);
    assert_eq!(journal(&record), stops);
}

#[tokio::test(start_paused = true)]
async fn a_nested_supervisor_that_escalates_is_restarted_by_its_parent() {
    let log = EventLog::new();
    let record = Journal::default();
    let inner_policy = RestartPolicy { max_restarts: 1, ..POLICY };
    let inner = spec(
        "inner",
        Strategy::OneForOne,
        inner_policy,
        vec![worker("a", &record), worker("b", &record)],
        &log,
    );
    let inner_child = ChildSpec::new("inner", move || (Supervisor, inner.clone()));
    let (outer, _handle) =
        spawn(spec("outer", Strategy::OneForOne, POLICY, vec![inner_child, worker("other", &record)], &log))
            .await;
    let before = children(&outer).await;
    let inner_ref: ActorRef<SupervisorMsg> = cell(&before, "inner").into();

    send(&inner_ref, "b", WorkerMsg::Fail).await;
    wait_nth(&log, &started("b"), 2).await;
    send(&inner_ref, "b", WorkerMsg::Fail).await;
    wait_nth(&log, &started("inner"), 2).await;

    let reason = "child b: 2 failures within 10s exceed max_restarts 1";
    let fail = failed("b", "injected failure");
    assert_eq!(
        log.snapshot(),
        vec![
            event("inner", started("a")),
            event("inner", started("b")),
            event("outer", started("inner")),
            event("outer", started("other")),
            event("inner", fail.clone()),
            event("inner", scheduled("b", 1, 100)),
            event("inner", started("b")),
            event("inner", fail),
            event("inner", stopped("a")),
            event("inner", EventKind::Escalated { reason: reason.to_owned() }),
            event("outer", failed("inner", &format!("supervisor inner: {reason}"))),
            event("outer", scheduled("inner", 1, 100)),
            event("inner", started("a")),
            event("inner", started("b")),
            event("outer", started("inner")),
        ]
    );
    let after = children(&outer).await;
    assert_eq!(cell(&after, "other").get_id(), cell(&before, "other").get_id());
    assert_eq!(info(&after, "inner").restarts, 1);
    let new_inner: ActorRef<SupervisorMsg> = cell(&after, "inner").into();
    assert!(children(&new_inner).await.iter().all(|child| child.cell.is_some() && child.restarts == 0));
    outer.stop_and_wait(None, Some(WAIT)).await.unwrap();
}

#[tokio::test(start_paused = true)]
async fn rest_for_one_restarts_the_failed_child_and_the_later_ones_in_order() {
    let log = EventLog::new();
    let record = Journal::default();
    let (sup, _handle) = spawn(spec(
        "s",
        Strategy::RestForOne,
        POLICY,
        vec![worker("bus", &record), worker("drives", &record)],
        &log,
    ))
    .await;

    send(&sup, "bus", WorkerMsg::Fail).await;
    wait_nth(&log, &started("drives"), 2).await;
    let bus_before = cell(&children(&sup).await, "bus").get_id();
    // The drives alone: the bus stays.
    send(&sup, "drives", WorkerMsg::Fail).await;
    wait_nth(&log, &started("drives"), 3).await;

    assert_eq!(
        log.kinds("s"),
        vec![
            started("bus"),
            started("drives"),
            failed("bus", "injected failure"),
            stopped("drives"),
            scheduled("bus", 1, 100),
            started("bus"),
            started("drives"),
            failed("drives", "injected failure"),
            scheduled("drives", 1, 100),
            started("drives"),
        ]
    );
    let bus_failed = at(&log, &failed("bus", "injected failure"), 1);
    assert_eq!(at(&log, &started("bus"), 2) - bus_failed, Duration::from_millis(100));
    assert_eq!(at(&log, &started("drives"), 2) - bus_failed, Duration::from_millis(100));
    let after = children(&sup).await;
    assert_eq!(cell(&after, "bus").get_id(), bus_before);
    assert_eq!(
        journal(&record),
        strings(&["start bus", "start drives", "stop drives", "start bus", "start drives", "start drives"])
    );
    sup.stop_and_wait(None, Some(WAIT)).await.unwrap();
}

#[tokio::test(start_paused = true)]
async fn rest_for_one_an_earlier_failure_supersedes_a_pending_restart() {
    let log = EventLog::new();
    let record = Journal::default();
    let (sup, _handle) = spawn(spec(
        "s",
        Strategy::RestForOne,
        POLICY,
        vec![worker("bus", &record), worker("drives", &record)],
        &log,
    ))
    .await;

    send(&sup, "drives", WorkerMsg::Fail).await;
    wait_nth(&log, &scheduled("drives", 1, 100), 1).await;
    // The bus fails while the drives' restart is pending: the drives wait for the bus instead.
    send(&sup, "bus", WorkerMsg::Fail).await;
    wait_nth(&log, &started("drives"), 2).await;
    tokio::time::sleep(Duration::from_secs(30)).await;

    assert_eq!(
        log.kinds("s"),
        vec![
            started("bus"),
            started("drives"),
            failed("drives", "injected failure"),
            scheduled("drives", 1, 100),
            failed("bus", "injected failure"),
            scheduled("bus", 1, 100),
            started("bus"),
            started("drives"),
        ]
    );
    let restarts: Vec<_> = children(&sup).await.iter().map(|info| info.restarts).collect();
    assert_eq!(restarts, vec![1, 1]);
    sup.stop_and_wait(None, Some(WAIT)).await.unwrap();
}

#[tokio::test(start_paused = true)]
async fn a_child_failing_to_start_is_retried_while_the_others_run() {
    let log = EventLog::new();
    let record = Journal::default();
    let children_specs = vec![worker("a", &record), flaky_worker("lidar", &record, 2), worker("c", &record)];
    let (sup, _handle) = spawn(spec("s", Strategy::OneForOne, POLICY, children_specs, &log)).await;

    let running: Vec<_> = children(&sup).await.iter().map(|info| info.cell.is_some()).collect();
    assert_eq!(running, vec![true, false, true]);
    wait_nth(&log, &started("lidar"), 1).await;

    let reason = "lidar not reachable";
    assert_eq!(
        log.kinds("s"),
        vec![
            started("a"),
            start_failed("lidar", reason),
            scheduled("lidar", 1, 100),
            started("c"),
            start_failed("lidar", reason),
            scheduled("lidar", 2, 200),
            started("lidar"),
        ]
    );
    assert_eq!(at(&log, &started("lidar"), 1) - at(&log, &started("a"), 1), Duration::from_millis(300));
    assert_eq!(info(&children(&sup).await, "lidar").restarts, 2);
    sup.stop_and_wait(None, Some(WAIT)).await.unwrap();
}

#[tokio::test(start_paused = true)]
async fn rest_for_one_later_children_start_once_a_failed_start_succeeds() {
    let log = EventLog::new();
    let record = Journal::default();
    let children_specs = vec![flaky_worker("bus", &record, 1), worker("drives", &record)];
    let (sup, _handle) = spawn(spec("s", Strategy::RestForOne, POLICY, children_specs, &log)).await;
    let t0 = Instant::now();

    let running: Vec<_> = children(&sup).await.iter().map(|info| info.cell.is_some()).collect();
    assert_eq!(running, vec![false, false]);
    wait_nth(&log, &started("drives"), 1).await;

    assert_eq!(
        log.kinds("s"),
        vec![
            start_failed("bus", "bus not reachable"),
            scheduled("bus", 1, 100),
            started("bus"),
            started("drives")
        ]
    );
    assert_eq!(at(&log, &started("drives"), 1) - t0, Duration::from_millis(100));
    assert_eq!(journal(&record), strings(&["start bus", "start drives"]));
    sup.stop_and_wait(None, Some(WAIT)).await.unwrap();
}

#[tokio::test(start_paused = true)]
async fn start_failures_beyond_the_intensity_fail_the_supervisor_start() {
    let log = EventLog::new();
    let record = Journal::default();
    let policy = RestartPolicy { max_restarts: 0, ..POLICY };
    let children_specs = vec![worker("a", &record), flaky_worker("lidar", &record, 1)];
    let result =
        Actor::spawn(None, Supervisor, spec("s", Strategy::OneForOne, policy, children_specs, &log)).await;

    assert!(result.is_err());
    assert_eq!(
        log.kinds("s"),
        vec![
            started("a"),
            start_failed("lidar", "lidar not reachable"),
            stopped("a"),
            EventKind::Escalated {
                reason: "child lidar: 1 failures within 10s exceed max_restarts 0".to_owned()
            },
        ]
    );
    assert_eq!(journal(&record), strings(&["start a", "stop a"]));
}

#[tokio::test(start_paused = true)]
async fn duplicate_child_names_are_refused() {
    let log = EventLog::new();
    let record = Journal::default();
    let children_specs = vec![worker("a", &record), worker("a", &record)];
    let result =
        Actor::spawn(None, Supervisor, spec("s", Strategy::OneForOne, POLICY, children_specs, &log)).await;
    assert!(result.is_err());
    assert!(log.is_empty());
    assert!(journal(&record).is_empty());
}

#[tokio::test(start_paused = true)]
async fn shutdown_stops_the_children_in_reverse_order() {
    let log = EventLog::new();
    let record = Journal::default();
    let children_specs = vec![worker("a", &record), worker("b", &record), worker("c", &record)];
    let (sup, handle) = spawn(spec("s", Strategy::OneForOne, POLICY, children_specs, &log)).await;

    sup.stop_and_wait(None, Some(WAIT)).await.unwrap();
    handle.await.unwrap();

    assert_eq!(
        log.kinds("s"),
        vec![started("a"), started("b"), started("c"), stopped("c"), stopped("b"), stopped("a")]
    );
    assert_eq!(journal(&record), strings(&["start a", "start b", "start c", "stop c", "stop b", "stop a"]));
}

#[tokio::test(start_paused = true)]
async fn shutdown_cancels_a_pending_restart() {
    let log = EventLog::new();
    let record = Journal::default();
    let (sup, handle) =
        spawn(spec("s", Strategy::OneForOne, POLICY, vec![worker("a", &record), worker("b", &record)], &log))
            .await;

    send(&sup, "b", WorkerMsg::Fail).await;
    wait_nth(&log, &scheduled("b", 1, 100), 1).await;
    sup.stop_and_wait(None, Some(WAIT)).await.unwrap();
    handle.await.unwrap();
    tokio::time::sleep(Duration::from_secs(30)).await;

    assert_eq!(
        log.kinds("s"),
        vec![
            started("a"),
            started("b"),
            failed("b", "injected failure"),
            scheduled("b", 1, 100),
            stopped("a")
        ]
    );
    assert_eq!(journal(&record), strings(&["start a", "start b", "stop a"]));
}

#[tokio::test(start_paused = true)]
async fn wait_for_sees_past_and_future_events_and_gives_up_after_the_timeout() {
    let log = EventLog::new();
    log.push(event("s", started("a")));
    assert_eq!(log.wait_for(|e| e.kind == started("a"), WAIT).await, Some(event("s", started("a"))));

    let later = log.clone();
    tokio::spawn(async move {
        tokio::time::sleep(Duration::from_secs(1)).await;
        later.push(event("s", stopped("a")));
    });
    let t0 = Instant::now();
    assert_eq!(log.wait_for(|e| e.kind == stopped("a"), WAIT).await, Some(event("s", stopped("a"))));
    assert_eq!(t0.elapsed(), Duration::from_secs(1));

    assert_eq!(log.wait_for_nth(|e| e.supervisor == "s", 3, Duration::from_secs(5)).await, None);
    assert_eq!(t0.elapsed(), Duration::from_secs(6));
    assert_eq!(log.len(), 2);
}
