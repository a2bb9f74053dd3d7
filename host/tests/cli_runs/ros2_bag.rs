//! `amr localize --bag` end to end: a simulated run (the CARMEN test's room, a laser mounted off
//! the base's centre and turned) written as ROS 2 bags by an independent writer, the PyPI package
//! `rosbags` (`.ci/run` installs it), localised by the binary and checked against the truth the
//! test drove. One bag has nav_msgs/Odometry on /odom, big-endian messages among the
//! little-endian ones and damaged scans; the other has its odometry on /tf only, other frame
//! names, the mounting through an intermediate frame, and a scan topic given on the command line.
//! The first bag again in rosbag2's sqlite3 storage gives the same poses. And `amr sim --record
//! --ros2` through the recorder actor, every message decoded by `rosbags`.
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::print_stderr,
    reason = "test code: a failed step fails the test; the errors measured are printed"
)]

use std::path::Path;
use std::process::{Command, Output};

use amr_core::geometry::{Polygon, cast_ray};
use amr_core::map::{MapMode, rasterize_outlines, save_map};
use amr_core::rng::Rng;
use amr_core::se2::{Se2, angle_diff};
use serde_json::{Value, json};

/// An L-shaped room with a pillar: asymmetric, so a pose is unique (as host/tests/cli_runs/localize.rs).
fn world() -> (Polygon, Vec<Polygon>) {
    let room =
        Polygon::new(vec![[0.0, 0.0], [8.0, 0.0], [8.0, 3.0], [5.0, 3.0], [5.0, 5.0], [0.0, 5.0]]).unwrap();
    let pillar = Polygon::new(vec![[2.0, 2.0], [2.5, 2.0], [2.5, 2.4], [2.0, 2.4]]).unwrap();
    (room.clone(), vec![room, pillar])
}

/// The laser in the base: ahead, to the left and turned, so a reader that drops the mounting
/// is off by about as much.
const MOUNT: Se2 = Se2 { x: 0.3, y: 0.1, theta: 0.4 };
/// Beams: not 1°, not symmetric, more than a half turn.
const ANGLE_MIN: f64 = -2.1;
const ANGLE_INCREMENT: f64 = 0.0125;
const BEAMS: usize = 329;
/// Scans at 5 Hz, odometry at 50 Hz.
const SCANS: usize = 120;
const ODOM_PER_SCAN: usize = 10;

pub(crate) struct Run {
    /// Scan stamps and the base's true pose then.
    pub truth: Vec<(f64, Se2)>,
    /// What the bag writer gets.
    pub data: Value,
}

/// Writes map.yaml + map.pgm into `dir`; drives the robot and returns the truth and the bags'
/// contents (scans as the laser saw them, odometry at 50 Hz).
pub(crate) fn simulate(dir: &Path) -> Run {
    let (room, walls) = world();
    let grid = rasterize_outlines(&walls, &room, 0.05, Se2::new(-0.5, -0.5, 0.0), 180, 120);
    let (yaml, image) = save_map(&grid, MapMode::Trinary, 0.65, 0.196, "map.pgm").unwrap();
    std::fs::write(dir.join("map.yaml"), yaml).unwrap();
    std::fs::write(dir.join("map.pgm"), image).unwrap();

    let scene: Vec<(Se2, &Polygon)> = walls.iter().map(|w| (Se2::IDENTITY, w)).collect();
    let mut rng = Rng::seed(7);
    let mut truth = Se2::new(1.0, 1.0, 0.0);
    // The odometry frame is not the map's: a reader that swaps or drops odometry axes moves the
    // filter the wrong way.
    let mut odom = Se2::new(10.0, -3.0, 1.0);
    let mut t = 100.0;
    let (mut scans, mut odoms, mut truths) = (Vec::new(), Vec::new(), Vec::new());
    for k in 0..SCANS {
        // Along the bottom, then up the left, turning on the way (per scan).
        let step = if k < 60 {
            Se2::new(0.1, 0.0, 0.0)
        } else if k < 75 {
            Se2::new(0.02, 0.0, 0.1)
        } else {
            Se2::new(0.06, 0.0, 0.0)
        };
        let sub = Se2::new(step.x / ODOM_PER_SCAN as f64, 0.0, step.theta / ODOM_PER_SCAN as f64);
        for _ in 0..ODOM_PER_SCAN {
            t += 0.2 / ODOM_PER_SCAN as f64;
            truth = truth * sub;
            odom = odom
                * Se2::new(
                    sub.x * 1.01 + rng.gaussian(0.0005),
                    rng.gaussian(0.0003),
                    sub.theta + rng.gaussian(0.0005),
                );
            odoms.push(json!({ "stamp": t, "x": odom.x, "y": odom.y, "theta": odom.theta }));
        }
        let laser = truth * MOUNT;
        let ranges: Vec<Value> = (0..BEAMS)
            .map(|i| {
                let a = laser.theta + ANGLE_MIN + i as f64 * ANGLE_INCREMENT;
                match cast_ray([laser.x, laser.y], a, 30.0, &scene) {
                    Some(r) if i % 50 != 7 => json!(r + rng.gaussian(0.01)),
                    Some(_) => json!("nan"),
                    None => json!("inf"),
                }
            })
            .collect();
        // The scan's stamp is a little before the last odometry sample: interpolated.
        let stamp = t - 0.007;
        let back = Se2::new(-sub.x * 0.35, 0.0, -sub.theta * 0.35);
        scans.push(json!({ "stamp": stamp, "ranges": ranges, "big_endian": k % 9 == 4 }));
        truths.push((stamp, truth * back));
    }
    let data = json!({
        "angle_min": ANGLE_MIN, "angle_increment": ANGLE_INCREMENT,
        "angle_max": ANGLE_MIN + (BEAMS - 1) as f64 * ANGLE_INCREMENT,
        "range_min": 0.05, "range_max": 30.0,
        "scans": scans, "odometry": odoms,
        "mount": { "x": MOUNT.x, "y": MOUNT.y, "theta": MOUNT.theta },
    });
    Run { truth: truths, data }
}

/// A nav2 params file with nav2's defaults but for the start pose (the bags' first pose).
const NAV2_DEFAULTS: &str =
    "amcl:\n  ros__parameters:\n    set_initial_pose: true\n    initial_pose: {x: 1.0, y: 1.0, yaw: 0.0}\n";

/// Writes the two bags with rosbags (its own CDR serializer, little and big endian).
const WRITER: &str = r#"
import json, math, sys
import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

ts = get_typestore(Stores.ROS2_HUMBLE)
T = ts.types
Time, Header = T['builtin_interfaces/msg/Time'], T['std_msgs/msg/Header']
V3, Q = T['geometry_msgs/msg/Vector3'], T['geometry_msgs/msg/Quaternion']

def stamp(t):
    # From whole nanoseconds: a time a hair below a whole second (100 + 0.02 k summed in floating
    # point) must carry into the seconds, not wrap to the start of the second before.
    ns = int(round(t * 1e9))
    return Time(sec=ns // 1000000000, nanosec=ns % 1000000000)

def quat(theta):
    return Q(x=0.0, y=0.0, z=math.sin(theta / 2), w=math.cos(theta / 2))

def tf(t, parent, child, x, y, theta):
    return T['geometry_msgs/msg/TransformStamped'](
        header=Header(stamp=stamp(t), frame_id=parent), child_frame_id=child,
        transform=T['geometry_msgs/msg/Transform'](translation=V3(x=x, y=y, z=0.0), rotation=quat(theta)))

def num(r):
    return float(r) if not isinstance(r, str) else float(r)

d = json.load(open(sys.argv[1]))
bag = json.load(open(sys.argv[2]))
out = []  # (log time ns, topic, type, bytes)
def put(t_ns, topic, typ, msg, big_endian=False):
    out.append((t_ns, topic, typ, bytes(ts.serialize_cdr(msg, typ, little_endian=not big_endian))))

TF = 'tf2_msgs/msg/TFMessage'
m = d['mount']
if bag['intermediate_frame']:
    statics = [tf(0, bag['base_frame'], 'laser_mount', m['x'], m['y'], 0.0),
               tf(0, 'laser_mount', 'laser', 0.0, 0.0, m['theta'])]
else:
    statics = [tf(0, bag['base_frame'], 'laser', m['x'], m['y'], m['theta'])]
put(0, '/tf_static', TF, T[TF](transforms=statics))
for o in d['odometry']:
    if bag.get('odometry_glitch') and abs(o['stamp'] - round(o['stamp'])) < 1e-6:
        # Each whole second's sample stamped a second early: the scan just after that stamp is
        # given odometry 0.3 m ahead, the next ones odometry back where it was.
        o = dict(o, stamp=round(o['stamp']) - 1.0)
    t_ns = int(round(o['stamp'] * 1e9))
    if bag['odometry'] == 'topic':
        P = T['geometry_msgs/msg/Pose'](position=T['geometry_msgs/msg/Point'](x=o['x'], y=o['y'], z=0.0), orientation=quat(o['theta']))
        msg = T['nav_msgs/msg/Odometry'](
            header=Header(stamp=stamp(o['stamp']), frame_id='odom'), child_frame_id=bag['base_frame'],
            pose=T['geometry_msgs/msg/PoseWithCovariance'](pose=P, covariance=np.zeros(36)),
            twist=T['geometry_msgs/msg/TwistWithCovariance'](
                twist=T['geometry_msgs/msg/Twist'](linear=V3(x=0.5, y=0.0, z=0.0), angular=V3(x=0.0, y=0.0, z=0.0)),
                covariance=np.zeros(36)))
        put(t_ns, '/odom', 'nav_msgs/msg/Odometry', msg)
    else:
        # With another transform in the same message, which the reader must leave alone.
        msg = T[TF](transforms=[tf(o['stamp'], 'map', bag['odom_frame'], 5.0, 5.0, 2.0),
                                 tf(o['stamp'], bag['odom_frame'], bag['base_frame'], o['x'], o['y'], o['theta'])])
        put(t_ns, '/tf', TF, msg)
LS = 'sensor_msgs/msg/LaserScan'
for i, s in enumerate(d['scans']):
    msg = T[LS](header=Header(stamp=stamp(s['stamp']), frame_id='laser'),
                angle_min=d['angle_min'], angle_max=d['angle_max'], angle_increment=d['angle_increment'],
                time_increment=0.0, scan_time=0.2, range_min=d['range_min'], range_max=d['range_max'],
                ranges=np.array([num(r) for r in s['ranges']], dtype=np.float32),
                intensities=np.array([], dtype=np.float32))
    t_ns = int(round((s['stamp'] + 0.01) * 1e9))
    put(t_ns, bag['scan_topic'], LS, msg, s['big_endian'] and bag['big_endian'])
for k, b in enumerate(bag['damaged']):
    # Damaged scans between the others: a cut message, another encapsulation (XCDR2), garbage.
    out.append((int(round((d['scans'][20 + 7 * k]['stamp'] + 0.011) * 1e9)), bag['scan_topic'], LS, bytes.fromhex(b)))
out.sort(key=lambda o: o[0])
if bag.get('storage') == 'sqlite3':
    # rosbag2's sqlite3 storage (rosbags writes bag versions 8 and 9 only; Humble's 5 has the
    # same topics and messages tables, without the type hash column).
    w = Writer(bag['path'], version=8, storage_plugin=StoragePlugin.SQLITE3)
else:
    w = Writer(bag['path'], version=9, storage_plugin=StoragePlugin.MCAP)
w.open()
conns = {}
for t_ns, topic, typ, data in out:
    if topic not in conns:
        conns[topic] = w.add_connection(topic, typ, typestore=ts)
    w.write(conns[topic], t_ns, data)
w.close()
"#;

/// A nav2 params file's `amcl` section saying, by nav2's names, what config/amcl.toml says (but
/// the slip tail, which nav2 has not).
pub(crate) fn ours_in_nav2_names() -> String {
    let ours: toml::Table =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../config/amcl.toml"))
            .unwrap()
            .parse()
            .unwrap();
    let mut yaml = String::from("amcl:\n  ros__parameters:\n");
    for (k, v) in &ours {
        if !v.is_table() && !k.starts_with("odom_slip") {
            yaml.push_str(&format!("    {k}: {v}\n"));
        }
    }
    yaml
}

fn write_bag(dir: &Path, run: &Run, bag: &Value) {
    let data = dir.join("sim.json");
    std::fs::write(&data, run.data.to_string()).unwrap();
    let spec = dir.join("bag.json");
    std::fs::write(&spec, bag.to_string()).unwrap();
    let out = Command::new("python3")
        .args(["-c", WRITER])
        .arg(&data)
        .arg(&spec)
        .output()
        .expect("python3 (the CI installs it with `rosbags`)");
    assert!(
        out.status.success(),
        "the rosbags writer failed (pip install rosbags): {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

fn localize(dir: &Path, bag: &Path, extra: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_amr"))
        .args(["localize", "--map"])
        .arg(dir.join("map.yaml"))
        .arg("--bag")
        .arg(bag)
        .args(["--initial", "1.0,1.0,0.0", "--seed", "3"])
        .args(extra)
        .env_remove("RUST_LOG")
        .output()
        .unwrap()
}

/// Scans of the CSV reported `tracking`, and `lost`.
fn states(csv: &str) -> (usize, usize) {
    let states: Vec<&str> = csv.lines().skip(1).filter_map(|l| l.split(',').nth(13)).collect();
    let count = |s: &str| states.iter().filter(|&&x| x == s).count();
    (count("tracking"), count("lost"))
}

/// Rows of the CSV against the truth: (rows, final error, worst error after the first 10 scans,
/// worst heading error in rad after them).
fn errors(csv: &str, truth: &[(f64, Se2)]) -> (usize, f64, f64, f64) {
    let mut lines = csv.lines();
    assert_eq!(
        lines.next(),
        Some(
            "timestamp,x,y,theta,cov_xx,cov_xy,cov_xtheta,cov_yx,cov_yy,cov_ytheta,cov_thetax,cov_thetay,cov_thetatheta,integrity,explained,level,ambiguous"
        )
    );
    // The pose and covariance (the integrity columns after them are the CARMEN test's).
    let rows: Vec<Vec<f64>> =
        lines.map(|l| l.split(',').take(13).map(|v| v.parse().unwrap()).collect()).collect();
    let (mut last, mut worst, mut worst_heading) = (f64::NAN, 0.0f64, 0.0f64);
    for (k, row) in rows.iter().enumerate() {
        assert_eq!(row.len(), 13);
        let (_, pose) =
            truth.iter().find(|(t, _)| (t - row[0]).abs() < 1e-6).expect("a pose at a scan's stamp");
        let e = (row[1] - pose.x).hypot(row[2] - pose.y);
        last = e;
        if k >= 10 {
            worst = worst.max(e);
            worst_heading = worst_heading.max(angle_diff(row[3], pose.theta).abs());
        }
    }
    eprintln!(
        "{} poses: final error {last:.3} m, worst {worst:.3} m, heading {worst_heading:.3} rad",
        rows.len()
    );
    (rows.len(), last, worst, worst_heading)
}

#[test]
fn simulated_ros2_bags_are_localised_end_to_end() {
    let dir = tempfile::tempdir().unwrap();
    let run = simulate(dir.path());

    // Bag 1: a bag directory; /scan, /odom, big-endian messages, three damaged scans.
    // Damaged scans: a cut message, XCDR2's encapsulation identifier, garbage.
    let damaged = ["0001000005000000", "000700000000000000000000", "ffffffffffffffff"];
    let bag1 = dir.path().join("bag1");
    write_bag(
        dir.path(),
        &run,
        &json!({
            "path": bag1, "scan_topic": "/scan", "odometry": "topic", "odom_frame": "odom",
            "base_frame": "base_link", "intermediate_frame": false, "big_endian": true, "damaged": damaged,
        }),
    );
    let out = dir.path().join("bag1.csv");
    let r = localize(dir.path(), &bag1, &["--out", out.to_str().unwrap()]);
    let stderr = String::from_utf8_lossy(&r.stderr);
    assert!(r.status.success(), "{stderr}");
    assert_eq!(stderr.matches("skipping a message").count(), 3, "each damaged scan is reported: {stderr}");
    assert!(stderr.contains("not plain CDR"), "XCDR2 is refused by name: {stderr}");
    assert!(stderr.contains("skipped=3"), "{stderr}");
    assert!(stderr.contains("laser mounting from /tf_static"), "{stderr}");
    let csv = std::fs::read_to_string(&out).unwrap();
    let (rows, last, worst, heading) = errors(&csv, &run.truth);
    assert_eq!(rows, SCANS, "one pose per scan, the damaged ones skipped");
    // Measured (2026-12-06, seed 3): final 2.0 cm, worst 3.3 cm after the first 10 scans, heading
    // 0.012 rad, both bags alike; over seeds 1–10: final 1.8–2.1 cm, worst 3.0–3.4 cm, heading
    // 0.011–0.013 rad, `tracking` on 115–118 scans of 120 (the first two are `uncertain`). A
    // stamp that wraps a time a hair below a whole second to the second before (each whole
    // second's odometry a second early) makes it 13.6 cm. Broken readers, measured by breaking ours:
    // the beam increment taken as 1° → 7.9 m off; odometry x and y swapped → worst 0.47 m; the
    // /tf_static mounting dropped → worst 0.86 m, heading 1.0 rad; big endian read as little →
    // the scans skipped.
    assert!(
        last < 0.05 && worst < 0.08 && heading < 0.05,
        "bag 1: final {last:.3} m, worst {worst:.3} m, heading {heading:.3} rad"
    );
    let (tracking, lost) = states(&csv);
    assert!(tracking >= 110 && lost == 0, "bag 1: {tracking} scans tracking, {lost} lost of {SCANS}");

    // Bag 1 with a ROS 2 user's nav2 parameter file instead of amcl.toml. A file that says, by
    // nav2's names, what our amcl.toml says (and the start as nav2 gives it) gives the very same
    // poses; nav2's own defaults give other ones (the file is what drives the filter).
    let nav2 = dir.path().join("nav2_params.yaml");
    let mut yaml = ours_in_nav2_names();
    yaml.push_str("    alpha5: 0.2\n    tf_broadcast: true\n    set_initial_pose: true\n    initial_pose: {x: 1.0, y: 1.0, z: 0.0, yaw: 0.0}\n");
    let nav2_localize = |file: &Path, extra: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_amr"))
            .args(["localize", "--map"])
            .arg(dir.path().join("map.yaml"))
            .arg("--bag")
            .arg(&bag1)
            .arg("--nav2-params")
            .arg(file)
            .args(extra)
            .env_remove("RUST_LOG")
            .output()
            .unwrap()
    };
    let run_nav2 = |file: &Path, csv: &Path| {
        let r = nav2_localize(file, &["--seed", "3", "--out", csv.to_str().unwrap()]);
        let stderr = String::from_utf8_lossy(&r.stderr).into_owned();
        assert!(r.status.success(), "{stderr}");
        (std::fs::read_to_string(csv).unwrap(), stderr)
    };
    std::fs::write(&nav2, &yaml).unwrap();
    let (same, stderr) = run_nav2(&nav2, &dir.path().join("bag1-nav2-ours.csv"));
    assert_eq!(same, csv, "our tuning by nav2's names gives the same poses\n{yaml}\n{stderr}");
    assert!(
        stderr.contains("nav2 parameters without an effect here") && stderr.contains("alpha5"),
        "{stderr}"
    );
    std::fs::write(&nav2, NAV2_DEFAULTS).unwrap();
    let (theirs, _) = run_nav2(&nav2, &dir.path().join("bag1-nav2-defaults.csv"));
    assert_ne!(theirs, csv, "nav2's defaults are not our tuning");
    let (rows, last, worst, _) = errors(&theirs, &run.truth);
    assert_eq!(rows, SCANS);
    // Measured (seeds 1–10): final 3.4–8.9 cm, worst 8.6–20.7 cm: nav2's update thresholds (0.25 m,
    // 0.2 rad) and motion noise on this 1 %-long odometry; never `lost`.
    assert!(last < 0.2 && worst < 0.4, "bag 1 with nav2's defaults: final {last:.3} m, worst {worst:.3} m");
    let (tracking, lost) = states(&theirs);
    assert!(tracking >= 90 && lost == 0, "bag 1 with nav2's defaults: {tracking} tracking, {lost} lost");
    std::fs::write(&nav2, "amcl:\n  ros__parameters:\n    laser_model_type: beam\n").unwrap();
    let r = nav2_localize(&nav2, &[]);
    assert_eq!(r.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&r.stderr).contains("beam is not supported"));

    // Bag 2: the .mcap file itself; odometry on /tf only (odom → base_footprint, beside a
    // map → odom), the mounting base_footprint → laser_mount → laser, the scans on /front/scan.
    let bag2 = dir.path().join("bag2");
    write_bag(
        dir.path(),
        &run,
        &json!({
            "path": bag2, "scan_topic": "/front/scan", "odometry": "tf", "odom_frame": "odom",
            "base_frame": "base_footprint", "intermediate_frame": true, "big_endian": false, "damaged": [],
        }),
    );
    let file = std::fs::read_dir(&bag2)
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.extension().is_some_and(|e| e == "mcap"))
        .unwrap();
    let out2 = dir.path().join("bag2.csv");
    let args =
        ["--scan-topic", "/front/scan", "--base-frame", "base_footprint", "--out", out2.to_str().unwrap()];
    let r = localize(dir.path(), &file, &args);
    let stderr = String::from_utf8_lossy(&r.stderr);
    assert!(r.status.success(), "{stderr}");
    assert!(stderr.contains("odom → base_footprint"), "odometry from /tf: {stderr}");
    let (rows, last, worst, heading) = errors(&std::fs::read_to_string(&out2).unwrap(), &run.truth);
    assert_eq!(rows, SCANS);
    assert!(
        last < 0.05 && worst < 0.08 && heading < 0.05,
        "bag 2: final {last:.3} m, worst {worst:.3} m, heading {heading:.3} rad"
    );

    // Bag 3: bag 1 again in rosbag2's sqlite3 storage (Humble's default): the directory, and its
    // .db3 file alone, give the same poses as bag 1.
    let bag3 = dir.path().join("bag3");
    write_bag(
        dir.path(),
        &run,
        &json!({
            "path": bag3, "scan_topic": "/scan", "odometry": "topic", "odom_frame": "odom", "storage": "sqlite3",
            "base_frame": "base_link", "intermediate_frame": false, "big_endian": true, "damaged": damaged,
        }),
    );
    let db3 = std::fs::read_dir(&bag3)
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.extension().is_some_and(|e| e == "db3"))
        .expect("rosbags wrote a .db3");
    for (k, input) in [bag3.clone(), db3].iter().enumerate() {
        let out3 = dir.path().join(format!("bag3-{k}.csv"));
        let r = localize(dir.path(), input, &["--out", out3.to_str().unwrap()]);
        let stderr = String::from_utf8_lossy(&r.stderr);
        assert!(r.status.success(), "{stderr}");
        assert!(stderr.contains("skipped=3"), "{stderr}");
        let csv3 = std::fs::read_to_string(&out3).unwrap();
        assert_eq!(csv3, csv, "the sqlite3 bag gives what the MCAP bag gave ({})", input.display());
    }
    // What is not a bag says what it is and what is read.
    let r = localize(dir.path(), &dir.path().join("map.pgm"), &[]);
    assert_eq!(r.status.code(), Some(1));
    let stderr = String::from_utf8_lossy(&r.stderr);
    assert!(
        stderr.contains("is a PGM image") && stderr.contains("MCAP (.mcap) or sqlite3 (.db3)"),
        "{stderr}"
    );

    // Wrong names are clear errors.
    let r = localize(dir.path(), &file, &["--scan-topic", "/scan"]);
    assert_eq!(r.status.code(), Some(1));
    let stderr = String::from_utf8_lossy(&r.stderr);
    assert!(
        stderr.contains("no topic /scan") && stderr.contains("/front/scan [sensor_msgs/msg/LaserScan]"),
        "{stderr}"
    );
    let r = localize(dir.path(), &file, &["--scan-topic", "/front/scan"]);
    assert_eq!(r.status.code(), Some(1));
    assert!(
        String::from_utf8_lossy(&r.stderr).contains("odom → base_link"),
        "names the transform it looked for"
    );
}

/// Reads a bag with python's `mcap` and decodes every message with `rosbags` (its own ROS 2
/// definitions): the profile, per topic its type, encoding, QoS durability and count, and a few
/// fields.
const CHECK: &str = r#"
import collections, json, sys
from mcap.reader import make_reader
from rosbags.typesys import Stores, get_typestore
from ruamel.yaml import YAML

ts = get_typestore(Stores.ROS2_HUMBLE)
with open(sys.argv[1], 'rb') as f:
    r = make_reader(f)
    out = {'profile': r.get_header().profile, 'topics': {}, 'static': [], 'map': None}
    n = collections.Counter()
    for schema, ch, m in r.iter_messages():
        msg = ts.deserialize_cdr(m.data, schema.name)
        n[ch.topic] += 1
        qos = YAML(typ='safe').load(ch.metadata['offered_qos_profiles'])[0]
        out['topics'][ch.topic] = {'type': schema.name, 'encoding': ch.message_encoding,
                                   'schema_encoding': schema.encoding, 'durability': qos['durability']}
        if ch.topic == '/tf_static':
            out['static'] += [[t.header.frame_id, t.child_frame_id] for t in msg.transforms]
        if ch.topic == '/map':
            out['map'] = [msg.info.width, msg.info.height, len(msg.data)]
        if ch.topic == '/robot_a/scan':
            out['scan_frame'], out['beams'] = msg.header.frame_id, len(msg.ranges)
    for t, c in n.items():
        out['topics'][t]['count'] = c
print(json.dumps(out))
"#;

#[test]
fn a_simulation_records_as_a_ros2_bag() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("sim.mcap");
    let run = Command::new(env!("CARGO_BIN_EXE_amr"))
        .args(["sim", "--virtual-time", "--quiet", "--duration", "3", "--seed", "4", "--ros2", "--record"])
        .arg(&file)
        .env_remove("RUST_LOG")
        .output()
        .unwrap();
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let out = Command::new("python3").args(["-c", CHECK]).arg(&file).output().unwrap();
    assert!(
        out.status.success(),
        "python (pip install mcap rosbags): {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["profile"], "ros2");
    let topics = v["topics"].as_object().unwrap();
    for (topic, ty) in [
        ("/robot_a/scan", "sensor_msgs/msg/LaserScan"),
        ("/robot_b/scan", "sensor_msgs/msg/LaserScan"),
        ("/virtual/scan", "sensor_msgs/msg/LaserScan"),
        ("/robot_a/odom", "nav_msgs/msg/Odometry"),
        ("/amcl/V", "geometry_msgs/msg/PoseWithCovarianceStamped"),
        ("/amcl/robot_b", "geometry_msgs/msg/PoseWithCovarianceStamped"),
        ("/tf", "tf2_msgs/msg/TFMessage"),
        ("/tf_static", "tf2_msgs/msg/TFMessage"),
        ("/map", "nav_msgs/msg/OccupancyGrid"),
    ] {
        assert_eq!(topics.get(topic).map(|t| &t["type"]), Some(&json!(ty)), "{topic}: {topics:?}");
    }
    for (topic, t) in topics {
        assert_eq!(
            (t["encoding"].as_str(), t["schema_encoding"].as_str()),
            (Some("cdr"), Some("ros2msg")),
            "{topic}"
        );
        let latched = topic == "/map" || topic == "/tf_static";
        assert_eq!(t["durability"], if latched { 1 } else { 2 }, "{topic}");
        assert!(!topic.contains('-'), "a valid ROS 2 topic name: {topic}");
    }
    assert_eq!(
        (topics["/map"]["count"].as_u64(), topics["/tf_static"]["count"].as_u64()),
        (Some(1), Some(1))
    );
    // 15 Hz for 3 s, less the start-up.
    assert!(topics["/robot_a/scan"]["count"].as_u64().unwrap() > 30, "{topics:?}");
    assert!(topics["/amcl/V"]["count"].as_u64().unwrap() > 30, "{topics:?}");
    assert_eq!(v["static"], json!([["robot-a", "robot-a/laser"], ["robot-b", "robot-b/laser"]]));
    let map = v["map"].as_array().unwrap();
    assert_eq!(map[0].as_u64().unwrap() * map[1].as_u64().unwrap(), map[2].as_u64().unwrap());
    assert_eq!(v["scan_frame"], "robot-a/laser");
    assert!(v["beams"].as_u64().unwrap() > 100, "{v}");
}

/// An odometry glitch in a room whose corners look alike: bag 1 with each whole second's odometry
/// sample stamped a second early (a writer's rounding bug once did this), so that once a second a
/// scan is given odometry 0.3 m ahead. The estimate is thrown off by it (nav2's update thresholds
/// keep it off for a few scans), and a scan of a corner is explained as fully at the room's other
/// corners: the filter must come back to the corner it was at, not go to another. Measured
/// (seeds 1–10, nav2's defaults): final 3.2–16.2 cm, worst 0.36–0.37 m (the scans given the
/// glitch). Without a rival at the estimate's own place kept first and counted among twins,
/// seeds 3 and 4 end 1.48 m and 2.50 m off at other corners (worst 5.8 m). Our amcl.toml (its
/// slip samples take the glitch): final 3.8–6.7 cm, worst 10–16 cm (seeds 1–10), heading at worst
/// 0.04–0.10 rad (seeds 1–3).
#[test]
fn an_odometry_glitch_does_not_send_the_filter_to_a_corner_that_looks_alike() {
    let dir = tempfile::tempdir().unwrap();
    let run = simulate(dir.path());
    let bag = dir.path().join("glitched");
    write_bag(
        dir.path(),
        &run,
        &json!({
            "path": bag, "scan_topic": "/scan", "odometry": "topic", "odom_frame": "odom",
            "base_frame": "base_link", "intermediate_frame": false, "big_endian": false, "damaged": [],
            "odometry_glitch": true,
        }),
    );
    let nav2 = dir.path().join("nav2_params.yaml");
    std::fs::write(&nav2, NAV2_DEFAULTS).unwrap();
    let run_with = |args: &[&str], seed: u64| {
        let csv = dir.path().join(format!("glitched-{seed}.csv"));
        let r = Command::new(env!("CARGO_BIN_EXE_amr"))
            .args(["localize", "--map"])
            .arg(dir.path().join("map.yaml"))
            .arg("--bag")
            .arg(&bag)
            .args(args)
            .args(["--seed", &seed.to_string(), "--out", csv.to_str().unwrap()])
            .env_remove("RUST_LOG")
            .output()
            .unwrap();
        assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
        errors(&std::fs::read_to_string(&csv).unwrap(), &run.truth)
    };
    for seed in 1..=10 {
        let (rows, last, worst, _) = run_with(&["--nav2-params", nav2.to_str().unwrap()], seed);
        assert_eq!(rows, SCANS);
        assert!(
            last < 0.2 && worst < 1.0,
            "nav2's defaults, seed {seed}: final {last:.3} m, worst {worst:.3} m (another corner is 1.5–6 m off)"
        );
    }
    let ours = concat!(env!("CARGO_MANIFEST_DIR"), "/../config/amcl.toml");
    for seed in 1..=3 {
        let args = ["--params", ours, "--initial", "1.0,1.0,0.0"];
        let (_, last, worst, heading) = run_with(&args, seed);
        assert!(
            last < 0.1 && worst < 0.25 && heading < 0.15,
            "amcl.toml, seed {seed}: final {last:.3} m, worst {worst:.3} m, heading {heading:.3} rad"
        );
    }
}
