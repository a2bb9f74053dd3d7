//! `robot-<id>.toml`: one robot's body, kinematics, limits and devices.

use serde::Deserialize;

use super::value::{Backoff, Count, Finite, Millis, Positive};
use super::{ConfigFileType, Violation, rule};
use crate::geometry::Polygon;
use crate::se2::Se2;

/// A robot's name: 1–32 characters of `a-z`, `0-9` and `-`, starting with a letter. It appears in
/// file names, log fields and network keys (`fleet/<id>/scan`), hence the narrow alphabet.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Hash, Deserialize)]
#[serde(try_from = "String")]
pub struct RobotId(String);

impl RobotId {
    pub fn new(id: &str) -> Result<Self, String> {
        let ok_chars = id.chars().all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-');
        let starts = id.chars().next().is_some_and(|c| c.is_ascii_lowercase());
        if (1..=32).contains(&id.len()) && ok_chars && starts {
            Ok(RobotId(id.to_owned()))
        } else {
            Err(format!("must be 1-32 characters of a-z, 0-9 and '-', starting with a letter (got `{id}`)"))
        }
    }

    #[must_use]
    pub fn as_str(&self) -> &str {
        &self.0
    }
}

impl TryFrom<String> for RobotId {
    type Error = String;
    fn try_from(id: String) -> Result<Self, String> {
        RobotId::new(&id)
    }
}

impl std::fmt::Display for RobotId {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

/// One robot (paper Table 3 for the values of the paper's platform).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RobotConfig {
    pub id: RobotId,
    pub chassis: ChassisConfig,
    pub kinematics: KinematicsConfig,
    /// `T_L^B`: the LiDAR frame in the base frame.
    pub lidar_mount: MountConfig,
    pub limits: MotionLimits,
    pub safety: SafetyConfig,
    pub devices: DevicesConfig,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ChassisConfig {
    /// Outline at scan height, in the base frame, metres, counter-clockwise.
    pub outline_m: Polygon,
}

#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct KinematicsConfig {
    pub wheel_radius_m: Positive,
    /// Distance between the two wheels' contact points.
    pub track_width_m: Positive,
}

/// A sensor's mounting pose in the base frame.
#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MountConfig {
    pub x_m: Finite,
    pub y_m: Finite,
    pub yaw_deg: Finite,
}

impl MountConfig {
    /// The mounting pose as a transform (sensor frame → base frame).
    #[must_use]
    pub fn to_se2(&self) -> Se2 {
        Se2::from_degrees(self.x_m.get(), self.y_m.get(), self.yaw_deg.get())
    }
}

/// Motion limits every robot enforces on itself, whatever it is told (spec §8).
#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MotionLimits {
    pub max_speed_mps: Positive,
    pub max_accel_mps2: Positive,
    pub max_yaw_rate_radps: Positive,
}

#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SafetyConfig {
    /// No fresh velocity command for this long → ramp to zero at the acceleration limit.
    pub command_timeout_ms: Millis,
}

/// Whether a device is the real hardware or a mock device served from the simulated world. The
/// driver is the same either way; only the far end of its transport changes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum DeviceSource {
    Real,
    Mock,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DevicesConfig {
    pub lidar: LidarConfig,
    pub can: CanConfig,
    pub drives: DrivesConfig,
    pub imu: ImuConfig,
}

/// SOPAS dialect: detect it, or insist on CoLa-A (ASCII) or CoLa-B (binary).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
pub enum LidarDialect {
    #[serde(rename = "auto")]
    Auto,
    A,
    B,
}

/// The SOPAS start-up sequence: the ROS `sick_tim` driver's short one, or SICK's `sick_scan_xd` one.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LidarStartup {
    Minimal,
    Full,
}

/// The SICK TiM551 on TCP (devices.md §1).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LidarConfig {
    pub source: DeviceSource,
    pub host: String,
    pub port: u16,
    pub dialect: LidarDialect,
    pub startup: LidarStartup,
    /// How long to wait for the reply to one command.
    pub reply_timeout_ms: Millis,
    /// No scan for this long while streaming → reconnect and run the start-up again.
    pub scan_timeout_ms: Millis,
    pub reconnect: Backoff,
}

/// How the CAN bus is reached.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(tag = "kind", rename_all = "kebab-case", deny_unknown_fields)]
pub enum CanTransport {
    /// Linux SocketCAN (the robot).
    Socketcan { interface: String },
    /// CAN over TCP, the `socketcand` daemon's protocol.
    Socketcand { address: String, channel: String },
    /// The in-process bus (simulation and tests).
    InProcess,
}

/// A CANopen node id, 1..=127.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Deserialize)]
#[serde(try_from = "i64")]
pub struct NodeId(u8);

impl NodeId {
    pub fn new(id: i64) -> Result<Self, String> {
        match u8::try_from(id) {
            Ok(v) if (1..=127).contains(&v) => Ok(NodeId(v)),
            _ => Err(format!("must be a CANopen node id in 1..=127 (got {id})")),
        }
    }

    #[must_use]
    pub fn get(self) -> u8 {
        self.0
    }
}

impl TryFrom<i64> for NodeId {
    type Error = String;
    fn try_from(id: i64) -> Result<Self, String> {
        NodeId::new(id)
    }
}

/// The CAN bus and the CANopen master on it (devices.md §2).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CanConfig {
    pub source: DeviceSource,
    pub transport: CanTransport,
    /// The master's own node id (its heartbeat is `0x700 + id`; the drives watch it).
    pub master_node_id: NodeId,
    /// The master's heartbeat producer period.
    pub master_heartbeat_ms: Millis,
    /// SYNC period: both wheels' targets apply together on each SYNC.
    pub sync_period_ms: Millis,
    pub sdo_timeout_ms: Millis,
    /// Longest wait for a drive's boot-up message after a reset.
    pub boot_timeout_ms: Millis,
    pub reconnect: Backoff,
}

/// What a drive does when it loses the master (object 0x6007, abort connection option code).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CommLossReaction {
    /// 1: fault signal.
    Fault,
    /// 2: disable voltage.
    DisableVoltage,
    /// 3: quick stop.
    QuickStop,
}

impl CommLossReaction {
    /// The value written to 0x6007.
    #[must_use]
    pub fn code(self) -> i16 {
        match self {
            CommLossReaction::Fault => 1,
            CommLossReaction::DisableVoltage => 2,
            CommLossReaction::QuickStop => 3,
        }
    }
}

/// One wheel drive.
#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DriveConfig {
    pub node_id: NodeId,
    /// The motor is mounted mirrored: positive drive velocity turns the wheel backwards.
    pub inverted: bool,
}

/// The two TECO wheel drives (CiA 402, profile velocity). The drive-specific values the research
/// could not pin down are all here, never constants in code.
#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DrivesConfig {
    pub left: DriveConfig,
    pub right: DriveConfig,
    /// Encoder counts per motor revolution (after quadrature).
    pub encoder_counts_per_rev: Count,
    /// Motor revolutions per wheel revolution.
    pub gear_ratio: Positive,
    /// Drive velocity units (0x60FF, 0x606C) per motor revolution per second.
    pub velocity_units_per_rps: Positive,
    /// Each drive's heartbeat producer period (0x1017).
    pub heartbeat_producer_ms: Millis,
    /// The master declares a drive lost after this long without its heartbeat.
    pub heartbeat_consumer_ms: Millis,
    /// Each drive stops (see `comm_loss_reaction`) after this long without the master's heartbeat (0x1016).
    pub master_consumer_ms: Millis,
    pub comm_loss_reaction: CommLossReaction,
    /// Longest wait for a drive to reach Operation enabled (or to leave Fault after a reset).
    pub enable_timeout_ms: Millis,
    /// How often 0x6061 is read back to confirm profile velocity mode before giving up.
    pub mode_confirm_attempts: Count,
    /// Wheel-surface deceleration of a quick stop (0x6085), m/s²: an emergency stop, so at least the
    /// normal acceleration limit.
    pub quick_stop_decel_mps2: Positive,
}

/// LPBUS data encoding.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ImuDataMode {
    Float,
    Int16,
}

/// The LPMS-B2 IMU on a serial port (devices.md §3).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImuConfig {
    pub source: DeviceSource,
    /// Serial path: a UART, an RFCOMM tty (`/dev/rfcomm0`) or a pty.
    pub path: String,
    pub baud: u32,
    /// Stream rate; the sensor offers 5, 10, 25, 50, 100, 200, 400 and 800 Hz.
    pub stream_hz: u32,
    /// The sensor's LPBUS id (replies carry it; commands are sent to it).
    pub imu_id: u16,
    pub data_mode: ImuDataMode,
    pub reply_timeout_ms: Millis,
    /// No data packet for this long while streaming → reopen the port.
    pub data_timeout_ms: Millis,
    pub reconnect: Backoff,
}

/// Stream rates the LPMS-B2 supports (config register bits 0–2).
pub const IMU_STREAM_RATES_HZ: [u32; 8] = [5, 10, 25, 50, 100, 200, 400, 800];
/// UART rates the LP sensors support.
pub const IMU_BAUD_RATES: [u32; 7] = [19_200, 38_400, 57_600, 115_200, 230_400, 460_800, 921_600];

impl ConfigFileType for RobotConfig {
    fn validate(&self) -> Result<(), Violation> {
        let d = &self.devices;
        rule(!d.lidar.host.trim().is_empty(), "devices.lidar.host", "must not be empty")?;
        rule(d.lidar.port != 0, "devices.lidar.port", "must be a TCP port in 1..=65535 (got 0)")?;
        rule(
            d.lidar.scan_timeout_ms.ms() >= 200,
            "devices.lidar.scan_timeout_ms",
            format!(
                "must be at least 200 ms (three scan periods at 15 Hz) (got {} ms)",
                d.lidar.scan_timeout_ms.ms()
            ),
        )?;
        d.lidar.reconnect.check("devices.lidar.reconnect")?;

        match &d.can.transport {
            CanTransport::Socketcan { interface } => rule(
                !interface.is_empty() && interface.len() <= 15,
                "devices.can.transport.interface",
                format!("must be a network interface name of 1-15 characters (got `{interface}`)"),
            )?,
            CanTransport::Socketcand { address, channel } => {
                let port_ok = address
                    .rsplit_once(':')
                    .is_some_and(|(host, port)| !host.is_empty() && port.parse::<u16>().is_ok_and(|p| p > 0));
                rule(
                    port_ok,
                    "devices.can.transport.address",
                    format!("must be host:port (got `{address}`)"),
                )?;
                rule(!channel.is_empty(), "devices.can.transport.channel", "must not be empty")?;
            }
            CanTransport::InProcess => {}
        }
        d.can.reconnect.check("devices.can.reconnect")?;

        let dr = &d.drives;
        rule(
            dr.left.node_id != dr.right.node_id,
            "devices.drives.right.node_id",
            format!("must differ from devices.drives.left.node_id (both are {})", dr.left.node_id.get()),
        )?;
        for (side, drive) in [("left", dr.left), ("right", dr.right)] {
            rule(
                drive.node_id != d.can.master_node_id,
                format!("devices.drives.{side}.node_id"),
                format!("must differ from devices.can.master_node_id (both are {})", drive.node_id.get()),
            )?;
        }
        rule(
            dr.heartbeat_consumer_ms > dr.heartbeat_producer_ms,
            "devices.drives.heartbeat_consumer_ms",
            format!(
                "must exceed devices.drives.heartbeat_producer_ms, or every heartbeat would arrive late \
                 ({} ms <= {} ms)",
                dr.heartbeat_consumer_ms.ms(),
                dr.heartbeat_producer_ms.ms()
            ),
        )?;
        rule(
            dr.master_consumer_ms > d.can.master_heartbeat_ms,
            "devices.drives.master_consumer_ms",
            format!(
                "must exceed devices.can.master_heartbeat_ms, or every heartbeat would arrive late \
                 ({} ms <= {} ms)",
                dr.master_consumer_ms.ms(),
                d.can.master_heartbeat_ms.ms()
            ),
        )?;
        rule(
            dr.master_consumer_ms.ms() <= u32::from(u16::MAX),
            "devices.drives.master_consumer_ms",
            format!("must fit the 16-bit time of object 0x1016 (got {} ms)", dr.master_consumer_ms.ms()),
        )?;
        rule(
            dr.heartbeat_producer_ms.ms() <= u32::from(u16::MAX),
            "devices.drives.heartbeat_producer_ms",
            format!("must fit the 16-bit object 0x1017 (got {} ms)", dr.heartbeat_producer_ms.ms()),
        )?;

        rule(
            dr.quick_stop_decel_mps2 >= self.limits.max_accel_mps2,
            "devices.drives.quick_stop_decel_mps2",
            format!(
                "must be at least limits.max_accel_mps2: a quick stop must not brake more gently than normal driving \
                 ({} < {} m/s²)",
                dr.quick_stop_decel_mps2.get(),
                self.limits.max_accel_mps2.get()
            ),
        )?;

        let imu = &d.imu;
        rule(!imu.path.trim().is_empty(), "devices.imu.path", "must not be empty")?;
        rule(
            IMU_BAUD_RATES.contains(&imu.baud),
            "devices.imu.baud",
            format!("must be one of {IMU_BAUD_RATES:?} (got {})", imu.baud),
        )?;
        rule(
            IMU_STREAM_RATES_HZ.contains(&imu.stream_hz),
            "devices.imu.stream_hz",
            format!("must be one of {IMU_STREAM_RATES_HZ:?} (got {})", imu.stream_hz),
        )?;
        let min_data_timeout_ms = 3000u64.div_ceil(u64::from(imu.stream_hz));
        rule(
            u64::from(imu.data_timeout_ms.ms()) >= min_data_timeout_ms,
            "devices.imu.data_timeout_ms",
            format!(
                "must cover at least three stream periods at {} Hz ({min_data_timeout_ms} ms) (got {} ms)",
                imu.stream_hz,
                imu.data_timeout_ms.ms()
            ),
        )?;
        imu.reconnect.check("devices.imu.reconnect")?;

        // The safety watchdog must be able to notice a missing command before the robot has travelled
        // far: a timeout beyond one second is a misconfiguration, not a tuning choice.
        rule(
            self.safety.command_timeout_ms.ms() <= 1000,
            "safety.command_timeout_ms",
            format!("must be at most 1000 ms (got {} ms)", self.safety.command_timeout_ms.ms()),
        )?;
        Ok(())
    }
}
