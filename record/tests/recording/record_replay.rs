#![allow(clippy::unwrap_used, clippy::expect_used, reason = "tests")]
//! Record a short run of the real server actor tree (virtual time, scans ray-cast on the paper's
//! site), read it back with the mcap crate, replay it exactly, cut it short like a crash.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};
use std::time::Duration;

use amr_actors::clock::FleetClock;
use amr_actors::config::{ConfigSource, load};
use amr_actors::link::in_process;
use amr_actors::robot::ports::{ImuReading, RobotPorts};
use amr_actors::server::{ServerSetup, formation_robots, start_server};
use amr_actors::supervisor::RestartPolicy;
use amr_core::config::Configuration;
use amr_core::formation::slots;
use amr_core::se2::Se2;
use amr_core::vamr::synthetic::Site;
use amr_msgs::{Device, Health, HealthReport, OdomMsg, ScanMsg, Uplink};
use amr_record::encode::Out;
use amr_record::read::{read_bytes, read_file};
use amr_record::sink::McapFile;
use amr_record::{FlushPolicy, LogLayer, LogTap, RecordOptions, RecordSources, Recorder, replay, wire};
use tracing_subscriber::layer::SubscriberExt;

/// Scans per robot (15 Hz): 4 s of driving.
const SCANS: usize = 60;

fn setup(configuration: Configuration) -> ServerSetup {
    let config = load(&ConfigSource::Embedded).unwrap();
    let scenario = config.scenarios["straight"].clone();
    let mut server = config.server.clone();
    server.configuration = configuration;
    ServerSetup {
        map: config.maps[&scenario.map].clone(),
        robots: formation_robots(&server, &config.robots).unwrap(),
        server,
        vamr: config.vamr.clone(),
        amcl: config.amcl.clone(),
        scenario,
        seed: 5,
        auto_arm: amr_actors::server::AutoArm::Off,
        policy: RestartPolicy::default(),
        progress: std::sync::Arc::new(amr_actors::server::progress::PlanProgress::in_memory()),
    }
}

struct Recorded {
    path: PathBuf,
    /// Uplink messages sent.
    sent: usize,
    _dir: tempfile::TempDir,
}

/// Drive the pair straight on at 0.2 m/s: each robot's scan ray-cast on the paper's site with the
/// other robot in view, its odometry exact, both sent through the in-process link to a running
/// server tree with a recorder on its ports.
#[derive(Clone, Copy, PartialEq)]
enum Clock {
    /// tokio's paused clock on one thread.
    Virtual,
    /// The real clock on a two-worker runtime (the actors race as on a real server).
    Real,
}

/// The setup of a real-time run: the sync gate's age limit out of the way. Its `t_rx` is the fusion
/// actor's clock reading, which no port shows; the recording has the recorder's, which a loaded
/// machine can put on the other side of the 100 ms limit (a known limit of the replay in real time,
/// see `replay`). The test is about the actors' interleaving, not that.
fn real_time_setup(configuration: Configuration) -> ServerSetup {
    let mut s = setup(configuration);
    s.server.sync.max_age_ms = amr_core::config::value::Millis::new(60_000).unwrap();
    s.server.sync.e2e_threshold_ms = amr_core::config::value::Millis::new(120_000).unwrap();
    s
}

fn record(configuration: Configuration, clock_kind: Clock, scans: usize) -> Recorded {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("run.mcap");
    let setup = match clock_kind {
        Clock::Virtual => setup(configuration),
        Clock::Real => real_time_setup(configuration),
    };
    let rt = match clock_kind {
        Clock::Virtual => {
            tokio::runtime::Builder::new_current_thread().enable_all().start_paused(true).build().unwrap()
        }
        Clock::Real => {
            tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap()
        }
    };
    let tap = LogTap::default();
    let subscriber = tracing_subscriber::registry().with(LogLayer::new(tap.clone()));
    let _guard = tracing::subscriber::set_default(subscriber);
    let sent = rt.block_on(async {
        let clock = FleetClock::start();
        let ids: Vec<String> = setup.robots.iter().map(|r| r.id.as_str().to_owned()).collect();
        let (server_end, robot_ends, _link) = in_process(&ids);
        let server = start_server(setup.clone(), server_end, clock).await.unwrap();
        let mut sources = RecordSources::server(&server.ports, &setup);
        // The robots' own ports too (as `amr sim` can): only their IMU is taken from there.
        let robot_ports: Vec<_> = ids.iter().map(|id| RobotPorts::new(id.clone(), clock)).collect();
        sources.robots = robot_ports.clone();
        sources.metadata.insert("command".into(), "test".into());
        sources.logs = Some(tap.clone());
        let options = RecordOptions {
            file: Some(path.clone()),
            live: None,
            flush: FlushPolicy::default(),
            ros2: false,
            ros2_live: None,
        };
        let recorder = Recorder::start(options, sources).await.unwrap();
        tracing::info!(robots = ids.len(), "test: recording started");

        let site = Site::paper(271).unwrap();
        let start = setup.scenario.start_pose();
        let y = slots(ids.len(), setup.scenario.spacing_m.get());
        let mut sent = 0;
        for k in 0..scans {
            tokio::time::sleep(Duration::from_micros(66_667)).await;
            let t = clock.now_s();
            let v = start * Se2::new(0.2 * k as f64 / 15.0, 0.0, 0.0);
            let poses: Vec<Se2> = y.iter().map(|yi| v * Se2::new(0.0, *yi, 0.0)).collect();
            for (i, end) in robot_ends.iter().enumerate() {
                let odom = (start * Se2::new(0.0, y[i], 0.0)).inverse() * poses[i];
                let scan = ScanMsg {
                    robot: ids[i].clone(),
                    seq: k as u64,
                    stamp_s: t,
                    received_s: t,
                    scan: Arc::new(site.scan(&poses, i)),
                    odom: Some(odom),
                    odom_frame: 1,
                };
                robot_ports[i].scans.send(ScanMsg { odom: None, ..scan.clone() });
                robot_ports[i].imu.send(ImuReading { stamp_s: t, yaw_rate_radps: 0.0 });
                assert!(end.up.send(Uplink::Scan(scan)));
                let msg = OdomMsg {
                    seq: k as u64,
                    frame: 1,
                    stamp_s: t,
                    pose: odom,
                    twist: (0.2, 0.0),
                    gyro: true,
                };
                assert!(end.up.send(Uplink::Odom { robot: ids[i].clone(), msg }));
                sent += 2;
            }
            // The same health twice (a robot re-sends its board): `/health` logs the change once.
            if k == 10 || k == 20 {
                let report =
                    HealthReport { device: Device::Imu, health: Health::Degraded, detail: "test".into() };
                assert!(robot_ends[1].up.send(Uplink::Health {
                    robot: ids[1].clone(),
                    seq: k as u64,
                    stamp_s: t,
                    report
                }));
                sent += 1;
            }
        }
        tokio::time::sleep(Duration::from_millis(500)).await;
        let stats = recorder.stop().await.unwrap();
        assert!(stats.flushes >= 2, "{stats:?}");
        server.shutdown().await;
        sent
    });
    Recorded { path, sent, _dir: dir }
}

fn t4() -> &'static Recorded {
    static R: OnceLock<Recorded> = OnceLock::new();
    R.get_or_init(|| record(Configuration::T4, Clock::Virtual, SCANS))
}

#[test]
fn a_recording_reads_back_with_foxglove_schemas_counts_and_time_order() {
    let r = t4();
    let bytes = std::fs::read(&r.path).unwrap();
    if let Ok(keep) = std::env::var("AMR_RECORD_KEEP") {
        std::fs::copy(&r.path, keep).unwrap();
    }
    // A finished file: the summary lists every channel with its schema.
    let summary = mcap::Summary::read(&bytes).unwrap().expect("a summary");
    let schemas: BTreeMap<String, String> = summary
        .channels
        .values()
        .map(|c| (c.topic.clone(), c.schema.as_ref().map(|s| s.name.clone()).unwrap_or_default()))
        .collect();
    for (topic, schema) in [
        ("/amr/uplink", "amr.Uplink"),
        ("/amr/fused", "amr.FusedFrame"),
        ("/amr/estimates", "amr.Estimate"),
        ("/robot-a/scan", "foxglove.LaserScan"),
        ("/robot-b/scan", "foxglove.LaserScan"),
        ("/virtual/scan", "foxglove.LaserScan"),
        ("/robot-a/odom", "foxglove.PoseInFrame"),
        ("/amcl/V", "foxglove.PoseInFrame"),
        ("/amcl/robot-b", "foxglove.PoseInFrame"),
        ("/amcl/robot-a/own", "foxglove.PoseInFrame"),
        ("/amcl/particles", "foxglove.PosesInFrame"),
        ("/tf", "foxglove.FrameTransforms"),
        ("/map", "foxglove.Grid"),
        ("/health", "foxglove.Log"),
        ("/log", "foxglove.Log"),
    ] {
        assert_eq!(schemas.get(topic).map(String::as_str), Some(schema), "{topic}: {schemas:?}");
    }
    for c in summary.channels.values() {
        assert_eq!(c.message_encoding, "json");
        assert_eq!(c.schema.as_ref().unwrap().encoding, "jsonschema");
    }

    let rec = read_file(&r.path).unwrap();
    assert!(rec.stopped.is_none(), "{:?}", rec.stopped);
    let count = |t: &str| rec.messages.iter().filter(|m| m.topic == t).count();
    assert_eq!(count("/amr/uplink"), r.sent, "every uplink message recorded");
    assert_eq!(count("/robot-a/scan"), SCANS);
    assert_eq!(count("/robot-b/scan"), SCANS, "from the uplink only, not twice");
    assert_eq!(count("/robot-a/imu"), SCANS, "from the robot's port");
    assert_eq!(count("/map"), 1);
    assert_eq!(count("/health"), 1);
    assert!(count("/amr/fused") > SCANS / 2, "{}", count("/amr/fused"));
    assert_eq!(count("/virtual/scan"), count("/amr/fused"));
    // V's filter starts once a robot's own estimate is verified (a few scans), then one V
    // estimate per fused frame in T4.
    let (v, fused) = (count("/amcl/V"), count("/amr/fused"));
    assert!(v <= fused && v + 5 >= fused && v > 0, "{v} V estimates, {fused} fused frames");
    assert!((3..=6).contains(&count("/amcl/particles")), "{}", count("/amcl/particles"));
    // The statistics agree with what is in the file.
    let stats = summary.stats.as_ref().unwrap();
    assert_eq!(stats.message_count, rec.messages.len() as u64);
    // Log time never goes back.
    assert!(rec.messages.windows(2).all(|w| w[0].log_time_ns <= w[1].log_time_ns));
    // The test's own log line is there, with its level and fields.
    let log: Vec<serde_json::Value> = rec
        .messages
        .iter()
        .filter(|m| m.topic == "/log")
        .map(|m| serde_json::from_slice(&m.data).unwrap())
        .collect();
    assert!(
        log.iter().any(|l| l["message"] == "test: recording started robots=2" && l["level"] == 2),
        "{log:?}"
    );
    // Foxglove's fields are there.
    let scan: serde_json::Value =
        serde_json::from_slice(&rec.messages.iter().find(|m| m.topic == "/robot-a/scan").unwrap().data)
            .unwrap();
    assert_eq!(scan["frame_id"], "robot-a/laser");
    assert_eq!(scan["ranges"].as_array().unwrap().len(), 271);
    assert!(scan["timestamp"]["sec"].is_u64() && scan["timestamp"]["nsec"].is_u64());
    // The metadata names what a replay needs.
    let meta = &amr_record::read::metadata(&bytes)["amr"];
    assert_eq!(meta["configuration"], "T4");
    assert_eq!(meta["seed"], "5");
    assert_eq!(meta["robots"], "robot-a,robot-b");
    assert_eq!(meta["command"], "test");
    assert_eq!(amr_record::read::metadata(&bytes[..bytes.len() / 2])["amr"], *meta, "a cut file too");
    // And the exact channel decodes.
    let first = rec.messages.iter().find(|m| m.topic == "/amr/uplink").unwrap();
    assert!(wire::decode_uplink(&first.data).is_ok());
}

#[test]
fn replay_reproduces_every_estimate_exactly() {
    let r = t4();
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("replayed.mcap");
    let report = replay(&r.path, Some(&out), &setup(Configuration::T4), None).unwrap();
    assert!(report.exact(), "{report:#?}");
    assert_eq!(report.fused, report.recorded_fused);
    assert_eq!(report.fused_identical, report.fused, "{report:#?}");
    assert_eq!(report.uplink, r.sent);
    assert!(!report.truncated);
    // The new recording says what it is, has the Foxglove views too, holds the same estimates and
    // replays to itself.
    let bytes = std::fs::read(&out).unwrap();
    let meta = &amr_record::read::metadata(&bytes)["amr"];
    assert_eq!(meta["seed"], "5");
    assert_eq!(meta["replay_of"], r.path.display().to_string());
    let topics: BTreeSet<String> =
        read_bytes(&bytes).unwrap().messages.into_iter().map(|m| m.topic).collect();
    for t in
        ["/amr/uplink", "/amr/fused", "/amr/estimates", "/robot-a/scan", "/virtual/scan", "/amcl/V", "/tf"]
    {
        assert!(topics.contains(t), "{t}: {topics:?}");
    }
    let again = replay(&out, None, &setup(Configuration::T4), None).unwrap();
    assert!(again.exact(), "{again:#?}");
    assert_eq!(again.recorded_estimates, report.recorded_estimates);
}

#[test]
fn replay_in_another_configuration_differs_and_says_so() {
    let r = t4();
    let report = replay(&r.path, None, &setup(Configuration::T4), Some(Configuration::T2)).unwrap();
    assert_eq!(report.configuration, Some(Configuration::T2));
    assert!(!report.exact());
    // The robots' own filters see the same scans: those estimates are still identical.
    assert!(report.identical >= 2 * SCANS, "{report:#?}");
    assert!(report.fused > 0);
}

/// Messages of a recording as comparable tuples.
fn keys(bytes: &[u8]) -> Vec<(String, u64, Vec<u8>)> {
    read_bytes(bytes).unwrap().messages.into_iter().map(|m| (m.topic, m.log_time_ns, m.data)).collect()
}

#[test]
fn a_recording_cut_anywhere_reads_up_to_its_last_whole_chunk() {
    let r = t4();
    let bytes = std::fs::read(&r.path).unwrap();
    let full = keys(&bytes);
    let mut counts = Vec::new();
    let step = (bytes.len() / 97).max(1);
    for cut in (0..bytes.len()).step_by(step).chain([bytes.len() - 1]) {
        // Never a panic; a cut inside the magic or the header is an error, anything later reads.
        let Ok(rec) = read_bytes(&bytes[..cut]) else {
            assert!(cut < 64, "cut at {cut} is unreadable");
            continue;
        };
        let got: Vec<_> = rec.messages.into_iter().map(|m| (m.topic, m.log_time_ns, m.data)).collect();
        assert_eq!(got[..], full[..got.len()], "cut at {cut}: a prefix of the messages");
        counts.push(got.len());
    }
    assert!(counts.windows(2).all(|w| w[0] <= w[1]), "{counts:?}");
    assert_eq!(counts.last(), Some(&full.len()), "only the footer cut: every message");
    assert!(counts.iter().filter(|c| **c > 0 && **c < full.len()).count() > 10, "{counts:?}");
}

fn out(topic: &str, t_ns: u64) -> Out {
    Out {
        topic: topic.into(),
        schema: amr_record::foxglove::LOG,
        log_time_ns: t_ns,
        publish_time_ns: t_ns,
        data: format!("{{\"n\":{t_ns}}}").into_bytes(),
    }
}

#[test]
fn a_killed_writer_leaves_every_flushed_message() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("crash.mcap");
    let policy = FlushPolicy { max_messages: 10, max_interval_ns: u64::MAX, lz4: true };
    let mut f = McapFile::create(&path, policy).unwrap();
    for k in 0..95u64 {
        f.write(&out(if k % 2 == 0 { "/a" } else { "/b" }, k)).unwrap();
    }
    // The process dies: no finish, nothing after the last flush reaches the disk.
    std::mem::forget(f);
    let rec = read_file(&path).unwrap();
    assert_eq!(rec.messages.len(), 90, "nine whole chunks of ten");
    let n: Vec<u64> = rec.messages.iter().map(|m| m.log_time_ns).collect();
    assert_eq!(n, (0..90).collect::<Vec<_>>());
    let topics: BTreeSet<&str> = rec.messages.iter().map(|m| m.topic.as_str()).collect();
    assert_eq!(topics, BTreeSet::from(["/a", "/b"]));
}

#[test]
fn chunks_are_lz4_compressed_by_default_and_read_back() {
    let dir = tempfile::tempdir().unwrap();
    let (lz4, plain) = (dir.path().join("lz4.mcap"), dir.path().join("plain.mcap"));
    for (path, compress) in [(&lz4, true), (&plain, false)] {
        let mut f = McapFile::create(path, FlushPolicy { lz4: compress, ..FlushPolicy::default() }).unwrap();
        for k in 0..3000u64 {
            f.write(&out("/a", k * 1_000_000)).unwrap();
        }
        f.finish().unwrap();
    }
    assert!(FlushPolicy::default().lz4);
    let bytes = std::fs::read(&lz4).unwrap();
    let summary = mcap::read::Summary::read(&bytes).unwrap().unwrap();
    assert!(!summary.chunk_indexes.is_empty());
    assert!(summary.chunk_indexes.iter().all(|c| c.compression == "lz4"), "every chunk compressed");
    let (a, b) = (read_file(&lz4).unwrap(), read_file(&plain).unwrap());
    assert_eq!(a.messages.len(), 3000);
    let key = |r: &amr_record::read::Recording| -> Vec<(String, u64, Vec<u8>)> {
        r.messages.iter().map(|m| (m.topic.clone(), m.log_time_ns, m.data.clone())).collect()
    };
    assert_eq!(key(&a), key(&b));
    let (small, big) = (bytes.len(), std::fs::metadata(&plain).unwrap().len() as usize);
    assert!(small * 3 < big * 2, "lz4 {small} bytes, uncompressed {big}");
}

#[test]
fn garbage_is_an_error_not_a_panic() {
    for bytes in [
        &b""[..],
        b"\x89MCAP0\r\n",
        b"\x89MCAP0\r\n\xff\xff\xff\xff\xff\xff\xff\xff\xff",
        b"not an mcap file at all",
    ] {
        if let Ok(r) = read_bytes(bytes) {
            assert!(r.messages.is_empty());
        }
    }
    assert!(replay(Path::new("/nonexistent/x.mcap"), None, &setup(Configuration::T4), None).is_err());
}

#[test]
fn a_damaged_recording_never_panics_the_reader() {
    let bytes = std::fs::read(&t4().path).unwrap();
    let all = keys(&bytes).len();
    let mut x: u64 = 0x2545_F491_4F6C_DD1D;
    for _ in 0..400 {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        let mut b = bytes.clone();
        let at = (x as usize) % (b.len() - 8);
        // Lengths, opcodes and counts set to their worst.
        let fill = if x & 1 == 0 { 0xff } else { 0x00 };
        b[at..at + 8].fill(fill);
        if let Ok(r) = read_bytes(&b) {
            assert!(r.messages.len() <= all + 1);
        }
    }
}

#[test]
fn in_virtual_time_replay_is_exact_in_t1_t2_and_t3_too() {
    // There the fusion takes relative poses from the robots' own AMCL, which the server core
    // updates on each scan before fusing it, live and in the replay alike. 4 s: T2's heading
    // search needs the robots' AMCL poses within about 2 cm of each other, which the product model
    // reaches about 1 s after the start's spread (measured: 46 of 60 fused in T2, all 60 in T1 and
    // T3).
    for c in [Configuration::T1, Configuration::T2, Configuration::T3] {
        let r = record(c, Clock::Virtual, 60);
        let report = replay(&r.path, None, &setup(c), None).unwrap();
        assert!(report.exact(), "{c:?}: {report:#?}");
        assert_eq!(report.fused_identical, report.recorded_fused, "{c:?}: {report:#?}");
        assert!(report.fused > 20, "{c:?}: {report:#?}");
    }
}

#[test]
fn a_real_time_run_on_many_threads_replays_exactly_in_t4() {
    let r = record(Configuration::T4, Clock::Real, 30);
    let report = replay(&r.path, None, &real_time_setup(Configuration::T4), None).unwrap();
    assert!(report.exact(), "{report:#?}");
    assert!(report.fused > 20, "{report:#?}");
    assert_eq!(report.fused_identical, report.fused, "{report:#?}");
}

#[test]
fn a_recording_cut_by_a_crash_replays_up_to_the_cut() {
    let r = t4();
    let bytes = std::fs::read(&r.path).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let cut = dir.path().join("cut.mcap");
    std::fs::write(&cut, &bytes[..bytes.len() * 2 / 3]).unwrap();
    let report = replay(&cut, None, &setup(Configuration::T4), None).unwrap();
    assert!(report.truncated, "{report:#?}");
    assert!(report.uplink > 0 && report.uplink < r.sent, "{report:#?}");
    assert!(report.compared > 50, "{report:#?}");
    assert_eq!(report.identical, report.compared, "{report:#?}");
    // Estimates of the last messages before the cut may be after it: extra, never missing.
    assert_eq!(report.missing, 0, "{report:#?}");
}

/// An independent reader: the Python `mcap` package (PyPI; `.ci/run` installs it) reads the
/// LZ4-compressed recording, every message, with the same count per topic as ours.
#[test]
fn the_python_mcap_reader_reads_a_compressed_recording() {
    let r = t4();
    let script = "import collections, json, sys\n\
                  from mcap.reader import make_reader\n\
                  with open(sys.argv[1], 'rb') as f:\n\
                  \x20   r = make_reader(f)\n\
                  \x20   chunks = {c.compression for c in r.get_summary().chunk_indexes}\n\
                  \x20   n = collections.Counter(ch.topic for _, ch, _ in r.iter_messages())\n\
                  print(json.dumps({'topics': n, 'compression': sorted(chunks)}))\n";
    let out = std::process::Command::new("python3")
        .args(["-c", script, r.path.to_str().unwrap()])
        .output()
        .expect("python3 (the CI installs it with the `mcap` package: pip install mcap)");
    assert!(
        out.status.success(),
        "python mcap reader failed (pip install mcap): {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["compression"], serde_json::json!(["lz4"]));
    let ours = read_file(&r.path).unwrap();
    let mut counts: BTreeMap<String, u64> = BTreeMap::new();
    for m in &ours.messages {
        *counts.entry(m.topic.clone()).or_default() += 1;
    }
    let theirs: BTreeMap<String, u64> = serde_json::from_value(v["topics"].clone()).unwrap();
    assert!(!counts.is_empty());
    assert_eq!(theirs, counts);
}
