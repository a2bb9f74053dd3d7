//! `amr sim --ros2-live zenoh` as a ROS 2 user sees it, through an independent rmw_zenoh peer
//! (`peers/ros2_live_peer.py`: eclipse-zenoh and rosbags) that joins after the fleet started: the
//! graph lists our publishers with ROS 2's type names and QoS, the scans, odometry, estimates and
//! /tf decode as ROS 2 types with rmw_zenoh attachments, /clock carries the fleet's clock, and /map and /tf_static reach the late
//! joiner. Loopback only: our node is the graph's Zenoh router on a free local port.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code: a failed step fails the test")]

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use amr_actors::config::{ConfigSource, load};
use hil_tests::config_dir;

#[test]
fn a_ros2_user_sees_the_simulated_fleet_live_over_rmw_zenoh() {
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let router = format!("tcp/127.0.0.1:{port}");
    let config = config_dir();
    let mut sim = Command::new(env!("CARGO_BIN_EXE_amr"))
        .args(["sim", "--quiet", "--duration", "14", "--config", config.to_str().unwrap()])
        .args(["--ros2-live", "zenoh", "--ros2-router", &router, "--ros2-domain", "9"])
        .env_remove("RUST_LOG")
        .env_remove("ROS_DOMAIN_ID")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Join late: the map and the mounts went out when the run started.
    std::thread::sleep(Duration::from_secs(3));
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/cli_runs/peers/ros2_live_peer.py");
    let peer = Command::new("python3")
        .args([script, &port.to_string(), "9", "5"])
        .output()
        .expect("python3 (the CI installs eclipse-zenoh and rosbags)");
    let deadline = Instant::now() + Duration::from_secs(60);
    let status = loop {
        if let Some(s) = sim.try_wait().unwrap() {
            break s;
        }
        assert!(Instant::now() < deadline, "amr sim did not end");
        std::thread::sleep(Duration::from_millis(200));
    };
    let mut err = String::new();
    std::io::Read::read_to_string(sim.stderr.as_mut().unwrap(), &mut err).unwrap();
    assert!(status.success(), "amr sim: {err}");
    assert!(peer.status.success(), "peer: {}", String::from_utf8_lossy(&peer.stderr));
    let v: serde_json::Value = serde_json::from_slice(&peer.stdout).unwrap();

    // The graph: our publishers with ROS 2's names, types and QoS.
    let publishers = v["publishers"].as_array().unwrap();
    let offered = |topic: &str| {
        publishers
            .iter()
            .find(|p| p["topic"] == topic)
            .map(|p| (p["type"].as_str().unwrap().to_owned(), p["qos"].as_str().unwrap().to_owned()))
    };
    assert_eq!(
        offered("/robot_a/scan"),
        Some(("sensor_msgs::msg::dds_::LaserScan_".into(), "2::,5:,:,:,,".into()))
    );
    assert_eq!(offered("/map"), Some(("nav_msgs::msg::dds_::OccupancyGrid_".into(), ":1:,1:,:,:,,".into())));
    assert_eq!(offered("/tf_static").map(|o| o.1), Some(":1:,1:,:,:,,".into()));
    assert_eq!(offered("/tf").map(|o| o.1), Some("::,100:,:,:,,".into()));
    assert_eq!(
        offered("/amcl/V").map(|o| o.0),
        Some("geometry_msgs::msg::dds_::PoseWithCovarianceStamped_".into())
    );

    // The RViz configuration shipped for ROS 2 users shows only what we publish, each with a QoS
    // our offer matches, and its "2D Pose Estimate" publishes where we listen.
    let rviz_path = concat!(env!("CARGO_MANIFEST_DIR"), "/../ros2/rviz/amr.rviz");
    let rviz: serde_norway::Value =
        serde_norway::from_str(&std::fs::read_to_string(rviz_path).unwrap()).unwrap();
    let manager = &rviz["Visualization Manager"];
    let mut shown = 0;
    for d in manager["Displays"].as_sequence().unwrap() {
        let Some(t) = d["Topic"]["Value"].as_str() else { continue };
        let want = match d["Class"].as_str().unwrap() {
            "rviz_default_plugins/Map" => "nav_msgs::msg::dds_::OccupancyGrid_",
            "rviz_default_plugins/LaserScan" => "sensor_msgs::msg::dds_::LaserScan_",
            "rviz_default_plugins/PoseWithCovariance" => {
                "geometry_msgs::msg::dds_::PoseWithCovarianceStamped_"
            }
            other => panic!("a display of {other} on {t}: say which type it shows"),
        };
        let (ty, qos) = offered(t).unwrap_or_else(|| panic!("RViz shows {t}, which is not published"));
        assert_eq!(ty, want, "{t}");
        let mut q = qos.split(':');
        let (reliability, durability) = (q.next().unwrap(), q.next().unwrap());
        if d["Topic"]["Reliability Policy"].as_str() == Some("Reliable") {
            assert_ne!(reliability, "2", "RViz asks {t} reliable; it is offered best effort");
        }
        if d["Topic"]["Durability Policy"].as_str() == Some("Transient Local") {
            assert_eq!(durability, "1", "RViz asks {t} transient local; it is offered volatile");
        }
        shown += 1;
    }
    assert!(shown >= 4);
    let pose_tool = manager["Tools"]
        .as_sequence()
        .unwrap()
        .iter()
        .find(|t| t["Class"] == "rviz_default_plugins/SetInitialPose");
    let pose_topic = pose_tool.and_then(|t| t["Topic"]["Value"].as_str()).unwrap();
    let subscribed = v["subscriptions"].as_array().unwrap();
    assert!(
        subscribed.iter().any(|s| s["topic"] == pose_topic
            && s["type"] == "geometry_msgs::msg::dds_::PoseWithCovarianceStamped_"),
        "{pose_topic} not subscribed: {subscribed:?}"
    );

    let topic = |t: &str| &v["topics"][t];
    // Scans at 15 Hz for 5 s, each with its attachment.
    let scans = topic("/robot_a/scan");
    let n = scans["count"].as_u64().unwrap();
    assert!(n >= 20, "{scans}");
    assert_eq!(scans["attachments"].as_u64(), Some(n));
    assert_eq!(scans["first"]["frame_id"], "robot-a/laser");
    assert!(scans["first"]["ranges"].as_u64().unwrap() > 100, "{scans}");
    assert!(scans["last"]["stamp"].as_f64().unwrap() > scans["first"]["stamp"].as_f64().unwrap());
    // The fleet's clock on /clock (for `use_sim_time`), and the scans stamped on it.
    let clock = topic("/clock");
    assert!(clock["count"].as_u64().unwrap() > 20, "{clock}");
    let (t0, t1) = (clock["first"]["t"].as_f64().unwrap(), clock["last"]["t"].as_f64().unwrap());
    assert!(t1 - t0 > 3.0, "{clock}");
    assert!((scans["last"]["stamp"].as_f64().unwrap() - t1).abs() < 1.0, "{scans} {clock}");
    assert_eq!(topic("/virtual/scan")["first"]["frame_id"], "V");
    assert_eq!(topic("/robot_a/odom")["first"]["child"], "robot-a");
    let v_pose = &topic("/amcl/V")["last"];
    assert_eq!(v_pose["frame_id"], "map", "{v_pose}");
    assert!(v_pose["x"].as_f64().unwrap().is_finite());
    let pairs = |t: &str| topic(t)["first"]["pairs"].as_array().unwrap().clone();
    let has = |t: &str, parent: &str, child: &str| pairs(t).iter().any(|p| p[0] == parent && p[1] == child);
    assert!(topic("/tf")["count"].as_u64().unwrap() > 5);

    // V under REP 105, as a robot: V/odom → V from V's odometry, map → V/odom from our estimate.
    let tf_pairs = topic("/tf")["pairs"].as_array().unwrap();
    let has_pair = |p: &str, c: &str| tf_pairs.iter().any(|x| x[0] == p && x[1] == c);
    assert!(has_pair("V/odom", "V") && has_pair("map", "V/odom"), "{tf_pairs:?}");
    assert!(has_pair("robot-a/odom", "robot-a") && has_pair("map", "robot-a/odom"), "{tf_pairs:?}");
    assert!(!has_pair("map", "V"), "V has one parent");

    // nav2_amcl on V (ros2/nav2/v_amcl.yaml): each topic it subscribes, with the QoS it asks
    // (nav2_amcl's amcl_node.cpp: the scan as sensor data, the map transient local; tf2's
    // listener), is offered compatibly; its frames are ours.
    let params_path = concat!(env!("CARGO_MANIFEST_DIR"), "/../ros2/nav2/v_amcl.yaml");
    let params: serde_norway::Value =
        serde_norway::from_str(&std::fs::read_to_string(params_path).unwrap()).unwrap();
    let amcl = &params["amcl"]["ros__parameters"];
    let scan_topic = amcl["scan_topic"].as_str().unwrap();
    for (t, want_type, reliable, transient) in [
        (scan_topic, "sensor_msgs::msg::dds_::LaserScan_", false, false),
        ("/map", "nav_msgs::msg::dds_::OccupancyGrid_", true, true),
        ("/tf", "tf2_msgs::msg::dds_::TFMessage_", true, false),
        ("/tf_static", "tf2_msgs::msg::dds_::TFMessage_", true, true),
    ] {
        let (ty, qos) = offered(t).unwrap_or_else(|| panic!("nav2_amcl subscribes {t}: not published"));
        assert_eq!(ty, want_type, "{t}");
        let mut q = qos.split(':');
        let (r, d) = (q.next().unwrap(), q.next().unwrap());
        assert!(!reliable || r != "2", "{t}: nav2_amcl asks reliable, offered {qos}");
        assert!(!transient || d == "1", "{t}: nav2_amcl asks transient local, offered {qos}");
    }
    assert!(has_pair(amcl["odom_frame_id"].as_str().unwrap(), amcl["base_frame_id"].as_str().unwrap()));
    assert_eq!(amcl["global_frame_id"], "map");
    assert_eq!(
        topic(scan_topic)["first"]["frame_id"].as_str(),
        amcl["base_frame_id"].as_str(),
        "the laser is V itself"
    );

    // /diagnostics: V's integrity and the formation's phase, as rqt_robot_monitor shows them.
    let statuses = topic("/diagnostics")["statuses"].as_array().unwrap().clone();
    let named = |n: &str| statuses.iter().filter(|s| s[0] == n).cloned().collect::<Vec<_>>();
    let v_diag = named("amr: V localisation");
    assert!(!v_diag.is_empty(), "{statuses:?}");
    assert!(v_diag.len() <= 12, "once a second or on a change, not at the scan rate: {}", v_diag.len());
    assert!(
        v_diag.iter().any(|s| s[1] == 0 && s[3]["state"] == "tracking"),
        "V tracking at some point of the run: {v_diag:?}"
    );
    let formation = named("amr: formation");
    assert!(formation.len() >= 3, "{formation:?}");
    assert!(
        formation.iter().any(|s| s[2].as_str().unwrap().starts_with("running") && s[1] == 0),
        "the formation was running: {formation:?}"
    );

    // The late joiner got the latched topics once each.
    assert_eq!(topic("/tf_static")["count"], 1, "{}", topic("/tf_static"));
    assert!(has("/tf_static", "robot-a", "robot-a/laser") && has("/tf_static", "robot-b", "robot-b/laser"));
    let map = topic("/map");
    assert_eq!(map["count"], 1, "{map}");
    let grid = load(&ConfigSource::Dir(config)).unwrap().scenario("straight").unwrap().map;
    assert_eq!(map["first"]["width"].as_u64(), Some(grid.width as u64));
    assert_eq!(map["first"]["height"].as_u64(), Some(grid.height as u64));
    assert_eq!(map["first"]["cells"].as_u64(), Some((grid.width * grid.height) as u64));
    assert!((map["first"]["resolution"].as_f64().unwrap() - grid.resolution_m).abs() < 1e-6);
}
