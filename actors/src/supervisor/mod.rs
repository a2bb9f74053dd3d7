//! Supervision: a generic OTP-style supervisor as a ractor actor, with our restart policy.
//!
//! # The policy (Erlang/OTP `supervisor`, trimmed to what the robot needs)
//!
//! * A `Supervisor` owns an ordered list of `ChildSpec`s. At start-up it starts them in list
//!   order, inside its own `pre_start`, so that spawning a supervisor returns once its children have
//!   been started (or their first start has failed and a retry is scheduled), as OTP's
//!   `start_link` does. Nested supervisors therefore log their children before themselves.
//! * Every child is *permanent*: any termination we did not ask for is a failure, whether the
//!   child returned an error, panicked, was killed or stopped on its own.
//! * `Strategy::OneForOne` restarts only the failed child. `Strategy::RestForOne` first stops
//!   every running child listed after the failed one (reverse order, each awaited), then, after the
//!   backoff, restarts the failed child and the later ones in list order. Under rest-for-one the
//!   running children are always a prefix of the list: a child is never started while an earlier
//!   one is down.
//! * Restart intensity: the supervisor remembers the times of the failures of the last
//!   [`RestartPolicy::window`]. When a failure makes their number exceed
//!   [`RestartPolicy::max_restarts`], it escalates: it stops all its running children in reverse
//!   list order, logs [`EventKind::Escalated`] and fails itself, so that its own parent sees a
//!   child failure and applies *its* policy. At the top of the tree, the owner of the root
//!   supervisor sees it terminate and puts the robot in its safe state.
//! * Backoff: each child waits `backoff_initial * 2^(n - 1)`, capped at `backoff_max`, before
//!   restart number `n` of a run of consecutive failures. The run is over (n starts again at 1)
//!   when the child fails after having run for at least `window`: the check is made at the
//!   failure, from the time the child last started. A failed *start* never resets the run.
//! * Restarts are driven by timer messages sent to the supervisor itself (ractor's `send_after`,
//!   i.e. tokio time), never by sleeping in a handler: the supervisor keeps handling events while a
//!   restart is pending. Each timer carries the child's generation number; cancelling a pending
//!   restart (a shutdown, an escalation, or under rest-for-one an earlier child failing) bumps the
//!   generation, so a timer that already fired does nothing.
//! * Orderly shutdown: when the supervisor is stopped, it stops its children in reverse list
//!   order, each awaited with `STOP_TIMEOUT` (2 s, then killed), so that e.g. the drives actor gets
//!   to command a quick stop in its `post_stop` before the CAN bus below it goes away.
//! * Every decision is recorded in a shared [`EventLog`] (for tests and drills: exact ordered
//!   logs) and with `tracing` (info for starts, stops and scheduled restarts, warn for failures,
//!   error for escalation), with the fields `supervisor` and `child`.
//!
//! "Reverse start order" means reverse *list* order, as in OTP: under one-for-one a restarted
//! child keeps its place in the list, which is its dependency order.
//!
//! # ractor pitfalls this module handles
//!
//! * ractor's default `handle_supervisor_evt` stops the parent when any child terminates or fails.
//!   `Supervisor` overrides it; an actor that spawns linked children without a supervisor of its
//!   own still gets the default.
//! * A failure (error or panic) in a child's `pre_start` is **not** a supervision event: ractor
//!   returns it as a [`SpawnErr`] from `spawn_linked`. We treat it as a failure of that child
//!   ([`EventKind::StartFailed`]): it counts toward the intensity and the start is retried with
//!   backoff. It never fails the supervisor nor the other children, unless the intensity is
//!   exceeded (then a supervisor that is itself starting fails its own start: its parent sees a
//!   start failure).
//! * Actor names are global in ractor: children are spawned unnamed, and child names are only
//!   unique within their supervisor. Tests can run in parallel.
//! * ractor does not call `post_stop` of an actor that failed or was killed, and kills the
//!   children of an actor that terminates. An escalating supervisor therefore stops its children
//!   itself, in order, before failing.
//! * Supervision events are matched to children by [`ActorId`]: a restarted child has a new id.
//!   The termination events of children we stopped on purpose arrive after we logged them as
//!   [`EventKind::Stopped`] and are ignored, as are events of ids we no longer know.
//! * Stopping a child is awaited inside the supervisor's handler, bounded by `STOP_TIMEOUT`
//!   (then the child is killed, bounded again): a child whose `post_stop` calls back into its
//!   supervisor delays it by at most that, it cannot deadlock it.
//!
//! It is one file because the policy is one state machine: starting, failing, backing off,
//! escalating and stopping all act on the same `SupervisorState` and its ordered list of children.

use std::collections::{HashSet, VecDeque};
use std::fmt;
use std::future::Future;
use std::pin::Pin;
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::time::Duration;

use ractor::concurrency::JoinHandle;
use ractor::{
    Actor, ActorCell, ActorId, ActorProcessingErr, ActorRef, MessagingErr, RactorErr, RpcReplyPort, SpawnErr,
    SupervisionEvent,
};
use tokio::sync::Notify;
use tokio::time::Instant;

#[cfg(test)]
mod tests;

/// How long the supervisor waits for a child to stop (and then again for it to die once killed).
pub(crate) const STOP_TIMEOUT: Duration = Duration::from_secs(2);

/// What starting a child returns: the new child's cell, or ractor's spawn error (e.g. its
/// `pre_start` failed).
pub(crate) type StartFuture = Pin<Box<dyn Future<Output = Result<ActorCell, SpawnErr>> + Send>>;

/// How a child is started: given the supervisor's cell, spawn a fresh instance linked to it.
type StartFn = dyn Fn(ActorCell) -> StartFuture + Send + Sync;

/// One child: a name (unique within its supervisor) and how to start a fresh instance linked to
/// the supervisor.
#[derive(Clone)]
pub(crate) struct ChildSpec {
    /// The child's name in the event log and in tracing; not a ractor (global) actor name.
    pub name: String,
    start: Arc<StartFn>,
}

impl ChildSpec {
    /// A child of actor type `A`. `make` builds a fresh actor value and its arguments for every
    /// (re)start; the child is spawned unnamed (ractor names are global) with
    /// `A::spawn_linked(None, actor, args, supervisor)`.
    pub(crate) fn new<A, F>(name: impl Into<String>, make: F) -> Self
    where
        A: Actor,
        F: Fn() -> (A, A::Arguments) + Send + Sync + 'static,
    {
        Self::from_start_fn(name, move |supervisor: ActorCell| -> StartFuture {
            let (actor, args) = make();
            Box::pin(async move {
                let (actor_ref, _join) = A::spawn_linked(None, actor, args, supervisor).await?;
                Ok(actor_ref.get_cell())
            })
        })
    }

    /// A child started by a custom function, for the cases [`ChildSpec::new`] does not cover.
    /// `start` gets the supervisor's cell and must link the new actor to it (e.g. spawn it with
    /// `spawn_linked(.., supervisor)`), otherwise the supervisor never hears of its failures.
    pub(crate) fn from_start_fn<F>(name: impl Into<String>, start: F) -> Self
    where
        F: Fn(ActorCell) -> StartFuture + Send + Sync + 'static,
    {
        Self { name: name.into(), start: Arc::new(start) }
    }
}

impl fmt::Debug for ChildSpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("ChildSpec").field("name", &self.name).finish_non_exhaustive()
    }
}

/// Which children are restarted when one fails.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Strategy {
    /// Restart only the failed child: for independent children (e.g. the sensors).
    OneForOne,
    /// Stop the children listed after the failed one, then restart it and them in order: for
    /// children that depend on earlier ones (e.g. the drives on the CAN bus).
    RestForOne,
}

/// Restart intensity and backoff.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RestartPolicy {
    /// At most this many failures within `window`; one more escalates.
    pub max_restarts: u32,
    /// The intensity window; also how long a child must run for its backoff to start over.
    pub window: Duration,
    /// Delay before the first restart of a run of consecutive failures.
    pub backoff_initial: Duration,
    /// Cap of the doubling delay.
    pub backoff_max: Duration,
}

impl RestartPolicy {
    /// The delay before restart number `attempt` (1-based) of a run of consecutive failures:
    /// `backoff_initial * 2^(attempt - 1)`, capped at `backoff_max` (attempt 0 counts as 1).
    #[must_use]
    pub fn backoff(&self, attempt: u32) -> Duration {
        let exponent = attempt.saturating_sub(1).min(31);
        self.backoff_initial
            .checked_mul(1_u32 << exponent)
            .map_or(self.backoff_max, |delay| delay.min(self.backoff_max))
    }
}

impl Default for RestartPolicy {
    /// Three failures in five seconds (Elixir's default intensity), backoff 100 ms doubling up
    /// to 5 s.
    fn default() -> Self {
        Self {
            max_restarts: 3,
            window: Duration::from_secs(5),
            backoff_initial: Duration::from_millis(100),
            backoff_max: Duration::from_secs(5),
        }
    }
}

/// Everything a [`Supervisor`] is started with.
#[derive(Clone, Debug)]
pub(crate) struct SupervisorSpec {
    /// The supervisor's name in the event log and in tracing (not a ractor actor name).
    pub name: String,
    pub strategy: Strategy,
    pub policy: RestartPolicy,
    /// The children, in start (dependency) order.
    pub children: Vec<ChildSpec>,
    /// Where the supervisor records its events; share one log across a tree for one ordered log.
    pub events: EventLog,
}

/// The supervisor actor. Spawn it with a [`SupervisorSpec`] (unnamed, or with a name of your
/// choice), or as the child of another supervisor: `ChildSpec::new("sensors", move || (Supervisor,
/// spec.clone()))`.
#[derive(Debug)]
pub(crate) struct Supervisor;

/// Messages to a `Supervisor`.
#[derive(Debug)]
pub enum SupervisorMsg {
    /// A restart timer fired (sent by the supervisor to itself; cannot be built outside).
    #[doc(hidden)]
    Restart(RestartTimer),
    /// The children, in list order, with their current cells (`None` while down).
    Children(RpcReplyPort<Vec<ChildInfo>>),
}

/// The payload of a restart timer: which child, and its generation when the timer was set.
/// Opaque outside this module.
#[derive(Debug)]
pub struct RestartTimer {
    child: usize,
    generation: u64,
}

/// A child as its supervisor sees it.
#[derive(Debug, Clone)]
pub struct ChildInfo {
    pub name: String,
    /// The running instance, `None` while the child is down (restart pending or waiting for an
    /// earlier child under rest-for-one).
    pub cell: Option<ActorCell>,
    /// How many times the supervisor tried to start the child again after its first start
    /// (successful or not; under rest-for-one, restarts after a sibling's failure count too).
    pub restarts: u32,
}

/// One supervision event.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SupervisorEvent {
    /// The name of the supervisor that recorded it.
    pub supervisor: String,
    pub kind: EventKind,
}

/// What happened.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum EventKind {
    /// The child is running (its spawn returned).
    Started { child: String },
    /// The child's start failed (spawn error, e.g. its `pre_start` failed): handled like a failure.
    StartFailed { child: String, reason: String },
    /// The child terminated without being asked to: it returned an error, panicked, was killed or
    /// stopped on its own.
    Failed { child: String, reason: String },
    /// The child was stopped by its supervisor (rest-for-one siblings, escalation, shutdown).
    Stopped { child: String },
    /// The child will be started again after `delay_ms`; `attempt` counts consecutive failures.
    RestartScheduled { child: String, attempt: u32, delay_ms: u64 },
    /// Restart intensity exceeded: the supervisor stopped its children and fails.
    Escalated { reason: String },
}

/// Shared, clonable, ordered log of supervision events, each stamped with tokio time. Waiters can
/// await an event (bounded).
#[derive(Debug, Clone, Default)]
pub struct EventLog {
    inner: Arc<LogInner>,
}

#[derive(Debug, Default)]
struct LogInner {
    events: Mutex<Vec<(Instant, SupervisorEvent)>>,
    changed: Notify,
}

impl EventLog {
    /// An empty log.
    #[must_use]
    pub fn new() -> Self {
        Self::default()
    }

    fn events(&self) -> MutexGuard<'_, Vec<(Instant, SupervisorEvent)>> {
        // A panic while holding the lock cannot leave the Vec half-written: keep using it.
        self.inner.events.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Appends an event stamped with the current (tokio) time and wakes the waiters.
    pub fn push(&self, event: SupervisorEvent) {
        self.events().push((Instant::now(), event));
        self.inner.changed.notify_waiters();
    }

    /// All events so far, in order.
    #[must_use]
    pub fn snapshot(&self) -> Vec<SupervisorEvent> {
        self.events().iter().map(|(_, event)| event.clone()).collect()
    }

    /// All events so far with the (tokio) time they were recorded, to check delays and latencies.
    #[must_use]
    pub fn timed_snapshot(&self) -> Vec<(Instant, SupervisorEvent)> {
        self.events().clone()
    }

    /// The kinds of the events recorded by the supervisor named `supervisor`, in order.
    #[must_use]
    pub fn kinds(&self, supervisor: &str) -> Vec<EventKind> {
        self.events()
            .iter()
            .filter(|(_, event)| event.supervisor == supervisor)
            .map(|(_, event)| event.kind.clone())
            .collect()
    }

    /// Number of events so far.
    #[must_use]
    pub fn len(&self) -> usize {
        self.events().len()
    }

    /// Whether nothing was recorded yet.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.events().is_empty()
    }

    /// The first event of the log (already recorded or yet to come) that satisfies `pred`, or
    /// `None` if there is none after `timeout`.
    pub async fn wait_for(
        &self,
        pred: impl Fn(&SupervisorEvent) -> bool,
        timeout: Duration,
    ) -> Option<SupervisorEvent> {
        self.wait_for_nth(pred, 1, timeout).await
    }

    /// The `n`-th (1-based; 0 counts as 1) event of the log that satisfies `pred`, or `None` if
    /// there is none after `timeout`.
    pub async fn wait_for_nth(
        &self,
        pred: impl Fn(&SupervisorEvent) -> bool,
        n: usize,
        timeout: Duration,
    ) -> Option<SupervisorEvent> {
        let skip = n.saturating_sub(1);
        let wait = async {
            loop {
                // Register before looking, so that a push between the look and the await wakes us.
                let notified = self.inner.changed.notified();
                let mut notified = std::pin::pin!(notified);
                notified.as_mut().enable();
                let found = self
                    .events()
                    .iter()
                    .map(|(_, event)| event)
                    .filter(|event| pred(event))
                    .nth(skip)
                    .cloned();
                if let Some(event) = found {
                    return event;
                }
                notified.await;
            }
        };
        tokio::time::timeout(timeout, wait).await.ok()
    }
}

/// A child's bookkeeping.
#[derive(Debug)]
struct Child {
    spec: ChildSpec,
    /// The running instance.
    cell: Option<ActorCell>,
    /// When the running instance started (for the backoff reset).
    running_since: Option<Instant>,
    /// Start attempts so far.
    attempts: u32,
    /// Consecutive failures (the backoff exponent).
    consecutive: u32,
    /// Bumped whenever a pending restart is set or cancelled; a timer of another generation is stale.
    generation: u64,
    /// The pending restart timer, if any.
    timer: Option<JoinHandle<Result<(), MessagingErr<SupervisorMsg>>>>,
}

/// The state of a running [`Supervisor`] (opaque).
#[derive(Debug)]
pub(crate) struct SupervisorState {
    name: String,
    strategy: Strategy,
    policy: RestartPolicy,
    events: EventLog,
    children: Vec<Child>,
    /// Times of the failures within the intensity window, oldest first.
    failures: VecDeque<Instant>,
    /// Children we stopped on purpose whose termination event has not arrived yet.
    stopped_on_purpose: HashSet<ActorId>,
}

impl SupervisorState {
    fn new(spec: SupervisorSpec) -> Result<Self, ActorProcessingErr> {
        let mut names = HashSet::new();
        if let Some(duplicate) = spec.children.iter().find(|child| !names.insert(child.name.as_str())) {
            return Err(format!("supervisor {}: duplicate child name {}", spec.name, duplicate.name).into());
        }
        let children = spec
            .children
            .into_iter()
            .map(|spec| Child {
                spec,
                cell: None,
                running_since: None,
                attempts: 0,
                consecutive: 0,
                generation: 0,
                timer: None,
            })
            .collect();
        Ok(Self {
            name: spec.name,
            strategy: spec.strategy,
            policy: spec.policy,
            events: spec.events,
            children,
            failures: VecDeque::new(),
            stopped_on_purpose: HashSet::new(),
        })
    }

    fn child_name(&self, index: usize) -> String {
        self.children.get(index).map(|child| child.spec.name.clone()).unwrap_or_default()
    }

    /// Logs an event to tracing and to the event log.
    fn record(&self, kind: EventKind) {
        let supervisor = self.name.as_str();
        match &kind {
            EventKind::Started { child } => tracing::info!(supervisor, child, "child started"),
            EventKind::StartFailed { child, reason } => {
                tracing::warn!(supervisor, child, reason, "child failed to start");
            }
            EventKind::Failed { child, reason } => tracing::warn!(supervisor, child, reason, "child failed"),
            EventKind::Stopped { child } => tracing::info!(supervisor, child, "child stopped"),
            EventKind::RestartScheduled { child, attempt, delay_ms } => {
                tracing::info!(supervisor, child, attempt, delay_ms, "child restart scheduled");
            }
            EventKind::Escalated { reason } => {
                tracing::error!(supervisor, reason, "restart intensity exceeded: escalating");
            }
        }
        self.events.push(SupervisorEvent { supervisor: self.name.clone(), kind });
    }

    /// Cancels the pending restart of a child, if any.
    fn cancel_restart(&mut self, index: usize) {
        if let Some(child) = self.children.get_mut(index) {
            child.generation = child.generation.wrapping_add(1);
            if let Some(timer) = child.timer.take() {
                timer.abort();
            }
        }
    }

    /// Starts the children at supervisor start-up: all of them in order under one-for-one; under
    /// rest-for-one, in order until one fails to start.
    async fn start_all(&mut self, myself: &ActorRef<SupervisorMsg>) -> Result<(), ActorProcessingErr> {
        match self.strategy {
            Strategy::OneForOne => {
                for index in 0..self.children.len() {
                    self.start_child(myself, index).await?;
                }
                Ok(())
            }
            Strategy::RestForOne => self.bring_up(myself, 0).await,
        }
    }

    /// Brings up a child whose restart is due: only it under one-for-one; under rest-for-one, it
    /// and then every later child that is down, in order, until one fails to start.
    async fn bring_up(
        &mut self,
        myself: &ActorRef<SupervisorMsg>,
        from: usize,
    ) -> Result<(), ActorProcessingErr> {
        match self.strategy {
            Strategy::OneForOne => {
                self.start_child(myself, from).await?;
            }
            Strategy::RestForOne => {
                for index in from..self.children.len() {
                    if self.children.get(index).is_some_and(|child| child.cell.is_some()) {
                        continue;
                    }
                    if !self.start_child(myself, index).await? {
                        break;
                    }
                }
            }
        }
        Ok(())
    }

    /// Starts one child. `Ok(true)` if it runs; `Ok(false)` if its start failed and a restart was
    /// scheduled; `Err` if that failure exceeded the intensity (children stopped, escalated).
    async fn start_child(
        &mut self,
        myself: &ActorRef<SupervisorMsg>,
        index: usize,
    ) -> Result<bool, ActorProcessingErr> {
        self.cancel_restart(index);
        let Some(child) = self.children.get_mut(index) else {
            return Ok(false);
        };
        child.attempts = child.attempts.saturating_add(1);
        let start = Arc::clone(&child.spec.start);
        let name = child.spec.name.clone();
        match start(myself.get_cell()).await {
            Ok(cell) => {
                if let Some(child) = self.children.get_mut(index) {
                    child.cell = Some(cell);
                    child.running_since = Some(Instant::now());
                }
                self.record(EventKind::Started { child: name });
                Ok(true)
            }
            Err(err) => {
                self.record(EventKind::StartFailed { child: name, reason: spawn_reason(&err) });
                self.after_failure(myself, index).await?;
                Ok(false)
            }
        }
    }

    /// Applies the policy to a child that just failed (already logged, already marked down):
    /// intensity, then rest-for-one siblings, then the backoff timer.
    async fn after_failure(
        &mut self,
        myself: &ActorRef<SupervisorMsg>,
        index: usize,
    ) -> Result<(), ActorProcessingErr> {
        let now = Instant::now();
        let window = self.policy.window;
        let Some(child) = self.children.get_mut(index) else {
            return Ok(());
        };
        if child.running_since.take().is_some_and(|since| now.duration_since(since) >= window) {
            child.consecutive = 0;
        }
        child.consecutive = child.consecutive.saturating_add(1);
        let attempt = child.consecutive;
        let name = child.spec.name.clone();

        while self.failures.front().is_some_and(|&at| now.duration_since(at) >= window) {
            self.failures.pop_front();
        }
        self.failures.push_back(now);
        let count = self.failures.len();
        if count > usize::try_from(self.policy.max_restarts).unwrap_or(usize::MAX) {
            let reason = format!(
                "child {name}: {count} failures within {window:?} exceed max_restarts {}",
                self.policy.max_restarts
            );
            return Err(self.escalate(&name, reason).await);
        }

        if self.strategy == Strategy::RestForOne {
            for later in (index + 1..self.children.len()).rev() {
                self.cancel_restart(later);
                self.stop_child(later).await;
            }
        }

        let delay = self.policy.backoff(attempt);
        let delay_ms = u64::try_from(delay.as_millis()).unwrap_or(u64::MAX);
        self.record(EventKind::RestartScheduled { child: name, attempt, delay_ms });
        self.cancel_restart(index);
        if let Some(child) = self.children.get_mut(index) {
            let timer = RestartTimer { child: index, generation: child.generation };
            child.timer = Some(myself.send_after(delay, move || SupervisorMsg::Restart(timer)));
        }
        Ok(())
    }

    /// Intensity exceeded: cancels every pending restart, stops the running children in reverse
    /// order and logs the escalation. Returns the error the supervisor fails with.
    async fn escalate(&mut self, child: &str, reason: String) -> ActorProcessingErr {
        tracing::error!(
            supervisor = self.name.as_str(),
            child,
            "restart intensity exceeded: stopping the children"
        );
        self.stop_all().await;
        self.record(EventKind::Escalated { reason: reason.clone() });
        format!("supervisor {}: {reason}", self.name).into()
    }

    /// Cancels every pending restart and stops the running children in reverse list order.
    async fn stop_all(&mut self) {
        for index in (0..self.children.len()).rev() {
            self.cancel_restart(index);
            self.stop_child(index).await;
        }
    }

    /// Stops a running child on purpose, awaited (bounded; killed if it does not stop), and logs
    /// it. Does nothing if the child is not running.
    async fn stop_child(&mut self, index: usize) {
        let Some(child) = self.children.get_mut(index) else {
            return;
        };
        let Some(cell) = child.cell.take() else {
            return;
        };
        child.running_since = None;
        let name = child.spec.name.clone();
        self.stopped_on_purpose.insert(cell.get_id());
        let reason = format!("stopped by supervisor {}", self.name);
        match cell.stop_and_wait(Some(reason), Some(STOP_TIMEOUT)).await {
            Ok(()) => {}
            Err(RactorErr::Timeout) => {
                tracing::warn!(
                    supervisor = self.name.as_str(),
                    child = name.as_str(),
                    "child did not stop in time: killing it"
                );
                if cell.kill_and_wait(Some(STOP_TIMEOUT)).await.is_err() {
                    tracing::error!(
                        supervisor = self.name.as_str(),
                        child = name.as_str(),
                        "killed child did not terminate"
                    );
                }
            }
            // Its stop channel is closed: it is terminating already (its event is on the way).
            Err(_) => {
                if cell.wait(Some(STOP_TIMEOUT)).await.is_err() {
                    cell.kill();
                }
            }
        }
        self.record(EventKind::Stopped { child: name });
    }

    fn position(&self, id: ActorId) -> Option<usize> {
        self.children.iter().position(|child| child.cell.as_ref().is_some_and(|cell| cell.get_id() == id))
    }

    fn infos(&self) -> Vec<ChildInfo> {
        self.children
            .iter()
            .map(|child| ChildInfo {
                name: child.spec.name.clone(),
                cell: child.cell.clone(),
                restarts: child.attempts.saturating_sub(1),
            })
            .collect()
    }
}

/// The failure reason of a spawn error: the error of a failed `pre_start` as is (ractor's own
/// wording says "panicked" even for an `Err`).
fn spawn_reason(err: &SpawnErr) -> String {
    match err {
        SpawnErr::StartupFailed(inner) => inner.to_string(),
        other => other.to_string(),
    }
}

impl Actor for Supervisor {
    type Msg = SupervisorMsg;
    type State = SupervisorState;
    type Arguments = SupervisorSpec;

    async fn pre_start(
        &self,
        myself: ActorRef<Self::Msg>,
        spec: SupervisorSpec,
    ) -> Result<Self::State, ActorProcessingErr> {
        let mut state = SupervisorState::new(spec)?;
        state.start_all(&myself).await?;
        Ok(state)
    }

    async fn handle(
        &self,
        myself: ActorRef<Self::Msg>,
        message: Self::Msg,
        state: &mut Self::State,
    ) -> Result<(), ActorProcessingErr> {
        match message {
            SupervisorMsg::Restart(RestartTimer { child, generation }) => {
                let due = state
                    .children
                    .get(child)
                    .is_some_and(|entry| entry.generation == generation && entry.cell.is_none());
                if due {
                    if let Some(entry) = state.children.get_mut(child) {
                        entry.timer = None;
                    }
                    state.bring_up(&myself, child).await?;
                } else {
                    tracing::debug!(
                        supervisor = state.name.as_str(),
                        child = state.child_name(child),
                        "stale restart timer"
                    );
                }
            }
            SupervisorMsg::Children(reply) => {
                // The caller may have given up waiting: nothing to do then.
                let _ = reply.send(state.infos());
            }
        }
        Ok(())
    }

    async fn handle_supervisor_evt(
        &self,
        myself: ActorRef<Self::Msg>,
        event: SupervisionEvent,
        state: &mut Self::State,
    ) -> Result<(), ActorProcessingErr> {
        let (cell, reason) = match event {
            SupervisionEvent::ActorFailed(cell, err) => (cell, err.to_string()),
            SupervisionEvent::ActorTerminated(cell, _, reason) => {
                (cell, reason.map_or_else(|| "exited".to_owned(), |reason| format!("exited: {reason}")))
            }
            // Started is logged when the spawn returns; nothing else concerns us.
            _ => return Ok(()),
        };
        let id = cell.get_id();
        if state.stopped_on_purpose.remove(&id) {
            return Ok(());
        }
        let Some(index) = state.position(id) else {
            tracing::debug!(supervisor = state.name.as_str(), ?id, "event of an unknown child ignored");
            return Ok(());
        };
        if let Some(child) = state.children.get_mut(index) {
            child.cell = None;
        }
        state.record(EventKind::Failed { child: state.child_name(index), reason });
        state.after_failure(&myself, index).await
    }

    async fn post_stop(
        &self,
        _myself: ActorRef<Self::Msg>,
        state: &mut Self::State,
    ) -> Result<(), ActorProcessingErr> {
        state.stop_all().await;
        Ok(())
    }
}
