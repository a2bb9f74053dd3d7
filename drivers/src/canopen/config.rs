//! `[devices.can]` and `[devices.drives]` of a robot file, deserialised straight into the types the
//! bus, the master and the differential-drive layer use (no copy of them elsewhere). Each rule is
//! checked with the key path it concerns, so a bad file is reported at the key and line.

use serde::Deserialize;

use amr_settings::value::Backoff;
use amr_settings::{DeviceSource, Violation, join, rule};

use super::frame::NodeId;

/// How the CAN bus is reached.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(tag = "kind", rename_all = "kebab-case", deny_unknown_fields)]
pub enum BusTransport {
    /// Linux SocketCAN (the robot).
    Socketcan { interface: String },
    /// CAN over TCP, the `socketcand` daemon's protocol.
    Socketcand { address: String, channel: String },
    /// The in-process bus (simulation and tests).
    InProcess,
}

/// The CAN bus and the CANopen master on it: `[devices.can]` (devices.md §2).
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BusConfig {
    pub source: DeviceSource,
    pub transport: BusTransport,
    /// The master's own node id (its heartbeat is `0x700 + id`; the drives watch it via 0x1016).
    #[serde(deserialize_with = "node_id")]
    pub master_node_id: NodeId,
    /// The master's heartbeat producer period.
    #[serde(deserialize_with = "amr_settings::value::ms")]
    pub master_heartbeat_ms: u32,
    /// SYNC period: both wheels' targets apply together on each SYNC.
    #[serde(deserialize_with = "amr_settings::value::ms")]
    pub sync_period_ms: u32,
    /// Per-request (and per-segment) SDO timeout (ros2_canopen #194: make it configurable).
    #[serde(deserialize_with = "amr_settings::value::ms")]
    pub sdo_timeout_ms: u32,
    /// Longest wait for a drive's boot-up message after a reset.
    #[serde(deserialize_with = "amr_settings::value::ms")]
    pub boot_timeout_ms: u32,
    /// Reconnecting the bus after its link fails.
    pub reconnect: Backoff,
}

impl Default for BusConfig {
    /// The shipped robot files' values, on the in-process bus.
    fn default() -> Self {
        BusConfig {
            source: DeviceSource::Mock,
            transport: BusTransport::InProcess,
            master_node_id: 127,
            master_heartbeat_ms: 100,
            sync_period_ms: 20,
            sdo_timeout_ms: 500,
            boot_timeout_ms: 5000,
            reconnect: Backoff {
                initial: std::time::Duration::from_millis(100),
                max: std::time::Duration::from_secs(5),
            },
        }
    }
}

/// A CANopen node id, 1..=127 (CiA 301 §7.3.2).
pub fn node_id<'de, D: serde::Deserializer<'de>>(deserializer: D) -> Result<NodeId, D::Error> {
    let id = i64::deserialize(deserializer)?;
    match u8::try_from(id) {
        Ok(v) if (1..=127).contains(&v) => Ok(v),
        _ => Err(serde::de::Error::custom(format!("must be a CANopen node id in 1..=127 (got {id})"))),
    }
}

impl BusConfig {
    /// The bus's own rules; `path` is where the section stands (`devices.can`).
    pub fn validate(&self, path: &str) -> Result<(), Violation> {
        match &self.transport {
            BusTransport::Socketcan { interface } => rule(
                !interface.is_empty() && interface.len() <= 15,
                join(path, "transport.interface"),
                format!("must be a network interface name of 1-15 characters (got `{interface}`)"),
            )?,
            BusTransport::Socketcand { address, channel } => {
                let port_ok = address
                    .rsplit_once(':')
                    .is_some_and(|(host, port)| !host.is_empty() && port.parse::<u16>().is_ok_and(|p| p > 0));
                rule(
                    port_ok,
                    join(path, "transport.address"),
                    format!("must be host:port (got `{address}`)"),
                )?;
                rule(!channel.is_empty(), join(path, "transport.channel"), "must not be empty")?;
            }
            BusTransport::InProcess => {}
        }
        self.reconnect.check(&join(path, "reconnect"))
    }
}

/// Reaction of a drive to a communication loss, object 0x6007 (CiA 402). A robot file spells it
/// `fault | disable-voltage | quick-stop`; "no action" is not offered there.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CommLossReaction {
    /// 0: no action.
    #[serde(skip)]
    None,
    /// 1: fault signal.
    Fault,
    /// 2: disable voltage.
    DisableVoltage,
    /// 3: quick stop.
    QuickStop,
}

impl CommLossReaction {
    /// The 0x6007 value.
    pub fn code(self) -> i16 {
        match self {
            CommLossReaction::None => 0,
            CommLossReaction::Fault => 1,
            CommLossReaction::DisableVoltage => 2,
            CommLossReaction::QuickStop => 3,
        }
    }
}

/// One wheel's drive: `left`/`right` of `[devices.drives]`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WheelDriveConfig {
    /// The drive's node id.
    #[serde(deserialize_with = "node_id")]
    pub node_id: NodeId,
    /// The motor is mounted mirrored: positive drive velocity moves this wheel backwards.
    pub inverted: bool,
}

/// The two TECO wheel drives (CiA 402, profile velocity): `[devices.drives]` of a robot file. The
/// drive-specific values the research could not pin down are all here, never constants in code.
/// Cross-field rules: [`DrivesConfig::validate`].
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DrivesConfig {
    /// Left wheel.
    pub left: WheelDriveConfig,
    /// Right wheel.
    pub right: WheelDriveConfig,
    /// Encoder counts per motor revolution, after quadrature (0x6064 units).
    #[serde(deserialize_with = "amr_settings::value::count")]
    pub encoder_counts_per_rev: u32,
    /// Motor revolutions per wheel revolution.
    #[serde(deserialize_with = "amr_settings::value::positive")]
    pub gear_ratio: f64,
    /// 0x60FF/0x606C units per motor revolution per second.
    #[serde(deserialize_with = "amr_settings::value::positive")]
    pub velocity_units_per_rps: f64,
    /// Each drive's heartbeat producer period, written to its 0x1017 (16 bits).
    #[serde(deserialize_with = "amr_settings::value::ms")]
    pub heartbeat_producer_ms: u32,
    /// The master declares a drive lost after this long without its heartbeat.
    #[serde(deserialize_with = "amr_settings::value::ms")]
    pub heartbeat_consumer_ms: u32,
    /// Each drive stops (see `comm_loss_reaction`) after this long without the master's heartbeat,
    /// written to its 0x1016 (16 bits).
    #[serde(deserialize_with = "amr_settings::value::ms")]
    pub master_consumer_ms: u32,
    /// Each drive's 0x6007.
    pub comm_loss_reaction: CommLossReaction,
    /// Longest wait for a drive to reach Operation enabled (or to leave Fault after a reset).
    #[serde(deserialize_with = "amr_settings::value::ms")]
    pub enable_timeout_ms: u32,
    /// How often 0x6061 is read back to confirm profile velocity mode before giving up
    /// (python-canopen #131: it may lag).
    #[serde(deserialize_with = "amr_settings::value::count")]
    pub mode_confirm_attempts: u32,
    /// Wheel-surface deceleration of a quick stop (0x6085), m/s²: an emergency stop, so at least the
    /// robot's normal acceleration limit.
    #[serde(deserialize_with = "amr_settings::value::positive")]
    pub quick_stop_decel_mps2: f64,
    /// The bit of either drive's digital inputs (0x60FD, 0–31; CiA 402 leaves 16–31 to the
    /// manufacturer) that the robot's e-stop chain is wired to, if any: the master maps 0x60FD into
    /// TPDO2 and the robot latches its e-stop when the input reads pressed.
    #[serde(default)]
    pub estop_input_bit: Option<u8>,
    /// The e-stop input reads 0 when pressed (a normally-closed chain: a broken wire stops the
    /// robot too). Default true.
    #[serde(default = "yes")]
    pub estop_input_active_low: bool,
}

fn yes() -> bool {
    true
}

impl DrivesConfig {
    /// The drives' rules, some of them against the bus they are on; `path` and `bus_path` are where
    /// the two sections stand (`devices.drives`, `devices.can`).
    pub fn validate(&self, path: &str, bus: &BusConfig, bus_path: &str) -> Result<(), Violation> {
        let key = |k: &str| join(path, k);
        rule(
            self.left.node_id != self.right.node_id,
            key("right.node_id"),
            format!("must differ from {} (both are {})", key("left.node_id"), self.left.node_id),
        )?;
        for (side, drive) in [("left", self.left), ("right", self.right)] {
            rule(
                drive.node_id != bus.master_node_id,
                key(&format!("{side}.node_id")),
                format!("must differ from {} (both are {})", join(bus_path, "master_node_id"), drive.node_id),
            )?;
        }
        rule(
            self.heartbeat_consumer_ms > self.heartbeat_producer_ms,
            key("heartbeat_consumer_ms"),
            format!(
                "must exceed {}, or every heartbeat would arrive late ({} ms <= {} ms)",
                key("heartbeat_producer_ms"),
                self.heartbeat_consumer_ms,
                self.heartbeat_producer_ms
            ),
        )?;
        rule(
            self.master_consumer_ms > bus.master_heartbeat_ms,
            key("master_consumer_ms"),
            format!(
                "must exceed {}, or every heartbeat would arrive late ({} ms <= {} ms)",
                join(bus_path, "master_heartbeat_ms"),
                self.master_consumer_ms,
                bus.master_heartbeat_ms
            ),
        )?;
        rule(
            self.master_consumer_ms <= u32::from(u16::MAX),
            key("master_consumer_ms"),
            format!("must fit the 16-bit time of object 0x1016 (got {} ms)", self.master_consumer_ms),
        )?;
        rule(
            self.heartbeat_producer_ms <= u32::from(u16::MAX),
            key("heartbeat_producer_ms"),
            format!("must fit the 16-bit object 0x1017 (got {} ms)", self.heartbeat_producer_ms),
        )?;
        rule(
            self.estop_input_bit.is_none_or(|b| b <= 31),
            key("estop_input_bit"),
            format!("must be a bit of the 32-bit object 0x60FD, 0..=31 (got {:?})", self.estop_input_bit),
        )
    }

    /// Whether digital inputs `bits` (0x60FD) show the e-stop pressed (false when no input is
    /// configured).
    #[must_use]
    pub fn estop_pressed(&self, bits: u32) -> bool {
        self.estop_input_bit.is_some_and(|b| {
            let high = bits.checked_shr(u32::from(b)).is_some_and(|v| v & 1 == 1);
            high != self.estop_input_active_low
        })
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "tests")]

    use super::*;

    /// `[devices.can]` and `[devices.drives]` as in a robot file.
    #[derive(Debug, Deserialize)]
    #[serde(deny_unknown_fields)]
    struct File {
        can: BusConfig,
        drives: DrivesConfig,
    }

    impl amr_settings::ConfigFileType for File {
        fn validate(&self) -> Result<(), Violation> {
            self.can.validate("can")?;
            self.drives.validate("drives", &self.can, "can")
        }
    }

    const GOOD: &str = r#"
[can]
source = "real"
transport = { kind = "socketcand", address = "127.0.0.1:29536", channel = "can0" }
master_node_id = 127
master_heartbeat_ms = 100
sync_period_ms = 20
sdo_timeout_ms = 100
boot_timeout_ms = 2000
reconnect = { initial_ms = 100, max_ms = 5000 }
[drives]
left = { node_id = 1, inverted = false }
right = { node_id = 2, inverted = true }
encoder_counts_per_rev = 10000
gear_ratio = 20.0
velocity_units_per_rps = 10000.0
heartbeat_producer_ms = 100
heartbeat_consumer_ms = 300
master_consumer_ms = 300
comm_loss_reaction = "quick-stop"
enable_timeout_ms = 1000
mode_confirm_attempts = 5
quick_stop_decel_mps2 = 0.5
"#;

    #[test]
    fn the_sections_deserialise_into_the_drivers_types() {
        let f: File = amr_settings::parse_file("robot-a.toml", GOOD).unwrap();
        assert_eq!(
            f.can.transport,
            BusTransport::Socketcand { address: "127.0.0.1:29536".into(), channel: "can0".into() }
        );
        assert_eq!((f.can.master_node_id, f.can.sync_period_ms), (127, 20));
        assert_eq!((f.drives.left.node_id, f.drives.right.inverted), (1, true));
        assert_eq!(f.drives.comm_loss_reaction, CommLossReaction::QuickStop);
        assert_eq!((f.drives.enable_timeout_ms, f.drives.mode_confirm_attempts), (1000, 5));
    }

    #[test]
    fn node_ids_are_checked_against_each_other_and_the_range() {
        let err = |from: &str, to: &str| {
            amr_settings::parse_file::<File>("robot-a.toml", &GOOD.replace(from, to)).unwrap_err().to_string()
        };
        assert_eq!(
            err("left = { node_id = 1", "left = { node_id = 128"),
            "robot-a.toml:12: drives.left.node_id: must be a CANopen node id in 1..=127 (got 128)"
        );
        assert_eq!(
            err("right = { node_id = 2", "right = { node_id = 1"),
            "robot-a.toml:13: drives.right.node_id: must differ from drives.left.node_id (both are 1)"
        );
        assert_eq!(
            err("master_node_id = 127", "master_node_id = 2"),
            "robot-a.toml:13: drives.right.node_id: must differ from can.master_node_id (both are 2)"
        );
        assert_eq!(
            err("\"quick-stop\"", "\"none\""),
            "robot-a.toml:20: drives.comm_loss_reaction: unknown variant `none`, expected one of `fault`, \
             `disable-voltage`, `quick-stop`"
        );
    }

    #[test]
    fn the_estop_input_is_a_bit_of_0x60fd_normally_closed_by_default() {
        let f: File = amr_settings::parse_file("robot-a.toml", GOOD).unwrap();
        assert_eq!(f.drives.estop_input_bit, None);
        assert!(!f.drives.estop_pressed(0), "no input configured: never pressed");
        let wired =
            GOOD.replace("quick_stop_decel_mps2 = 0.5", "quick_stop_decel_mps2 = 0.5\nestop_input_bit = 16");
        let f: File = amr_settings::parse_file("robot-a.toml", &wired).unwrap();
        assert!(f.drives.estop_input_active_low);
        assert!(!f.drives.estop_pressed(1 << 16), "the chain closed");
        assert!(f.drives.estop_pressed(0), "pressed, or a broken wire");
        assert!(f.drives.estop_pressed(0xFFFE_FFFF), "other inputs do not matter");
        let high =
            wired.replace("estop_input_bit = 16", "estop_input_bit = 16\nestop_input_active_low = false");
        let f: File = amr_settings::parse_file("robot-a.toml", &high).unwrap();
        assert!(f.drives.estop_pressed(1 << 16) && !f.drives.estop_pressed(0));
        let e = amr_settings::parse_file::<File>("robot-a.toml", &wired.replace("= 16", "= 32")).unwrap_err();
        assert_eq!(
            e.to_string(),
            "robot-a.toml:24: drives.estop_input_bit: must be a bit of the 32-bit object 0x60FD, 0..=31 (got Some(32))"
        );
    }
}
