//! The link between the robots and the server, behind one interface: channel ends. A robot gets a
//! [`RobotEnd`] (send [`Uplink`], receive [`Downlink`]); the server gets a [`ServerEnd`] (receive
//! every robot's uplink, send to any robot). The in-process link here joins them through a router
//! that a drill can cut; the network link (Zenoh) hands out the same ends from its bridge actors.
//!
//! Sensor data is lossy by design: when a queue is full the newest message is dropped and counted,
//! so a slow consumer never blocks a robot. Scans travel apart from everything else, in
//! [`ScanSlots`]: a few per robot, the newest replacing the oldest, so a robot that sends scans at
//! any rate costs the server bounded memory and never crowds out the other robots' odometry, health
//! and safety reports. Commands are small and few; the robot's command watchdog, not the link,
//! decides what a late command means.

use std::collections::{BTreeMap, VecDeque};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock, PoisonError};

use tokio::sync::{Notify, mpsc, watch};

use crate::clock::FleetClock;
use amr_msgs::{Downlink, ScanMsg, Uplink};

/// Scans the server holds per robot before the newest replaces the oldest: half a second at
/// 15 Hz, more than a localisation that keeps up ever needs.
pub const SCANS_PER_ROBOT: usize = 8;

/// Scans on their way to the server: per robot at most [`SCANS_PER_ROBOT`], the newest replacing
/// the oldest; taken in arrival order. Each is stamped with the server's clock when it arrives
/// (once the server has given its clock: [`ScanSlots::stamp_with`]; before that, when taken).
#[derive(Debug, Clone)]
pub struct ScanSlots(Arc<SlotsInner>);

/// A scan held: its arrival number, the scan, and when it arrived (once the clock is known).
type Held = (u64, ScanMsg, Option<f64>);

#[derive(Debug)]
struct SlotsInner {
    per_robot: usize,
    /// Arrival counter, and per robot its queue.
    queues: Mutex<(u64, BTreeMap<String, VecDeque<Held>>)>,
    ready: Notify,
    clock: OnceLock<FleetClock>,
    dropped: AtomicU64,
    held_peak: AtomicU64,
}

impl Default for ScanSlots {
    fn default() -> Self {
        ScanSlots::new(SCANS_PER_ROBOT)
    }
}

impl ScanSlots {
    /// Slots for `per_robot` scans of each robot.
    #[must_use]
    pub fn new(per_robot: usize) -> Self {
        ScanSlots(Arc::new(SlotsInner {
            per_robot: per_robot.max(1),
            queues: Mutex::new((0, BTreeMap::new())),
            ready: Notify::new(),
            clock: OnceLock::new(),
            dropped: AtomicU64::new(0),
            held_peak: AtomicU64::new(0),
        }))
    }

    /// Stamp arrivals with `clock` from now on.
    pub fn stamp_with(&self, clock: FleetClock) {
        let _ = self.0.clock.set(clock);
    }

    /// A scan arrived; false if it replaced its robot's oldest.
    pub fn push(&self, scan: ScanMsg) -> bool {
        let received = self.0.clock.get().map(FleetClock::now_s);
        let mut q = self.0.queues.lock().unwrap_or_else(PoisonError::into_inner);
        let (next, queues) = &mut *q;
        *next += 1;
        let robot = queues.entry(scan.robot.clone()).or_default();
        let kept = robot.len() < self.0.per_robot;
        if !kept {
            robot.pop_front();
            self.0.dropped.fetch_add(1, Ordering::Relaxed);
        }
        robot.push_back((*next, scan, received));
        let held: usize = queues.values().map(VecDeque::len).sum();
        self.0.held_peak.fetch_max(held as u64, Ordering::Relaxed);
        drop(q);
        self.0.ready.notify_one();
        kept
    }

    /// Every scan held, in arrival order, with when it arrived (`now_s` for those that came
    /// before the server gave its clock).
    #[must_use]
    pub fn take(&self, now_s: f64) -> Vec<(ScanMsg, f64)> {
        let mut q = self.0.queues.lock().unwrap_or_else(PoisonError::into_inner);
        let mut all: Vec<Held> = q.1.values_mut().flat_map(std::mem::take).collect();
        drop(q);
        all.sort_by_key(|(n, _, _)| *n);
        all.into_iter().map(|(_, s, rx)| (s, rx.unwrap_or(now_s))).collect()
    }

    /// Wait until a scan arrives (returns at once if one arrived since the last wait).
    pub async fn ready(&self) {
        self.0.ready.notified().await;
    }

    /// Scans replaced by newer ones before they were taken.
    #[must_use]
    pub fn dropped(&self) -> u64 {
        self.0.dropped.load(Ordering::Relaxed)
    }

    /// The most scans held at once.
    #[must_use]
    pub fn held_peak(&self) -> u64 {
        self.0.held_peak.load(Ordering::Relaxed)
    }
}

/// Depth of each queue: about one second of scans at 15 Hz with odometry at 50 Hz.
const DEPTH: usize = 128;

/// A robot's end of the link.
#[derive(Debug)]
pub struct RobotEnd {
    pub robot: String,
    pub up: UplinkSender,
    pub down: mpsc::Receiver<Downlink>,
    /// Safety messages that found `down` full.
    pub missed: Arc<Missed>,
}

/// Safety messages the link could not queue for the robot because its queue was full. The robot
/// halts on seeing `any` (and latches the e-stop on `estop`): the stated overflow policy, so a
/// disarm or an e-stop is never silently lost between the link and the safety layer.
#[derive(Debug, Default)]
pub struct Missed {
    pub any: AtomicBool,
    pub estop: AtomicBool,
}

/// The link's side of a robot's downlink queue (bounded, `DEPTH`). A command that finds it full is
/// dropped and counted by the caller (the next one replaces it; the watchdog covers a gap); a
/// safety message (arm, disarm, e-stop, reset) is remembered in [`Missed`].
#[derive(Debug, Clone)]
pub struct DownlinkTx {
    tx: mpsc::Sender<Downlink>,
    missed: Arc<Missed>,
}

impl DownlinkTx {
    /// A robot's downlink queue: the link's side, the robot's, and the record of missed messages.
    #[must_use]
    pub fn queue() -> (DownlinkTx, mpsc::Receiver<Downlink>, Arc<Missed>) {
        let (tx, rx) = mpsc::channel(DEPTH);
        let missed = Arc::new(Missed::default());
        (DownlinkTx { tx, missed: Arc::clone(&missed) }, rx, missed)
    }

    /// Queue `d` without waiting; `false` if the queue was full or closed.
    pub fn send(&self, d: Downlink) -> bool {
        if self.tx.try_send(d).is_ok() {
            return true;
        }
        if !matches!(d, Downlink::Command(_)) {
            self.missed.any.store(true, Ordering::SeqCst);
            if d == Downlink::EStop {
                self.missed.estop.store(true, Ordering::SeqCst);
            }
        }
        false
    }

    /// Wait until the robot's end is dropped.
    pub async fn closed(&self) {
        self.tx.closed().await;
    }
}

/// Sends up the link without ever waiting: a full queue drops the message and counts it.
#[derive(Debug, Clone)]
pub struct UplinkSender {
    tx: mpsc::Sender<Uplink>,
    dropped: Arc<AtomicU64>,
}

impl UplinkSender {
    /// Wraps a channel sender.
    #[must_use]
    pub fn new(tx: mpsc::Sender<Uplink>) -> Self {
        UplinkSender { tx, dropped: Arc::default() }
    }

    /// Queue `msg`; false if it was dropped (queue full or link closed).
    pub fn send(&self, msg: Uplink) -> bool {
        match self.tx.try_send(msg) {
            Ok(()) => true,
            Err(_) => {
                self.dropped.fetch_add(1, Ordering::Relaxed);
                false
            }
        }
    }

    /// Messages dropped so far.
    #[must_use]
    pub fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }
}

/// The server's end of the link.
#[derive(Debug)]
pub struct ServerEnd {
    /// Everything but scans.
    pub up: mpsc::Receiver<Uplink>,
    pub scans: ScanSlots,
    pub down: DownlinkSender,
}

/// Sends to any robot without waiting.
#[derive(Debug, Clone, Default)]
pub struct DownlinkSender {
    robots: BTreeMap<String, mpsc::Sender<Downlink>>,
}

impl DownlinkSender {
    /// Routes to these robots.
    #[must_use]
    pub fn new(robots: BTreeMap<String, mpsc::Sender<Downlink>>) -> Self {
        DownlinkSender { robots }
    }

    /// Queue `msg` for `robot`; false if the robot is unknown, its queue full or its link closed.
    pub fn send(&self, robot: &str, msg: Downlink) -> bool {
        self.robots.get(robot).is_some_and(|tx| tx.try_send(msg).is_ok())
    }

    /// The robots it routes to.
    pub fn robots(&self) -> impl Iterator<Item = &str> {
        self.robots.keys().map(String::as_str)
    }
}

/// Drill control of the in-process link: cut and restore one robot's link, hold it (a stalled
/// transport that delivers its backlog late), and attach a new server (a restarted one).
#[derive(Debug, Clone, Default)]
pub struct LinkControl {
    cut: Arc<BTreeMap<String, AtomicBool>>,
    /// Per robot: how late its scans reach the server, µs (0: not delayed).
    scan_delay_us: Arc<BTreeMap<String, AtomicU64>>,
    held: Arc<BTreeMap<String, watch::Sender<bool>>>,
    lost: Arc<AtomicU64>,
    late: Arc<AtomicU64>,
    server: Option<Arc<ServerSwitch>>,
}

/// Where the routers send: the current server's uplink queue, and each robot's router's supply of
/// downlink queues.
#[derive(Debug)]
struct ServerSwitch {
    robots: usize,
    up: watch::Sender<(mpsc::Sender<Uplink>, ScanSlots)>,
    down: BTreeMap<String, mpsc::UnboundedSender<mpsc::Receiver<Downlink>>>,
}

impl LinkControl {
    /// Cut (`true`) or restore (`false`) `robot`'s link in both directions: what meets the cut is
    /// lost.
    pub fn set_cut(&self, robot: &str, cut: bool) {
        if let Some(flag) = self.cut.get(robot) {
            flag.store(cut, Ordering::Relaxed);
        }
    }

    /// Hold (`true`) or release (`false`) `robot`'s link in both directions: nothing passes while
    /// held, the queues fill (up to their depth; then the senders drop and count) and the backlog is
    /// delivered, late, on release — a stalled transport, the worst case for stale commands.
    pub fn set_held(&self, robot: &str, held: bool) {
        if let Some(flag) = self.held.get(robot) {
            flag.send_replace(held);
        }
    }

    /// Deliver `robot`'s scans `delay` late (`Duration::ZERO`: on time), everything else as it
    /// comes: a loaded host or network between one LiDAR and the server, which puts that robot's
    /// scans past the fusion's age gate while its odometry and health still arrive.
    pub fn set_scan_delay(&self, robot: &str, delay: std::time::Duration) {
        if let Some(d) = self.scan_delay_us.get(robot) {
            d.store(u64::try_from(delay.as_micros()).unwrap_or(u64::MAX), Ordering::Relaxed);
        }
    }

    fn scan_delay(&self, robot: &str) -> std::time::Duration {
        let us = self.scan_delay_us.get(robot).map_or(0, |d| d.load(Ordering::Relaxed));
        std::time::Duration::from_micros(us)
    }

    fn is_cut(&self, robot: &str) -> bool {
        self.cut.get(robot).is_some_and(|f| f.load(Ordering::Relaxed))
    }

    /// Wait while `robot`'s link is held; true if it was.
    async fn pass(&self, robot: &str) -> bool {
        let Some(flag) = self.held.get(robot) else { return false };
        if !*flag.borrow() {
            return false;
        }
        let mut rx = flag.subscribe();
        // Bounded by whoever holds the link (a drill); a dropped control releases it.
        let _ = rx.wait_for(|held| !*held).await;
        true
    }

    /// Count a message delivered late: the one a router held, and then its backlog until the
    /// queue is empty.
    fn count_late(&self, was_held: bool, draining: &mut bool, queue_empty: bool) {
        *draining |= was_held;
        if *draining {
            self.late.fetch_add(1, Ordering::Relaxed);
            *draining = !queue_empty;
        }
    }

    /// Messages that met a cut link.
    #[must_use]
    pub fn lost(&self) -> u64 {
        self.lost.load(Ordering::Relaxed)
    }

    /// Messages delivered late because the link was held (the backlog delivered on release).
    #[must_use]
    pub fn late(&self) -> u64 {
        self.late.load(Ordering::Relaxed)
    }

    /// A new server end, replacing the current one (a restarted server): the robots' uplink goes
    /// to it from now on and it reaches every robot; whatever was queued for or by the old server
    /// is dropped with it. `None` for a control that came with no link.
    #[must_use]
    pub fn new_server_end(&self) -> Option<ServerEnd> {
        self.server.as_ref().map(|s| s.new_end())
    }
}

impl ServerSwitch {
    fn new_end(&self) -> ServerEnd {
        let (up_tx, up_rx) = mpsc::channel(DEPTH * self.robots.max(1));
        let scans = ScanSlots::default();
        self.up.send_replace((up_tx, scans.clone()));
        let mut downs = BTreeMap::new();
        for (robot, supply) in &self.down {
            let (tx, rx) = mpsc::channel(DEPTH);
            if supply.send(rx).is_ok() {
                downs.insert(robot.clone(), tx);
            }
        }
        ServerEnd { up: up_rx, scans, down: DownlinkSender::new(downs) }
    }
}

/// What a downlink router waits for.
enum DownEvent {
    /// A new server's queue (`None`: no more will come).
    Server(Option<mpsc::Receiver<Downlink>>),
    /// From the current server (`None`: it is gone).
    Msg(Option<Downlink>),
}

/// Build an in-process link for `robots`: the server's end, each robot's end (in the order given)
/// and the control. Must be called inside a tokio runtime (it spawns the router tasks, which end
/// when their robot's end is dropped, or the server's end and every control).
#[must_use]
pub fn in_process(robots: &[String]) -> (ServerEnd, Vec<RobotEnd>, LinkControl) {
    let (first_up, _) = mpsc::channel(1);
    let (up_switch, _) = watch::channel((first_up, ScanSlots::default()));
    let mut supplies = BTreeMap::new();
    let mut ends = Vec::new();
    let mut routers = Vec::new();
    for robot in robots {
        let (supply, queues) = mpsc::unbounded_channel();
        supplies.insert(robot.clone(), supply);
        let (up_tx, up_rx) = mpsc::channel::<Uplink>(DEPTH);
        let (to_robot, robot_rx, missed) = DownlinkTx::queue();
        ends.push(RobotEnd { robot: robot.clone(), up: UplinkSender::new(up_tx), down: robot_rx, missed });
        routers.push((robot.clone(), up_rx, to_robot, queues));
    }
    let switch = Arc::new(ServerSwitch { robots: robots.len(), up: up_switch, down: supplies });
    let server_end = switch.new_end();
    let control = LinkControl {
        cut: Arc::new(robots.iter().map(|r| (r.clone(), AtomicBool::new(false))).collect()),
        scan_delay_us: Arc::new(robots.iter().map(|r| (r.clone(), AtomicU64::new(0))).collect()),
        held: Arc::new(robots.iter().map(|r| (r.clone(), watch::Sender::new(false))).collect()),
        lost: Arc::default(),
        late: Arc::default(),
        server: Some(Arc::clone(&switch)),
    };
    // The routers' own handle does not keep the switch: once every control is dropped no new
    // server can come, and a router ends with its ends.
    let routers_ctl = LinkControl { server: None, ..control.clone() };
    for (name, up_rx, to_robot, queues) in routers {
        tokio::spawn(route_up(name.clone(), up_rx, switch.up.subscribe(), routers_ctl.clone()));
        tokio::spawn(route_down(name, queues, to_robot, routers_ctl.clone()));
    }
    (server_end, ends, control)
}

/// Robot → router → the current server: scans into the server's slots (each on its own timer
/// when the link delays them), the rest into its queue; what meets a cut or a full queue is lost.
async fn route_up(
    robot: String,
    mut up_rx: mpsc::Receiver<Uplink>,
    mut server_rx: watch::Receiver<(mpsc::Sender<Uplink>, ScanSlots)>,
    ctl: LinkControl,
) {
    let mut to_server = server_rx.borrow_and_update().clone();
    let mut draining = false;
    while let Some(msg) = up_rx.recv().await {
        let held = ctl.pass(&robot).await;
        ctl.count_late(held, &mut draining, up_rx.is_empty());
        if server_rx.has_changed().unwrap_or(false) {
            to_server = server_rx.borrow_and_update().clone();
        }
        if ctl.is_cut(&robot) {
            ctl.lost.fetch_add(1, Ordering::Relaxed);
            continue;
        }
        let msg = match msg {
            Uplink::Scan(scan) => {
                let (slots, delay) = (to_server.1.clone(), ctl.scan_delay(&robot));
                if delay.is_zero() {
                    slots.push(scan);
                } else {
                    // Each scan on its own timer: late, not slower (the others are not held up).
                    tokio::spawn(async move {
                        tokio::time::sleep(delay).await;
                        slots.push(scan);
                    });
                }
                continue;
            }
            other => other,
        };
        if to_server.0.try_send(msg).is_err() {
            ctl.lost.fetch_add(1, Ordering::Relaxed);
        }
    }
}

/// The current server → router → robot: follows each new server's queue; what meets a cut or a
/// closed robot end is lost. Ends when no server is attached and none can come.
async fn route_down(
    name: String,
    mut queues: mpsc::UnboundedReceiver<mpsc::Receiver<Downlink>>,
    to_robot: DownlinkTx,
    ctl: LinkControl,
) {
    let mut current: Option<mpsc::Receiver<Downlink>> = None;
    let mut more = true;
    let mut draining = false;
    loop {
        let event = match current.as_mut() {
            Some(rx) => tokio::select! {
                biased;
                q = queues.recv(), if more => DownEvent::Server(q),
                m = rx.recv() => DownEvent::Msg(m),
                () = to_robot.closed() => break,
            },
            None if more => tokio::select! {
                biased;
                q = queues.recv() => DownEvent::Server(q),
                () = to_robot.closed() => break,
            },
            None => break,
        };
        match event {
            DownEvent::Server(Some(rx)) => current = Some(rx),
            DownEvent::Server(None) => more = false,
            DownEvent::Msg(None) => current = None,
            DownEvent::Msg(Some(msg)) => {
                let held = ctl.pass(&name).await;
                let empty = current.as_ref().is_none_or(mpsc::Receiver::is_empty);
                ctl.count_late(held, &mut draining, empty);
                if ctl.is_cut(&name) || !to_robot.send(msg) {
                    ctl.lost.fetch_add(1, Ordering::Relaxed);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests;
