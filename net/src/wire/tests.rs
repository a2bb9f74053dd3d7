//! Tests of the link's wire format and gate: round trips, freshness, senders, damaged input.

#![allow(clippy::unwrap_used, reason = "tests")]

use std::sync::Arc;

use super::*;
use amr_core::scan::Scan;
use amr_core::se2::Se2;
use amr_msgs::{Command, Device, DisarmReason, Health, HealthReport, OdomMsg, SafetyState, ScanMsg};
use proptest::prelude::*;

fn env(body: Body) -> Envelope {
    Envelope {
        version: SCHEMA_VERSION,
        session: 7,
        seq: 1,
        origin: "robot-a".into(),
        robot: "robot-a".into(),
        stamp_s: 12.5,
        sent_s: 12.6,
        body,
    }
}

fn scan_uplink() -> Uplink {
    let mut ranges: Vec<f64> = (0..271).map(|i| 1.0 + f64::from(i) * 0.001_234_5).collect();
    ranges[3] = f64::NAN;
    Uplink::Scan(ScanMsg {
        robot: "robot-a".into(),
        seq: 9,
        stamp_s: 12.5,
        received_s: 12.51,
        scan: Arc::new(Scan::new(-2.35, 0.0174, 0.05, 10.0, ranges)),
        odom: Some(Se2 { x: 1.0, y: -2.0, theta: 0.3 }),
        odom_frame: 1,
    })
}

#[test]
fn a_scan_crosses_bit_for_bit_with_its_odometry_and_invalid_beams() {
    let u = scan_uplink();
    let (stamp, body) = from_uplink(&u);
    let e = Envelope { stamp_s: stamp, ..env(body) };
    let bytes = e.encode().unwrap();
    assert!(bytes.len() < 2600, "{} bytes", bytes.len());
    let back = to_uplink(Envelope::decode(&bytes).unwrap(), "robot-a", "scan").unwrap();
    let (Uplink::Scan(a), Uplink::Scan(b)) = (&u, &back) else { panic!("not a scan: {back:?}") };
    assert_eq!((a.seq, a.stamp_s, a.odom), (b.seq, b.stamp_s, b.odom));
    assert!(b.scan.ranges_m()[3].is_nan());
    for (x, y) in a.scan.ranges_m().iter().zip(b.scan.ranges_m()) {
        assert!(x.is_nan() && y.is_nan() || x.to_bits() == y.to_bits(), "{x} vs {y}");
    }
}

#[test]
fn another_version_and_trailing_bytes_are_refused() {
    let mut e = env(Body::Downlink(Downlink::Disarm));
    e.version = SCHEMA_VERSION + 1;
    assert_eq!(Envelope::decode(&e.encode().unwrap()), Err(Reject::Version { got: SCHEMA_VERSION + 1 }));
    let mut bytes = env(Body::Downlink(Downlink::Disarm)).encode().unwrap();
    bytes.push(0);
    assert_eq!(Envelope::decode(&bytes), Err(Reject::Trailing(1)));
    assert!(matches!(Envelope::decode(&bytes[..bytes.len() - 3]), Err(Reject::Malformed(_))));
}

#[test]
fn commands_only_from_the_server_and_only_for_me() {
    let c = Command { seq: 5, stamp_s: 12.5, v_mps: 0.1, w_radps: 0.0 };
    let mut e = env(Body::Downlink(Downlink::Command(c)));
    e.origin = "server".into();
    assert_eq!(to_downlink(e.clone(), "robot-a", "server"), Ok(Downlink::Command(c)));
    assert!(matches!(to_downlink(e.clone(), "robot-b", "server"), Err(Reject::WrongRobot { .. })));
    e.origin = "robot-b".into();
    assert!(matches!(to_downlink(e, "robot-a", "server"), Err(Reject::NotFromServer { .. })));
    // A robot's message on its own key from another robot is refused too.
    let safety = Uplink::Safety {
        robot: "robot-a".into(),
        seq: 1,
        stamp_s: 1.0,
        state: SafetyState::Armed,
        stops: 1,
        mock: false,
    };
    let mut u = env(Body::Uplink(safety.clone()));
    u.origin = "robot-b".into();
    assert!(matches!(to_uplink(u, "robot-a", "health"), Err(Reject::WrongRobot { .. })));
    // So is an envelope of robot-a's whose message names robot-b.
    let b = Uplink::Safety {
        robot: "robot-b".into(),
        seq: 1,
        stamp_s: 1.0,
        state: SafetyState::Armed,
        stops: 1,
        mock: false,
    };
    assert!(matches!(to_uplink(env(Body::Uplink(b)), "robot-a", "health"), Err(Reject::WrongRobot { .. })));
    let odom = Uplink::Odom {
        robot: "robot-a".into(),
        msg: OdomMsg { seq: 1, frame: 1, stamp_s: 1.0, pose: Se2::IDENTITY, twist: (0.0, 0.0), gyro: true },
    };
    assert!(matches!(
        to_uplink(env(Body::Uplink(odom)), "robot-a", "scan"),
        Err(Reject::WrongChannel { .. })
    ));
    assert!(matches!(
        to_uplink(env(Body::Downlink(Downlink::Disarm)), "robot-a", "health"),
        Err(Reject::WrongChannel { .. })
    ));
}

#[test]
fn freshness_refuses_replays_and_older_or_future_sessions_and_takes_a_newer_one() {
    // Sessions are start times in ns: this sender started at 1000 s, the receiver's clock is at
    // 2000 s.
    let now = 2000.0;
    let mut f = Freshness::default();
    let mut e = env(Body::Downlink(Downlink::Disarm));
    e.session = 1_000_000_000_000;
    assert!(f.check(&e, now).is_ok());
    assert!(matches!(f.check(&e, now), Err(Reject::Replayed { .. })));
    e.seq = 2;
    assert!(f.check(&e, now).is_ok());
    // The sender restarted at 1500 s: its new session is taken.
    let mut newer = e.clone();
    newer.session = 1_500_000_000_000;
    newer.seq = 1;
    assert!(f.check(&newer, now).is_ok(), "a restarted sender");
    // A sample recorded from its earlier run is refused, whatever its sequence number.
    e.seq = 99;
    assert!(matches!(f.check(&e, now), Err(Reject::OldSession { .. })));
    // A session that starts beyond the tolerance in the future would lock the sender out.
    let mut ahead = newer.clone();
    ahead.session = 2_010_000_000_000;
    assert!(matches!(f.check(&ahead, now), Err(Reject::FutureSession { .. })));
    ahead.session = 2_004_000_000_000;
    assert!(f.check(&ahead, now).is_ok(), "within the clocks' tolerance");
}

#[test]
fn a_stale_or_future_arm_or_reset_is_refused_a_stale_stop_is_not() {
    let at = |d: Downlink, stamp_s: f64| Envelope { stamp_s, ..env(Body::Downlink(d)) };
    let now = 100.0;
    let arm = Downlink::Arm { seq: 1, stops: 1, stamp_s: 97.0 };
    assert!(matches!(check_enabling_age(&at(arm, 97.0), now), Err(Reject::Stale { kind: "arm", .. })));
    assert!(check_enabling_age(&at(arm, 98.5), now).is_ok());
    assert!(check_enabling_age(&at(arm, 100.4), now).is_ok());
    assert!(matches!(check_enabling_age(&at(arm, 102.0), now), Err(Reject::Ahead { kind: "arm", .. })));
    assert!(matches!(
        check_enabling_age(&at(Downlink::ResetEStop, 100.6), now),
        Err(Reject::Ahead { kind: "reset_estop", .. })
    ));
    assert!(matches!(
        check_enabling_age(&at(Downlink::ResetEStop, f64::NAN), now),
        Err(Reject::Stale { kind: "reset_estop", .. })
    ));
    assert!(check_enabling_age(&at(Downlink::EStop, 10.0), now).is_ok(), "stopping is always safe");
    assert!(check_enabling_age(&at(Downlink::Disarm, 10.0), now).is_ok());
}

/// An envelope on robot-a's downlink keys: session `session_s` (s), sequence `seq`, stamped
/// `stamp_s`, from `origin`.
fn down(d: Downlink, origin: &str, session_s: u64, seq: u64, stamp_s: f64) -> Envelope {
    Envelope {
        session: session_s * 1_000_000_000,
        seq,
        origin: origin.into(),
        stamp_s,
        ..env(Body::Downlink(d))
    }
}

fn senders() -> Vec<String> {
    vec!["server".into(), "op".into()]
}

#[test]
fn the_gate_takes_an_estop_whatever_its_session_sequence_or_stamp() {
    let now = 2000.0;
    let mut g = DownlinkGate::default();
    // The operator's newer session resets; an e-stop from its earlier run, replayed, long
    // stamped, is taken all the same.
    let reset = down(Downlink::ResetEStop, "op", 1500, 5, now);
    assert_eq!(g.on_estop(&reset, "robot-a", "op", &senders(), now, now), Ok(Downlink::ResetEStop));
    let old = down(Downlink::EStop, "op", 1000, 1, 10.0);
    assert_eq!(g.on_estop(&old, "robot-a", "op", &senders(), now, now), Ok(Downlink::EStop));
    assert_eq!(g.on_estop(&old, "robot-a", "op", &senders(), now, now), Ok(Downlink::EStop), "again");
    // A reset is checked against the sender's record: a replay or an earlier session is refused.
    assert!(matches!(
        g.on_estop(&reset, "robot-a", "op", &senders(), now, now),
        Err(Reject::Replayed { .. })
    ));
    let older = down(Downlink::ResetEStop, "op", 1000, 9, now);
    assert!(matches!(
        g.on_estop(&older, "robot-a", "op", &senders(), now, now),
        Err(Reject::OldSession { .. })
    ));
    // Each sender has its own record: the server's reset of the same numbers is taken.
    let server = down(Downlink::ResetEStop, "server", 1500, 5, now);
    assert_eq!(g.on_estop(&server, "robot-a", "server", &senders(), now, now), Ok(Downlink::ResetEStop));
    // A stale or future reset is refused before it touches the record.
    let stale = down(Downlink::ResetEStop, "server", 1900, 1, now - 3.0);
    assert!(matches!(
        g.on_estop(&stale, "robot-a", "server", &senders(), now, now),
        Err(Reject::Stale { .. })
    ));
    let next = down(Downlink::ResetEStop, "server", 1500, 6, now);
    assert!(g.on_estop(&next, "robot-a", "server", &senders(), now, now).is_ok());
}

#[test]
fn the_gate_refuses_a_forged_origin_an_unknown_sender_or_another_robot_on_the_estop_key() {
    let now = 2000.0;
    let mut g = DownlinkGate::default();
    // On the operator's key, an envelope that says it is the server's.
    let forged = down(Downlink::ResetEStop, "server", 1500, 1, now);
    assert!(matches!(
        g.on_estop(&forged, "robot-a", "op", &senders(), now, now),
        Err(Reject::ForgedOrigin { .. })
    ));
    let stranger = down(Downlink::EStop, "mallory", 1500, 1, now);
    assert!(matches!(
        g.on_estop(&stranger, "robot-a", "mallory", &senders(), now, now),
        Err(Reject::NotAnOperator { .. })
    ));
    let mut other = down(Downlink::EStop, "op", 1500, 1, now);
    other.robot = "robot-b".into();
    assert!(matches!(
        g.on_estop(&other, "robot-a", "op", &senders(), now, now),
        Err(Reject::WrongRobot { .. })
    ));
    let arm = down(Downlink::Arm { seq: 1, stops: 1, stamp_s: now }, "op", 1500, 1, now);
    assert!(matches!(
        g.on_estop(&arm, "robot-a", "op", &senders(), now, now),
        Err(Reject::WrongChannel { channel: "estop", .. })
    ));
    // None of them touched the operator's record.
    let reset = down(Downlink::ResetEStop, "op", 1500, 1, now);
    assert!(g.on_estop(&reset, "robot-a", "op", &senders(), now, now).is_ok());
}

#[test]
fn the_gate_takes_a_replayed_disarm_and_refuses_a_replayed_command_or_arm() {
    let now = 2000.0;
    let mut g = DownlinkGate::default();
    let c = |seq: u64| Downlink::Command(Command { seq, stamp_s: now, v_mps: 0.1, w_radps: 0.0 });
    let first = down(c(1), "server", 1500, 1, now);
    assert_eq!(g.on_cmd(&first, "robot-a", "server", now, now), Ok(c(1)));
    assert!(matches!(g.on_cmd(&first, "robot-a", "server", now, now), Err(Reject::Replayed { .. })));
    // A disarm replayed, from an earlier session, stamped long ago: taken, and it leaves the
    // record as it was (the next command is still taken).
    let disarm = down(Downlink::Disarm, "server", 1000, 1, 10.0);
    assert_eq!(g.on_cmd(&disarm, "robot-a", "server", now, now), Ok(Downlink::Disarm));
    assert_eq!(g.on_cmd(&disarm, "robot-a", "server", now, now), Ok(Downlink::Disarm));
    let far = down(Downlink::Disarm, "server", 9000, u64::MAX, 1e12);
    assert_eq!(g.on_cmd(&far, "robot-a", "server", now, now), Ok(Downlink::Disarm));
    let second = down(c(2), "server", 1500, 2, now);
    assert_eq!(g.on_cmd(&second, "robot-a", "server", now, now), Ok(c(2)));
    // An arm: fresh and new, or refused.
    let arm = Downlink::Arm { seq: 3, stops: 1, stamp_s: now };
    assert!(matches!(
        g.on_cmd(&down(arm, "server", 1500, 3, now - 2.5), "robot-a", "server", now, now),
        Err(Reject::Stale { .. })
    ));
    assert_eq!(g.on_cmd(&down(arm, "server", 1500, 3, now), "robot-a", "server", now, now), Ok(arm));
    assert!(matches!(
        g.on_cmd(&down(arm, "server", 1500, 3, now), "robot-a", "server", now, now),
        Err(Reject::Replayed { .. })
    ));
    // Not from the server, or for another robot: refused before it touches the record (a newer
    // session from elsewhere does not lock the server out).
    let forged = down(c(1), "op", 1900, 1, now);
    assert!(matches!(g.on_cmd(&forged, "robot-a", "server", now, now), Err(Reject::NotFromServer { .. })));
    let newer_elsewhere = down(c(1), "server", 1900, 1, now);
    assert!(matches!(
        g.on_cmd(&newer_elsewhere, "robot-b", "server", now, now),
        Err(Reject::WrongRobot { .. })
    ));
    assert!(g.on_cmd(&down(c(4), "server", 1500, 4, now), "robot-a", "server", now, now).is_ok());
    // Sessions compare with the wall clock, stamps with the fleet clock.
    let ahead = down(c(5), "server", 2100, 1, now);
    assert!(matches!(g.on_cmd(&ahead, "robot-a", "server", now, 2000.0), Err(Reject::FutureSession { .. })));
    assert!(g.on_cmd(&ahead, "robot-a", "server", now, 2096.0).is_ok());
}

#[test]
fn an_uplink_with_a_stamp_or_odometry_that_is_not_finite_is_refused() {
    let odom = |x: f64, stamp_s: f64| Uplink::Odom {
        robot: "robot-a".into(),
        msg: OdomMsg {
            seq: 1,
            frame: 1,
            stamp_s,
            pose: Se2 { x, y: 0.0, theta: 0.0 },
            twist: (0.0, 0.0),
            gyro: true,
        },
    };
    assert!(to_uplink(env(Body::Uplink(odom(1.0, 3.0))), "robot-a", "odom").is_ok());
    assert_eq!(
        to_uplink(env(Body::Uplink(odom(f64::NAN, 3.0))), "robot-a", "odom"),
        Err(Reject::NotFinite("odometry"))
    );
    assert_eq!(
        to_uplink(env(Body::Uplink(odom(1.0, f64::INFINITY))), "robot-a", "odom"),
        Err(Reject::NotFinite("stamp"))
    );
    let safety = Uplink::Safety {
        robot: "robot-a".into(),
        seq: 1,
        stamp_s: f64::NAN,
        state: SafetyState::Armed,
        stops: 1,
        mock: false,
    };
    assert_eq!(to_uplink(env(Body::Uplink(safety)), "robot-a", "health"), Err(Reject::NotFinite("stamp")));
}

#[test]
fn every_uplink_kind_round_trips() {
    let report = HealthReport { device: Device::Imu, health: Health::Degraded, detail: "ü".repeat(400) };
    let ups = [
        Uplink::Odom {
            robot: "robot-a".into(),
            msg: OdomMsg {
                seq: 3,
                frame: 1,
                stamp_s: 1.0,
                pose: Se2 { x: 1.0, y: 2.0, theta: 0.5 },
                twist: (0.1, 0.2),
                gyro: false,
            },
        },
        Uplink::Health { robot: "robot-a".into(), seq: 4, stamp_s: 2.0, report },
        Uplink::Safety {
            robot: "robot-a".into(),
            seq: 5,
            stamp_s: 3.0,
            state: SafetyState::Disarmed(DisarmReason::Watchdog),
            stops: 1,
            mock: false,
        },
    ];
    for u in ups {
        let (stamp, body) = from_uplink(&u);
        let bytes = Envelope { stamp_s: stamp, ..env(body) }.encode().unwrap();
        let back = to_uplink(Envelope::decode(&bytes).unwrap(), "robot-a", uplink_channel(&u)).unwrap();
        match (&u, &back) {
            (Uplink::Health { report: a, .. }, Uplink::Health { report: b, .. }) => {
                assert_eq!((a.device, a.health), (b.device, b.health));
                assert_eq!(b.detail.len(), MAX_DETAIL_BYTES, "cut at a char boundary");
            }
            _ => assert_eq!(u, back),
        }
    }
}

proptest! {
    #[test]
    fn decoding_never_panics(bytes in proptest::collection::vec(any::<u8>(), 0..2048)) {
        let _ = Envelope::decode(&bytes);
    }

    #[test]
    fn a_damaged_envelope_is_refused_or_decoded_never_a_panic(
        flip in 0usize..2600, value in any::<u8>(), cut in 0usize..2700,
    ) {
        let (stamp, body) = from_uplink(&scan_uplink());
        let mut bytes = Envelope { stamp_s: stamp, ..env(body) }.encode().unwrap();
        let i = flip % bytes.len();
        bytes[i] = value;
        bytes.truncate(cut.max(1));
        if let Ok(e) = Envelope::decode(&bytes) {
            let _ = to_uplink(e, "robot-a", "scan");
        }
    }
}
