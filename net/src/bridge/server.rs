//! The server's bridge: it listens, takes each robot's uplink checked into the server tree,
//! watches the robots' liveliness tokens, pumps each robot's downlink, and publishes the
//! formation's status.

use std::collections::{BTreeMap, BTreeSet};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};

use amr_actors::clock::FleetClock;
use amr_actors::link::{DownlinkSender, ScanSlots, ServerEnd};
use amr_actors::robot::ports::AbortOnDrop;
use amr_msgs::{Device, Downlink, Health, HealthReport, ServerStatus, Uplink};
use tokio::sync::{mpsc, watch};
use zenoh::pubsub::Subscriber;
use zenoh::qos::{CongestionControl, Priority};
use zenoh::sample::SampleKind;

use super::{
    Bridge, BridgeState, BridgeStats, DEPTH, Role, SessionSlot, Stamper, count_put, estop_key, new_session,
    wall_now_s, zerr,
};
use crate::settings::{NetError, NetSettings, PREFIX};
use crate::wire::{Body, Envelope, Freshness, Reject, from_downlink, is_estop, to_uplink};

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
    let scans = ScanSlots::default();
    let known: Arc<BTreeSet<String>> = Arc::new(robots.iter().cloned().collect());
    let mut declared: Vec<Box<dyn std::any::Any + Send>> = Vec::new();

    for channel in ["scan", "odom", "health"] {
        let (up_tx, stats, known, scans) =
            (up_tx.clone(), Arc::clone(&stats), Arc::clone(&known), scans.clone());
        let sub = subscribe_uplink(&session, channel, up_tx, stats, known, scans).await?;
        declared.push(Box::new(sub));
    }

    // Liveliness: a robot's token appears when its bridge connects and vanishes when its session
    // closes or its lease runs out. The server tree hears it as the robot's link health.
    let (live, alive_rx) = watch_liveliness(&session, up_tx.clone(), Arc::clone(&known), clock).await?;
    declared.push(Box::new(live));

    // Downlink: one pump per robot.
    let sid = new_session();
    let server = settings.server_user().to_owned();
    let mut downs = BTreeMap::new();
    let mut pumps = Vec::new();
    for robot in robots {
        let (tx, pump) = downlink_pump(&session, robot, &server, sid, &stats, clock).await?;
        downs.insert(robot.clone(), tx);
        pumps.push(pump);
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

/// Subscribe `fleet/*/<channel>` for the robots in `known`: each sample checked (its key, its
/// robot, its envelope, its freshness) and passed to the server tree, scans into their own slots.
async fn subscribe_uplink(
    session: &zenoh::Session,
    channel: &str,
    up_tx: mpsc::Sender<Uplink>,
    stats: Arc<BridgeStats>,
    known: Arc<BTreeSet<String>>,
    scans: ScanSlots,
) -> Result<Subscriber<()>, NetError> {
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
    Ok(sub)
}

/// Watch the robots' liveliness tokens: the receiver returned holds the robots of `known` whose
/// token is present, and each join or leave goes to the server tree as the robot's link health.
async fn watch_liveliness(
    session: &zenoh::Session,
    up_tx: mpsc::Sender<Uplink>,
    known: Arc<BTreeSet<String>>,
    clock: FleetClock,
) -> Result<(Subscriber<()>, watch::Receiver<BTreeSet<String>>), NetError> {
    let (alive_tx, alive_rx) = watch::channel(BTreeSet::<String>::new());
    let live_seq = AtomicU64::new(0);
    let live = session
        .liveliness()
        .declare_subscriber(format!("{PREFIX}/*/alive"))
        .history(true)
        .callback(move |sample| {
            let Some((robot, "alive")) = split_key(sample.key_expr().as_str()) else { return };
            if !known.contains(robot) {
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
            let _ = up_tx.try_send(Uplink::Health {
                robot: robot.to_owned(),
                seq: live_seq.fetch_add(1, Ordering::Relaxed) + 1,
                stamp_s: clock.now_s(),
                report: HealthReport { device: Device::Link, health, detail: detail.to_owned() },
            });
        })
        .await
        .map_err(zerr)?;
    Ok((live, alive_rx))
}

/// `robot`'s downlink pump: what the server tree sends it, stamped and published, commands on
/// `fleet/<robot>/cmd`, the safety messages at the highest priority (e-stops and resets on the
/// server's own e-stop key).
async fn downlink_pump(
    session: &zenoh::Session,
    robot: &str,
    server: &str,
    sid: u64,
    stats: &Arc<BridgeStats>,
    clock: FleetClock,
) -> Result<(mpsc::Sender<Downlink>, AbortOnDrop<()>), NetError> {
    let (tx, mut rx) = mpsc::channel::<Downlink>(DEPTH);
    let key = format!("{PREFIX}/{robot}/cmd");
    let cmd_pub = session
        .declare_publisher(key.clone())
        .priority(Priority::InteractiveHigh)
        .congestion_control(CongestionControl::Drop)
        .express(true)
        .await
        .map_err(zerr)?;
    let estop_key = estop_key(robot, server);
    let (session, stats) = (session.clone(), Arc::clone(stats));
    let mut stamper = Stamper::new(sid, server, robot);
    let mut estop_stamper = Stamper::new(sid, server, robot);
    let pump = AbortOnDrop(tokio::spawn(async move {
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
    }));
    Ok((tx, pump))
}

/// Decode a status sample (observers and tests).
pub fn decode_status(bytes: &[u8]) -> Result<ServerStatus, Reject> {
    match Envelope::decode(bytes)?.body {
        Body::Status(s) => Ok(s),
        _ => Err(Reject::WrongChannel { kind: "not-status", channel: "status" }),
    }
}
