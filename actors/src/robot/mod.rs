//! The robot's actor tree (docs/architecture.md, "The robot's actor tree" and "Supervision"):
//!
//! ```text
//! robot-<id>            one-for-one
//! ├── lidar             LidarActor     (SOPAS/TCP)
//! ├── imu               ImuActor       (LPBUS/serial)
//! ├── drives            rest-for-one
//! │   ├── can-bus       CanBusActor    (transport + CANopen master)
//! │   └── drive         DriveActor     (CiA 402 diff drive, wheel travel)
//! ├── odometry          OdometryActor  (wheels + gyro)
//! ├── safety            SafetyActor    (limits, watchdog, e-stop latch)
//! └── uplink            UplinkActor    (scans with odometry, health, safety → link)
//! ```
//!
//! The actors talk through [`RobotPorts`], which outlive every actor, so a restart re-subscribes
//! and nothing holds a stale reference. If the top supervisor escalates (restart intensity
//! exceeded), every child has been stopped — the drive actor quick-stops on its way out and the
//! drives' own heartbeat consumer stops them if the master is gone — and the robot reports
//! `Fault` up the link.

pub mod canbus;
pub mod drive;
pub mod imu;
pub mod latches;
pub mod lidar;
pub mod odometry;
pub mod ports;
pub mod safety;
pub mod status;
pub mod uplink;

use std::sync::Arc;
use std::time::Duration;

use crate::config::RobotConfig;
use amr_drivers::canopen::config::BusTransport;
use ractor::{Actor, ActorRef};

use crate::clock::FleetClock;
use crate::link::{RobotEnd, UplinkSender};
use crate::supervisor::{
    ChildSpec, EventLog, RestartPolicy, Strategy, Supervisor, SupervisorMsg, SupervisorSpec,
};
use amr_msgs::{SafetyState, Uplink};
use canbus::{CanBusActor, CanLink};
use drive::DriveActor;
use imu::ImuActor;
use lidar::LidarActor;
pub(crate) use lidar::TIM551_RANGE_M;
use odometry::OdometryActor;
pub use ports::SafetyControl;
use ports::{AbortOnDrop, RobotPorts, SafetyInput};
use safety::{SafetyActor, SafetyParams};
use status::Counters;
use uplink::UplinkActor;

/// Where the devices are, when not where the configuration says (mock devices in a simulation).
#[derive(Debug, Clone, Default)]
pub struct DeviceOverrides {
    pub lidar: Option<(String, u16)>,
    pub imu_path: Option<String>,
    pub can: Option<CanLink>,
    /// In-memory pipes instead of TCP / the tty (virtual-time simulation).
    pub lidar_stream: Option<ports::StreamConnector>,
    pub imu_stream: Option<ports::StreamConnector>,
}

/// Supervision settings of the robot tree.
#[derive(Debug, Clone)]
pub struct RobotOptions {
    /// The top supervisor's policy (devices, odometry, safety, uplink).
    pub policy: RestartPolicy,
    /// The drives subtree's policy (CAN bus, then drives).
    pub drives_policy: RestartPolicy,
    /// Send every n-th odometry update up the link.
    pub odom_decimation: u64,
    /// Where the robot keeps its latched stops and stop counter across restarts
    /// ([`latches::LatchFile`]); `None` starts with nothing latched and keeps nothing.
    pub latch_file: Option<std::path::PathBuf>,
    /// The devices are mocks in a simulated world (reported to the server with the safety state).
    pub mock: bool,
}

impl Default for RobotOptions {
    fn default() -> Self {
        // OTP's default intensity is 1 restart in 5 s; devices deserve a few more, with backoff.
        let policy = RestartPolicy {
            max_restarts: 3,
            window: Duration::from_secs(10),
            backoff_initial: Duration::from_millis(100),
            backoff_max: Duration::from_secs(5),
        };
        RobotOptions { policy, drives_policy: policy, odom_decimation: 5, latch_file: None, mock: false }
    }
}

/// Why a robot could not start.
#[derive(Debug, thiserror::Error)]
pub enum RobotError {
    #[error("devices.can.transport is in-process but no bus was given (only a simulation has one)")]
    NoInProcessBus,
    #[error("the robot supervisor did not start: {0}")]
    Spawn(#[from] ractor::SpawnErr),
}

/// A running robot.
#[derive(Debug)]
pub struct RobotTree {
    pub id: String,
    pub supervisor: ActorRef<SupervisorMsg>,
    pub ports: Arc<RobotPorts>,
    pub events: EventLog,
    pub counters: Counters,
    stopping: Arc<std::sync::atomic::AtomicBool>,
    join: tokio::task::JoinHandle<()>,
    _tasks: Vec<AbortOnDrop<()>>,
}

impl RobotTree {
    /// Latch the e-stop (also when no safety actor runs at this moment: the next one starts in it).
    pub fn estop(&self) {
        self.ports.estop_latch.set(ports::EStopSource::Local);
        self.ports.safety_inbox.push(SafetyInput::Control(SafetyControl::EStop));
    }

    /// Clear the e-stop (the robot stays disarmed until armed).
    pub fn reset_estop(&self) {
        self.ports.safety_inbox.push(SafetyInput::Control(SafetyControl::ResetEStop));
    }

    /// Orderly shutdown: children stop in reverse order (the drives quick-stop), bounded in time.
    pub async fn shutdown(self) {
        self.stopping.store(true, std::sync::atomic::Ordering::SeqCst);
        self.supervisor.stop(Some("shutdown".into()));
        let _ = tokio::time::timeout(Duration::from_secs(5), self.join).await;
    }

    /// Whether the tree is still running.
    #[must_use]
    pub fn is_running(&self) -> bool {
        !self.join.is_finished()
    }
}

/// The safety parameters of a robot configuration.
#[must_use]
pub(crate) fn safety_params(cfg: &RobotConfig) -> SafetyParams {
    SafetyParams {
        max_speed_mps: cfg.limits.max_speed_mps.get(),
        max_yaw_rate_radps: cfg.limits.max_yaw_rate_radps.get(),
        max_accel_mps2: cfg.limits.max_accel_mps2.get(),
        stop_decel_mps2: cfg.stop_decel_mps2(),
        track_width_m: cfg.kinematics.track_width_m.get(),
        command_timeout_s: f64::from(cfg.safety.command_timeout_ms.ms()) / 1000.0,
        period_s: f64::from(cfg.devices.can.sync_period_ms) / 1000.0,
    }
}

/// Start robot `cfg`'s tree on `link`.
pub async fn start_robot(
    cfg: &RobotConfig,
    overrides: DeviceOverrides,
    link: RobotEnd,
    clock: FleetClock,
    options: RobotOptions,
) -> Result<RobotTree, RobotError> {
    let id = cfg.id.as_str().to_owned();
    let (file, latched) = restore_latches(&id, options.latch_file.as_ref());
    let ports = RobotPorts::restored(id.clone(), clock, file, latched, options.mock);
    let counters = Counters::default();
    let events = EventLog::default();

    let mut lidar_cfg = cfg.devices.lidar.clone();
    if let Some((host, port)) = overrides.lidar {
        (lidar_cfg.host, lidar_cfg.port) = (host, port);
    }
    let mut imu_cfg = cfg.devices.imu.clone();
    if let Some(path) = overrides.imu_path {
        imu_cfg.path = path;
    }
    let can = can_link(overrides.can, &cfg.devices.can.transport)?;
    let reconnect = &cfg.devices.can.reconnect;

    let lidar = LidarActor {
        ports: Arc::clone(&ports),
        config: lidar_cfg,
        counters: counters.clone(),
        stream: overrides.lidar_stream,
    };
    let imu = ImuActor {
        ports: Arc::clone(&ports),
        config: imu_cfg,
        counters: counters.clone(),
        stream: overrides.imu_stream,
    };
    let bus = CanBusActor {
        ports: Arc::clone(&ports),
        link: can,
        master: cfg.master(),
        backoff: (reconnect.initial, reconnect.max),
        counters: counters.clone(),
    };
    let drive = DriveActor { ports: Arc::clone(&ports), drive: cfg.diff_drive(), counters: counters.clone() };
    let odometry =
        OdometryActor { ports: Arc::clone(&ports), track_width_m: cfg.kinematics.track_width_m.get() };
    let safety =
        SafetyActor { ports: Arc::clone(&ports), params: safety_params(cfg), counters: counters.clone() };
    let uplink = UplinkActor {
        ports: Arc::clone(&ports),
        link: link.up.clone(),
        odom_decimation: options.odom_decimation,
    };

    let drives = SupervisorSpec {
        name: format!("{id}/drives"),
        strategy: Strategy::RestForOne,
        policy: options.drives_policy,
        children: vec![
            ChildSpec::new("can-bus", move || (bus.clone(), ())),
            ChildSpec::new("drive", move || (drive.clone(), ())),
        ],
        events: events.clone(),
    };
    let top = SupervisorSpec {
        name: id.clone(),
        strategy: Strategy::OneForOne,
        policy: options.policy,
        children: vec![
            ChildSpec::new("lidar", move || (lidar.clone(), ())),
            ChildSpec::new("imu", move || (imu.clone(), ())),
            ChildSpec::new("drives", move || (Supervisor, drives.clone())),
            ChildSpec::new("odometry", move || (odometry.clone(), ())),
            ChildSpec::new("safety", move || (safety.clone(), ())),
            ChildSpec::new("uplink", move || (uplink.clone(), ())),
        ],
        events: events.clone(),
    };
    let (supervisor, join) = Supervisor::spawn(None, Supervisor, top).await?;

    let pump = downlink_pump(link.down, link.missed, Arc::clone(&ports));
    let stopping = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let join =
        watch_tree(join, Arc::clone(&ports), link.up.clone(), supervisor.clone(), Arc::clone(&stopping));
    Ok(RobotTree { id, supervisor, ports, events, counters, stopping, join, _tasks: vec![AbortOnDrop(pump)] })
}

/// The latches from before a restart (none without a latch file). A file that cannot be read
/// counts as a latched local e-stop: only a reset on the robot clears it (and writes a good file).
fn restore_latches(
    id: &str,
    path: Option<&std::path::PathBuf>,
) -> (Option<latches::LatchFile>, latches::Latched) {
    let file = path.map(latches::LatchFile::new);
    let latched = match &file {
        None => latches::Latched::default(),
        Some(f) => match f.load() {
            Ok(l) => {
                if l.estop != 0 || l.fault {
                    tracing::warn!(robot = %id, file = %f.path().display(), estop = l.estop, fault = l.fault,
                        "starting latched: the stop from before the restart holds until it is reset");
                }
                l
            }
            Err(e) => {
                tracing::error!(robot = %id, error = %e,
                    "counting the e-stop as latched; reset it on the robot (SIGUSR2 to `amr robot`), which rewrites the file");
                latches::Latched { estop: ports::EStopSource::Local as u8, fault: false, stops: 0 }
            }
        },
    };
    (file, latched)
}

/// The CAN link: an override (tests, mocks), else the configured transport.
fn can_link(over: Option<CanLink>, transport: &BusTransport) -> Result<CanLink, RobotError> {
    Ok(match (over, transport) {
        (Some(c), _) => c,
        (None, BusTransport::Socketcan { interface }) => CanLink::SocketCan { interface: interface.clone() },
        (None, BusTransport::Socketcand { address, channel }) => {
            CanLink::Socketcand { address: address.clone(), channel: channel.clone() }
        }
        (None, BusTransport::InProcess) => return Err(RobotError::NoInProcessBus),
    })
}

/// What comes down the link goes to whichever safety actor is running.
fn downlink_pump(
    mut down: tokio::sync::mpsc::Receiver<amr_msgs::Downlink>,
    missed: Arc<crate::link::Missed>,
    p: Arc<RobotPorts>,
) -> tokio::task::JoinHandle<()> {
    tokio::spawn(async move {
        while let Some(msg) = down.recv().await {
            p.deliver(msg);
            // The link's queue was full for a safety message (it is not empty then, so this runs).
            if missed.estop.swap(false, std::sync::atomic::Ordering::SeqCst) {
                p.deliver(amr_msgs::Downlink::EStop);
            }
            if missed.any.swap(false, std::sync::atomic::Ordering::SeqCst) {
                tracing::error!(robot = %p.robot, "a safety message found the link's queue full: halting");
                p.safety_inbox.push(SafetyInput::Missed);
            }
        }
    })
}

/// The top supervisor ending on its own means it escalated: report Fault, and keep reporting it
/// (the server may not be listening yet) until the tree is dropped. `asked`: a stop was asked for.
fn watch_tree(
    join: tokio::task::JoinHandle<()>,
    p: Arc<RobotPorts>,
    up: UplinkSender,
    sup: ractor::ActorRef<SupervisorMsg>,
    asked: Arc<std::sync::atomic::AtomicBool>,
) -> tokio::task::JoinHandle<()> {
    tokio::spawn(async move {
        let _ = join.await;
        if asked.load(std::sync::atomic::Ordering::SeqCst) {
            tracing::info!(robot = %p.robot, "robot stopped");
        } else {
            tracing::error!(robot = %p.robot, "robot supervisor escalated: robot stopped, Fault");
            report_fault(&p, &up);
        }
        drop(sup);
    })
}

fn report_fault(ports: &RobotPorts, up: &UplinkSender) {
    // Latched on disk before it is reported: a restart does not clear it.
    ports.fault_latch.store(true, std::sync::atomic::Ordering::SeqCst);
    let stops = ports.stops.fetch_add(1, std::sync::atomic::Ordering::SeqCst).wrapping_add(1);
    ports.reserve_stops(stops);
    if let Err(e) = ports.persist_latches() {
        tracing::error!(robot = %ports.robot, error = %e, "the fault is not on disk");
    }
    ports.safety_now.send_replace(Some(SafetyState::Fault));
    ports.safety.send(SafetyState::Fault);
    up.send(Uplink::Safety {
        robot: ports.robot.clone(),
        seq: u64::MAX,
        stamp_s: ports.clock.now_s(),
        state: SafetyState::Fault,
        stops,
        mock: ports.mock,
    });
}
