#![allow(clippy::unwrap_used, reason = "tests")]

use std::sync::Arc;

use amr_core::config::value::Count;
use amr_core::scan::Scan;
use proptest::prelude::*;

use super::*;
use crate::config::{ConfigSource, load};

/// The shipped server on the paper site, with few particles (fast in a debug build).
fn core() -> ServerCore {
    core_with(&[0.45, -0.45])
}

/// [`core`] with a robot in each of `slots`.
fn core_with(slots: &[f64]) -> ServerCore {
    let config = load(&ConfigSource::Embedded).unwrap();
    let mut amcl = config.amcl.clone();
    amcl.min_particles = Count::new(100).unwrap();
    amcl.max_particles = Count::new(100).unwrap();
    let map = &config.maps["paper-site"];
    let ids: Vec<String> = (0..slots.len())
        .map(|i| if i < 2 { ["robot-a", "robot-b"][i].to_owned() } else { format!("robot-{i}") })
        .collect();
    let members = ids
        .iter()
        .zip(slots.iter().copied())
        .map(|(id, y)| Member {
            id: (*id).to_owned(),
            lidar_to_base: Se2::new(0.175, 0.0, 0.0),
            chassis: config.robots[0].chassis.outline_m.clone(),
            weight: 1.0,
            slot_y_m: y,
        })
        .collect();
    ServerCore::new(CoreSetup {
        members,
        configurations: vec![Configuration::T4],
        vamr: config.vamr.clone(),
        max_spread_s: 0.05,
        max_age_s: 0.1,
        field: Arc::new(LikelihoodField::new(map, &amcl, 10.0)),
        amcl,
        initial_v: Se2::new(-2.0, 0.0, 0.0),
        seed: 1,
        oracle: amr_core::vamr::pipeline::Oracle::default(),
        checks: amr_core::config::IntegrityChecks::default(),
    })
}

fn scan(robot: &str, stamp_s: f64, step: f64, n: usize) -> Uplink {
    Uplink::Scan(ScanMsg {
        robot: robot.to_owned(),
        seq: 1,
        stamp_s,
        received_s: stamp_s,
        scan: Arc::new(Scan::new(-135f64.to_radians(), step, 0.05, 10.0, vec![3.0; n])),
        odom: Some(Se2::IDENTITY),
        odom_frame: 1,
    })
}

fn tim551(robot: &str, stamp_s: f64) -> Uplink {
    scan(robot, stamp_s, 1f64.to_radians(), 271)
}

#[test]
fn impossible_geometry_is_refused_with_its_reason() {
    let mut c = core();
    let refused = |c: &mut ServerCore, u: &Uplink| c.offer(u, 1.0, &mut |_| {}).refused;
    assert_eq!(refused(&mut c, &scan("robot-a", 1.0, 0.0, 271)), Some(Refusal::AngleStep(0.0)));
    assert_eq!(refused(&mut c, &scan("robot-a", 1.0, 1e-9, 271)), Some(Refusal::AngleStep(1e-9)));
    assert_eq!(refused(&mut c, &scan("robot-a", 1.0, f64::NAN, 271)).map(|r| r.kind()), Some("geometry"));
    // 271 beams 2° apart sweep more than a turn.
    assert!(matches!(
        refused(&mut c, &scan("robot-a", 1.0, 2f64.to_radians(), 271)),
        Some(Refusal::AngleStep(_))
    ));
    assert_eq!(refused(&mut c, &scan("robot-a", 1.0, 1e-3, 5000)), Some(Refusal::BeamCount(5000)));
    assert_eq!(refused(&mut c, &scan("robot-a", 1.0, 1e-3, 0)), Some(Refusal::BeamCount(0)));
    assert_eq!(refused(&mut c, &tim551("robot-c", 1.0)), Some(Refusal::UnknownRobot("robot-c".into())));
    assert_eq!(refused(&mut c, &tim551("robot-a", f64::NAN)).map(|r| r.kind()), Some("stamp"));
    assert_eq!(refused(&mut c, &tim551("robot-a", 1.0)), None, "a TiM551 scan");
    assert_eq!(refused(&mut c, &tim551("robot-a", 1.0)), Some(Refusal::NotNewer));
}

#[test]
fn a_future_stamp_is_refused_and_does_not_hold_back_later_scans() {
    let mut c = core();
    let mut fused = 0;
    // Robot-a's clock jumps an hour ahead once.
    let step = c.offer(&tim551("robot-a", 3600.0), 0.0, &mut |_| {});
    assert!(matches!(step.refused, Some(Refusal::Stamp { .. })), "{:?}", step.refused);
    for k in 0..10 {
        let t = 0.1 + f64::from(k) / 15.0;
        for r in ["robot-a", "robot-b"] {
            let step = c.offer(&tim551(r, t), t + 0.01, &mut |_| {});
            assert_eq!(step.refused, None, "{r} at {t}");
            fused += step.fusions.len();
        }
    }
    assert_eq!(fused, 10, "every pair of scans fused");
}

fn any_f64() -> impl Strategy<Value = f64> {
    prop_oneof![
        Just(0.0),
        Just(-0.0),
        Just(f64::NAN),
        Just(f64::INFINITY),
        Just(f64::NEG_INFINITY),
        Just(f64::MIN_POSITIVE),
        Just(1e-300),
        Just(1f64.to_radians()),
        -10.0..10.0f64,
        any::<f64>(),
    ]
}

fn any_uplink() -> impl Strategy<Value = (Uplink, f64)> {
    (
        prop_oneof![Just("robot-a"), Just("robot-b"), Just("robot-x")],
        prop_oneof![0usize..400, Just(271), 4090usize..4200],
        (any_f64(), any_f64(), any_f64(), any_f64()),
        (any_f64(), 0.0..1e6f64, proptest::option::of((any_f64(), any_f64(), any_f64()))),
        proptest::collection::vec(any_f64(), 0..16),
        any::<bool>(),
    )
        .prop_map(|(robot, n, (min, step, lo, hi), (stamp, rx, odom), pattern, sane)| {
            // Half the scans have a TiM551's geometry and a plausible stamp, so the pipeline and
            // the filters run on whatever ranges and odometry come with them.
            let (min, step, lo, hi, stamp) = if sane {
                (-2.356, 1f64.to_radians(), 0.05, 10.0, rx - 0.01)
            } else {
                (min, step, lo, hi, stamp)
            };
            let ranges =
                (0..n).map(|i| pattern.get(i % pattern.len().max(1)).copied().unwrap_or(2.0)).collect();
            let u = Uplink::Scan(ScanMsg {
                robot: robot.to_owned(),
                seq: 0,
                stamp_s: stamp,
                received_s: stamp,
                scan: Arc::new(Scan::new(min, step, lo, hi, ranges)),
                odom: odom.map(|(x, y, t)| Se2 { x, y, theta: t }),
                odom_frame: 1,
            });
            (u, rx)
        })
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 200, ..ProptestConfig::default() })]

    /// The server's whole scan path (the checks, both robots' AMCL, the Virtual-AMR pipeline, AMCL
    /// on the virtual scan) takes any scan a network peer could send: used or refused, never a
    /// panic, and the core still fuses good scans afterwards.
    #[test]
    fn any_uplink_is_used_or_refused_never_a_panic(inputs in proptest::collection::vec(any_uplink(), 1..6)) {
        let mut c = core();
        for (u, rx) in &inputs {
            let step = c.offer(u, *rx, &mut |_| {});
            if step.refused.is_none() {
                let Uplink::Scan(s) = u else { unreachable!() };
                prop_assert!(check_scan(s, *rx).is_ok());
            }
        }
        // The receive time is the server's own clock (never from the wire): after these, 2e6 s
        // is later than any stamp the core can have accepted.
        let late = 2e6;
        let mut fused = 0;
        for k in 0..3 {
            let t = late + f64::from(k) / 15.0;
            for r in ["robot-a", "robot-b"] {
                fused += c.offer(&tim551(r, t), t + 0.01, &mut |_| {}).fusions.len();
            }
        }
        prop_assert_eq!(fused, 3);
    }
}

fn scan_in_frame(robot: &str, stamp_s: f64, odom: Se2, frame: u64) -> Uplink {
    Uplink::Scan(ScanMsg {
        robot: robot.to_owned(),
        seq: 1,
        stamp_s,
        received_s: stamp_s,
        scan: Arc::new(Scan::new(-135f64.to_radians(), 1f64.to_radians(), 0.05, 10.0, vec![3.0; 271])),
        odom: Some(odom),
        odom_frame: frame,
    })
}

/// A robot that restarts comes back with its odometry at the origin of a new frame.
/// Its AMCL must not read that as a jump of the robot (2 m back here): the pose holds.
#[test]
fn a_restarted_robots_odometry_is_not_read_as_motion() {
    let mut c = core();
    let own = |step: &Step| {
        step.estimates
            .iter()
            .find(|e| e.source == EstimateSource::Robot(0))
            .and_then(|e| e.robots[0])
            .map(|a| a.map)
    };
    let mut before = None;
    for k in 0..10 {
        let t = 0.1 + f64::from(k) / 15.0;
        let step = c.offer(&scan_in_frame("robot-a", t, Se2::new(2.0, 0.0, 0.0), 7), t, &mut |_| {});
        assert!(!step.odometry_restarted);
        before = own(&step).or(before);
    }
    let before = before.unwrap();
    let t = 1.0;
    let step = c.offer(&scan_in_frame("robot-a", t, Se2::IDENTITY, 8), t, &mut |_| {});
    assert!(step.odometry_restarted, "the new frame was seen");
    let after = own(&step).unwrap();
    let moved = ((after.x - before.x).powi(2) + (after.y - before.y).powi(2)).sqrt();
    assert!(moved < 0.5, "the estimate moved {moved} m across the restart: {before:?} -> {after:?}");
    // Same frame again: no restart.
    let step = c.offer(&scan_in_frame("robot-a", 1.1, Se2::IDENTITY, 8), 1.1, &mut |_| {});
    assert!(!step.odometry_restarted);
}

#[test]
fn in_a_line_each_robot_is_observed_by_its_neighbour_nearer_to_the_reference() {
    let members = |n: usize| -> Vec<Member> {
        amr_core::formation::slots(n, 0.9)
            .into_iter()
            .enumerate()
            .map(|(i, y)| Member {
                id: format!("r{i}"),
                lidar_to_base: Se2::IDENTITY,
                chassis: amr_core::geometry::Polygon::new(vec![
                    [-0.2, -0.2],
                    [0.2, -0.2],
                    [0.2, 0.2],
                    [-0.2, 0.2],
                ])
                .unwrap(),
                weight: 1.0,
                slot_y_m: y,
            })
            .collect()
    };
    let observers = |n: usize| (1..n).map(|i| observer(&members(n), i)).collect::<Vec<_>>();
    // Two robots: the paper's pair. Three: both beside the reference in the middle.
    assert_eq!(observers(2), vec![0]);
    assert_eq!(observers(3), vec![0, 0]);
    // Slots 0, +s, −s, +2s, −2s, …: each by the one a slot nearer, on its side.
    assert_eq!(observers(4), vec![0, 0, 1]);
    assert_eq!(observers(8), vec![0, 0, 1, 2, 3, 4, 5]);
}

/// A virtual-scan filter is not started when the core is built (it starts where the robots' own
/// estimates put V at the first fused update: the virtual-time simulation whose fusion starts late
/// checks where), and keeps every robot's beam budget.
#[test]
fn a_virtual_filter_waits_for_fusion_and_keeps_every_robots_beams() {
    let slots = amr_core::formation::slots(4, 0.6);
    let core = core_with(&slots);
    let f = core.filter(EstimateSource::Fused(Configuration::T4)).unwrap();
    assert!(f.particles().is_empty() && f.estimate().is_none(), "V's filter is not started before fusion");
    assert_eq!(f.integrity_state(), amr_core::amcl::IntegrityState::Uncertain);
    let config = load(&ConfigSource::Embedded).unwrap();
    assert_eq!(virtual_params(&config.amcl, 4).max_beams.get(), 4 * config.amcl.max_beams.get());
}

/// RViz's "2D Pose Estimate": every robot's filter starts again in its slot around the given V,
/// not yet verified; nonsense is refused and changes nothing.
#[test]
fn an_initial_pose_restarts_each_robots_filter_in_its_slot() {
    let mut core = core();
    let v = Se2::new(1.0, 2.0, 0.5);
    assert!(!core.set_initial_pose(Se2::new(f64::NAN, 0.0, 0.0), 0.2, 0.1));
    assert!(!core.set_initial_pose(v, 0.0, 0.1));
    assert!(!core.set_initial_pose(v, 0.2, f64::INFINITY));
    let before = core.filter(EstimateSource::Robot(0)).unwrap().estimate().unwrap().pose;
    assert!((before.x - -2.0).abs() < 0.3, "{before:?}");
    assert!(core.set_initial_pose(v, 0.2, 0.1));
    for (i, slot) in [0.45, -0.45].into_iter().enumerate() {
        let f = core.filter(EstimateSource::Robot(i)).unwrap();
        let want = v * Se2::new(0.0, slot, 0.0);
        let n = f.particles().len() as f64;
        let (mx, my) =
            f.particles().iter().fold((0.0, 0.0), |(x, y), p| (x + p.pose.x / n, y + p.pose.y / n));
        assert!((mx - want.x).hypot(my - want.y) < 0.1, "robot {i}: mean ({mx}, {my}), want {want:?}");
        assert_ne!(f.integrity_state(), amr_core::amcl::IntegrityState::Tracking, "not verified yet");
    }
}

/// A robot's own filter is given its scan without the returns on its teammates' bodies: where
/// the fusion last placed them (carried on by the odometry), before that where their own estimates
/// put them; the rest of the scan is kept, and with no teammate known nothing is masked.
#[test]
fn a_robots_own_filter_does_not_see_its_teammates() {
    let mut core = core_with(&[0.25, -0.25]);
    // In robot-b's base frame robot-a stands 0.5 m to the left (+y), facing the same way.
    let on_a = [[0.0, 0.5 - 0.2], [0.1, 0.5 - 0.21], [-0.1, 0.5 - 0.19]];
    let elsewhere = [[3.0, 0.0], [0.0, -2.0], [0.0, 0.5 - 0.6]];
    let all: Vec<[f64; 2]> = on_a.iter().chain(&elsewhere).copied().collect();
    let masked = |core: &ServerCore, i: usize, odom: Se2, rx_s: f64| {
        let mut points = all.clone();
        core.mask_teammates(i, odom, rx_s, &mut points);
        points
    };
    assert_eq!(masked(&core, 1, Se2::IDENTITY, 1.0), all, "robot-a has sent no scan: nothing to mask it by");
    assert!(core.offer(&tim551("robot-a", 1.0), 1.0, &mut |_| {}).refused.is_none());
    let chassis = core.members()[0].chassis.clone();
    assert!(
        on_a.iter().all(|p| chassis.contains_inflated([p[0], p[1] - 0.5], 0.05)),
        "the test's points are on robot-a"
    );
    assert_eq!(
        masked(&core, 1, Se2::IDENTITY, 1.0),
        elsewhere.to_vec(),
        "robot-a's returns go, the others stay"
    );
    // Robot-a's own view: robot-b has sent nothing yet.
    assert_eq!(masked(&core, 0, Se2::IDENTITY, 1.0), all);
    // The fusion placed robot-a 1 m ahead of robot-b and 0.5 m to its left, whatever the two
    // estimates say; robot-b has driven 1 m since (its odometry), robot-a not.
    core.placed = Some(Placed {
        robots: vec![(Se2::new(1.0, 0.25, 0.0), Se2::IDENTITY), (Se2::new(0.0, -0.25, 0.0), Se2::IDENTITY)],
        rx_s: 1.0,
    });
    assert_eq!(masked(&core, 1, Se2::new(1.0, 0.0, 0.0), 1.5), elsewhere.to_vec(), "placed by the fusion");
    assert_eq!(masked(&core, 1, Se2::IDENTITY, 1.5), all, "1 m behind: none of these is on robot-a");
    // Too long ago: the estimates place the teammates again.
    assert_eq!(masked(&core, 1, Se2::IDENTITY, 1.0 + PLACED_FOR_S + 0.1), elsewhere.to_vec());
}
