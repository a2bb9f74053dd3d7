#![allow(clippy::unwrap_used, clippy::expect_used, reason = "tests")]
//! `--record --ros2`'s encoding checked by an independent reader: the Python `mcap` package reads
//! the file and `rosbags` (PyPI; `.ci/run` installs both) decodes every message with its own
//! definitions of the ROS 2 types, and parses our schema texts to compare them with those
//! definitions. Then the values that come out are compared with the events that went in.

use std::sync::Arc;

use amr_core::config::Configuration;
use amr_core::map::OccupancyGrid;
use amr_core::scan::Scan;
use amr_core::se2::Se2;
use amr_msgs::{Anchored, Estimate, EstimateSource, FusedFrame, OdomMsg, ScanMsg, StageTimes};
use amr_record::FileRecorder;
use amr_record::encode::Event;
use serde_json::Value;

/// Reads the bag with python's `mcap` and deserializes each message with `rosbags`' ROS 2 Humble
/// type store; prints the header profile, channels, schemas' agreement, QoS and decoded values.
const READER: &str = r#"
import json, math, sys
from mcap.reader import make_reader
from rosbags.typesys import Stores, get_typestore, get_types_from_msg
from ruamel.yaml import YAML

ts = get_typestore(Stores.ROS2_HUMBLE)

def plain(v):
    if hasattr(v, '__dataclass_fields__'):
        return {k: plain(getattr(v, k)) for k in v.__dataclass_fields__ if k != '__msgtype__'}
    if hasattr(v, 'tolist'):
        v = v.tolist()
    if isinstance(v, (list, tuple)):
        return [plain(x) for x in v]
    if isinstance(v, float) and not math.isfinite(v):
        return 'nan' if math.isnan(v) else ('inf' if v > 0 else '-inf')
    return v

out = {'channels': {}, 'messages': [], 'schema_mismatches': [], 'metadata': []}
with open(sys.argv[1], 'rb') as f:
    r = make_reader(f)
    out['profile'] = r.get_header().profile
    summary = r.get_summary()
    for s in summary.schemas.values():
        ours = get_types_from_msg(s.data.decode(), s.name)
        for name, (consts, fields) in ours.items():
            if ts.fielddefs[name][1] != fields:
                out['schema_mismatches'].append(name)
        out.setdefault('schemas', {})[s.name] = {'encoding': s.encoding, 'types': sorted(ours)}
    for c in summary.channels.values():
        qos = YAML(typ='safe').load(c.metadata.get('offered_qos_profiles', '')) or []
        out['channels'][c.topic] = {
            'encoding': c.message_encoding,
            'schema': summary.schemas[c.schema_id].name,
            'qos': qos,
        }
    for m in r.iter_metadata():
        out['metadata'].append({'name': m.name, 'keys': sorted(m.metadata)})
    f.seek(0)
    for schema, channel, message in make_reader(f).iter_messages():
        msg = ts.deserialize_cdr(message.data, schema.name)
        out['messages'].append({'topic': channel.topic, 'log_time': message.log_time, 'msg': plain(msg)})
print(json.dumps(out))
"#;

fn python_read(path: &std::path::Path) -> Value {
    let out = std::process::Command::new("python3")
        .args(["-c", READER, path.to_str().unwrap()])
        .output()
        .expect("python3 (the CI installs it with `mcap` and `rosbags`)");
    assert!(
        out.status.success(),
        "the python reader failed (pip install mcap rosbags): {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

fn f(v: &Value) -> f64 {
    match v {
        Value::String(s) if s == "nan" => f64::NAN,
        Value::String(s) if s == "inf" => f64::INFINITY,
        v => v.as_f64().unwrap(),
    }
}

fn stamp(h: &Value) -> f64 {
    h["stamp"]["sec"].as_f64().unwrap() + h["stamp"]["nanosec"].as_f64().unwrap() * 1e-9
}

/// The planar pose of a `geometry_msgs/Pose` (or a Transform's translation and rotation).
fn planar(position: &Value, q: &Value) -> Se2 {
    let (x, y, z, w) = (f(&q["x"]), f(&q["y"]), f(&q["z"]), f(&q["w"]));
    assert!(x.abs() < 1e-12 && y.abs() < 1e-12, "a planar rotation");
    Se2::new(f(&position["x"]), f(&position["y"]), 2.0 * z.atan2(w))
}

fn close(a: Se2, b: Se2) -> bool {
    (a.x - b.x).abs() < 1e-9
        && (a.y - b.y).abs() < 1e-9
        && amr_core::se2::angle_diff(a.theta, b.theta).abs() < 1e-9
}

#[test]
fn an_independent_cdr_reader_decodes_every_message_with_the_values_that_went_in() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("run.mcap");
    let robots = vec!["robot-a".to_owned(), "robot-b".to_owned()];
    let mut rec = FileRecorder::create_ros2(&path, robots).unwrap();

    let mut map = OccupancyGrid::filled(7, 3, 0.05, Se2::new(-1.0, -2.0, 0.3), -1);
    map.cells[0] = 100;
    map.cells[8] = 0;
    map.cells[20] = 42;
    rec.put(0.5, &Event::Map(map.clone())).unwrap();
    let mounts = vec![
        ("robot-a".to_owned(), Se2::new(0.2, 0.1, 0.05)),
        ("robot-b".to_owned(), Se2::new(0.3, -0.1, 3.1)),
    ];
    rec.put(0.5, &Event::Mounts(mounts.clone())).unwrap();
    // 271 beams of 1° from −135°, every 7th invalid.
    let ranges: Vec<f64> =
        (0..271).map(|i| if i % 7 == 3 { f64::NAN } else { 0.5 + f64::from(i) * 0.01 }).collect();
    let scan = Scan::new(-135f64.to_radians(), 1f64.to_radians(), 0.05, 10.0, ranges.clone());
    let scan_msg = ScanMsg {
        robot: "robot-a".into(),
        seq: 1,
        stamp_s: 1.25,
        received_s: 1.26,
        scan: Arc::new(scan),
        odom: None,
        odom_frame: 0,
    };
    rec.put(1.26, &Event::Scan(scan_msg)).unwrap();
    let odom_pose = Se2::new(1.5, -0.25, 2.5);
    let odom = OdomMsg { seq: 1, frame: 1, stamp_s: 1.3, pose: odom_pose, twist: (0.2, -0.1), gyro: true };
    rec.put(1.31, &Event::Odom("robot-b".into(), odom)).unwrap();
    let (v, a_map, a_odom) = (Se2::new(3.0, 4.0, -2.0), Se2::new(3.1, 4.4, -1.9), Se2::new(0.5, 0.1, 0.2));
    let v_odom = Se2::new(0.7, -0.2, 0.4);
    let estimate = Estimate {
        source: EstimateSource::Fused(Configuration::T4),
        stamp_s: 1.4,
        v: Some(v),
        robots: vec![Some(Anchored { map: a_map, odom: a_odom, stamp_s: 1.4 }), None],
        integrity: amr_msgs::EstimateIntegrity::default(),
        covariance: Some([[0.04, 0.01, 0.0], [0.01, 0.09, 0.002], [0.0, 0.002, 0.0025]]),
    };
    rec.put(1.41, &Event::Estimate(estimate)).unwrap();
    let points = vec![[1.0, 0.0], [0.0, 2.0], [1.2, 0.001], [-3.0, 0.0]];
    let fused = FusedFrame {
        seq: 1,
        configuration: Configuration::T4,
        // The frame of the estimate above (the same stamp), after it, as it may come live.
        stamp_s: 1.4,
        oldest_stamp_s: 1.39,
        v_odom,
        points: Some(Arc::new(points)),
        robots: vec![],
        times: StageTimes::default(),
    };
    rec.put(1.46, &Event::Fused(fused)).unwrap();
    rec.finish().unwrap();

    let out = python_read(&path);
    assert_eq!(out["profile"], "ros2");
    assert_eq!(
        out["schema_mismatches"],
        serde_json::json!([]),
        "our schema texts against rosbags' definitions"
    );
    let meta: Vec<&str> =
        out["metadata"].as_array().unwrap().iter().map(|m| m["name"].as_str().unwrap()).collect();
    assert!(meta.contains(&"rosbag2"), "{meta:?}");
    let ch = &out["channels"];
    for (topic, schema) in [
        ("/map", "nav_msgs/msg/OccupancyGrid"),
        ("/tf_static", "tf2_msgs/msg/TFMessage"),
        ("/robot_a/scan", "sensor_msgs/msg/LaserScan"),
        ("/robot_b/odom", "nav_msgs/msg/Odometry"),
        ("/tf", "tf2_msgs/msg/TFMessage"),
        ("/amcl/V", "geometry_msgs/msg/PoseWithCovarianceStamped"),
        ("/amcl/robot_a", "geometry_msgs/msg/PoseWithCovarianceStamped"),
        ("/virtual/scan", "sensor_msgs/msg/LaserScan"),
        ("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray"),
    ] {
        assert_eq!(ch[topic]["schema"], schema, "{topic}: {ch}");
        assert_eq!(ch[topic]["encoding"], "cdr");
        let qos = &ch[topic]["qos"][0];
        assert_eq!(qos["reliability"], 1, "{topic}: reliable");
        let latched = topic == "/map" || topic == "/tf_static";
        assert_eq!(
            qos["durability"],
            if latched { 1 } else { 2 },
            "{topic}: transient_local only if latched"
        );
    }
    assert_eq!(ch.as_object().unwrap().len(), 9, "{ch}");
    for s in out["schemas"].as_object().unwrap().values() {
        assert_eq!(s["encoding"], "ros2msg");
    }

    let msgs = out["messages"].as_array().unwrap();
    let one = |topic: &str| -> &Value {
        let all: Vec<&Value> = msgs.iter().filter(|m| m["topic"] == topic).collect();
        assert_eq!(all.len(), 1, "{topic}");
        &all[0]["msg"]
    };
    // The map: geometry and every cell in the same order.
    let m = one("/map");
    assert_eq!(m["header"]["frame_id"], "map");
    assert_eq!((m["info"]["width"].as_u64(), m["info"]["height"].as_u64()), (Some(7), Some(3)));
    assert!((f(&m["info"]["resolution"]) - 0.05).abs() < 1e-7);
    assert!(close(planar(&m["info"]["origin"]["position"], &m["info"]["origin"]["orientation"]), map.origin));
    let cells: Vec<i64> = m["data"].as_array().unwrap().iter().map(|c| c.as_i64().unwrap()).collect();
    assert_eq!(cells, map.cells.iter().map(|c| i64::from(*c)).collect::<Vec<_>>());
    // The mounts, on /tf_static.
    let t = one("/tf_static")["transforms"].as_array().unwrap();
    assert_eq!(t.len(), 2);
    for (tr, (robot, p)) in t.iter().zip(&mounts) {
        assert_eq!(tr["header"]["frame_id"], robot.as_str());
        assert_eq!(tr["child_frame_id"], format!("{robot}/laser"));
        assert!(close(planar(&tr["transform"]["translation"], &tr["transform"]["rotation"]), *p));
    }
    // The scan: stamp, geometry, every range (f32), invalid beams NaN.
    let s = one("/robot_a/scan");
    assert_eq!(s["header"]["frame_id"], "robot-a/laser");
    assert!((stamp(&s["header"]) - 1.25).abs() < 1e-9);
    assert!((f(&s["angle_min"]) + 135f64.to_radians()).abs() < 1e-6);
    assert!((f(&s["angle_increment"]) - 1f64.to_radians()).abs() < 1e-7);
    assert!((f(&s["angle_max"]) - 135f64.to_radians()).abs() < 1e-5);
    let got: Vec<f64> = s["ranges"].as_array().unwrap().iter().map(f).collect();
    assert_eq!(got.len(), 271);
    for (g, r) in got.iter().zip(&ranges) {
        assert!(g.is_nan() == r.is_nan() && (r.is_nan() || (g - r).abs() < 1e-6), "{g} vs {r}");
    }
    // Odometry: pose, twist, frames; and the same on /tf.
    let o = one("/robot_b/odom");
    assert_eq!(
        (o["header"]["frame_id"].as_str(), o["child_frame_id"].as_str()),
        (Some("robot-b/odom"), Some("robot-b"))
    );
    assert!(close(planar(&o["pose"]["pose"]["position"], &o["pose"]["pose"]["orientation"]), odom_pose));
    assert_eq!(
        (f(&o["twist"]["twist"]["linear"]["x"]), f(&o["twist"]["twist"]["angular"]["z"])),
        (0.2, -0.1)
    );
    assert_eq!(o["pose"]["covariance"].as_array().unwrap().len(), 36);
    // The fused estimate: V, robot-a, and map→V, map→robot-a/odom on /tf.
    let pv = one("/amcl/V");
    assert!(close(planar(&pv["pose"]["pose"]["position"], &pv["pose"]["pose"]["orientation"]), v));
    // V's integrity on /diagnostics (the estimate's default, tracking: OK), as rosbags reads it.
    let d = &one("/diagnostics")["status"][0];
    assert_eq!(
        (d["name"].as_str(), d["level"].as_i64(), d["hardware_id"].as_str()),
        (Some("amr: V localisation"), Some(0), Some("V")),
        "{d}"
    );
    assert!(
        d["values"].as_array().unwrap().iter().any(|kv| kv["key"] == "state" && kv["value"] == "tracking"),
        "{d}"
    );
    let pa = one("/amcl/robot_a");
    assert!(close(planar(&pa["pose"]["pose"]["position"], &pa["pose"]["pose"]["orientation"]), a_map));
    // V's covariance in ROS's 6×6 layout (x, y, yaw at rows/columns 0, 1, 5), as rosbags reads it.
    let cov = |m: &Value| -> Vec<f64> {
        m["pose"]["covariance"].as_array().unwrap().iter().map(|c| c.as_f64().unwrap()).collect()
    };
    let cv = cov(pv);
    assert_eq!(
        (cv[0], cv[1], cv[6], cv[7], cv[35], cv[5], cv[11]),
        (0.04, 0.01, 0.01, 0.09, 0.0025, 0.0, 0.002)
    );
    assert_eq!(cv[14], 0.0, "no z variance");
    // robot-a inherits it through its offset from V: more position variance from V's heading's.
    let ca = cov(pa);
    assert!(ca[0] + ca[7] > cv[0] + cv[7] && (ca[35] - 0.0025).abs() < 1e-12, "{ca:?}");
    let tfs: Vec<&Value> = msgs
        .iter()
        .filter(|m| m["topic"] == "/tf")
        .flat_map(|m| m["msg"]["transforms"].as_array().unwrap())
        .collect();
    let find = |parent: &str, child: &str| -> Se2 {
        let t =
            tfs.iter().find(|t| t["header"]["frame_id"] == parent && t["child_frame_id"] == child).unwrap();
        planar(&t["transform"]["translation"], &t["transform"]["rotation"])
    };
    // V as a robot under REP 105: V/odom → V from V's odometry, map → V/odom from the estimate.
    assert!(close(find("V/odom", "V"), v_odom));
    assert!(close(find("map", "V/odom") * find("V/odom", "V"), v));
    assert!(close(find("map", "robot-a/odom"), a_map * a_odom.inverse()));
    assert!(close(find("robot-b/odom", "robot-b"), odom_pose));
    // The virtual scan: 720 bins of 0.5° from −π, the nearest point per bin.
    let vs = one("/virtual/scan");
    assert_eq!(vs["header"]["frame_id"], "V");
    let bins: Vec<f64> = vs["ranges"].as_array().unwrap().iter().map(f).collect();
    assert_eq!(bins.len(), 720);
    assert!((f(&vs["angle_min"]) + std::f64::consts::PI).abs() < 1e-6);
    assert!((f(&vs["angle_increment"]) - 0.5f64.to_radians()).abs() < 1e-7);
    assert!((bins[360] - 1.0).abs() < 1e-6, "bearing 0: the nearer of 1.0 and 1.2");
    assert!((bins[540] - 2.0).abs() < 1e-6, "bearing 90°");
    assert!((bins[0] - 3.0).abs() < 1e-6, "bearing 180° is bin 0");
    assert_eq!(bins.iter().filter(|b| !b.is_nan()).count(), 3);
}

/// A small bag from `rosbags`' own writer and serializer: two scans (one big endian), odometry at
/// 10 Hz, the mounting on /tf_static.
const BAG_WRITER: &str = r#"
import math, sys
import numpy as np
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

ts = get_typestore(Stores.ROS2_HUMBLE)
T = ts.types
Time, Header = T['builtin_interfaces/msg/Time'], T['std_msgs/msg/Header']
V3, Q = T['geometry_msgs/msg/Vector3'], T['geometry_msgs/msg/Quaternion']
def quat(th):
    return Q(x=0.0, y=0.0, z=math.sin(th / 2), w=math.cos(th / 2))
w = Writer(sys.argv[1], version=9, storage_plugin=StoragePlugin.MCAP)
if len(sys.argv) > 2:
    w.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
w.open()
TF, LS, OD = 'tf2_msgs/msg/TFMessage', 'sensor_msgs/msg/LaserScan', 'nav_msgs/msg/Odometry'
c_static = w.add_connection('/tf_static', TF, typestore=ts)
c_scan = w.add_connection('/scan', LS, typestore=ts)
c_odom = w.add_connection('/odom', OD, typestore=ts)
mount = T['geometry_msgs/msg/TransformStamped'](
    header=Header(stamp=Time(sec=0, nanosec=0), frame_id='base_link'), child_frame_id='laser',
    transform=T['geometry_msgs/msg/Transform'](translation=V3(x=0.25, y=-0.125, z=0.3), rotation=quat(0.5)))
w.write(c_static, 0, ts.serialize_cdr(T[TF](transforms=[mount]), TF))
for k in range(3):
    t = 1.0 + 0.1 * k
    pose = T['geometry_msgs/msg/Pose'](position=T['geometry_msgs/msg/Point'](x=2.0 + k, y=-1.0 * k, z=0.0), orientation=quat(0.25 * k))
    msg = T[OD](header=Header(stamp=Time(sec=1, nanosec=100000000 * k), frame_id='odom'), child_frame_id='base_link',
        pose=T['geometry_msgs/msg/PoseWithCovariance'](pose=pose, covariance=np.zeros(36)),
        twist=T['geometry_msgs/msg/TwistWithCovariance'](twist=T['geometry_msgs/msg/Twist'](linear=V3(x=0.0, y=0.0, z=0.0), angular=V3(x=0.0, y=0.0, z=0.0)), covariance=np.zeros(36)))
    w.write(c_odom, int(t * 1e9), ts.serialize_cdr(msg, OD))
ranges = np.array([0.5 + 0.01 * i for i in range(201)], dtype=np.float32)
ranges[3], ranges[4], ranges[5], ranges[6] = np.inf, np.nan, 0.05, 25.0
for k, big in enumerate([False, True]):
    msg = T[LS](header=Header(stamp=Time(sec=1, nanosec=50000000 + 100000000 * k), frame_id='laser'),
        angle_min=-1.0, angle_max=1.0, angle_increment=0.01, time_increment=0.0, scan_time=0.1,
        range_min=0.1, range_max=20.0, ranges=ranges, intensities=np.array([], dtype=np.float32))
    w.write(c_scan, int((1.06 + 0.1 * k) * 1e9), ts.serialize_cdr(msg, LS, little_endian=not big))
w.close()
"#;

/// Writes the bag (zstd-compressed chunks if `zstd`) into `dir`, returns its .mcap file.
fn rosbags_bag(dir: &std::path::Path, zstd: bool) -> std::path::PathBuf {
    let bag = dir.join("bag");
    let mut cmd = std::process::Command::new("python3");
    cmd.args(["-c", BAG_WRITER]).arg(&bag);
    if zstd {
        cmd.arg("zstd");
    }
    let out = cmd.output().unwrap();
    assert!(
        out.status.success(),
        "rosbags writer (pip install rosbags): {}",
        String::from_utf8_lossy(&out.stderr)
    );
    std::fs::read_dir(&bag)
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.extension().is_some_and(|e| e == "mcap"))
        .unwrap()
}

#[test]
fn a_zstd_compressed_bag_is_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let rec = amr_record::read::read_file(&rosbags_bag(dir.path(), true)).unwrap();
    assert!(rec.messages.is_empty());
    let why = rec.stopped.unwrap();
    assert!(why.contains("zstd-compressed chunk"), "{why}");
}

#[test]
fn a_bag_written_by_rosbags_reads_back_exactly() {
    use amr_core::carmen::Record;
    use amr_record::ros2::bag::{BagOptions, OdomSource, read};

    let dir = tempfile::tempdir().unwrap();
    let file = rosbags_bag(dir.path(), false);
    let rec = amr_record::read::read_file(&file).unwrap();
    assert!(rec.stopped.is_none(), "{:?}", rec.stopped);
    let log = read(&rec.messages, &BagOptions::default()).unwrap();
    assert_eq!(log.odometry, OdomSource::Topic("/odom".into()));
    assert_eq!(log.odometry_samples, 3);
    assert!(log.skipped.is_empty(), "{:?}", log.skipped);
    assert_eq!(log.records.len(), 2);
    for (k, r) in log.records.iter().enumerate() {
        let Record::Laser(l) = r else { panic!("a laser record") };
        // Stamps, beam geometry and ranges exactly as written (f32 widened), either byte order.
        assert!((l.timestamp_s - (1.05 + 0.1 * k as f64)).abs() < 1e-9, "{}", l.timestamp_s);
        assert_eq!(l.scan.angle_min_rad, -1.0);
        assert_eq!(l.scan.angle_increment_rad, f64::from(0.01f32));
        assert_eq!((l.scan.range_min_m, l.scan.range_max_m), (f64::from(0.1f32), 20.0));
        let r = l.scan.ranges_m();
        assert_eq!(r.len(), 201);
        assert!(r[3..7].iter().all(|x| x.is_nan()), "inf, NaN, below and above the limits: invalid");
        for i in (0..201).filter(|i| !(3..7).contains(i)) {
            assert_eq!(r[i], f64::from((0.5 + 0.01 * i as f64) as f32), "beam {i}");
        }
        // The odometry halfway between two samples.
        let o = l.odometry.unwrap();
        let expected = Se2::new(2.5 + k as f64, -0.5 - k as f64, 0.125 + 0.25 * k as f64);
        assert!(close(o, expected), "scan {k}: {o:?} vs {expected:?}");
        // The mounting, on the plane.
        assert!(close(l.laser_in_robot, Se2::new(0.25, -0.125, 0.5)), "{:?}", l.laser_in_robot);
    }
}

/// Our type hashes against `rosbags`' own computation of REP 2011's hash from its definitions of
/// the types (Jazzy's store).
#[test]
fn type_hashes_match_an_independent_computation() {
    let ours = amr_record::ros2::msg::TYPE_HASHES;
    // nav2_msgs is not in rosbags' store: its two types registered from their .msg files
    // (ros-navigation/navigation2, nav2_msgs/msg/Particle.msg and ParticleCloud.msg, comments left
    // out: they do not enter the hash).
    let script = "import sys\nfrom rosbags.typesys import Stores, get_typestore, get_types_from_msg\n\
                  ts = get_typestore(Stores.ROS2_JAZZY)\n\
                  t = get_types_from_msg('geometry_msgs/Pose pose\\n\\nfloat64 weight\\n', 'nav2_msgs/msg/Particle')\n\
                  t.update(get_types_from_msg('std_msgs/Header header\\n\\nParticle[] particles\\n', \
                  'nav2_msgs/msg/ParticleCloud'))\n\
                  ts.register(t)\n\
                  for name in sys.argv[1:]:\n    print(name, ts.hash_rihs01(name))\n";
    let out = std::process::Command::new("python3")
        .args(["-c", script])
        .args(ours.iter().map(|(t, _)| *t))
        .output()
        .expect("python3 (the CI installs `rosbags`)");
    assert!(out.status.success(), "rosbags failed: {}", String::from_utf8_lossy(&out.stderr));
    let theirs = String::from_utf8(out.stdout).unwrap();
    let theirs: Vec<(&str, &str)> = theirs.lines().filter_map(|l| l.split_once(' ')).collect();
    assert_eq!(theirs, ours);
}
