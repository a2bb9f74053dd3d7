#![allow(clippy::unwrap_used, reason = "tests")]

use super::*;
use proptest::prelude::*;

fn scan_msg() -> ScanMsg {
    let mut ranges: Vec<f64> = (0..271).map(|i| 1.0 + f64::from(i) * 0.001_234_567).collect();
    ranges[3] = f64::NAN;
    ranges[4] = 0.0;
    ScanMsg {
        robot: "robot-a".into(),
        seq: 9,
        stamp_s: 12.5,
        received_s: 12.51,
        scan: Arc::new(Scan::new(-2.35, 0.0174, 0.05, 10.0, ranges)),
        odom: Some(Se2 { x: 1.0, y: -2.0, theta: 0.3 }),
        odom_frame: 17,
    }
}

/// One of every message kind (each enum variant at least once).
fn samples() -> (Vec<Uplink>, Vec<Downlink>, Vec<Estimate>, FusedFrame, Vec<FusionStatus>) {
    let p = Se2 { x: 0.1, y: -0.2, theta: 0.7 };
    let uplinks = vec![
        Uplink::Scan(scan_msg()),
        Uplink::Odom {
            robot: "robot-a".into(),
            msg: OdomMsg { seq: 3, frame: 17, stamp_s: 1.0, pose: p, twist: (0.1, 0.2), gyro: false },
        },
        Uplink::Health {
            robot: "robot-b".into(),
            seq: 4,
            stamp_s: 2.0,
            report: HealthReport { device: Device::CanBus, health: Health::Degraded, detail: "ü".into() },
        },
        Uplink::Safety {
            robot: "robot-b".into(),
            seq: 5,
            stamp_s: 3.0,
            state: SafetyState::Disarmed(DisarmReason::EStopReset),
            stops: 41,
            mock: false,
        },
        Uplink::Safety {
            robot: "robot-b".into(),
            seq: 6,
            stamp_s: 3.5,
            state: SafetyState::Disarmed(DisarmReason::FaultReset),
            stops: 42,
            mock: true,
        },
        Uplink::Safety {
            robot: "robot-b".into(),
            seq: 7,
            stamp_s: 3.6,
            state: SafetyState::EStop,
            stops: 43,
            mock: false,
        },
    ];
    let downlinks = vec![
        Downlink::Command(Command { seq: 7, stamp_s: 4.0, v_mps: 0.22, w_radps: -0.01 }),
        Downlink::Arm { seq: 8, stops: 43, stamp_s: 4.5 },
        Downlink::Disarm,
        Downlink::EStop,
        Downlink::ResetEStop,
    ];
    let anchored = Anchored { map: p, odom: Se2::IDENTITY, stamp_s: 5.0 };
    let estimates = vec![
        Estimate {
            source: EstimateSource::Fused(Configuration::T4),
            stamp_s: 5.0,
            v: Some(p),
            robots: vec![Some(anchored), None],
            integrity: EstimateIntegrity {
                state: IntegrityState::Uncertain,
                explained: 0.71,
                level: 0.93,
                disagrees: Some(1),
                ambiguous: true,
            },
            covariance: Some([[0.01, 0.002, 0.0], [0.002, 0.02, -1e-4], [0.0, -1e-4, 0.003]]),
        },
        Estimate {
            source: EstimateSource::Robot(1),
            stamp_s: 5.0,
            v: None,
            robots: vec![None, Some(anchored)],
            integrity: EstimateIntegrity::default(),
            covariance: None,
        },
    ];
    let fused = FusedFrame {
        seq: 11,
        configuration: Configuration::T2,
        stamp_s: 6.0,
        oldest_stamp_s: 5.98,
        v_odom: p,
        points: Some(Arc::new(vec![[1.0, 2.0], [-0.5, 1e-9]])),
        robots: vec![(p, Se2::IDENTITY), (Se2::IDENTITY, p)],
        times: StageTimes { amcl_s: Some(0.001), ..StageTimes::default() },
    };
    (uplinks, downlinks, estimates, fused, vec![FusionStatus::Fusing, FusionStatus::RobotLost(1)])
}

fn same_scan(a: &Scan, b: &Scan) -> bool {
    let bits = |s: &Scan| {
        let mut v = vec![
            s.angle_min_rad.to_bits(),
            s.angle_increment_rad.to_bits(),
            s.range_min_m.to_bits(),
            s.range_max_m.to_bits(),
        ];
        v.extend(s.ranges_m().iter().map(|r| if r.is_nan() { u64::MAX } else { r.to_bits() }));
        v
    };
    bits(a) == bits(b)
}

fn same_uplink(a: &Uplink, b: &Uplink) -> bool {
    match (a, b) {
        (Uplink::Scan(x), Uplink::Scan(y)) => {
            same_scan(&x.scan, &y.scan)
                && (x.robot.as_str(), x.seq, x.stamp_s.to_bits(), x.received_s.to_bits(), x.odom)
                    == (y.robot.as_str(), y.seq, y.stamp_s.to_bits(), y.received_s.to_bits(), y.odom)
        }
        _ => a == b,
    }
}

#[test]
fn every_message_round_trips_bit_for_bit_through_postcard_and_json() {
    let (ups, downs, ests, fused, statuses) = samples();
    for u in &ups {
        let p: Uplink = postcard::from_bytes(&postcard::to_stdvec(u).unwrap()).unwrap();
        let j: Uplink = serde_json::from_slice(&serde_json::to_vec(u).unwrap()).unwrap();
        assert!(same_uplink(u, &p) && same_uplink(u, &j), "{u:?}");
    }
    for d in &downs {
        assert_eq!(postcard::from_bytes::<Downlink>(&postcard::to_stdvec(d).unwrap()).unwrap(), *d);
        assert_eq!(serde_json::from_slice::<Downlink>(&serde_json::to_vec(d).unwrap()).unwrap(), *d);
    }
    for e in &ests {
        assert_eq!(postcard::from_bytes::<Estimate>(&postcard::to_stdvec(e).unwrap()).unwrap(), *e);
        assert_eq!(serde_json::from_slice::<Estimate>(&serde_json::to_vec(e).unwrap()).unwrap(), *e);
    }
    assert_eq!(postcard::from_bytes::<FusedFrame>(&postcard::to_stdvec(&fused).unwrap()).unwrap(), fused);
    assert_eq!(serde_json::from_slice::<FusedFrame>(&serde_json::to_vec(&fused).unwrap()).unwrap(), fused);
    for s in &statuses {
        assert_eq!(serde_json::from_slice::<FusionStatus>(&serde_json::to_vec(s).unwrap()).unwrap(), *s);
    }
}

#[test]
fn invalid_beams_travel_as_null_and_stay_invalid() {
    let m = scan_msg();
    let json = serde_json::to_string(&m).unwrap();
    assert!(json.contains("null"), "{json}");
    let back: ScanMsg = serde_json::from_str(&json).unwrap();
    assert_eq!(back.scan.valid_count(), 269);
    assert!(!back.scan.is_valid(3) && !back.scan.is_valid(4));
    // A range the receiver's rules refuse (beyond range_max) arrives invalid, not as it was sent.
    let forged = json.replacen("1.0,", "99.0,", 1);
    let back: ScanMsg = serde_json::from_str(&forged).unwrap();
    assert!(!back.scan.is_valid(0), "{forged}");
}

/// FNV-1a 64 (offset basis 0xcbf29ce484222325, prime 0x100000001b3).
fn fnv(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, b| (h ^ u64::from(*b)).wrapping_mul(0x0100_0000_01b3))
}

/// The encoding of every message kind, pinned. If this fails, a change to these types changed
/// what goes on the network and into recordings: bump [`SCHEMA_VERSION`] and put the new values
/// here (the old readers must refuse the new encoding rather than misread it).
#[test]
fn the_encoding_is_pinned_to_the_schema_version() {
    let (ups, downs, ests, fused, statuses) = samples();
    let mut postcard_bytes = Vec::new();
    let mut json_bytes = Vec::new();
    for u in &ups {
        postcard_bytes.extend(postcard::to_stdvec(u).unwrap());
        json_bytes.extend(serde_json::to_vec(u).unwrap());
    }
    for d in &downs {
        postcard_bytes.extend(postcard::to_stdvec(d).unwrap());
        json_bytes.extend(serde_json::to_vec(d).unwrap());
    }
    for e in &ests {
        postcard_bytes.extend(postcard::to_stdvec(e).unwrap());
        json_bytes.extend(serde_json::to_vec(e).unwrap());
    }
    postcard_bytes.extend(postcard::to_stdvec(&fused).unwrap());
    json_bytes.extend(serde_json::to_vec(&fused).unwrap());
    for s in &statuses {
        postcard_bytes.extend(postcard::to_stdvec(s).unwrap());
        json_bytes.extend(serde_json::to_vec(s).unwrap());
    }
    let got = (SCHEMA_VERSION, fnv(&postcard_bytes), fnv(&json_bytes));
    let pinned = (8, 0x9ba4_a75e_7113_4974, 0x020e_747e_f0f3_c671);
    assert_eq!(got, pinned, "the encoding changed: bump SCHEMA_VERSION and pin the new hashes");
}

proptest! {
    #[test]
    fn decoding_any_bytes_never_panics(bytes in proptest::collection::vec(any::<u8>(), 0..4096)) {
        let _ = postcard::from_bytes::<Uplink>(&bytes);
        let _ = postcard::from_bytes::<Downlink>(&bytes);
        let _ = serde_json::from_slice::<Uplink>(&bytes);
        let _ = serde_json::from_slice::<Estimate>(&bytes);
    }
}
