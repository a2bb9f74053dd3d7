//! The bridge actors: one per process, owning its Zenoh session. A robot's bridge hands the robot
//! tree a [`RobotEnd`](amr_actors::link::RobotEnd); the server's bridge hands the server tree a
//! [`ServerEnd`](amr_actors::link::ServerEnd): the same ends as the in-process link, so the trees
//! do not know which link they are on.
//!
//! | key | from → to | what |
//! |---|---|---|
//! | `fleet/<robot>/scan` | robot → server | scans with the odometry pose at their stamp |
//! | `fleet/<robot>/odom` | robot → server | odometry |
//! | `fleet/<robot>/health` | robot → server | health and safety-state changes |
//! | `fleet/<robot>/cmd` | server → robot | velocity commands, arm, disarm |
//! | `fleet/<robot>/estop/<sender>` | server or operator → robot | e-stop and its reset (highest priority) |
//! | `fleet/<robot>/alive` | robot (liveliness token) | the server sees a robot join and leave |
//! | `fleet/server/status` | server → observers | the formation's phase and the robots alive |
//!
//! QoS (Zenoh priorities, congestion control and express):
//! - scans (`DataLow`) and odometry (`Data`) may be dropped under congestion, and locally only the
//!   latest waits to be sent (latest wins): a stale scan is worth less than none;
//! - health and safety changes (`InteractiveLow`) queue and block their own pump only;
//! - commands (`InteractiveHigh`, express, dropped under congestion: the next one replaces it) and
//!   arm/disarm (`RealTime`, express, blocking) skip the batching queue.
//!
//! Every received sample is decoded and checked ([`crate::wire`]); what fails is counted by reason
//! and logged (the first ten of each reason, then every thousandth), never passed on.
//!
//! A robot's bridge is in `robot`, the server's in `server`, an operator's e-stop in `operator`;
//! the actor, the counters, the session slot and the envelope stamper they share are here.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use amr_actors::robot::ports::AbortOnDrop;
use amr_msgs::SCHEMA_VERSION;
use ractor::{Actor, ActorProcessingErr, ActorRef};

use crate::settings::{NetError, PREFIX};
use crate::wire::{Body, Envelope};

mod operator;
mod robot;
mod server;

pub use operator::{EstopOutcome, operator_estop};
pub use robot::start_robot_bridge;
pub use server::{ServerBridge, decode_status, start_server_bridge};

/// Queue depth between the trees and the bridge (as the in-process link's).
const DEPTH: usize = 128;
/// How often a robot's bridge checks that it reaches the server.
const CHECK_PERIOD: Duration = Duration::from_millis(500);

fn zerr(e: impl std::fmt::Display) -> NetError {
    NetError::Zenoh(e.to_string())
}

/// A new session number: the wall clock's nanoseconds now, so a restarted sender's session is
/// larger than its last one (receivers refuse an older session:
/// [`Freshness`](crate::wire::Freshness)).
fn new_session() -> u64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_nanos() as u64)
}

/// The wall clock now, Unix seconds: what sessions are compared with.
fn wall_now_s() -> f64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0.0, |d| d.as_secs_f64())
}

/// What a bridge counted.
#[derive(Debug, Default)]
pub struct BridgeStats {
    /// Samples published.
    pub sent: AtomicU64,
    /// Samples that Zenoh refused to take (session closed).
    pub send_failed: AtomicU64,
    /// Valid messages passed to the tree.
    pub delivered: AtomicU64,
    /// Valid messages dropped because the tree's queue was full.
    pub queue_full: AtomicU64,
    /// Refused samples by reason ([`Reject::kind`](crate::wire::Reject::kind), or `unknown-robot`,
    /// `bad-key`).
    rejected: Mutex<BTreeMap<&'static str, u64>>,
    /// A robot's bridge: it reaches the server.
    pub connected: AtomicBool,
}

impl BridgeStats {
    /// Refused samples of `kind` so far.
    #[must_use]
    pub fn rejected(&self, kind: &str) -> u64 {
        self.rejected.lock().unwrap_or_else(PoisonError::into_inner).get(kind).copied().unwrap_or(0)
    }

    /// All refusals by reason.
    #[must_use]
    pub fn rejections(&self) -> BTreeMap<&'static str, u64> {
        self.rejected.lock().unwrap_or_else(PoisonError::into_inner).clone()
    }

    fn reject(&self, key: &str, kind: &'static str, why: &dyn std::fmt::Display) {
        let n = {
            let mut map = self.rejected.lock().unwrap_or_else(PoisonError::into_inner);
            let n = map.entry(kind).or_default();
            *n += 1;
            *n
        };
        if n <= 10 || n.is_multiple_of(1000) {
            tracing::warn!(key, reason = %why, count = n, "link: sample refused");
        }
    }
}

/// The bridge actor: it owns the session and the pumps; stopping it closes the session (a robot's
/// liveliness token goes with it).
struct BridgeActor;

enum BridgeMsg {
    /// A robot's bridge checks whether it reaches the server.
    Check,
}

struct BridgeState {
    /// Set once the session is open (a robot's bridge opens it in the background).
    session: SessionSlot,
    role: Role,
    stats: Arc<BridgeStats>,
    _pumps: Vec<AbortOnDrop<()>>,
    /// Subscribers and the liveliness token: declared as long as the bridge lives.
    _declared: Vec<Box<dyn std::any::Any + Send>>,
}

#[derive(Debug, Clone)]
enum Role {
    Robot(String),
    Server,
}

impl Actor for BridgeActor {
    type Msg = BridgeMsg;
    type State = BridgeState;
    type Arguments = BridgeState;

    async fn pre_start(
        &self,
        myself: ActorRef<BridgeMsg>,
        state: BridgeState,
    ) -> Result<BridgeState, ActorProcessingErr> {
        if matches!(state.role, Role::Robot(_)) {
            let _ = myself.cast(BridgeMsg::Check);
            myself.send_interval(CHECK_PERIOD, || BridgeMsg::Check);
        }
        Ok(state)
    }

    async fn handle(
        &self,
        _myself: ActorRef<BridgeMsg>,
        msg: BridgeMsg,
        state: &mut BridgeState,
    ) -> Result<(), ActorProcessingErr> {
        match msg {
            BridgeMsg::Check => {
                let Role::Robot(robot) = &state.role else { return Ok(()) };
                let session = state.session.get();
                let now = match session {
                    Some(s) => s.info().routers_zid().await.next().is_some(),
                    None => false,
                };
                let was = state.stats.connected.swap(now, Ordering::Relaxed);
                if now && !was {
                    tracing::info!(robot = %robot, "link: connected to the server");
                } else if was && !now {
                    tracing::warn!(robot = %robot, "link: lost the server; retrying (the command watchdog stops the robot)");
                }
            }
        }
        Ok(())
    }

    async fn post_stop(
        &self,
        _myself: ActorRef<BridgeMsg>,
        state: &mut BridgeState,
    ) -> Result<(), ActorProcessingErr> {
        state._pumps.clear();
        state._declared.clear();
        if let Some(session) = state.session.take()
            && let Err(e) = session.close().await
        {
            tracing::debug!(error = %e, "link: closing the session");
        }
        Ok(())
    }
}

/// A running bridge.
#[derive(Debug)]
pub struct Bridge {
    pub stats: Arc<BridgeStats>,
    actor: ActorRef<BridgeMsg>,
    handle: tokio::task::JoinHandle<()>,
    session: SessionSlot,
}

/// The bridge's session, once open.
#[derive(Debug, Clone, Default)]
struct SessionSlot(Arc<Mutex<Option<zenoh::Session>>>);

impl SessionSlot {
    fn of(session: zenoh::Session) -> Self {
        SessionSlot(Arc::new(Mutex::new(Some(session))))
    }

    fn get(&self) -> Option<zenoh::Session> {
        self.0.lock().unwrap_or_else(PoisonError::into_inner).clone()
    }

    fn set(&self, session: zenoh::Session) {
        *self.0.lock().unwrap_or_else(PoisonError::into_inner) = Some(session);
    }

    fn take(&self) -> Option<zenoh::Session> {
        self.0.lock().unwrap_or_else(PoisonError::into_inner).take()
    }
}

impl std::fmt::Debug for BridgeMsg {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Check")
    }
}

impl Bridge {
    async fn spawn(state: BridgeState) -> Result<Bridge, NetError> {
        let stats = Arc::clone(&state.stats);
        let session = state.session.clone();
        let (actor, handle) =
            Actor::spawn(None, BridgeActor, state).await.map_err(|e| NetError::Actor(e.to_string()))?;
        Ok(Bridge { stats, actor, handle, session })
    }

    /// The Zenoh session once open (tests publish raw samples through it).
    #[must_use]
    pub fn session(&self) -> Option<zenoh::Session> {
        self.session.get()
    }

    /// Stop the bridge and close its session.
    pub async fn shutdown(self) {
        self.actor.stop(None);
        let _ = self.handle.await;
    }
}

/// An envelope stamper for one key: session and sequence numbers.
struct Stamper {
    session: u64,
    seq: u64,
    origin: String,
    robot: String,
}

impl Stamper {
    fn new(session: u64, origin: &str, robot: &str) -> Self {
        Stamper { session, seq: 0, origin: origin.to_owned(), robot: robot.to_owned() }
    }

    fn encode(&mut self, stamp_s: f64, sent_s: f64, body: Body) -> Option<Vec<u8>> {
        self.seq += 1;
        let env = Envelope {
            version: SCHEMA_VERSION,
            session: self.session,
            seq: self.seq,
            origin: self.origin.clone(),
            robot: self.robot.clone(),
            stamp_s,
            sent_s,
            body,
        };
        match env.encode() {
            Ok(b) => Some(b),
            Err(e) => {
                tracing::error!(error = %e, "link: cannot encode");
                None
            }
        }
    }
}

impl std::fmt::Debug for Stamper {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Stamper {{ session: {:#x}, seq: {} }}", self.session, self.seq)
    }
}

fn count_put(stats: &BridgeStats, r: zenoh::Result<()>) {
    match r {
        Ok(()) => stats.sent.fetch_add(1, Ordering::Relaxed),
        Err(_) => stats.send_failed.fetch_add(1, Ordering::Relaxed),
    };
}

/// The key `sender` publishes e-stops and resets for `robot` on.
#[must_use]
pub fn estop_key(robot: &str, sender: &str) -> String {
    format!("{PREFIX}/{robot}/estop/{sender}")
}
