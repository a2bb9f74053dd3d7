//! Tests of the formation actor: resuming, arming, non-finite poses, robots out of slot, V's twists.

use super::super::AutoArm;
use super::arm_authorised;

/// Stopped 10° into a turn on the spot, the plan resumes there, not at the turn's end (every
/// point of the turn stands at the same position).
#[test]
fn a_plan_resumes_mid_turn_where_v_heads() {
    use amr_core::plan::Reference;
    use amr_core::se2::Se2;
    let plan: Vec<Reference> = (0..=90)
        .map(|d| Reference { pose: Se2::new(1.0, 2.0, f64::from(d).to_radians()), v_mps: 0.0, w_radps: 0.1 })
        .collect();
    let v = Se2::new(1.0, 2.0, 10f64.to_radians());
    assert_eq!(super::nearest_ahead(&plan, 0, 200, v), Some(10));
    assert_eq!(super::nearest_ahead(&plan, 20, 200, v), Some(20), "never back");
}

/// The reason the formation holds names the check that failed: an ambiguous V (a rival place
/// explains its scans as well) is said as such, not as a share too low.
#[test]
fn an_unverified_v_is_held_with_the_reason() {
    use amr_msgs::{Anchored, EstimateIntegrity, IntegrityState};
    let fused = Some(Anchored {
        map: amr_core::se2::Se2::IDENTITY,
        odom: amr_core::se2::Se2::IDENTITY,
        stamp_s: 10.0,
    });
    let names = ["robot-a".to_owned(), "robot-b".to_owned()];
    let view = |integrity: EstimateIntegrity| super::RobotView {
        fused,
        fused_integrity: integrity,
        ..Default::default()
    };
    let i = |state, ambiguous, disagrees| EstimateIntegrity {
        state,
        explained: 0.9,
        level: 0.93,
        disagrees,
        ambiguous,
    };
    assert_eq!(view(i(IntegrityState::Tracking, false, None)).verified(10.1, &names), Ok(()));
    let ambiguous = view(i(IntegrityState::Uncertain, true, None)).verified(10.1, &names).unwrap_err();
    assert!(ambiguous.contains("another place explains its scans as well"), "{ambiguous}");
    let low = view(i(IntegrityState::Uncertain, false, None)).verified(10.1, &names).unwrap_err();
    assert!(low.starts_with("V is uncertain (the map explains 90 %"), "{low}");
    let disagrees = view(i(IntegrityState::Tracking, false, Some(1))).verified(10.1, &names).unwrap_err();
    assert!(disagrees.contains("robot-b"), "{disagrees}");
    assert!(view(i(IntegrityState::Tracking, false, None)).verified(20.0, &names).is_err(), "stale");
}

#[test]
fn auto_arm_moves_only_mock_robots_unless_the_operator_says() {
    assert!(arm_authorised(AutoArm::Mock, false, &[true, true]));
    assert!(!arm_authorised(AutoArm::Mock, false, &[true, false]), "one robot on hardware");
    assert!(arm_authorised(AutoArm::Mock, true, &[false, false]), "the operator's rearm");
    assert!(arm_authorised(AutoArm::Hardware, false, &[false, false]));
    assert!(!arm_authorised(AutoArm::Off, false, &[true, true]));
}

use std::sync::Arc;
use std::time::Duration;

use amr_core::amcl::IntegrityState;
use amr_core::config::value::Count;
use amr_core::map::OccupancyGrid;
use amr_core::se2::Se2;
use amr_msgs::{
    Anchored, Device, DisarmReason, Downlink, Estimate, EstimateIntegrity, EstimateSource, Health,
    HealthReport, OdomMsg, SafetyState, Uplink,
};
use ractor::ActorRef;
use tokio::sync::mpsc;

use super::super::progress::PlanProgress;
use super::super::{ServerSetup, ServerTree, formation_robots, start_server};
use super::{FormationMsg, Phase};
use crate::clock::FleetClock;
use crate::config::{ConfigSource, load};
use crate::link::{DownlinkSender, ScanSlots, ServerEnd};
use crate::supervisor::RestartPolicy;

/// A server on the embedded configuration (the straight scenario, no auto-arm) whose link ends
/// the test holds: the formation actor and each robot's downlink queue.
async fn server() -> (ServerTree, ActorRef<FormationMsg>, Vec<mpsc::Receiver<Downlink>>, Vec<Se2>) {
    let config = load(&ConfigSource::Embedded).unwrap();
    let robots = formation_robots(&config.server, &config.robots).unwrap();
    let scenario = config.scenarios["straight"].clone();
    let slots = amr_core::formation::slots(robots.len(), scenario.spacing_m.get());
    let starts = slots.iter().map(|y| scenario.start_pose() * Se2::new(0.0, *y, 0.0)).collect();
    let mut amcl = config.amcl.clone();
    amcl.min_particles = Count::new(10).unwrap();
    amcl.max_particles = Count::new(10).unwrap();
    let setup = ServerSetup {
        server: config.server.clone(),
        vamr: config.vamr.clone(),
        amcl,
        // No scan comes: the localizer needs no map.
        map: OccupancyGrid::filled(8, 8, 0.5, Se2::new(-2.0, -2.0, 0.0), 0),
        robots,
        scenario,
        seed: 1,
        auto_arm: super::super::AutoArm::Off,
        policy: RestartPolicy::default(),
        progress: Arc::new(PlanProgress::in_memory()),
    };
    let (_, up) = mpsc::channel(1);
    let mut downs = std::collections::BTreeMap::new();
    let mut queues = Vec::new();
    for r in &setup.robots {
        let (tx, rx) = mpsc::channel(4096);
        downs.insert(r.id.as_str().to_owned(), tx);
        queues.push(rx);
    }
    let end = ServerEnd { up, scans: ScanSlots::default(), down: DownlinkSender::new(downs) };
    let tree = start_server(setup, end, FleetClock::start()).await.unwrap();
    let formation = tree.formation_actor().await.unwrap();
    (tree, formation, queues, starts)
}

const ROBOTS: [&str; 2] = ["robot-a", "robot-b"];

fn odom(robot: &str, seq: u64, stamp_s: f64, pose: Se2) -> FormationMsg {
    let msg = OdomMsg { seq, frame: 1, stamp_s, pose, twist: (0.0, 0.0), gyro: true };
    FormationMsg::Uplink(Box::new(Uplink::Odom { robot: robot.into(), msg }))
}

fn safety(robot: &str, state: SafetyState, stops: u64) -> FormationMsg {
    FormationMsg::Uplink(Box::new(Uplink::Safety {
        robot: robot.into(),
        seq: 1,
        stamp_s: 0.0,
        state,
        stops,
        mock: true,
    }))
}

/// Both robots healthy, at their odometry's origin, placed in their slots by a fused estimate.
fn localised(f: &ActorRef<FormationMsg>, starts: &[Se2], seq: u64, now: f64) {
    for (robot, start) in ROBOTS.iter().zip(starts) {
        f.cast(odom(robot, seq, now, Se2::IDENTITY)).unwrap();
        for device in [Device::Lidar, Device::CanBus, Device::Drives] {
            let report = HealthReport { device, health: Health::Ok, detail: String::new() };
            let u = Uplink::Health { robot: (*robot).into(), seq, stamp_s: now, report };
            f.cast(FormationMsg::Uplink(Box::new(u))).unwrap();
        }
        let _ = start;
    }
    let robots =
        starts.iter().map(|s| Some(Anchored { map: *s, odom: Se2::IDENTITY, stamp_s: now })).collect();
    let integrity = EstimateIntegrity {
        state: IntegrityState::Tracking,
        explained: 0.9,
        level: 0.9,
        ..Default::default()
    };
    let e = Estimate {
        source: EstimateSource::Fused(amr_core::config::Configuration::T4),
        stamp_s: now,
        v: None,
        robots,
        integrity,
        covariance: None,
    };
    f.cast(FormationMsg::Estimate(Box::new(e))).unwrap();
}

/// Advance by one formation period and wait until the formation has ticked; what it sent.
async fn period(
    f: &ActorRef<FormationMsg>,
    queues: &mut [mpsc::Receiver<Downlink>],
) -> Vec<(usize, Downlink)> {
    tokio::time::advance(Duration::from_millis(50)).await;
    for _ in 0..4 {
        tokio::task::yield_now().await;
    }
    ractor::call!(f, FormationMsg::Status).unwrap();
    let mut sent = Vec::new();
    for (i, q) in queues.iter_mut().enumerate() {
        while let Ok(d) = q.try_recv() {
            sent.push((i, d));
        }
    }
    sent
}

#[tokio::test(start_paused = true)]
async fn no_arm_goes_out_while_a_robot_is_latched_nor_after_its_reset_without_a_new_rearm() {
    let (tree, f, mut queues, starts) = server().await;
    f.cast(safety("robot-a", SafetyState::EStop, 2)).unwrap();
    f.cast(safety("robot-b", SafetyState::Disarmed(DisarmReason::Startup), 1)).unwrap();
    f.cast(FormationMsg::Rearm).unwrap();
    for k in 1..=40u32 {
        localised(&f, &starts, u64::from(k), f64::from(k) * 0.05);
        let sent = period(&f, &mut queues).await;
        assert!(sent.is_empty(), "sent {sent:?} while robot-a is e-stopped");
        if k == 20 {
            f.cast(safety("robot-a", SafetyState::Fault, 3)).unwrap();
        }
    }
    // Reset on the robot: the rearm given before lapsed (a reset starts nothing).
    f.cast(safety("robot-a", SafetyState::Disarmed(DisarmReason::FaultReset), 4)).unwrap();
    for k in 41..=50u32 {
        localised(&f, &starts, u64::from(k), f64::from(k) * 0.05);
        let sent = period(&f, &mut queues).await;
        assert!(sent.iter().all(|(_, d)| !matches!(d, Downlink::Arm { .. })), "armed on a reset: {sent:?}");
    }
    // A new rearm: the arm carries each robot's count.
    f.cast(FormationMsg::Rearm).unwrap();
    localised(&f, &starts, 51, 2.55);
    let sent = period(&f, &mut queues).await;
    let arms: Vec<(usize, u64)> = sent
        .iter()
        .filter_map(|(i, d)| match d {
            Downlink::Arm { stops, .. } => Some((*i, *stops)),
            _ => None,
        })
        .collect();
    assert_eq!(arms, vec![(0, 4), (1, 1)], "{sent:?}");
    tree.shutdown().await;
}

#[tokio::test(start_paused = true)]
async fn a_pose_that_is_not_finite_is_no_pose_and_nothing_that_is_not_finite_is_sent() {
    let (tree, f, mut queues, starts) = server().await;
    for robot in ROBOTS {
        f.cast(safety(robot, SafetyState::Disarmed(DisarmReason::Startup), 1)).unwrap();
    }
    f.cast(FormationMsg::Rearm).unwrap();
    let mut moving = false;
    let mut stopped = false;
    for k in 1..=60u32 {
        let now = f64::from(k) * 0.05;
        localised(&f, &starts, u64::from(k), now);
        if k >= 3 {
            for robot in ROBOTS {
                f.cast(safety(robot, SafetyState::Armed, 1)).unwrap();
            }
        }
        if k >= 30 {
            // robot-a's odometry breaks: NaN, then beyond any map.
            let pose = if k < 45 { Se2::new(f64::NAN, 0.0, 0.0) } else { Se2::new(1e308, -1e308, 3.0) };
            f.cast(odom("robot-a", 100 + u64::from(k), now, pose)).unwrap();
        }
        for (i, d) in period(&f, &mut queues).await {
            match d {
                Downlink::Command(c) => {
                    assert!(c.v_mps.is_finite() && c.w_radps.is_finite(), "to robot {i} at {now}: {c:?}");
                    moving |= c.v_mps != 0.0 && k < 30;
                }
                Downlink::Disarm => stopped = true,
                _ => {}
            }
        }
    }
    assert!(moving, "the formation never ran");
    assert!(stopped, "robot-a not localised: the formation stops (on_robot_lost = stop)");
    tree.shutdown().await;
}

/// Running on a verified V, robot-b is put 0.5 m beside its slot: the plan waits (its time
/// does not advance), the status says who, and robot-b is driven towards its slot (with V at
/// rest the tracking law would leave it there); back in its slot, the plan goes on.
#[tokio::test(start_paused = true)]
async fn a_robot_out_of_its_slot_stops_the_plan_until_the_formation_has_re_formed() {
    let (tree, f, mut queues, starts) = server().await;
    for robot in ROBOTS {
        f.cast(safety(robot, SafetyState::Disarmed(DisarmReason::Startup), 1)).unwrap();
    }
    f.cast(FormationMsg::Rearm).unwrap();
    let beside = vec![starts[0], starts[1] * Se2::new(0.0, -0.5, 0.0)];
    let status = || async { ractor::call!(f, FormationMsg::Status).unwrap() };
    let (mut plan_at_push, mut turned) = (None, false);
    for k in 1..=80u32 {
        let now = f64::from(k) * 0.05;
        let at = if (30..60).contains(&k) { &beside } else { &starts };
        localised(&f, at, u64::from(k), now);
        if k >= 3 {
            for robot in ROBOTS {
                f.cast(safety(robot, SafetyState::Armed, 1)).unwrap();
            }
        }
        let sent = period(&f, &mut queues).await;
        let st = status().await;
        if k == 30 {
            plan_at_push = Some(st.plan_s);
        }
        if (32..60).contains(&k) {
            match &st.phase {
                Phase::Holding { reason } => {
                    assert!(reason.starts_with("re-forming: robot-b"), "{reason}")
                }
                p => panic!("at {k}: {p:?}"),
            }
            assert!(plan_at_push.is_some_and(|p| (st.plan_s - p).abs() < 0.11), "at {k}: {}", st.plan_s);
            turned |=
                sent.iter().any(|(i, d)| *i == 1 && matches!(d, Downlink::Command(c) if c.w_radps != 0.0));
        }
        if k == 79 {
            assert_eq!(st.phase, Phase::Running);
            assert!(plan_at_push.is_some_and(|p| st.plan_s > p + 0.5), "{}", st.plan_s);
        }
    }
    assert!(turned, "robot-b was not driven towards its slot");
    tree.shutdown().await;
}

/// Twists for V (a teleop on `/cmd_vel`) drive the armed formation instead of its plan: both
/// robots forward, within their limits, the plan paused; when the twists stop, V stops within
/// the timeout and the formation holds, armed, saying why; the next twist moves it again. A
/// twist that is not finite is ignored.
#[tokio::test(start_paused = true)]
async fn twists_for_v_drive_the_formation_and_their_silence_stops_it() {
    let (tree, f, mut queues, starts) = server().await;
    for robot in ROBOTS {
        f.cast(safety(robot, SafetyState::Disarmed(DisarmReason::Startup), 1)).unwrap();
    }
    f.cast(FormationMsg::Rearm).unwrap();
    let status = || async { ractor::call!(f, FormationMsg::Status).unwrap() };
    let speed = |sent: &[(usize, Downlink)], i: usize| {
        sent.iter().rev().find_map(|(j, d)| match d {
            Downlink::Command(c) if *j == i => Some((c.v_mps, c.w_radps)),
            _ => None,
        })
    };
    let max = load(&ConfigSource::Embedded).unwrap().scenarios["straight"].limits.max_speed_mps.get();
    let (mut last_moving, mut plan_at_twist) = (None, None);
    for k in 1..=100u32 {
        let now = f64::from(k) * 0.05;
        localised(&f, &starts, u64::from(k), now);
        if k >= 3 {
            for robot in ROBOTS {
                f.cast(safety(robot, SafetyState::Armed, 1)).unwrap();
            }
        }
        // Twists from 10 to 40, a NaN one at 41, none after, one again at 80.
        if (10..=40).contains(&k) || k == 80 {
            f.cast(FormationMsg::Twist { v_mps: 5.0, w_radps: 0.0 }).unwrap();
        }
        if k == 41 {
            f.cast(FormationMsg::Twist { v_mps: f64::NAN, w_radps: 0.0 }).unwrap();
        }
        let sent = period(&f, &mut queues).await;
        let st = status().await;
        if k == 10 {
            plan_at_twist = Some(st.plan_s);
        }
        if (30..=40).contains(&k) {
            for i in 0..2 {
                let (v, _) =
                    speed(&sent, i).unwrap_or_else(|| panic!("at {k}: nothing to robot {i}: {sent:?}"));
                assert!(v > 0.05 && v <= max + 1e-9, "at {k}: robot {i} at {v} m/s (limit {max})");
            }
            assert_eq!(st.phase, Phase::Running, "at {k}");
            assert_eq!(Some(st.plan_s), plan_at_twist, "the plan is paused while teleoperated");
            last_moving = Some(k);
        }
        // 0.5 s (10 periods) after the last twist, and a period of slack.
        if (52..80).contains(&k) {
            for i in 0..2 {
                assert_eq!(speed(&sent, i), Some((0.0, 0.0)), "at {k}: robot {i} {sent:?}");
            }
            match &st.phase {
                Phase::Holding { reason } => {
                    assert!(reason.starts_with("teleoperated: no twist"), "{reason}")
                }
                p => panic!("at {k}: {p:?}"),
            }
            assert!(!sent.iter().any(|(_, d)| matches!(d, Downlink::Disarm)), "stays armed: {sent:?}");
        }
        if k == 82 {
            assert_eq!(st.phase, Phase::Running, "the next twist moves it again");
            assert!(speed(&sent, 0).is_some_and(|(v, _)| v > 0.0), "{sent:?}");
        }
    }
    assert_eq!(last_moving, Some(40));
    tree.shutdown().await;
}
