//! The mock devices of a robot, backed by the world: the LiDAR, the IMU (with bad values on
//! demand), the two drives on an in-process CAN bus and, when asked for, a socketcand server in
//! front of that bus; and where the robot finds them.

use std::sync::Arc;

use amr_actors::config::RobotConfig;
use amr_actors::robot::DeviceOverrides;
use amr_actors::robot::canbus::CanLink;
use amr_actors::robot::ports::{AbortOnDrop, StreamConnector};
use amr_drivers::canopen::transport::in_process::InProcessBus;
use amr_msgs::Device;
use hil_mocks::lpms::{MockImuHandle, MockImuOptions, start_mock_imu};
use hil_mocks::teco_drive::{DriveHandle, TecoDrive, TecoDriveConfig, spawn_drive};
use hil_mocks::tim551::{MockConfig, Tim551Mock};
use hil_mocks::world::{Noise, SharedWorld, WorldImu, WorldLidar};
use tokio::time::Instant;

use crate::options::{SimCan, SimError};

/// The socketcand server in front of a robot's mock bus.
#[derive(Debug)]
pub struct SocketcandMock {
    pub address: std::net::SocketAddr,
    pub control: hil_mocks::teco_drive::socketcand::SocketcandControl,
    _task: AbortOnDrop<()>,
}

/// One robot's mock devices.
#[derive(Debug)]
pub struct RobotMocks {
    pub lidar: Tim551Mock,
    pub imu: MockImuHandle,
    /// Set to n: the IMU's next n samples carry a NaN or an out-of-range yaw rate (drills).
    pub imu_bad: Arc<std::sync::atomic::AtomicU32>,
    pub bus: InProcessBus,
    /// Left, right.
    pub drives: Vec<DriveHandle>,
    pub socketcand: Option<SocketcandMock>,
    /// Virtual time: the in-memory ways to the LiDAR and the IMU.
    pub lidar_pipe: Option<hil_mocks::tim551::MemoryConnector>,
    pub imu_pipe: Option<hil_mocks::lpms::ImuConnector>,
}

fn drive_config(robot: &RobotConfig, node: u8, noise: &Noise, seed: u64) -> TecoDriveConfig {
    let d = &robot.devices.drives;
    TecoDriveConfig {
        encoder_counts_per_rev: d.encoder_counts_per_rev,
        velocity_units_per_rps: d.velocity_units_per_rps,
        encoder_noise_counts: noise.encoder_sigma_counts,
        seed: seed.wrapping_mul(1000).wrapping_add(u64::from(node)),
        ..TecoDriveConfig::new(node)
    }
}

/// Robot `i`'s mock devices, backed by `world`.
pub async fn start_mocks(
    world: &SharedWorld,
    i: usize,
    r: &RobotConfig,
    noise: &Noise,
    seed: u64,
    can: SimCan,
) -> Result<RobotMocks, SimError> {
    let lidar_config = MockConfig {
        serial: 0x0100_0000 + i as u32,
        initial_tick_us: 1_000_000 * i as u32,
        ..MockConfig::default()
    };
    let lidar_source = Arc::new(WorldLidar { world: Arc::clone(world), robot: i });
    let (lidar, lidar_pipe) = if can == SimCan::VirtualTime {
        let (mock, connector) = Tim551Mock::spawn_in_memory(lidar_config, lidar_source);
        (mock, Some(connector))
    } else {
        let mock = Tim551Mock::spawn("127.0.0.1:0", lidar_config, lidar_source)
            .await
            .map_err(|e| SimError::Mock("lidar", e.to_string()))?;
        (mock, None)
    };
    let mut imu_opts = MockImuOptions::default();
    imu_opts.device.stream_hz = r.devices.imu.stream_hz;
    imu_opts.device.imu_id = r.devices.imu.imu_id;
    let imu_bad = Arc::new(std::sync::atomic::AtomicU32::new(0));
    let source =
        BadValues { inner: WorldImu { world: Arc::clone(world), robot: i }, left: Arc::clone(&imu_bad) };
    let (imu, imu_pipe) = if can == SimCan::VirtualTime {
        let (mock, connector) = hil_mocks::lpms::start_mock_imu_in_memory(imu_opts, Box::new(source));
        (mock, Some(connector))
    } else {
        let mock = start_mock_imu(imu_opts, Box::new(source))
            .await
            .map_err(|e| SimError::Mock("imu", e.to_string()))?;
        (mock, None)
    };
    let bus = InProcessBus::default();
    let now = Instant::now().into_std();
    let drives = [r.devices.drives.left.node_id, r.devices.drives.right.node_id]
        .iter()
        .map(|n| spawn_drive(TecoDrive::new(drive_config(r, *n, noise, seed), now), bus.port()))
        .collect();
    let socketcand = match can {
        SimCan::InProcess | SimCan::VirtualTime => None,
        SimCan::Socketcand => {
            let control = hil_mocks::teco_drive::socketcand::SocketcandControl::default();
            let (addr, task) =
                hil_mocks::teco_drive::socketcand::bind_with("127.0.0.1:0", bus.clone(), control.clone())
                    .await
                    .map_err(|e| SimError::Mock("socketcand", e.to_string()))?;
            Some(SocketcandMock { address: addr, control, _task: AbortOnDrop(task) })
        }
    };
    Ok(RobotMocks { lidar, imu, imu_bad, bus, drives, socketcand, lidar_pipe, imu_pipe })
}

impl RobotMocks {
    /// Where the robot finds these mocks.
    #[must_use]
    pub fn overrides(&self) -> DeviceOverrides {
        DeviceOverrides {
            lidar: Some(("127.0.0.1".to_owned(), self.lidar.port())),
            imu_path: Some(self.imu.tty_path().display().to_string()),
            can: Some(match &self.socketcand {
                Some(s) => CanLink::Socketcand { address: s.address.to_string(), channel: "can0".into() },
                None => CanLink::InProcess(self.bus.clone()),
            }),
            lidar_stream: self.lidar_pipe.clone().map(|c| {
                StreamConnector(Arc::new(move || {
                    let c = c.clone();
                    Box::pin(async move { c.connect().await })
                }))
            }),
            imu_stream: self.imu_pipe.clone().map(|c| {
                StreamConnector(Arc::new(move || {
                    let c = c.clone();
                    Box::pin(async move { c.connect().await })
                }))
            }),
        }
    }
}

/// The world's IMU motion, with bad values on demand: well-framed packets whose yaw rate is NaN
/// or beyond the gyro's range, alternately.
#[derive(Debug)]
struct BadValues {
    inner: WorldImu,
    left: Arc<std::sync::atomic::AtomicU32>,
}

impl hil_mocks::lpms::MotionSource for BadValues {
    fn motion_at(&mut self, t_s: f64) -> hil_mocks::lpms::Motion {
        let mut m = self.inner.motion_at(t_s);
        let n = self.left.load(std::sync::atomic::Ordering::Relaxed);
        if n > 0 {
            self.left.store(n - 1, std::sync::atomic::Ordering::Relaxed);
            m.angular_velocity_radps[2] = if n.is_multiple_of(2) { f64::NAN } else { 1.0e3 };
        }
        m
    }
}

/// The devices every robot has.
pub const DEVICES: [Device; 6] =
    [Device::Lidar, Device::Imu, Device::CanBus, Device::Drives, Device::Odometry, Device::Safety];
