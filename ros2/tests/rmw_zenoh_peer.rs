//! Our rmw_zenoh node against an independent peer (`peers/rmw_zenoh_peer.py`: eclipse-zenoh,
//! rosbags and xxhash, written from rmw_zenoh's design document): it sees our node and endpoints
//! in the graph, decodes our scans, gets our `/map` though it joins after it was published, finds
//! each attachment and GID as rmw_zenoh writes them; and we decode its `/cmd_vel`, and get its
//! latched `/peer_map` though we subscribe after it was published.
//! Loopback only; the Zenoh session has multicast scouting off.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code: a failed step fails the test")]

use std::time::Duration;

use amr_ros2::msg::{Header, LaserScan, OccupancyGrid, Pose, Ros2Message, Time, Twist};
use amr_ros2::node::{Mode, Node, NodeOptions};
use amr_ros2::rmw_zenoh::Qos;

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

fn scan(i: u32) -> LaserScan {
    LaserScan {
        header: Header::new(100.0 + f64::from(i) * 0.1, "robot_a/laser"),
        angle_min: -2.0,
        angle_max: 2.0,
        angle_increment: 0.5,
        range_max: 10.0,
        ranges: vec![1.0, 2.0, f32::NAN, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0],
        ..Default::default()
    }
}

fn map() -> OccupancyGrid {
    OccupancyGrid {
        header: Header::new(1.0, "map"),
        map_load_time: Time::from_secs(1.0),
        resolution: 0.05,
        width: 4,
        height: 3,
        origin: Pose::planar(-1.0, -2.0, 0.0),
        data: vec![0, 100, -1, 0, 0, 0, 100, 100, -1, -1, 0, 0],
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_independent_rmw_zenoh_peer_sees_decodes_and_drives_our_node() {
    let port = free_port();
    let domain = 7;
    let mut o = NodeOptions::new("amr");
    o.domain = domain;
    o.mode = Mode::Router;
    o.connect = vec![];
    o.listen = vec![format!("tcp/127.0.0.1:{port}")];
    let node = Node::open(&o).await.unwrap();
    let map_pub = node.publisher("/map", OccupancyGrid::TYPE, Qos::LATCHED).await.unwrap();
    let scan_pub = node.publisher("/robot_a/scan", LaserScan::TYPE, Qos::SENSOR_DATA).await.unwrap();
    let cmd = node.subscription("/cmd_vel", Twist::TYPE, Qos::reliable(10)).await.unwrap();
    // Published once, before the peer exists.
    map_pub.put(map().to_cdr()).unwrap();

    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/peers/rmw_zenoh_peer.py");
    let peer = tokio::process::Command::new("python3")
        .args([script, &port.to_string(), &domain.to_string()])
        .kill_on_drop(true)
        .output();
    let done = std::sync::atomic::AtomicBool::new(false);
    let peer = async {
        let out = peer.await;
        done.store(true, std::sync::atomic::Ordering::SeqCst);
        out
    };
    let publishing = async {
        // Scans at about 10 Hz while the peer runs (it gives up after 16 s), and its /cmd_vel; once
        // a twist came, the peer has put its latched /peer_map: a subscription made now must still
        // get it.
        let (mut got, mut late) = (None, None);
        let mut late_map = None;
        for i in 0..250u32 {
            if done.load(std::sync::atomic::Ordering::SeqCst) {
                break;
            }
            scan_pub.put(scan(i).to_cdr()).unwrap();
            match tokio::time::timeout(Duration::from_millis(100), cmd.recv()).await {
                Ok(Some(r)) if got.is_none() => {
                    got = Some(r);
                    late = Some(
                        node.subscription("/peer_map", OccupancyGrid::TYPE, Qos::LATCHED).await.unwrap(),
                    );
                }
                _ => {}
            }
            if let (Some(sub), None) = (&late, &late_map)
                && let Ok(Some(r)) = tokio::time::timeout(Duration::from_millis(1), sub.recv()).await
            {
                late_map = Some(r);
            }
        }
        (got, late_map)
    };
    let (out, (got, late_map)) =
        tokio::time::timeout(Duration::from_secs(40), async { tokio::join!(peer, publishing) })
            .await
            .expect("the peer finishes within 40 s");
    let out = out.expect("python3 (the CI installs eclipse-zenoh, rosbags and xxhash)");
    assert!(out.status.success(), "peer failed: {}", String::from_utf8_lossy(&out.stderr));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();

    // The graph, as rmw_zenoh's design document spells it, with rosbags' type hashes.
    let zid = &node.info().zid;
    let hash = |t: &str| v["hashes"][t].as_str().unwrap().to_owned();
    let tokens: Vec<&str> = v["tokens"].as_array().unwrap().iter().map(|t| t.as_str().unwrap()).collect();
    let want = [
        format!("@ros2_lv/{domain}/{zid}/0/0/NN/%/%/amr"),
        format!(
            "@ros2_lv/{domain}/{zid}/0/1/MP/%/%/amr/%map/nav_msgs::msg::dds_::OccupancyGrid_/{}/:1:,1:,:,:,,",
            hash("nav_msgs/msg/OccupancyGrid")
        ),
        format!(
            "@ros2_lv/{domain}/{zid}/0/2/MP/%/%/amr/%robot_a%scan/sensor_msgs::msg::dds_::LaserScan_/{}/2::,5:,:,:,,",
            hash("sensor_msgs/msg/LaserScan")
        ),
        format!(
            "@ros2_lv/{domain}/{zid}/0/3/MS/%/%/amr/%cmd_vel/geometry_msgs::msg::dds_::Twist_/{}/::,10:,:,:,,",
            hash("geometry_msgs/msg/Twist")
        ),
    ];
    for w in &want {
        assert!(tokens.contains(&w.as_str()), "{w} not among {tokens:#?}");
    }

    // Our scans, decoded by rosbags, each with a valid attachment whose GID is the token's hash.
    let scans = v["scans"].as_array().unwrap();
    assert_eq!(scans.len(), 5, "{v}");
    let mut last = 0;
    for s in scans {
        assert_eq!(s["frame_id"], "robot_a/laser");
        assert_eq!(s["ranges"], 9);
        assert_eq!(s["angle_increment"], 0.5);
        let a = &s["attachment"];
        assert_eq!(
            (a["len"].as_i64(), a["gid_ok"].as_bool(), a["time_ok"].as_bool()),
            (Some(16), Some(true), Some(true)),
            "{a}"
        );
        let seq = a["seq"].as_i64().unwrap();
        assert!(seq > last, "sequence numbers rise: {scans:?}");
        last = seq;
    }

    // The late joiner got the one /map.
    let maps = v["map"].as_array().unwrap();
    assert_eq!(maps.len(), 1, "{v}");
    let m = &maps[0];
    assert_eq!(
        (m["width"].as_u64(), m["height"].as_u64(), m["cells"].as_u64()),
        (Some(4), Some(3), Some(12))
    );
    assert_eq!(m["frame_id"], "map");
    assert_eq!(m["attachment"]["seq"], 1);
    assert_eq!(m["attachment"]["gid_ok"], true);

    // Its /cmd_vel, decoded by us, with its attachment.
    assert!(v["cmd_vel_sent"].as_u64().unwrap() >= 1);
    let got = got.expect("a /cmd_vel from the peer");
    assert_eq!(
        Twist::from_cdr(&got.payload).unwrap(),
        Twist { linear: [0.25, 0.0, 0.0], angular: [0.0, 0.0, -0.5] }
    );
    let a = got.attachment.expect("an rmw_zenoh attachment");
    assert!(a.sequence >= 1);

    // Our transient-local subscription, made after the peer put /peer_map, got it from the peer's
    // cache, as rmw_zenoh's would.
    let m = late_map.expect("the latched /peer_map, published before we subscribed");
    let grid = OccupancyGrid::from_cdr(&m.payload).unwrap();
    assert_eq!((grid.width, grid.height, grid.data.clone()), (2, 2, vec![0, 100, -1, 0]));
    assert_eq!(grid.header.frame_id, "peer");
    assert_eq!(m.attachment.map(|a| a.sequence), Some(1));
    node.close().await.unwrap();
}
