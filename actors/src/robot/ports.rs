//! The robot's wiring: output ports that outlive any one actor, so an actor restarted by its
//! supervisor subscribes again in `pre_start` and the rest of the tree never holds a stale
//! reference. Ports are lossy (a lagging subscriber skips messages), which suits sensor data; the
//! safety loop re-sends its output every cycle. What the safety layer must see (commands, arm,
//! disarm, e-stop, reset, health changes) goes through [`SafetyInbox`] instead, which loses nothing.

use std::collections::{BTreeMap, VecDeque};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};

use amr_drivers::canopen::master::MasterEvent;
use amr_drivers::canopen::shell::MasterCommand;
use ractor::OutputPort;
use tokio::sync::{Notify, mpsc, watch};

use crate::clock::FleetClock;
use amr_msgs::{Device, Downlink, HealthReport, OdomMsg, SafetyState, ScanMsg};

/// One gyro reading.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImuReading {
    pub stamp_s: f64,
    /// Yaw rate about the robot's z axis, rad/s.
    pub yaw_rate_radps: f64,
}

pub use super::latches::{EStopLatch, EStopSource};
/// Wheel travel since the previous cycle, from the encoders: what the odometer folds in.
pub use amr_core::odometry::Travel as WheelTravel;

/// What the safety layer asks of the drives, every cycle.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WheelCommand {
    pub v_mps: f64,
    pub w_radps: f64,
    /// Quick stop the drives (e-stop, fault) instead of ramping.
    pub quick_stop: bool,
}

/// An operator's control of the safety layer (a signal to `amr robot`, a button).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SafetyControl {
    EStop,
    ResetEStop,
}

/// One input of the safety layer.
#[derive(Debug, Clone, PartialEq)]
pub enum SafetyInput {
    Link(Downlink),
    Health(HealthReport),
    Control(SafetyControl),
    /// The e-stop input of a drive reads pressed (already latched as [`EStopSource::Input`]).
    EStopInput,
    /// A safety message was lost before it reached the inbox (the link's queue was full).
    Missed,
}

/// How many inputs the safety inbox holds. At 50 commands a second this is five seconds of
/// backlog: a safety actor that far behind is stalled, and the overflow halts the robot.
pub const SAFETY_INBOX_CAPACITY: usize = 256;

/// How many CANopen master events wait for the drive actor: twenty seconds of SYNC cycles.
pub const BUS_EVENTS_CAPACITY: usize = 1024;

/// The safety layer's inputs, in order, none dropped: a bounded queue that outlives the safety
/// actor, so what arrives while it is being restarted waits for the next one.
///
/// Overflow policy: a full inbox refuses the input and sets a flag; the safety actor, on seeing
/// it, halts the robot (output zero, disarmed) until an explicit re-arm. An e-stop is latched in
/// [`RobotPorts::estop_latch`] before it is queued, so even a full inbox cannot lose it.
pub type SafetyInbox = Inbox<SafetyInput>;

/// A bounded queue between actors that loses nothing silently: items in order, a full queue
/// refuses the item and flags it, and the consumer decides what a loss means (the safety layer
/// halts; the drive actor marks the drives degraded, which halts too).
#[derive(Debug)]
pub struct Inbox<T> {
    queue: Mutex<VecDeque<T>>,
    capacity: usize,
    overflowed: AtomicBool,
    ready: Notify,
}

impl<T> Inbox<T> {
    /// An empty inbox for `capacity` items.
    #[must_use]
    pub fn new(capacity: usize) -> Self {
        Inbox { queue: Mutex::default(), capacity, overflowed: AtomicBool::new(false), ready: Notify::new() }
    }

    /// Queue `input`; `false` if the inbox was full (the consumer will see the overflow).
    pub fn push(&self, input: T) -> bool {
        let mut q = self.queue.lock().unwrap_or_else(PoisonError::into_inner);
        let queued = if q.len() >= self.capacity {
            self.overflowed.store(true, Ordering::SeqCst);
            false
        } else {
            q.push_back(input);
            true
        };
        drop(q);
        self.ready.notify_one();
        queued
    }

    /// Everything queued, oldest first, and whether anything was refused since the last take.
    pub(crate) fn take(&self) -> (Vec<T>, bool) {
        let items = self.queue.lock().unwrap_or_else(PoisonError::into_inner).drain(..).collect();
        (items, self.overflowed.swap(false, Ordering::SeqCst))
    }

    /// Wait until something was pushed.
    pub(crate) async fn wait(&self) {
        self.ready.notified().await;
    }
}

/// A task that casts `msg()` to `actor` each time the inbox `which(ports)` gets something, until
/// the actor is gone; dropping the guard ends it. (The safety actor and the drive actor read their
/// inboxes this way.)
pub(crate) fn wake_on<T: Send + 'static, M: ractor::Message>(
    ports: Arc<RobotPorts>,
    which: fn(&RobotPorts) -> &Inbox<T>,
    actor: ractor::ActorRef<M>,
    msg: fn() -> M,
) -> AbortOnDrop<()> {
    AbortOnDrop(tokio::spawn(async move {
        // Ends with the actor (a cast to a stopped actor fails).
        loop {
            which(&ports).wait().await;
            if actor.cast(msg()).is_err() {
                break;
            }
        }
    }))
}

/// A connected CAN bus: the running master's command queue and which connection it is.
#[derive(Debug, Clone)]
pub struct BusLink {
    /// Increases with every (re)connection of the bus.
    pub generation: u64,
    pub commands: mpsc::Sender<MasterCommand>,
}

/// How many stops one reservation in the latch file covers.
pub const STOP_RESERVE: u64 = 1000;

/// Every port of one robot.
#[derive(Debug)]
pub struct RobotPorts {
    pub robot: String,
    pub clock: FleetClock,
    pub scans: OutputPort<ScanMsg>,
    pub imu: OutputPort<ImuReading>,
    pub wheels: OutputPort<WheelTravel>,
    pub odom: OutputPort<OdomMsg>,
    pub health: OutputPort<HealthReport>,
    /// Every device's current health (the port carries the changes; this holds the state, for
    /// whoever starts listening late, e.g. a restarted uplink).
    pub health_board: watch::Sender<BTreeMap<Device, HealthReport>>,
    pub safety: OutputPort<SafetyState>,
    /// The safety layer's current state.
    pub safety_now: watch::Sender<Option<SafetyState>>,
    /// What came down the link (for observers such as a recorder; the safety layer reads
    /// [`RobotPorts::safety_inbox`]).
    pub downlink: OutputPort<Downlink>,
    /// The safety layer's inputs.
    pub safety_inbox: SafetyInbox,
    pub wheel_cmd: OutputPort<WheelCommand>,
    /// The current bus, set by the CAN bus actor (`None` while disconnected).
    pub bus: watch::Sender<Option<BusLink>>,
    /// The CANopen master's events, for the drive actor (drive health is made of them).
    pub bus_events: Inbox<MasterEvent>,
    /// The e-stop latch: the next safety actor starts in `EStop` if it is set. Set by every e-stop
    /// source; cleared only by the safety actor, on a reset from the same place.
    pub estop_latch: EStopLatch,
    /// A fault is latched (a supervisor escalated, in this run or before a restart): the next
    /// safety actor starts in `Fault`; only a reset on the robot clears it.
    pub fault_latch: AtomicBool,
    /// The safety layer's stop counter (an arm must carry it), kept here across restarts of the
    /// safety actor.
    pub stops: AtomicU64,
    /// The stop count reserved in the latch file: every count used so far is below it, so a
    /// restart starts above it (see [`RobotPorts::reserve_stops`]).
    pub stops_reserved: AtomicU64,
    /// Where the latches and the counter are kept across restarts of the robot (none in a
    /// simulation that starts every robot afresh).
    pub latch_file: Option<super::latches::LatchFile>,
    /// The devices are mocks in a simulated world.
    pub mock: bool,
}

impl RobotPorts {
    /// A downlink message arrived: e-stops latch at once; the safety layer gets it in order and
    /// observers on the lossy port.
    pub fn deliver(&self, msg: Downlink) {
        if msg == Downlink::EStop {
            // Latched before anything else, so that it holds even if no safety actor runs now.
            self.estop_latch.set(EStopSource::Network);
        }
        self.safety_inbox.push(SafetyInput::Link(msg));
        self.downlink.send(msg);
    }

    #[must_use]
    pub fn new(robot: impl Into<String>, clock: FleetClock) -> Arc<Self> {
        Self::restored(robot, clock, None, super::latches::Latched::default(), false)
    }

    /// Ports whose latches and stop counter start as `latched` (read from `file`, where they are
    /// kept from now on).
    #[must_use]
    pub fn restored(
        robot: impl Into<String>,
        clock: FleetClock,
        file: Option<super::latches::LatchFile>,
        latched: super::latches::Latched,
        mock: bool,
    ) -> Arc<Self> {
        let estop_latch = EStopLatch::holding(latched.estop);
        Arc::new(RobotPorts {
            robot: robot.into(),
            clock,
            scans: OutputPort::default(),
            imu: OutputPort::default(),
            wheels: OutputPort::default(),
            odom: OutputPort::default(),
            health: OutputPort::default(),
            health_board: watch::Sender::new(BTreeMap::new()),
            safety: OutputPort::default(),
            safety_now: watch::Sender::new(None),
            downlink: OutputPort::default(),
            safety_inbox: Inbox::new(SAFETY_INBOX_CAPACITY),
            wheel_cmd: OutputPort::default(),
            bus: watch::Sender::new(None),
            bus_events: Inbox::new(BUS_EVENTS_CAPACITY),
            estop_latch,
            fault_latch: AtomicBool::new(latched.fault),
            stops: AtomicU64::new(latched.stops),
            stops_reserved: AtomicU64::new(latched.stops),
            latch_file: file,
            mock,
        })
    }

    /// What is latched now.
    #[must_use]
    pub fn latched(&self) -> super::latches::Latched {
        super::latches::Latched {
            estop: self.estop_latch.sources(),
            fault: self.fault_latch.load(Ordering::SeqCst),
            stops: self.stops_reserved.load(Ordering::SeqCst),
        }
    }

    /// Make sure the count `stops` is below the reservation; true if the reservation moved (the
    /// latch file must be written). The file holds a count reserved [`STOP_RESERVE`] ahead rather
    /// than the count itself, so the control loop writes it once per that many stops, not on every
    /// disarm.
    pub fn reserve_stops(&self, stops: u64) -> bool {
        let reserved = self.stops_reserved.load(Ordering::SeqCst);
        if stops < reserved {
            return false;
        }
        self.stops_reserved.store(stops.saturating_add(STOP_RESERVE), Ordering::SeqCst);
        true
    }

    /// Write what is latched now to the latch file (if any). A failure is logged and counted by
    /// the caller; what is latched in memory holds whatever the disk does.
    pub fn persist_latches(&self) -> Result<(), super::latches::LatchFileError> {
        match &self.latch_file {
            Some(f) => f.store(self.latched()),
            None => Ok(()),
        }
    }
}

/// Opens a byte stream to a device without a socket or a tty: an in-memory pipe to a mock in a
/// virtual-time simulation (on a robot the drivers open TCP and serial ports themselves).
#[derive(Clone)]
pub struct StreamConnector(pub std::sync::Arc<dyn Fn() -> ConnectFuture + Send + Sync>);

/// A connection being opened.
pub(crate) type ConnectFuture =
    std::pin::Pin<Box<dyn Future<Output = std::io::Result<tokio::io::DuplexStream>> + Send>>;

impl std::fmt::Debug for StreamConnector {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("StreamConnector")
    }
}

impl StreamConnector {
    /// Open a new connection.
    pub fn connect(
        &self,
    ) -> impl Future<Output = std::io::Result<tokio::io::DuplexStream>> + Send + 'static + use<> {
        (self.0)()
    }
}

/// Aborts a task when dropped: an actor keeps its driver tasks in its state, so a panic, an error
/// or a stop ends them with it.
#[derive(Debug)]
pub struct AbortOnDrop<T>(pub tokio::task::JoinHandle<T>);

impl<T> Drop for AbortOnDrop<T> {
    fn drop(&mut self) {
        self.0.abort();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn disarm() -> SafetyInput {
        SafetyInput::Link(Downlink::Disarm)
    }

    #[test]
    fn the_stop_count_on_disk_is_a_reservation_above_every_count_used() {
        use crate::robot::latches::Latched;
        let from_disk = Latched { stops: 5, ..Latched::default() };
        let p = RobotPorts::restored("r", FleetClock::start(), None, from_disk, false);
        // The first count after a restart (5 + 1) moves the reservation: one write.
        assert!(p.reserve_stops(6));
        assert_eq!(p.latched().stops, 6 + STOP_RESERVE);
        // The next thousand stops need no write.
        assert!((7..6 + STOP_RESERVE).all(|n| !p.reserve_stops(n)));
        assert!(p.reserve_stops(6 + STOP_RESERVE));
        assert_eq!(p.latched().stops, 6 + 2 * STOP_RESERVE);
        // A restart from what is on disk starts above every count used.
        assert!(p.latched().stops > 6 + STOP_RESERVE);
    }

    #[test]
    fn an_estop_latch_clears_only_by_a_reset_from_where_it_was_pressed() {
        let l = EStopLatch::default();
        assert!(!l.is_set());
        l.set(EStopSource::Network);
        assert!(!l.reset(true) && l.is_set(), "a local reset leaves a network e-stop");
        assert!(l.reset(false) && !l.is_set());
        l.set(EStopSource::Local);
        assert!(!l.reset(false) && l.is_set(), "the network cannot clear a local e-stop");
        assert!(l.reset(true) && !l.is_set());
        // The input: not while it reads pressed, and never from the network.
        l.input(true);
        assert!(l.is_set());
        assert!(!l.reset(true) && !l.reset(false));
        l.input(false);
        assert!(l.is_set(), "released, it stays latched");
        assert!(!l.reset(false));
        assert!(l.reset(true) && !l.is_set());
        // Both: each place clears its own.
        l.set(EStopSource::Network);
        l.set(EStopSource::Local);
        assert!(!l.reset(false) && l.reset(true));
    }

    #[test]
    fn the_safety_inbox_keeps_order_and_a_full_one_refuses_and_flags() {
        let inbox = SafetyInbox::new(SAFETY_INBOX_CAPACITY);
        let health = SafetyInput::Health(HealthReport {
            device: Device::Drives,
            health: amr_msgs::Health::Lost,
            detail: String::new(),
        });
        assert!(inbox.push(disarm()));
        assert!(inbox.push(health.clone()));
        assert!(inbox.push(SafetyInput::Control(SafetyControl::EStop)));
        assert_eq!(inbox.take(), (vec![disarm(), health, SafetyInput::Control(SafetyControl::EStop)], false));
        assert_eq!(inbox.take(), (vec![], false));
        // Full: the capacity is taken, the rest refused, and the take reports the overflow once.
        let taken = (0..SAFETY_INBOX_CAPACITY + 3).filter(|_| inbox.push(disarm())).count();
        assert_eq!(taken, SAFETY_INBOX_CAPACITY);
        let (items, overflowed) = inbox.take();
        assert_eq!((items.len(), overflowed), (SAFETY_INBOX_CAPACITY, true));
        assert!(inbox.push(disarm()));
        assert_eq!(inbox.take(), (vec![disarm()], false));
    }
}
