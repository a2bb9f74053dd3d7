//! Our own exact channels: what the server received (`/amr/uplink`), what fusion produced
//! (`/amr/fused`), what AMCL estimated (`/amr/estimates`) and the fusion status (`/amr/status`), as
//! JSON that gives every `f64` back bit for bit (serde_json's `float_roundtrip`: shortest
//! round-trip output, correctly rounded parsing). Invalid beams (NaN) travel as `null`.
//!
//! Every record carries [`VERSION`]; a reader refuses another version rather than guess. Decoding
//! never panics: bad bytes are an [`WireError`].

use std::sync::Arc;

use amr_actors::messages::{
    Device, DisarmReason, Health, HealthReport, OdomMsg, SafetyState, ScanMsg, Uplink,
};
use amr_actors::server::ports::{Anchored, Estimate, EstimateSource, FusedFrame, FusionStatus};
use amr_core::config::Configuration;
use amr_core::scan::Scan;
use amr_core::se2::Se2;
use serde::{Deserialize, Serialize};

/// Version of the exact encodings; bumped on any change of their shape.
pub const VERSION: u32 = 1;

/// Schema names of the exact channels (schema encoding "jsonschema", message encoding "json").
pub const UPLINK_SCHEMA: &str = "amr.Uplink";
pub const FUSED_SCHEMA: &str = "amr.FusedFrame";
pub const ESTIMATE_SCHEMA: &str = "amr.Estimate";
pub const STATUS_SCHEMA: &str = "amr.FusionStatus";

/// Why a record could not be decoded.
#[derive(Debug, thiserror::Error)]
pub enum WireError {
    #[error("not a valid record: {0}")]
    Json(#[from] serde_json::Error),
    #[error("record version {found}, this build reads {VERSION}")]
    Version { found: u32 },
    #[error("unknown {what} `{value}`")]
    Unknown { what: &'static str, value: String },
}

fn pose(p: &Se2) -> [f64; 3] {
    [p.x, p.y, p.theta]
}

fn se2(p: [f64; 3]) -> Se2 {
    Se2 { x: p[0], y: p[1], theta: p[2] }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct ScanRec {
    angle_min_rad: f64,
    angle_increment_rad: f64,
    range_min_m: f64,
    range_max_m: f64,
    /// `null` for an invalid beam.
    ranges_m: Vec<Option<f64>>,
}

impl ScanRec {
    fn of(s: &Scan) -> Self {
        ScanRec {
            angle_min_rad: s.angle_min_rad,
            angle_increment_rad: s.angle_increment_rad,
            range_min_m: s.range_min_m,
            range_max_m: s.range_max_m,
            ranges_m: s.ranges_m().iter().map(|r| r.is_finite().then_some(*r)).collect(),
        }
    }

    /// `Scan::new` keeps every valid range as it is and makes the rest NaN: the same scan.
    fn scan(self) -> Scan {
        Scan::new(
            self.angle_min_rad,
            self.angle_increment_rad,
            self.range_min_m,
            self.range_max_m,
            self.ranges_m.into_iter().map(|r| r.unwrap_or(f64::NAN)).collect(),
        )
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
enum UplinkRec {
    Scan { robot: String, seq: u64, stamp_s: f64, sent_s: f64, odom: [f64; 3], scan: ScanRec },
    Odom { robot: String, seq: u64, stamp_s: f64, pose: [f64; 3], twist: [f64; 2], gyro: bool },
    Health { robot: String, seq: u64, stamp_s: f64, device: String, health: String, detail: String },
    Safety { robot: String, seq: u64, stamp_s: f64, state: String },
}

/// One message as the server received it: `rx_s` is the recorder's reading of the fleet clock when
/// the message came off the server's uplink port (the fusion actor's own reading in virtual time;
/// within scheduling jitter of it in real time).
#[derive(Debug, Clone)]
pub struct Received {
    pub rx_s: f64,
    pub msg: Uplink,
}

#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct UplinkEnvelope {
    v: u32,
    rx_s: f64,
    msg: UplinkRec,
}

pub(crate) fn device_name(d: Device) -> &'static str {
    match d {
        Device::Lidar => "lidar",
        Device::CanBus => "can_bus",
        Device::Drives => "drives",
        Device::Imu => "imu",
        Device::Odometry => "odometry",
        Device::Safety => "safety",
        Device::Link => "link",
    }
}

fn device_of(s: &str) -> Result<Device, WireError> {
    Ok(match s {
        "lidar" => Device::Lidar,
        "can_bus" => Device::CanBus,
        "drives" => Device::Drives,
        "imu" => Device::Imu,
        "odometry" => Device::Odometry,
        "safety" => Device::Safety,
        "link" => Device::Link,
        _ => return Err(WireError::Unknown { what: "device", value: s.to_owned() }),
    })
}

pub(crate) fn health_name(h: Health) -> &'static str {
    match h {
        Health::Starting => "starting",
        Health::Ok => "ok",
        Health::Degraded => "degraded",
        Health::Lost => "lost",
        Health::Fault => "fault",
    }
}

fn health_of(s: &str) -> Result<Health, WireError> {
    Ok(match s {
        "starting" => Health::Starting,
        "ok" => Health::Ok,
        "degraded" => Health::Degraded,
        "lost" => Health::Lost,
        "fault" => Health::Fault,
        _ => return Err(WireError::Unknown { what: "health", value: s.to_owned() }),
    })
}

pub(crate) fn safety_name(s: SafetyState) -> &'static str {
    match s {
        SafetyState::Armed => "armed",
        SafetyState::EStop => "estop",
        SafetyState::Fault => "fault",
        SafetyState::Disarmed(DisarmReason::Startup) => "disarmed:startup",
        SafetyState::Disarmed(DisarmReason::Watchdog) => "disarmed:watchdog",
        SafetyState::Disarmed(DisarmReason::Requested) => "disarmed:requested",
        SafetyState::Disarmed(DisarmReason::EStopReset) => "disarmed:estop_reset",
        SafetyState::Disarmed(DisarmReason::DeviceLost) => "disarmed:device_lost",
    }
}

fn safety_of(s: &str) -> Result<SafetyState, WireError> {
    Ok(match s {
        "armed" => SafetyState::Armed,
        "estop" => SafetyState::EStop,
        "fault" => SafetyState::Fault,
        "disarmed:startup" => SafetyState::Disarmed(DisarmReason::Startup),
        "disarmed:watchdog" => SafetyState::Disarmed(DisarmReason::Watchdog),
        "disarmed:requested" => SafetyState::Disarmed(DisarmReason::Requested),
        "disarmed:estop_reset" => SafetyState::Disarmed(DisarmReason::EStopReset),
        "disarmed:device_lost" => SafetyState::Disarmed(DisarmReason::DeviceLost),
        _ => return Err(WireError::Unknown { what: "safety state", value: s.to_owned() }),
    })
}

pub fn configuration_name(c: Configuration) -> &'static str {
    match c {
        Configuration::T1 => "T1",
        Configuration::T2 => "T2",
        Configuration::T3 => "T3",
        Configuration::T4 => "T4",
    }
}

/// `T1`…`T4`.
pub fn configuration_of(s: &str) -> Result<Configuration, WireError> {
    Ok(match s {
        "T1" => Configuration::T1,
        "T2" => Configuration::T2,
        "T3" => Configuration::T3,
        "T4" => Configuration::T4,
        _ => return Err(WireError::Unknown { what: "configuration", value: s.to_owned() }),
    })
}

fn check(v: u32) -> Result<(), WireError> {
    if v == VERSION { Ok(()) } else { Err(WireError::Version { found: v }) }
}

/// Encode one received uplink message.
pub fn encode_uplink(rx_s: f64, msg: &Uplink) -> Result<Vec<u8>, WireError> {
    let msg = match msg {
        Uplink::Scan(s) => UplinkRec::Scan {
            robot: s.robot.clone(),
            seq: s.seq,
            stamp_s: s.stamp_s,
            sent_s: s.sent_s,
            odom: pose(&s.odom),
            scan: ScanRec::of(&s.scan),
        },
        Uplink::Odom { robot, msg } => UplinkRec::Odom {
            robot: robot.clone(),
            seq: msg.seq,
            stamp_s: msg.stamp_s,
            pose: pose(&msg.pose),
            twist: [msg.twist.0, msg.twist.1],
            gyro: msg.gyro,
        },
        Uplink::Health { robot, seq, stamp_s, report } => UplinkRec::Health {
            robot: robot.clone(),
            seq: *seq,
            stamp_s: *stamp_s,
            device: device_name(report.device).to_owned(),
            health: health_name(report.health).to_owned(),
            detail: report.detail.clone(),
        },
        Uplink::Safety { robot, seq, stamp_s, state } => UplinkRec::Safety {
            robot: robot.clone(),
            seq: *seq,
            stamp_s: *stamp_s,
            state: safety_name(*state).to_owned(),
        },
    };
    Ok(serde_json::to_vec(&UplinkEnvelope { v: VERSION, rx_s, msg })?)
}

/// Decode one received uplink message.
pub fn decode_uplink(bytes: &[u8]) -> Result<Received, WireError> {
    let e: UplinkEnvelope = serde_json::from_slice(bytes)?;
    check(e.v)?;
    let msg = match e.msg {
        UplinkRec::Scan { robot, seq, stamp_s, sent_s, odom, scan } => Uplink::Scan(ScanMsg {
            robot,
            seq,
            stamp_s,
            sent_s,
            scan: Arc::new(scan.scan()),
            odom: se2(odom),
        }),
        UplinkRec::Odom { robot, seq, stamp_s, pose, twist, gyro } => Uplink::Odom {
            robot,
            msg: OdomMsg { seq, stamp_s, pose: se2(pose), twist: (twist[0], twist[1]), gyro },
        },
        UplinkRec::Health { robot, seq, stamp_s, device, health, detail } => Uplink::Health {
            robot,
            seq,
            stamp_s,
            report: HealthReport { device: device_of(&device)?, health: health_of(&health)?, detail },
        },
        UplinkRec::Safety { robot, seq, stamp_s, state } => {
            Uplink::Safety { robot, seq, stamp_s, state: safety_of(&state)? }
        }
    };
    Ok(Received { rx_s: e.rx_s, msg })
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct AnchoredRec {
    map: [f64; 3],
    odom: [f64; 3],
    stamp_s: f64,
}

#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct EstimateRec {
    v: u32,
    /// "fused:T4" or "robot:0".
    source: String,
    stamp_s: f64,
    v_map: Option<[f64; 3]>,
    robots: Vec<Option<AnchoredRec>>,
}

/// The source as text: `fused:T1`…`fused:T4`, `robot:<index>`.
#[must_use]
pub fn source_name(s: EstimateSource) -> String {
    match s {
        EstimateSource::Fused(c) => format!("fused:{}", configuration_name(c)),
        EstimateSource::Robot(i) => format!("robot:{i}"),
    }
}

fn source_of(s: &str) -> Result<EstimateSource, WireError> {
    let bad = || WireError::Unknown { what: "estimate source", value: s.to_owned() };
    if let Some(c) = s.strip_prefix("fused:") {
        return Ok(EstimateSource::Fused(configuration_of(c)?));
    }
    let i = s.strip_prefix("robot:").ok_or_else(bad)?;
    i.parse().map(EstimateSource::Robot).map_err(|_| bad())
}

/// Encode an estimate.
pub fn encode_estimate(e: &Estimate) -> Result<Vec<u8>, WireError> {
    Ok(serde_json::to_vec(&EstimateRec {
        v: VERSION,
        source: source_name(e.source),
        stamp_s: e.stamp_s,
        v_map: e.v.as_ref().map(pose),
        robots: e
            .robots
            .iter()
            .map(|a| a.map(|a| AnchoredRec { map: pose(&a.map), odom: pose(&a.odom), stamp_s: a.stamp_s }))
            .collect(),
    })?)
}

/// Decode an estimate.
pub fn decode_estimate(bytes: &[u8]) -> Result<Estimate, WireError> {
    let e: EstimateRec = serde_json::from_slice(bytes)?;
    check(e.v)?;
    Ok(Estimate {
        source: source_of(&e.source)?,
        stamp_s: e.stamp_s,
        v: e.v_map.map(se2),
        robots: e
            .robots
            .into_iter()
            .map(|a| a.map(|a| Anchored { map: se2(a.map), odom: se2(a.odom), stamp_s: a.stamp_s }))
            .collect(),
    })
}

#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct FusedRec {
    v: u32,
    seq: u64,
    configuration: String,
    stamp_s: f64,
    oldest_stamp_s: f64,
    v_odom: [f64; 3],
    /// The virtual scan's points by count and digest: they are what the uplink gives again by
    /// replay, and at ~20 kB a frame they were the largest channel (the view is `/virtual/scan`).
    points: Option<PointsDigest>,
    /// Per robot: its base in V, its odometry pose at its scan.
    robots: Vec<([f64; 3], [f64; 3])>,
}

#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PointsDigest {
    pub n: usize,
    /// FNV-1a 64 over every coordinate's bits, little-endian, as 16 hex digits.
    pub fnv1a64: String,
}

/// What a fused frame holds that the estimates depend on (the stage times are left out: they are
/// wall-clock measurements, not results).
#[derive(Debug, Clone, PartialEq)]
pub struct FusedRecord {
    pub seq: u64,
    pub configuration: Configuration,
    pub stamp_s: f64,
    pub oldest_stamp_s: f64,
    pub v_odom: Se2,
    pub points: Option<Vec<[f64; 2]>>,
    pub robots: Vec<(Se2, Se2)>,
}

impl FusedRecord {
    #[must_use]
    pub fn of(f: &FusedFrame) -> Self {
        FusedRecord {
            seq: f.seq,
            configuration: f.configuration,
            stamp_s: f.stamp_s,
            oldest_stamp_s: f.oldest_stamp_s,
            v_odom: f.v_odom,
            points: f.points.as_ref().map(|p| p.as_ref().clone()),
            robots: f.robots.clone(),
        }
    }
}

/// FNV-1a, 64 bits (<http://www.isthe.com/chongo/tech/comp/fnv/>): offset basis 0xcbf29ce484222325,
/// prime 0x100000001b3.
fn digest(points: &[[f64; 2]]) -> PointsDigest {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for b in points.iter().flatten().flat_map(|c| c.to_bits().to_le_bytes()) {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x0100_0000_01b3);
    }
    PointsDigest { n: points.len(), fnv1a64: format!("{h:016x}") }
}

/// Encode a fused frame (its points as a [`PointsDigest`]).
pub fn encode_fused(f: &FusedRecord) -> Result<Vec<u8>, WireError> {
    Ok(serde_json::to_vec(&FusedRec {
        v: VERSION,
        seq: f.seq,
        configuration: configuration_name(f.configuration).to_owned(),
        stamp_s: f.stamp_s,
        oldest_stamp_s: f.oldest_stamp_s,
        v_odom: pose(&f.v_odom),
        points: f.points.as_deref().map(digest),
        robots: f.robots.iter().map(|(b, o)| (pose(b), pose(o))).collect(),
    })?)
}

/// A recorded fused frame: its points only by digest.
#[derive(Debug, Clone, PartialEq)]
pub struct FusedDigest {
    pub seq: u64,
    pub configuration: Configuration,
    pub stamp_s: f64,
    pub oldest_stamp_s: f64,
    pub v_odom: Se2,
    pub points: Option<PointsDigest>,
    pub robots: Vec<(Se2, Se2)>,
}

/// Decode a fused frame.
pub fn decode_fused(bytes: &[u8]) -> Result<FusedDigest, WireError> {
    let f: FusedRec = serde_json::from_slice(bytes)?;
    check(f.v)?;
    Ok(FusedDigest {
        seq: f.seq,
        configuration: configuration_of(&f.configuration)?,
        stamp_s: f.stamp_s,
        oldest_stamp_s: f.oldest_stamp_s,
        v_odom: se2(f.v_odom),
        points: f.points,
        robots: f.robots.into_iter().map(|(b, o)| (se2(b), se2(o))).collect(),
    })
}

#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct StatusRec {
    v: u32,
    /// "fusing" or "robot_lost".
    status: String,
    robot: Option<usize>,
}

/// Encode a fusion status change.
pub fn encode_status(s: FusionStatus) -> Result<Vec<u8>, WireError> {
    let (status, robot) = match s {
        FusionStatus::Fusing => ("fusing", None),
        FusionStatus::RobotLost(i) => ("robot_lost", Some(i)),
    };
    Ok(serde_json::to_vec(&StatusRec { v: VERSION, status: status.to_owned(), robot })?)
}

/// Decode a fusion status change.
pub fn decode_status(bytes: &[u8]) -> Result<FusionStatus, WireError> {
    let s: StatusRec = serde_json::from_slice(bytes)?;
    check(s.v)?;
    match (s.status.as_str(), s.robot) {
        ("fusing", None) => Ok(FusionStatus::Fusing),
        ("robot_lost", Some(i)) => Ok(FusionStatus::RobotLost(i)),
        _ => Err(WireError::Unknown { what: "fusion status", value: s.status }),
    }
}

/// A JSON schema for an exact channel: an object with its version; Foxglove shows the fields
/// as they are (the schema only names the type).
#[must_use]
pub fn schema(name: &str) -> String {
    serde_json::json!({
        "title": name,
        "description": format!("amr exact record, version {VERSION} (record/src/wire.rs)"),
        "type": "object",
        "properties": { "v": { "type": "integer", "const": VERSION } },
        "required": ["v"],
    })
    .to_string()
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used, reason = "tests")]
    use super::*;

    /// Finite doubles from all over the bit space, and awkward ones.
    fn doubles() -> Vec<f64> {
        let mut x: u64 = 0x9E37_79B9_7F4A_7C15;
        let mut v = vec![0.0, -0.0, 1e-310, -5e-324, f64::MAX, f64::MIN_POSITIVE, 0.1, 1.0 / 3.0];
        while v.len() < 4000 {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            let f = f64::from_bits(x);
            if f.is_finite() {
                v.push(f);
            }
        }
        v
    }

    #[test]
    fn every_double_comes_back_bit_for_bit() {
        for chunk in doubles().chunks(3) {
            let [x, y, t] = [chunk[0], chunk[1 % chunk.len()], chunk[2 % chunk.len()]];
            let e = Estimate {
                source: EstimateSource::Robot(1),
                stamp_s: x,
                v: Some(Se2 { x, y, theta: t }),
                robots: vec![
                    None,
                    Some(Anchored { map: Se2 { x: t, y, theta: x }, odom: Se2::IDENTITY, stamp_s: y }),
                ],
            };
            let back = decode_estimate(&encode_estimate(&e).unwrap()).unwrap();
            let bits = |e: &Estimate| {
                let v = e.v.unwrap();
                let a = e.robots[1].unwrap();
                [v.x, v.y, v.theta, e.stamp_s, a.map.x, a.map.y, a.map.theta, a.stamp_s].map(f64::to_bits)
            };
            assert_eq!(bits(&back), bits(&e));
            assert_eq!(back.robots[0], None);
        }
    }

    #[test]
    fn a_scan_with_invalid_beams_round_trips() {
        let scan = Scan::new(-2.35, 0.0174, 0.05, 10.0, vec![1.0, f64::NAN, 0.01, 3.3333333333333335, 11.0]);
        let msg = Uplink::Scan(ScanMsg {
            robot: "robot-a".into(),
            seq: 7,
            stamp_s: 12.345,
            sent_s: 12.35,
            scan: Arc::new(scan.clone()),
            odom: Se2::new(1.0, -2.0, 0.3),
        });
        let r = decode_uplink(&encode_uplink(99.5, &msg).unwrap()).unwrap();
        assert_eq!(r.rx_s, 99.5);
        let Uplink::Scan(s) = r.msg else { panic!("not a scan") };
        assert_eq!(s.seq, 7);
        assert_eq!(s.odom, Se2::new(1.0, -2.0, 0.3));
        let bits = |s: &Scan| s.ranges_m().iter().map(|r| r.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&s.scan), bits(&scan));
    }

    #[test]
    fn health_safety_odom_and_status_round_trip() {
        let msgs = [
            Uplink::Health {
                robot: "b".into(),
                seq: 1,
                stamp_s: 0.5,
                report: HealthReport {
                    device: Device::Imu,
                    health: Health::Degraded,
                    detail: "nan \"x\"".into(),
                },
            },
            Uplink::Safety {
                robot: "b".into(),
                seq: 2,
                stamp_s: 0.6,
                state: SafetyState::Disarmed(DisarmReason::Watchdog),
            },
            Uplink::Odom {
                robot: "a".into(),
                msg: OdomMsg {
                    seq: 3,
                    stamp_s: 0.7,
                    pose: Se2::new(0.1, 0.2, 0.3),
                    twist: (0.2, -0.1),
                    gyro: true,
                },
            },
        ];
        for m in &msgs {
            let back = decode_uplink(&encode_uplink(1.0, m).unwrap()).unwrap().msg;
            assert_eq!(format!("{back:?}"), format!("{m:?}"));
        }
        for s in [FusionStatus::Fusing, FusionStatus::RobotLost(1)] {
            assert_eq!(decode_status(&encode_status(s).unwrap()).unwrap(), s);
        }
    }

    #[test]
    fn a_fused_frame_keeps_its_poses_and_a_digest_of_its_points() {
        let f = FusedRecord {
            seq: 3,
            configuration: Configuration::T2,
            stamp_s: 1.5,
            oldest_stamp_s: 1.49,
            v_odom: Se2::new(0.1, 0.2, 0.3),
            points: Some(vec![[1.0, 2.0], [3.0, -0.0]]),
            robots: vec![(Se2::new(0.0, 0.45, 0.0), Se2::new(1.0, 1.0, 1.0))],
        };
        let d = decode_fused(&encode_fused(&f).unwrap()).unwrap();
        assert_eq!(
            (d.seq, d.configuration, d.v_odom, d.robots.clone()),
            (3, Configuration::T2, f.v_odom, f.robots.clone())
        );
        let p = d.points.unwrap();
        assert_eq!(p.n, 2);
        // -0.0 and 0.0 differ in bits: the digest tells them apart.
        let g = FusedRecord { points: Some(vec![[1.0, 2.0], [3.0, 0.0]]), ..f };
        assert_ne!(decode_fused(&encode_fused(&g).unwrap()).unwrap().points.unwrap(), p);
        assert_eq!(digest(&[]).fnv1a64, "cbf29ce484222325");
    }

    #[test]
    fn garbage_and_other_versions_are_errors_not_panics() {
        let good = encode_status(FusionStatus::Fusing).unwrap();
        for cut in 0..good.len() {
            assert!(decode_status(&good[..cut]).is_err());
        }
        assert!(matches!(
            decode_status(br#"{"v":2,"status":"fusing","robot":null}"#),
            Err(WireError::Version { found: 2 })
        ));
        for bytes in [&b"\xff\xfe"[..], b"{}", b"[]", br#"{"v":1,"rx_s":0,"msg":{"kind":"scan"}}"#] {
            assert!(decode_uplink(bytes).is_err());
            assert!(decode_estimate(bytes).is_err());
            assert!(decode_fused(bytes).is_err());
        }
        assert!(
            decode_estimate(br#"{"v":1,"source":"robot:x","stamp_s":0,"v_map":null,"robots":[]}"#).is_err()
        );
    }
}
