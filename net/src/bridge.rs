//! The bridge actors: one per process, owning its Zenoh session. A robot's bridge hands the robot
//! tree a [`RobotEnd`]; the server's bridge hands the server tree a [`ServerEnd`]: the same ends as
//! the in-process link, so the trees do not know which link they are on.
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

use std::collections::{BTreeMap, BTreeSet};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use amr_actors::clock::FleetClock;
use amr_actors::link::{DownlinkSender, DownlinkTx, RobotEnd, ServerEnd, UplinkSender};
use amr_actors::robot::ports::AbortOnDrop;
use amr_msgs::{Device, Downlink, Health, HealthReport, SCHEMA_VERSION, ServerStatus, Uplink};
use ractor::{Actor, ActorProcessingErr, ActorRef};
use tokio::sync::{mpsc, watch};
use zenoh::qos::{CongestionControl, Priority};
use zenoh::sample::SampleKind;

use crate::settings::{NetError, NetSettings, PREFIX};
use crate::wire::{
    Body, DownlinkGate, Envelope, Freshness, Reject, from_downlink, from_uplink, is_estop, to_uplink,
    uplink_channel,
};

/// Queue depth between the trees and the bridge (as the in-process link's).
const DEPTH: usize = 128;
/// How often a robot's bridge checks that it reaches the server.
const CHECK_PERIOD: Duration = Duration::from_millis(500);

fn zerr(e: impl std::fmt::Display) -> NetError {
    NetError::Zenoh(e.to_string())
}

/// A new session number: the wall clock's nanoseconds now, so a restarted sender's session is
/// larger than its last one (receivers refuse an older session: [`Freshness`]).
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
    /// Refused samples by reason ([`Reject::kind`], or `unknown-robot`, `bad-key`).
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

fn count_put(stats: &BridgeStats, r: zenoh::Result<()>) {
    match r {
        Ok(()) => stats.sent.fetch_add(1, Ordering::Relaxed),
        Err(_) => stats.send_failed.fetch_add(1, Ordering::Relaxed),
    };
}

/// Start a robot's bridge and return the end for its tree at once. The bridge opens its session in
/// the background, retrying with backoff until the server admits it (it may boot later than the
/// robot), then declares the robot's liveliness token; Zenoh reconnects by itself after that. The
/// robot runs whether or not the server is reachable: its command watchdog keeps it safe.
pub async fn start_robot_bridge(
    settings: &NetSettings,
    robot: &str,
    clock: FleetClock,
) -> Result<(RobotEnd, Bridge), NetError> {
    let config = settings.client_config(robot)?;
    let stats = Arc::new(BridgeStats::default());
    let slot = SessionSlot::default();

    // The tree's uplink: one queue in, split by channel. Scans and odometry keep only the latest.
    let (up_tx, mut up_rx) = mpsc::channel::<Uplink>(DEPTH);
    let (scan_tx, scan_rx) = watch::channel::<Option<Uplink>>(None);
    let (odom_tx, odom_rx) = watch::channel::<Option<Uplink>>(None);
    let (health_tx, health_rx) = mpsc::channel::<Uplink>(DEPTH);
    let split = tokio::spawn(async move {
        while let Some(u) = up_rx.recv().await {
            match uplink_channel(&u) {
                "scan" => {
                    scan_tx.send_replace(Some(u));
                }
                "odom" => {
                    odom_tx.send_replace(Some(u));
                }
                _ => {
                    let _ = health_tx.try_send(u);
                }
            }
        }
    });
    let (down_tx, down_rx, missed) = DownlinkTx::queue();
    let link = RobotLink {
        robot: robot.to_owned(),
        server: settings.server_user().to_owned(),
        estop_senders: settings.estop_senders(),
        clock,
        stats: Arc::clone(&stats),
        scans: scan_rx,
        odom: odom_rx,
        health: health_rx,
        down: down_tx,
    };
    let connector_slot = slot.clone();
    let connector_stats = Arc::clone(&stats);
    let who = robot.to_owned();
    let connector = tokio::spawn(async move {
        let mut backoff = Duration::from_millis(100);
        let mut attempt = 0u32;
        let session = loop {
            attempt += 1;
            match zenoh::open(config.clone()).await {
                Ok(s) => break s,
                Err(e) => {
                    if attempt <= 3 || attempt.is_multiple_of(20) {
                        tracing::warn!(robot = %who, attempt, error = %e, "link: cannot reach the server; retrying");
                    }
                    tokio::time::sleep(backoff).await;
                    backoff = (backoff * 2).min(Duration::from_secs(5));
                }
            }
        };
        connector_slot.set(session.clone());
        // A client's session opens only through the router: the server is reached.
        connector_stats.connected.store(true, Ordering::Relaxed);
        tracing::info!(robot = %who, "link: connected to the server");
        if let Err(e) = link.run(session).await {
            tracing::error!(robot = %who, error = %e, "link: the bridge failed");
        }
    });
    let bridge = Bridge::spawn(BridgeState {
        session: slot,
        role: Role::Robot(robot.to_owned()),
        stats,
        _pumps: vec![AbortOnDrop(split), AbortOnDrop(connector)],
        _declared: Vec::new(),
    })
    .await?;
    tracing::info!(robot, endpoints = ?settings.connect.as_ref().unwrap_or(&settings.network.server.connect), "link: robot bridge started");
    Ok((RobotEnd { robot: robot.to_owned(), up: UplinkSender::new(up_tx), down: down_rx, missed }, bridge))
}

/// The key `sender` publishes e-stops and resets for `robot` on.
#[must_use]
pub fn estop_key(robot: &str, sender: &str) -> String {
    format!("{PREFIX}/{robot}/estop/{sender}")
}

/// A robot's side of the link once its session is open.
struct RobotLink {
    robot: String,
    server: String,
    /// Who may e-stop this robot: the server and the operators.
    estop_senders: Vec<String>,
    clock: FleetClock,
    stats: Arc<BridgeStats>,
    scans: watch::Receiver<Option<Uplink>>,
    odom: watch::Receiver<Option<Uplink>>,
    health: mpsc::Receiver<Uplink>,
    down: DownlinkTx,
}

impl RobotLink {
    /// Declare the robot's keys and token and pump until the bridge stops.
    async fn run(self, session: zenoh::Session) -> Result<(), NetError> {
        let RobotLink { robot, server, estop_senders, clock, stats, scans, odom, mut health, down } = self;
        let key = |ch: &str| format!("{PREFIX}/{robot}/{ch}");
        let sid = new_session();
        let scan_pub = session
            .declare_publisher(key("scan"))
            .priority(Priority::DataLow)
            .congestion_control(CongestionControl::Drop)
            .await
            .map_err(zerr)?;
        let odom_pub = session
            .declare_publisher(key("odom"))
            .priority(Priority::Data)
            .congestion_control(CongestionControl::Drop)
            .await
            .map_err(zerr)?;
        let health_pub = session
            .declare_publisher(key("health"))
            .priority(Priority::InteractiveLow)
            .congestion_control(CongestionControl::Block)
            .await
            .map_err(zerr)?;

        // Commands: decoded, checked (for me, from the server, newer than the last) and passed on.
        // The safety layer then applies its own rules (armed, sequence floor, stamp age). A disarm
        // is taken whatever its session, sequence or stamp: a stop is never refused
        // ([`DownlinkGate::on_cmd`]).
        let gate = Arc::new(Mutex::new(DownlinkGate::default()));
        let (me, cmd_stats, cmd_key, cmd_down, cmd_gate) =
            (robot.clone(), Arc::clone(&stats), key("cmd"), down.clone(), Arc::clone(&gate));
        let _subscriber = session
            .declare_subscriber(cmd_key.clone())
            .callback(move |sample| {
                let bytes = sample.payload().to_bytes();
                let checked = Envelope::decode(&bytes).and_then(|env| {
                    let mut gate = cmd_gate.lock().unwrap_or_else(PoisonError::into_inner);
                    gate.on_cmd(&env, &me, &server, clock.now_s(), wall_now_s())
                });
                match checked {
                    Ok(d) => deliver(&cmd_down, &cmd_stats, d),
                    Err(r) => cmd_stats.reject(&cmd_key, r.kind(), &r),
                }
            })
            .await
            .map_err(zerr)?;
        // E-stops and resets, from the server or an operator, each on its own key
        // (`fleet/<robot>/estop/<sender>`), which the server's access control lets only that
        // authenticated name publish on: the sender is the key's, never a field it fills in. An
        // e-stop is taken whatever its session, sequence or stamp; a reset is checked for age and
        // replay against that sender's own record ([`DownlinkGate::on_estop`]). Then into the same
        // queue as the commands, in arrival order.
        let (me, estop_stats, estop_key) = (robot.clone(), Arc::clone(&stats), key("estop/*"));
        let _estop_subscriber = session
            .declare_subscriber(estop_key.clone())
            .callback(move |sample| {
                let bytes = sample.payload().to_bytes();
                let sender = sample.key_expr().as_str().rsplit('/').next().unwrap_or_default();
                let checked = Envelope::decode(&bytes).and_then(|env| {
                    let mut gate = gate.lock().unwrap_or_else(PoisonError::into_inner);
                    gate.on_estop(&env, &me, sender, &estop_senders, clock.now_s(), wall_now_s())
                });
                match checked {
                    Ok(d) => deliver(&down, &estop_stats, d),
                    Err(r) => estop_stats.reject(&estop_key, r.kind(), &r),
                }
            })
            .await
            .map_err(zerr)?;
        let _token = session.liveliness().declare_token(key("alive")).await.map_err(zerr)?;

        let latest = |mut rx: watch::Receiver<Option<Uplink>>,
                      publisher: zenoh::pubsub::Publisher<'static>| {
            let stats = Arc::clone(&stats);
            let mut stamper = Stamper::new(sid, &robot, &robot);
            async move {
                while rx.changed().await.is_ok() {
                    let Some(u) = rx.borrow_and_update().clone() else { continue };
                    let (stamp, body) = from_uplink(&u);
                    if let Some(bytes) = stamper.encode(stamp, clock.now_s(), body) {
                        count_put(&stats, publisher.put(bytes).await);
                    }
                }
            }
        };
        let health_pump = {
            let stats = Arc::clone(&stats);
            let mut stamper = Stamper::new(sid, &robot, &robot);
            async move {
                while let Some(u) = health.recv().await {
                    let (stamp, body) = from_uplink(&u);
                    if let Some(bytes) = stamper.encode(stamp, clock.now_s(), body) {
                        count_put(&stats, health_pub.put(bytes).await);
                    }
                }
            }
        };
        tokio::join!(latest(scans, scan_pub), latest(odom, odom_pub), health_pump);
        Ok(())
    }
}

/// Queue a checked downlink message for the robot tree, counting it delivered or (queue full)
/// dropped; a safety message that finds the queue full is remembered and halts the robot
/// ([`DownlinkTx`]).
fn deliver(down: &DownlinkTx, stats: &BridgeStats, d: Downlink) {
    if down.send(d) {
        stats.delivered.fetch_add(1, Ordering::Relaxed);
    } else {
        stats.queue_full.fetch_add(1, Ordering::Relaxed);
    }
}

/// The server's bridge: its end for the server tree, the robots it sees, and its status channel.
#[derive(Debug)]
pub struct ServerBridge {
    pub bridge: Bridge,
    /// Robots whose liveliness token is present.
    pub alive: watch::Receiver<BTreeSet<String>>,
    status: zenoh::pubsub::Publisher<'static>,
    stamper: Mutex<Stamper>,
    clock: FleetClock,
}

impl std::fmt::Debug for Stamper {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Stamper {{ session: {:#x}, seq: {} }}", self.session, self.seq)
    }
}

impl ServerBridge {
    /// Publish the formation's status on `fleet/server/status`.
    pub async fn publish_status(&self, status: ServerStatus) {
        let now = self.clock.now_s();
        let bytes = self.stamper.lock().unwrap_or_else(PoisonError::into_inner).encode(
            now,
            now,
            Body::Status(status),
        );
        if let Some(bytes) = bytes {
            count_put(&self.bridge.stats, self.status.put(bytes).await);
        }
    }
}

/// Parse `fleet/<robot>/<channel>`.
fn split_key(key: &str) -> Option<(&str, &str)> {
    let rest = key.strip_prefix(PREFIX)?.strip_prefix('/')?;
    let (robot, channel) = rest.split_once('/')?;
    (!channel.contains('/')).then_some((robot, channel))
}

/// Start the server's bridge: listen, admit only the credentials file's users under the access
/// control of [`crate::settings::access_control`], watch the robots' liveliness tokens.
pub async fn start_server_bridge(
    settings: &NetSettings,
    robots: &[String],
    clock: FleetClock,
) -> Result<(ServerEnd, ServerBridge), NetError> {
    let session = zenoh::open(settings.server_config(robots)?).await.map_err(zerr)?;
    let stats = Arc::new(BridgeStats::default());
    let (up_tx, up_rx) = mpsc::channel::<Uplink>(DEPTH * robots.len().max(1));
    // Scans apart, a few per robot (the newest replacing the oldest): a robot flooding scans costs
    // bounded memory and never crowds out the others' odometry, health and safety.
    let scans = amr_actors::link::ScanSlots::default();
    let known: Arc<BTreeSet<String>> = Arc::new(robots.iter().cloned().collect());
    let mut declared: Vec<Box<dyn std::any::Any + Send>> = Vec::new();

    for channel in ["scan", "odom", "health"] {
        let (up_tx, stats, known, scans) =
            (up_tx.clone(), Arc::clone(&stats), Arc::clone(&known), scans.clone());
        let fresh: Mutex<BTreeMap<String, Freshness>> = Mutex::default();
        let sub = session
            .declare_subscriber(format!("{PREFIX}/*/{channel}"))
            .callback(move |sample| {
                let key = sample.key_expr().as_str();
                let Some((robot, ch)) = split_key(key) else {
                    stats.reject(key, "bad-key", &"not fleet/<robot>/<channel>");
                    return;
                };
                if !known.contains(robot) {
                    stats.reject(key, "unknown-robot", &format!("`{robot}` is not in the formation"));
                    return;
                }
                let bytes = sample.payload().to_bytes();
                let checked = Envelope::decode(&bytes).and_then(|env| {
                    // From that robot, on its channel, before it may touch the replay record (an
                    // envelope refused here must not lock the sender out with a newer session).
                    let u = to_uplink(env.clone(), robot, ch)?;
                    fresh
                        .lock()
                        .unwrap_or_else(PoisonError::into_inner)
                        .entry(robot.to_owned())
                        .or_default()
                        .check(&env, wall_now_s())?;
                    Ok(u)
                });
                match checked {
                    Ok(Uplink::Scan(scan)) => {
                        stats.delivered.fetch_add(1, Ordering::Relaxed);
                        if !scans.push(scan) {
                            stats.queue_full.fetch_add(1, Ordering::Relaxed);
                        }
                    }
                    Ok(u) => {
                        if up_tx.try_send(u).is_ok() {
                            stats.delivered.fetch_add(1, Ordering::Relaxed);
                        } else {
                            stats.queue_full.fetch_add(1, Ordering::Relaxed);
                        }
                    }
                    Err(r) => stats.reject(key, r.kind(), &r),
                }
            })
            .await
            .map_err(zerr)?;
        declared.push(Box::new(sub));
    }

    // Liveliness: a robot's token appears when its bridge connects and vanishes when its session
    // closes or its lease runs out. The server tree hears it as the robot's link health.
    let (alive_tx, alive_rx) = watch::channel(BTreeSet::<String>::new());
    let live_seq = AtomicU64::new(0);
    let (live_up, live_known) = (up_tx.clone(), Arc::clone(&known));
    let live = session
        .liveliness()
        .declare_subscriber(format!("{PREFIX}/*/alive"))
        .history(true)
        .callback(move |sample| {
            let Some((robot, "alive")) = split_key(sample.key_expr().as_str()) else { return };
            if !live_known.contains(robot) {
                return;
            }
            let (health, detail) = match sample.kind() {
                SampleKind::Put => {
                    tracing::info!(robot, "link: robot joined");
                    alive_tx.send_modify(|a| {
                        a.insert(robot.to_owned());
                    });
                    (Health::Ok, "liveliness token present")
                }
                SampleKind::Delete => {
                    tracing::warn!(robot, "link: robot left (liveliness token gone)");
                    alive_tx.send_modify(|a| {
                        a.remove(robot);
                    });
                    (Health::Lost, "liveliness token gone: process stopped or lease expired")
                }
            };
            let _ = live_up.try_send(Uplink::Health {
                robot: robot.to_owned(),
                seq: live_seq.fetch_add(1, Ordering::Relaxed) + 1,
                stamp_s: clock.now_s(),
                report: HealthReport { device: Device::Link, health, detail: detail.to_owned() },
            });
        })
        .await
        .map_err(zerr)?;
    declared.push(Box::new(live));

    // Downlink: one pump per robot.
    let sid = new_session();
    let server = settings.server_user().to_owned();
    let mut downs = BTreeMap::new();
    let mut pumps = Vec::new();
    for robot in robots {
        let (tx, mut rx) = mpsc::channel::<Downlink>(DEPTH);
        downs.insert(robot.clone(), tx);
        let key = format!("{PREFIX}/{robot}/cmd");
        let cmd_pub = session
            .declare_publisher(key.clone())
            .priority(Priority::InteractiveHigh)
            .congestion_control(CongestionControl::Drop)
            .express(true)
            .await
            .map_err(zerr)?;
        let estop_key = estop_key(robot, &server);
        let (session, stats) = (session.clone(), Arc::clone(&stats));
        let mut stamper = Stamper::new(sid, &server, robot);
        let mut estop_stamper = Stamper::new(sid, &server, robot);
        pumps.push(AbortOnDrop(tokio::spawn(async move {
            while let Some(d) = rx.recv().await {
                let now = clock.now_s();
                let (stamp, body) = from_downlink(&d, now);
                let (key, stamper) =
                    if is_estop(&d) { (&estop_key, &mut estop_stamper) } else { (&key, &mut stamper) };
                let Some(bytes) = stamper.encode(stamp, now, body) else { continue };
                let r = match d {
                    Downlink::Command(_) => cmd_pub.put(bytes).await,
                    // The safety messages go at the highest priority and are never dropped; e-stops
                    // and resets on their own key, which operators may publish on too.
                    Downlink::Arm { .. } | Downlink::Disarm | Downlink::EStop | Downlink::ResetEStop => {
                        session
                            .put(key.as_str(), bytes)
                            .priority(Priority::RealTime)
                            .congestion_control(CongestionControl::Block)
                            .express(true)
                            .await
                    }
                };
                count_put(&stats, r);
            }
        })));
    }
    let status = session
        .declare_publisher(format!("{PREFIX}/server/status"))
        .priority(Priority::InteractiveLow)
        .congestion_control(CongestionControl::Drop)
        .await
        .map_err(zerr)?;
    let bridge = Bridge::spawn(BridgeState {
        session: SessionSlot::of(session),
        role: Role::Server,
        stats,
        _pumps: pumps,
        _declared: declared,
    })
    .await?;
    tracing::info!(
        endpoints = ?settings.listen.as_ref().unwrap_or(&settings.network.server.listen),
        robots = ?robots,
        "link: server bridge listening"
    );
    let end = ServerEnd { up: up_rx, scans, down: DownlinkSender::new(downs) };
    let sb = ServerBridge {
        bridge,
        alive: alive_rx,
        status,
        stamper: Mutex::new(Stamper::new(sid, &server, "server")),
        clock,
    };
    Ok((end, sb))
}

/// Decode a status sample (observers and tests).
pub fn decode_status(bytes: &[u8]) -> Result<ServerStatus, Reject> {
    match Envelope::decode(bytes)?.body {
        Body::Status(s) => Ok(s),
        _ => Err(Reject::WrongChannel { kind: "not-status", channel: "status" }),
    }
}

/// What an operator's e-stop (or reset) found: per robot, the safety state it reported after the
/// message was sent, if it confirmed within the time allowed.
pub type EstopOutcome = BTreeMap<String, Option<amr_msgs::SafetyState>>;

/// E-stop `robots` (or, with `reset`, clear their e-stop) as operator `user`: publish on each
/// robot's `fleet/<robot>/estop/<user>` at the highest priority, then wait up to `timeout` for each
/// robot's own report (its safety state comes up `fleet/<robot>/health` on every change and
/// periodically): `EStop`, or after a reset any other state. The server's access control lets only
/// `user` publish on its own key.
pub async fn operator_estop(
    settings: &NetSettings,
    user: &str,
    robots: &[String],
    reset: bool,
    clock: FleetClock,
    timeout: Duration,
) -> Result<EstopOutcome, NetError> {
    use amr_msgs::SafetyState;
    let session = tokio::time::timeout(timeout, zenoh::open(settings.client_config(user)?))
        .await
        .map_err(|_| NetError::Zenoh(format!("no server reached within {timeout:?}")))?
        .map_err(zerr)?;
    let seen: Arc<Mutex<EstopOutcome>> =
        Arc::new(Mutex::new(robots.iter().map(|r| (r.clone(), None)).collect()));
    let sent_at = clock.now_s();
    let mut subscribers = Vec::new();
    for robot in robots {
        let (seen, me) = (Arc::clone(&seen), robot.clone());
        let sub = session
            .declare_subscriber(format!("{PREFIX}/{robot}/health"))
            .callback(move |sample| {
                let bytes = sample.payload().to_bytes();
                let Ok(u) = Envelope::decode(&bytes).and_then(|env| to_uplink(env, &me, "health")) else {
                    return;
                };
                if let Uplink::Safety { stamp_s, state, .. } = u
                    && stamp_s >= sent_at
                {
                    let ok = if reset { state != SafetyState::EStop } else { state == SafetyState::EStop };
                    if ok {
                        seen.lock().unwrap_or_else(PoisonError::into_inner).insert(me.clone(), Some(state));
                    }
                }
            })
            .await
            .map_err(zerr)?;
        subscribers.push(sub);
    }
    let msg = if reset { Downlink::ResetEStop } else { Downlink::EStop };
    let sid = new_session();
    for robot in robots {
        let mut stamper = Stamper::new(sid, user, robot);
        let now = clock.now_s();
        let (stamp, body) = from_downlink(&msg, now);
        let Some(bytes) = stamper.encode(stamp, now, body) else { continue };
        session
            .put(estop_key(robot, user), bytes)
            .priority(Priority::RealTime)
            .congestion_control(CongestionControl::Block)
            .express(true)
            .await
            .map_err(zerr)?;
    }
    let until = tokio::time::Instant::now() + timeout;
    // Bounded by `timeout`.
    while tokio::time::Instant::now() < until {
        if seen.lock().unwrap_or_else(PoisonError::into_inner).values().all(Option::is_some) {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    drop(subscribers);
    let _ = session.close().await;
    let outcome = seen.lock().unwrap_or_else(PoisonError::into_inner).clone();
    Ok(outcome)
}
