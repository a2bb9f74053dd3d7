//! `amr eval` through the binary on a shortened scenario: the outputs exist, agree with the raw
//! errors, and two runs with the same seed are identical.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code: a failed step fails the test")]

use std::path::Path;
use std::process::Command;

use amr_actors::config::{ConfigSource, read_files};
use hil_tests::{config_dir, write_dir};

/// The shipped configuration with the straight run cut to 0.6 m and back and 200 particles.
fn short_config(dir: &Path) {
    let mut files = read_files(&ConfigSource::Dir(config_dir())).unwrap();
    for f in &mut files {
        let text = String::from_utf8(f.bytes.clone()).unwrap_or_default();
        if f.path == "scenarios/straight.toml" {
            f.bytes = text
                .replace("straight_m = 4.0", "straight_m = 0.6")
                .replace("straight_m = -4.0", "straight_m = -0.6")
                .into_bytes();
        } else if f.path == "amcl.toml" {
            f.bytes = text
                .replace("min_particles = 500", "min_particles = 200")
                .replace("max_particles = 2000", "max_particles = 200")
                .into_bytes();
        }
    }
    write_dir(&files, dir).unwrap();
}

fn eval(config: &Path, out: &Path) {
    let run = Command::new(env!("CARGO_BIN_EXE_amr"))
        .args(["eval", "--scenario", "straight", "--trials", "2", "--seed", "3", "--config"])
        .arg(config)
        .arg("--out")
        .arg(out)
        .env_remove("RUST_LOG")
        .output()
        .unwrap();
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    assert!(String::from_utf8_lossy(&run.stdout).contains("| T4 |"));
}

#[test]
fn a_short_evaluation_is_consistent_and_reproducible() {
    let tmp = tempfile::tempdir().unwrap();
    let config = tmp.path().join("config");
    short_config(&config);
    let (a, b) = (tmp.path().join("a"), tmp.path().join("b"));
    eval(&config, &a);
    eval(&config, &b);
    for file in ["report.md", "report.json", "trials.json"] {
        let x = std::fs::read(a.join("straight").join(file)).unwrap();
        assert!(!x.is_empty(), "{file}");
        assert_eq!(
            x,
            std::fs::read(b.join("straight").join(file)).unwrap(),
            "{file} differs between two runs with one seed"
        );
    }
    // The report's trial-level RMSE is the mean of the trials' RMSEs computed from the raw errors.
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(a.join("straight/report.json")).unwrap()).unwrap();
    let trials: serde_json::Value =
        serde_json::from_slice(&std::fs::read(a.join("straight/trials.json")).unwrap()).unwrap();
    assert_eq!(trials.as_array().unwrap().len(), 2);
    for (k, summary) in report["summary"].as_array().unwrap().iter().enumerate() {
        let rmses: Vec<f64> = trials
            .as_array()
            .unwrap()
            .iter()
            .map(|t| {
                let errs = t["series"][k][1]["truth"].as_array().unwrap();
                let sq: f64 = errs
                    .iter()
                    .map(|e| e["e_x"].as_f64().unwrap().powi(2) + e["e_y"].as_f64().unwrap().powi(2))
                    .sum();
                (sq / errs.len() as f64).sqrt()
            })
            .collect();
        let mean = rmses.iter().sum::<f64>() / rmses.len() as f64;
        let reported = summary["trial_rmse_2d"]["mean"].as_f64().unwrap();
        assert!((mean - reported).abs() < 1e-12, "{}: {mean} vs {reported}", summary["configuration"]);
    }
}

#[test]
fn the_sensitivity_study_reports_every_setting_beside_the_paper() {
    let tmp = tempfile::tempdir().unwrap();
    let config = tmp.path().join("config");
    short_config(&config);
    let run = Command::new(env!("CARGO_BIN_EXE_amr"))
        .args(["eval", "--scenario", "straight", "--sweep", "step", "--trials", "1", "--config"])
        .arg(&config)
        .arg("--out")
        .arg(tmp.path().join("out"))
        .env_remove("RUST_LOG")
        .output()
        .unwrap();
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let rows: serde_json::Value =
        serde_json::from_slice(&std::fs::read(tmp.path().join("out/straight/sweep-step.json")).unwrap())
            .unwrap();
    let rows = rows.as_array().unwrap();
    let settings: Vec<&str> = rows.iter().map(|r| r["setting"].as_str().unwrap()).collect();
    assert_eq!(settings, ["0.05", "0.1", "0.2", "0.5", "1"]);
    for r in rows {
        let f = r["failure_rate_pct"].as_f64().unwrap();
        assert!((0.0..=100.0).contains(&f), "{r}");
        assert!(r["pipeline_ms"].as_f64().unwrap() > 0.0);
    }
    // Table 7's row for the nominal 0.1°: 2.0 %, 3.5 cm, 0.16°, 150 ms.
    assert_eq!(rows[1]["paper"], serde_json::json!([2.0, 3.5, 0.16, 150.0]));
}
