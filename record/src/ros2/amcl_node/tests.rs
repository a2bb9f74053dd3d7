//! `AmclNode` without a network: a small room, scans cast in it, odometry on /tf.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "tests")]
use amr_core::geometry::Polygon;
use amr_core::map::rasterize_outlines;
use amr_core::scan::Scan;

use super::*;
use crate::ros2::{laser_scan, occupancy_grid};

/// An L-shaped room with a pillar (a pose is unique in it).
fn grid() -> Grid {
    let room =
        Polygon::new(vec![[0.0, 0.0], [8.0, 0.0], [8.0, 3.0], [5.0, 3.0], [5.0, 5.0], [0.0, 5.0]]).unwrap();
    let pillar = Polygon::new(vec![[2.0, 2.0], [2.5, 2.0], [2.5, 2.4], [2.0, 2.4]]).unwrap();
    rasterize_outlines(&[room.clone(), pillar], &room, 0.05, Se2::new(-0.5, -0.5, 0.0), 180, 120)
}

fn config(initial: Option<Se2>) -> AmclNodeConfig {
    let text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../config/amcl.toml")).unwrap();
    let mut params: AmclParams = amr_core::config::parse_file("amcl.toml", &text).unwrap();
    params.initial_pose = None;
    let mut node_params = params;
    if let Some(p) = initial {
        let yaml = format!(
            "amcl:\n  ros__parameters:\n    set_initial_pose: true\n    initial_pose: {{x: {}, y: {}, yaw: {}}}\n",
            p.x, p.y, p.theta
        );
        node_params = amr_core::config::nav2::from_nav2_params("t.yaml", &yaml, &text).unwrap().params;
        // Our tuning, with nav2's initial pose.
        let ip = node_params.initial_pose;
        node_params = amr_core::config::parse_file("amcl.toml", &text).unwrap();
        node_params.initial_pose = ip;
    }
    let frames = Nav2Frames {
        base_frame_id: "base_link".into(),
        odom_frame_id: "odom".into(),
        global_frame_id: "map".into(),
        scan_topic: "scan".into(),
        map_topic: "map".into(),
        transform_tolerance_s: 0.3,
        tf_broadcast: true,
    };
    AmclNodeConfig { frames, params: node_params, seed: 3 }
}

/// The laser 0.2 m ahead of the base, turned by 0.3 rad.
const MOUNT: Se2 = Se2 { x: 0.2, y: 0.0, theta: 0.3 };

fn scan_at(g: &Grid, base: Se2, stamp: f64) -> LaserScan {
    let laser = base * MOUNT;
    let ranges = (0..241)
        .map(|i| {
            g.cast_ray([laser.x, laser.y], laser.theta - 2.0 + i as f64 * 0.0167, 20.0).unwrap_or(f64::NAN)
        })
        .collect();
    laser_scan(stamp, "laser", &Scan::new(-2.0, 0.0167, 0.05, 20.0, ranges))
}

fn tf(stamp: f64, parent: &str, child: &str, p: Se2) -> TfMessage {
    TfMessage { transforms: vec![TransformStamped::planar(stamp, parent, child, p.x, p.y, p.theta)] }
}

/// The odometry frame is not the map's.
const ODOM_IN_MAP: Se2 = Se2 { x: 3.0, y: -1.0, theta: 0.7 };

/// Drive along the bottom of the room: each scan after the odometry that covers it.
fn drive(node: &mut AmclNode, g: &Grid, scans: usize) -> Vec<(f64, Se2, Vec<Output>)> {
    let mut out = Vec::new();
    for k in 0..scans {
        let t = 10.0 + 0.2 * k as f64;
        let truth = Se2::new(1.0 + 0.1 * k as f64, 1.0, 0.02 * k as f64);
        let mut o = node.on_scan(scan_at(g, truth, t));
        assert!(o.is_empty() || k == 0, "a scan went before the odometry reached it");
        // The odometry 10 ms after the scan, the robot a little further on.
        let later = Se2::new(truth.x + 0.005, 1.0, truth.theta + 0.001);
        o.extend(node.on_tf(&tf(t + 0.01, "odom", "base_link", ODOM_IN_MAP.inverse() * later)));
        out.push((t, truth, o));
    }
    out
}

fn poses(o: &[Output]) -> Vec<&PoseWithCovarianceStamped> {
    o.iter().filter_map(|o| if let Output::Pose(p) = o { Some(&**p) } else { None }).collect()
}

#[test]
fn a_scan_waits_for_its_odometry_and_the_pose_follows_the_truth() {
    let g = grid();
    let mut node = AmclNode::new(config(Some(Se2::new(1.1, 0.9, 0.05))));
    node.on_tf(&tf(0.0, "base_link", "laser", MOUNT));
    node.on_tf(&tf(9.9, "odom", "base_link", ODOM_IN_MAP.inverse() * Se2::new(1.0, 1.0, 0.0)));
    node.on_map(&occupancy_grid(0.0, &g)).unwrap();
    let run = drive(&mut node, &g, 40);
    assert_eq!(node.stats.used, 40, "{:?}", node.stats);
    let mut errors = Vec::new();
    for (t, truth, o) in &run[10..] {
        // map → odom for every scan, stamped after it by the tolerance; map → odom ∘ odom = the pose.
        let tfs: Vec<&TfMessage> =
            o.iter().filter_map(|o| if let Output::Tf(m) = o { Some(m) } else { None }).collect();
        assert_eq!(tfs.len(), 1);
        let m = &tfs[0].transforms[0];
        assert_eq!((m.header.frame_id.as_str(), m.child_frame_id.as_str()), ("map", "odom"));
        assert!((m.header.stamp.secs() - (t + 0.3)).abs() < 1e-6);
        let map_odom = planar(m);
        assert!((map_odom.x - ODOM_IN_MAP.x).hypot(map_odom.y - ODOM_IN_MAP.y) < 0.1, "{map_odom:?}");
        for p in poses(o) {
            assert_eq!(p.header.frame_id, "map");
            assert!((p.header.stamp.secs() - t).abs() < 1e-6);
            let (x, y, th) = p.pose.pose.planar_parts();
            errors.push((x - truth.x).hypot(y - truth.y));
            assert!((th - truth.theta).abs() < 0.05, "{th} vs {}", truth.theta);
            let c = &p.pose.covariance;
            assert!(c[0] > 0.0 && c[7] > 0.0 && c[35] > 0.0, "{c:?}");
        }
    }
    assert!(errors.len() >= 5, "{} poses", errors.len());
    assert!(errors.iter().all(|e| *e < 0.1), "{errors:?}");
    let clouds: Vec<&ParticleCloud> = run
        .iter()
        .flat_map(|(_, _, o)| o.iter())
        .filter_map(|o| if let Output::Particles(c) = o { Some(c) } else { None })
        .collect();
    let last = clouds.last().unwrap();
    let total: f64 = last.particles.iter().map(|p| p.weight).sum();
    assert!(
        (total - 1.0).abs() < 1e-6 && last.particles.len() >= 100,
        "{total} over {}",
        last.particles.len()
    );
}

#[test]
fn without_an_initial_pose_nothing_is_published_until_the_filter_tracks() {
    let g = grid();
    let mut node = AmclNode::new(config(None));
    node.on_tf(&tf(0.0, "base_link", "laser", MOUNT));
    node.on_tf(&tf(9.9, "odom", "base_link", ODOM_IN_MAP.inverse() * Se2::new(1.0, 1.0, 0.0)));
    node.on_map(&occupancy_grid(0.0, &g)).unwrap();
    let run = drive(&mut node, &g, 40);
    let first = run.iter().position(|(_, _, o)| !o.is_empty()).expect("the filter localised globally");
    for (_, truth, o) in &run[first..] {
        for p in poses(o) {
            let (x, y, _) = p.pose.pose.planar_parts();
            assert!((x - truth.x).hypot(y - truth.y) < 0.2, "published off the truth: {x}, {y} vs {truth:?}");
        }
    }
    let diag = run[first..]
        .iter()
        .flat_map(|(_, _, o)| o.iter())
        .find_map(|o| if let Output::Diagnostics(d) = o { Some(d) } else { None });
    assert_eq!(diag.unwrap().status[0].level, DiagnosticStatus::OK);
}

#[test]
fn scans_without_map_or_odometry_are_counted_not_used() {
    let g = grid();
    let mut node = AmclNode::new(config(Some(Se2::new(1.0, 1.0, 0.0))));
    node.on_tf(&tf(20.0, "odom", "base_link", Se2::IDENTITY));
    node.on_tf(&tf(21.0, "odom", "base_link", Se2::IDENTITY));
    // Before the odometry kept; then one with no map.
    assert!(node.on_scan(scan_at(&g, Se2::new(1.0, 1.0, 0.0), 5.0)).is_empty());
    assert!(node.on_scan(scan_at(&g, Se2::new(1.0, 1.0, 0.0), 20.5)).is_empty());
    // Waiting for odometry that never comes: the queue keeps the newest ten.
    for k in 0..12 {
        assert!(node.on_scan(scan_at(&g, Se2::new(1.0, 1.0, 0.0), 30.0 + f64::from(k))).is_empty());
    }
    assert_eq!(
        node.stats,
        NodeStats { scans: 14, used: 0, without_map: 1, without_odometry: 3, unusable: 0, poses: 0 }
    );
}

#[test]
fn maps_that_cannot_be_a_grid_are_refused() {
    let good = occupancy_grid(0.0, &grid());
    assert!(grid_of(&good).is_ok());
    let mut cut = good.clone();
    cut.data.pop();
    assert!(grid_of(&cut).unwrap_err().contains("values"));
    let mut zero = good.clone();
    zero.resolution = 0.0;
    assert!(grid_of(&zero).is_err());
    let mut nan = good;
    nan.origin.position[0] = f64::NAN;
    assert!(grid_of(&nan).is_err());
}

#[test]
fn an_initial_pose_in_another_frame_is_refused_and_one_in_the_map_restarts_the_filter() {
    let mut node = AmclNode::new(config(None));
    let mut m = PoseWithCovarianceStamped {
        header: Header::new(1.0, "odom"),
        pose: PoseWithCovariance { pose: Pose::planar(1.0, 1.0, 0.0), covariance: [0.0; 36] },
    };
    assert!(node.on_initial_pose(&m).is_err());
    assert!(!node.pose_known);
    m.header.frame_id = "map".into();
    node.on_initial_pose(&m).unwrap();
    assert!(node.pose_known);
    assert!(matches!(node.start, Start::Pose { pose, .. } if pose == Se2::new(1.0, 1.0, 0.0)));
}
