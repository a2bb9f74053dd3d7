//! A robot's bridge: its session opened in the background, its uplink published by channel (scans
//! and odometry latest-wins, health queued), its commands and e-stops checked and queued for the
//! robot tree.

use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use amr_actors::clock::FleetClock;
use amr_actors::link::{DownlinkTx, RobotEnd, UplinkSender};
use amr_actors::robot::ports::AbortOnDrop;
use amr_msgs::{Downlink, Uplink};
use tokio::sync::{mpsc, watch};
use zenoh::pubsub::Subscriber;
use zenoh::qos::{CongestionControl, Priority};

use super::{
    Bridge, BridgeState, BridgeStats, DEPTH, Role, SessionSlot, Stamper, count_put, new_session, wall_now_s,
    zerr,
};
use crate::settings::{NetError, NetSettings, PREFIX};
use crate::wire::{DownlinkGate, Envelope, from_uplink, uplink_channel};

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

        let (_subscriber, _estop_subscriber) =
            subscribe_downlink(&session, &robot, server, estop_senders, clock, &stats, down).await?;
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

/// Subscribe a robot's downlink: its commands on `fleet/<robot>/cmd`, its e-stops and resets on
/// `fleet/<robot>/estop/<sender>`, both checked by one [`DownlinkGate`] and queued for the tree.
/// The subscribers are declared as long as they live.
async fn subscribe_downlink(
    session: &zenoh::Session,
    robot: &str,
    server: String,
    estop_senders: Vec<String>,
    clock: FleetClock,
    stats: &Arc<BridgeStats>,
    down: DownlinkTx,
) -> Result<(Subscriber<()>, Subscriber<()>), NetError> {
    let key = |ch: &str| format!("{PREFIX}/{robot}/{ch}");
    // Commands: decoded, checked (for me, from the server, newer than the last) and passed on.
    // The safety layer then applies its own rules (armed, sequence floor, stamp age). A disarm
    // is taken whatever its session, sequence or stamp: a stop is never refused
    // ([`DownlinkGate::on_cmd`]).
    let gate = Arc::new(Mutex::new(DownlinkGate::default()));
    let (me, cmd_stats, cmd_key, cmd_down, cmd_gate) =
        (robot.to_owned(), Arc::clone(stats), key("cmd"), down.clone(), Arc::clone(&gate));
    let subscriber = session
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
    let (me, estop_stats, estop_key) = (robot.to_owned(), Arc::clone(stats), key("estop/*"));
    let estop_subscriber = session
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
    Ok((subscriber, estop_subscriber))
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
