//! Recording through the binary: `amr sim --virtual-time --record` then `amr replay`
//! gives back every estimate bit for bit; `amr eval --record` writes the true poses and T1–T4's
//! estimates side by side; the files read back with Foxglove's schemas.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code: a failed step fails the test")]

use std::collections::BTreeMap;
use std::path::Path;
use std::process::{Command, Output};

use amr_actors::config::{ConfigSource, read_files};
use hil_tests::{config_dir, write_dir};

fn amr(args: &[&str]) -> Output {
    let out = Command::new(env!("CARGO_BIN_EXE_amr")).args(args).env_remove("RUST_LOG").output().unwrap();
    assert!(out.status.success(), "amr {args:?}: {}", String::from_utf8_lossy(&out.stderr));
    out
}

fn topics(path: &Path) -> BTreeMap<String, (String, usize)> {
    let rec = amr_record::read::read_file(path).unwrap();
    assert!(rec.stopped.is_none(), "{:?}", rec.stopped);
    let mut t: BTreeMap<String, (String, usize)> = BTreeMap::new();
    let mut last = 0;
    for m in &rec.messages {
        assert!(m.log_time_ns >= last, "log time goes back on {}", m.topic);
        last = m.log_time_ns;
        t.entry(m.topic.clone()).or_insert_with(|| (m.schema.clone(), 0)).1 += 1;
    }
    t
}

#[test]
fn a_recorded_simulation_replays_exactly_through_the_cli() {
    let dir = tempfile::tempdir().unwrap();
    let (rec, out) = (dir.path().join("sim.mcap"), dir.path().join("replayed.mcap"));
    let (rec_s, out_s) = (rec.to_str().unwrap(), out.to_str().unwrap());
    amr(&["sim", "--virtual-time", "--quiet", "--duration", "8", "--seed", "4", "--record", rec_s]);
    let t = topics(&rec);
    for (topic, schema) in [
        ("/robot-a/scan", "foxglove.LaserScan"),
        ("/virtual/scan", "foxglove.LaserScan"),
        ("/amcl/V", "foxglove.PoseInFrame"),
        ("/tf", "foxglove.FrameTransforms"),
        ("/map", "foxglove.Grid"),
        ("/log", "foxglove.Log"),
    ] {
        assert_eq!(t.get(topic).map(|(s, _)| s.as_str()), Some(schema), "{topic} in {t:?}");
    }
    assert!(t["/robot-a/scan"].1 > 50, "{t:?}");

    let report = amr(&["replay", rec_s, "--out", out_s]);
    let text = String::from_utf8_lossy(&report.stdout).into_owned();
    let json: serde_json::Value = serde_json::from_str(text.split("written to").next().unwrap()).unwrap();
    assert_eq!(json["exact"], true, "{json:#}");
    assert!(json["recorded_estimates"].as_u64().unwrap() > 50, "{json:#}");
    assert_eq!(topics(&out).get("/amcl/V").map(|(_, n)| *n), t.get("/amcl/V").map(|(_, n)| *n));

    // Another configuration on the same data is a different run, and the report says so.
    let t2 = amr(&["replay", rec_s, "--configuration", "T2"]);
    assert!(String::from_utf8_lossy(&t2.stdout).contains("\"exact\": false"));
}

#[test]
fn an_evaluation_records_the_truth_and_every_configuration() {
    let dir = tempfile::tempdir().unwrap();
    let mut files = read_files(&ConfigSource::Dir(config_dir())).unwrap();
    for f in &mut files {
        if f.path == "scenarios/straight.toml" {
            let text = String::from_utf8(f.bytes.clone()).unwrap();
            f.bytes = text
                .replace("straight_m = 4.0", "straight_m = 0.4")
                .replace("straight_m = -4.0", "straight_m = -0.4")
                .into_bytes();
        }
    }
    let config = dir.path().join("config");
    write_dir(&files, &config).unwrap();
    let rec = dir.path().join("eval.mcap");
    amr(&[
        "eval",
        "--trials",
        "1",
        "--config",
        config.to_str().unwrap(),
        "--out",
        dir.path().join("out").to_str().unwrap(),
        "--record",
        rec.to_str().unwrap(),
    ]);
    let t = topics(&rec);
    let scans = t["/robot-a/scan"].1;
    assert!(scans > 20, "{t:?}");
    assert_eq!(t["/truth/V"].1, scans, "one true pose per scan step");
    for c in ["T1", "T2", "T3", "T4"] {
        let n = t.get(&format!("/eval/{c}/V")).map_or(0, |(_, n)| *n);
        assert!(n > scans / 2 && n <= scans, "{c}: {n} estimates for {scans} scans");
    }
    for c in ["T2", "T3", "T4"] {
        let n = t.get(&format!("/eval/{c}/virtual_scan")).map_or(0, |(_, n)| *n);
        assert!(n > scans / 2 && n <= scans, "{c}: {n} virtual scans for {scans} scans");
    }
    assert_eq!(t.get("/amcl/particles").map(|(s, _)| s.as_str()), Some("foxglove.PosesInFrame"), "{t:?}");
    assert_eq!(t.get("/map").map(|(_, n)| *n), Some(1));
}
