//! Our own exact channels: what the server received (`/amr/uplink`), what fusion produced
//! (`/amr/fused`), what AMCL estimated (`/amr/estimates`) and the fusion status (`/amr/status`), as
//! JSON that gives every `f64` back bit for bit (serde_json's `float_roundtrip`: shortest
//! round-trip output, correctly rounded parsing). Invalid beams (NaN) travel as `null`.
//!
//! The bodies are the fleet's own message types (`amr-msgs`) as serde writes them; every record
//! carries their [`SCHEMA_VERSION`] and a reader refuses another version rather than guess.
//! Decoding never panics: bad bytes are a [`WireError`].

use amr_core::config::Configuration;
use amr_core::se2::Se2;
use amr_msgs::{Estimate, FusedFrame, FusionStatus, SCHEMA_VERSION, Uplink};
use serde::{Deserialize, Serialize};

/// Version of the exact encodings: the message types' schema version.
pub const VERSION: u16 = SCHEMA_VERSION;

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
    Version { found: u16 },
    #[error("an uplink record without its receive time `rx_s`")]
    NoReceiveTime,
}

/// One message as the server received it: `rx_s` is the server's reading of the fleet clock when
/// the message came off the link (stamped once; the localizer used the same time).
#[derive(Debug, Clone)]
pub struct Received {
    pub rx_s: f64,
    pub msg: Uplink,
}

#[derive(Serialize)]
struct Out<'a, T> {
    v: u16,
    #[serde(skip_serializing_if = "Option::is_none")]
    rx_s: Option<f64>,
    msg: &'a T,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct In<T> {
    #[serde(rename = "v")]
    _v: u16,
    #[serde(default)]
    rx_s: Option<f64>,
    msg: T,
}

fn encode<T: Serialize>(rx_s: Option<f64>, msg: &T) -> Result<Vec<u8>, WireError> {
    Ok(serde_json::to_vec(&Out { v: VERSION, rx_s, msg })?)
}

fn decode<'de, T: Deserialize<'de>>(bytes: &'de [u8]) -> Result<(Option<f64>, T), WireError> {
    // The version first, so another version is named as such rather than as a shape error.
    #[derive(Deserialize)]
    struct V {
        v: u16,
    }
    let v: V = serde_json::from_slice(bytes)?;
    if v.v != VERSION {
        return Err(WireError::Version { found: v.v });
    }
    let r: In<T> = serde_json::from_slice(bytes)?;
    Ok((r.rx_s, r.msg))
}

/// Encode one received uplink message.
pub fn encode_uplink(rx_s: f64, msg: &Uplink) -> Result<Vec<u8>, WireError> {
    encode(Some(rx_s), msg)
}

/// Decode one received uplink message.
pub fn decode_uplink(bytes: &[u8]) -> Result<Received, WireError> {
    let (rx_s, msg) = decode(bytes)?;
    Ok(Received { rx_s: rx_s.ok_or(WireError::NoReceiveTime)?, msg })
}

/// Encode an estimate.
pub fn encode_estimate(e: &Estimate) -> Result<Vec<u8>, WireError> {
    encode(None, e)
}

/// Decode an estimate.
pub fn decode_estimate(bytes: &[u8]) -> Result<Estimate, WireError> {
    decode(bytes).map(|(_, e)| e)
}

/// Encode a fusion status change.
pub fn encode_status(s: FusionStatus) -> Result<Vec<u8>, WireError> {
    encode(None, &s)
}

/// Decode a fusion status change.
pub fn decode_status(bytes: &[u8]) -> Result<FusionStatus, WireError> {
    decode(bytes).map(|(_, s)| s)
}

/// A fused frame as recorded: its points by count and digest (they are what the uplink gives
/// again by replay, and at ~20 kB a frame they were the largest channel; the view is
/// `/virtual/scan`), without the stage times (wall-clock measurements, not results).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FusedRecord {
    pub seq: u64,
    pub configuration: Configuration,
    pub stamp_s: f64,
    pub oldest_stamp_s: f64,
    pub v_odom: Se2,
    pub points: Option<PointsDigest>,
    /// Per robot: its base in V, its odometry pose at its scan.
    pub robots: Vec<(Se2, Se2)>,
}

#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PointsDigest {
    pub n: usize,
    /// FNV-1a 64 over every coordinate's bits, little-endian, as 16 hex digits.
    pub fnv1a64: String,
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
            points: f.points.as_deref().map(|p| digest(p)),
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
    encode(None, f)
}

/// Decode a fused frame.
pub fn decode_fused(bytes: &[u8]) -> Result<FusedRecord, WireError> {
    decode(bytes).map(|(_, f)| f)
}

/// A JSON schema for an exact channel: an object with its version; Foxglove shows the fields
/// as they are (the schema only names the type).
#[must_use]
pub fn schema(name: &str) -> String {
    serde_json::json!({
        "title": name,
        "description": format!("amr exact record, version {VERSION} (the amr-msgs types as serde writes them)"),
        "type": "object",
        "properties": { "v": { "type": "integer", "const": VERSION } },
        "required": ["v"],
    })
    .to_string()
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used, reason = "tests")]
    use std::sync::Arc;

    use super::*;
    use amr_core::scan::Scan;
    use amr_msgs::{
        Anchored, Device, DisarmReason, EstimateSource, Health, HealthReport, OdomMsg, SafetyState, ScanMsg,
    };

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
                integrity: amr_msgs::EstimateIntegrity::default(),
                covariance: Some([[x, y, t], [y, t, x], [t, x, y]]),
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
            received_s: 12.35,
            scan: Arc::new(scan.clone()),
            odom: Some(Se2::new(1.0, -2.0, 0.3)),
            odom_frame: 1,
        });
        let r = decode_uplink(&encode_uplink(99.5, &msg).unwrap()).unwrap();
        assert_eq!(r.rx_s, 99.5);
        let Uplink::Scan(s) = r.msg else { panic!("not a scan") };
        assert_eq!(s.seq, 7);
        assert_eq!(s.odom, Some(Se2::new(1.0, -2.0, 0.3)));
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
                stops: 3,
                mock: false,
            },
            Uplink::Odom {
                robot: "a".into(),
                msg: OdomMsg {
                    seq: 3,
                    frame: 1,
                    stamp_s: 0.7,
                    pose: Se2::new(0.1, 0.2, 0.3),
                    twist: (0.2, -0.1),
                    gyro: true,
                },
            },
        ];
        for m in &msgs {
            let back = decode_uplink(&encode_uplink(1.0, m).unwrap()).unwrap().msg;
            assert_eq!(&back, m);
        }
        for s in [FusionStatus::Fusing, FusionStatus::RobotLost(1)] {
            assert_eq!(decode_status(&encode_status(s).unwrap()).unwrap(), s);
        }
    }

    #[test]
    fn a_fused_frame_keeps_its_poses_and_a_digest_of_its_points() {
        let frame = |points: Vec<[f64; 2]>| FusedFrame {
            seq: 3,
            configuration: Configuration::T2,
            stamp_s: 1.5,
            oldest_stamp_s: 1.49,
            v_odom: Se2::new(0.1, 0.2, 0.3),
            points: Some(Arc::new(points)),
            robots: vec![(Se2::new(0.0, 0.45, 0.0), Se2::new(1.0, 1.0, 1.0))],
            times: amr_msgs::StageTimes::default(),
        };
        let f = FusedRecord::of(&frame(vec![[1.0, 2.0], [3.0, -0.0]]));
        let d = decode_fused(&encode_fused(&f).unwrap()).unwrap();
        assert_eq!(d, f);
        let p = d.points.unwrap();
        assert_eq!(p.n, 2);
        // -0.0 and 0.0 differ in bits: the digest tells them apart.
        let g = FusedRecord::of(&frame(vec![[1.0, 2.0], [3.0, 0.0]]));
        assert_ne!(g.points.unwrap(), p);
        assert_eq!(digest(&[]).fnv1a64, "cbf29ce484222325");
    }

    #[test]
    fn garbage_and_other_versions_are_errors_not_panics() {
        let good = encode_status(FusionStatus::Fusing).unwrap();
        for cut in 0..good.len() {
            assert!(decode_status(&good[..cut]).is_err());
        }
        let other = format!(r#"{{"v":{},"msg":"fusing"}}"#, VERSION + 1);
        assert!(
            matches!(decode_status(other.as_bytes()), Err(WireError::Version { found }) if found == VERSION + 1)
        );
        let v = VERSION;
        let shapes = [
            "\u{ff}".to_owned(),
            "{}".to_owned(),
            "[]".to_owned(),
            format!(r#"{{"v":{v},"rx_s":0,"msg":{{"scan":{{}}}}}}"#),
            format!(r#"{{"v":{v},"msg":{{"source":{{"robot":"x"}},"stamp_s":0,"v":null,"robots":[]}}}}"#),
        ];
        for bytes in &shapes {
            let bytes = bytes.as_bytes();
            assert!(decode_uplink(bytes).is_err());
            assert!(decode_estimate(bytes).is_err());
            assert!(decode_fused(bytes).is_err());
        }
    }
}
