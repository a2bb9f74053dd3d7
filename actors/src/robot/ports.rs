//! The robot's wiring: output ports that outlive any one actor, so an actor restarted by its
//! supervisor subscribes again in `pre_start` and the rest of the tree never holds a stale
//! reference. Ports are lossy (a lagging subscriber skips messages), which suits sensor data; the
//! safety loop re-sends its output every cycle.

use std::collections::BTreeMap;
use std::sync::Arc;

use amr_drivers::canopen::master::MasterEvent;
use amr_drivers::canopen::shell::MasterCommand;
use ractor::OutputPort;
use tokio::sync::{mpsc, watch};

use crate::clock::FleetClock;
use amr_msgs::{Device, Downlink, HealthReport, OdomMsg, SafetyState, ScanMsg};

/// One gyro reading.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImuReading {
    pub stamp_s: f64,
    /// Yaw rate about the robot's z axis, rad/s.
    pub yaw_rate_radps: f64,
}

/// Wheel travel since the previous cycle, from the encoders.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WheelTravel {
    pub stamp_s: f64,
    /// Time since the previous travel, s.
    pub dt_s: f64,
    pub left_m: f64,
    pub right_m: f64,
}

/// What the safety layer asks of the drives, every cycle.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WheelCommand {
    pub v_mps: f64,
    pub w_radps: f64,
    /// Quick stop the drives (e-stop, fault) instead of ramping.
    pub quick_stop: bool,
}

/// A connected CAN bus: the running master's command queue and which connection it is.
#[derive(Debug, Clone)]
pub struct BusLink {
    /// Increases with every (re)connection of the bus.
    pub generation: u64,
    pub commands: mpsc::Sender<MasterCommand>,
}

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
    /// What came down the link.
    pub downlink: OutputPort<Downlink>,
    pub wheel_cmd: OutputPort<WheelCommand>,
    /// The current bus, set by the CAN bus actor (`None` while disconnected).
    pub bus: watch::Sender<Option<BusLink>>,
    pub bus_events: OutputPort<MasterEvent>,
    /// The e-stop latch. It lives here, not in the safety actor, so that it survives the actor's
    /// restart and an e-stop that arrives while no safety actor runs is not lost: the next one
    /// starts in `EStop`. Set by every e-stop source; cleared only by the safety actor's reset.
    pub estop_latch: std::sync::atomic::AtomicBool,
}

impl RobotPorts {
    #[must_use]
    pub fn new(robot: impl Into<String>, clock: FleetClock) -> Arc<Self> {
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
            wheel_cmd: OutputPort::default(),
            bus: watch::Sender::new(None),
            bus_events: OutputPort::default(),
            estop_latch: std::sync::atomic::AtomicBool::new(false),
        })
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
