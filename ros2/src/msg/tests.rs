//! Tests of the ROS 2 messages' CDR encoding and round trips, and of their schema text.

#![allow(clippy::unwrap_used, clippy::expect_used, reason = "tests")]
use super::*;

#[test]
fn diagnostics_round_trip_and_refuse_a_cut_message() {
    let d = DiagnosticArray {
        header: Header::new(3.5, ""),
        status: vec![
            DiagnosticStatus {
                level: DiagnosticStatus::WARN,
                name: "amr: V localisation".into(),
                message: "uncertain".into(),
                hardware_id: "V".into(),
                values: vec![("explained".into(), "0.71".into()), ("level".into(), "0.93".into())],
            },
            DiagnosticStatus::default(),
        ],
    };
    let b = d.to_cdr();
    assert_eq!(DiagnosticArray::from_cdr(&b).unwrap(), d);
    for cut in 0..b.len() {
        assert!(DiagnosticArray::from_cdr(&b[..cut]).is_err(), "cut at {cut}");
    }
}

#[test]
fn a_twist_is_six_doubles_after_the_header() {
    let t = Twist { linear: [0.5, 0.0, 0.0], angular: [0.0, 0.0, -0.25] };
    let b = t.to_cdr();
    assert_eq!(b.len(), 4 + 48);
    assert_eq!(b[4..12], 0.5f64.to_le_bytes());
    assert_eq!(b[44..52], (-0.25f64).to_le_bytes());
    assert_eq!(Twist::from_cdr(&b).unwrap(), t);
    assert!(Twist::from_cdr(&b[..40]).is_err());
    assert_eq!(type_hash("geometry_msgs/msg/Twist"), Some(Twist::TYPE_HASH));
    assert_eq!(type_hash("geometry_msgs/msg/Wrench"), None);
}

#[test]
fn messages_round_trip() {
    let scan = LaserScan {
        header: Header::new(12.25, "robot-a/laser"),
        angle_min: -2.0,
        angle_max: 2.0,
        angle_increment: 0.5,
        range_max: 10.0,
        ranges: vec![1.0, f32::INFINITY, 2.5, f32::NAN, 3.0, 0.0, 4.0, 5.0, 6.0],
        ..Default::default()
    };
    let back = LaserScan::from_cdr(&scan.to_cdr()).unwrap();
    assert_eq!(back.header, scan.header);
    assert_eq!(back.header.stamp, Time { sec: 12, nanosec: 250_000_000 });
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&back.ranges), bits(&scan.ranges));
    let odom = Odometry {
        header: Header::new(1.0, "odom"),
        child_frame_id: "base_link".into(),
        pose: PoseWithCovariance { pose: Pose::planar(1.0, -2.0, 0.5), covariance: [0.25; 36] },
        twist: TwistWithCovariance { linear: [0.2, 0.0, 0.0], ..Default::default() },
    };
    assert_eq!(Odometry::from_cdr(&odom.to_cdr()).unwrap(), odom);
    let tf = TfMessage {
        transforms: vec![
            TransformStamped::planar(3.0, "map", "V", 1.0, 2.0, 3.0),
            TransformStamped::planar(3.5, "odom", "base_link", -1.0, 0.0, -0.1),
        ],
    };
    assert_eq!(TfMessage::from_cdr(&tf.to_cdr()).unwrap(), tf);
    let grid = OccupancyGrid {
        header: Header::new(0.0, "map"),
        resolution: 0.05,
        width: 3,
        height: 2,
        origin: Pose::planar(-1.0, -2.0, 0.0),
        data: vec![-1, 0, 100, 50, 0, 0],
        ..Default::default()
    };
    assert_eq!(OccupancyGrid::from_cdr(&grid.to_cdr()).unwrap(), grid);
    let p = PoseWithCovarianceStamped {
        header: Header::new(2.0, "map"),
        pose: PoseWithCovariance { pose: Pose::planar(4.0, 5.0, -3.0), covariance: [1.0; 36] },
    };
    assert_eq!(PoseWithCovarianceStamped::from_cdr(&p.to_cdr()).unwrap(), p);
}

#[test]
fn times_and_yaw() {
    assert_eq!(Time::from_secs(1.999_999_999_9), Time { sec: 2, nanosec: 0 });
    assert_eq!(Time::from_secs(-0.5), Time { sec: -1, nanosec: 500_000_000 });
    assert_eq!(Time::from_secs(f64::NAN), Time::default());
    assert_eq!(Time::from_secs(1e12).sec, i32::MAX);
    for t in [-3.0, -1.0, 0.0, 0.7, 3.1] {
        let (_, _, y) = Pose::planar(0.0, 0.0, t).planar_parts();
        assert!((y - t).abs() < 1e-12, "{t} → {y}");
    }
    // Not normalised: the same yaw.
    let q = Pose::planar(0.0, 0.0, 1.0).orientation.map(|v| v * 3.0);
    assert!((yaw(q) - 1.0).abs() < 1e-12);
}

#[test]
fn schema_text_lists_each_dependency_once_after_its_separator() {
    let s = schema_text("nav_msgs/msg/Odometry").unwrap();
    assert!(s.starts_with("std_msgs/Header header\nstring child_frame_id\n"));
    let sep = format!("{}\nMSG: ", "=".repeat(80));
    let deps: Vec<&str> = s.split(&sep).skip(1).map(|b| b.lines().next().unwrap()).collect();
    assert_eq!(
        deps,
        [
            "std_msgs/Header",
            "builtin_interfaces/Time",
            "geometry_msgs/PoseWithCovariance",
            "geometry_msgs/Pose",
            "geometry_msgs/Point",
            "geometry_msgs/Quaternion",
            "geometry_msgs/TwistWithCovariance",
            "geometry_msgs/Twist",
            "geometry_msgs/Vector3"
        ]
    );
    assert!(schema_text("sensor_msgs/msg/Imu").is_none());
}
