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

/// A hall of our own, 8 m × 4 m, with three boxes along its +y wall only: a map_server YAML + PGM
/// beside a scenario file that names it by path.
fn hall(dir: &Path, straight_m: f64) -> std::path::PathBuf {
    use amr_core::geometry::Polygon;
    use amr_core::map::{MapMode, rasterize_outlines, save_map};
    use amr_core::se2::Se2;
    let room = Polygon::centered_rectangle(8.0, 4.0).unwrap();
    let boxes: Vec<Polygon> = [-2.5, 0.0, 2.5]
        .iter()
        .map(|x| Polygon::new(vec![[x - 0.3, 1.4], [x + 0.3, 1.4], [x + 0.3, 2.0], [x - 0.3, 2.0]]).unwrap())
        .collect();
    let mut outlines = vec![room.clone()];
    outlines.extend(boxes);
    let grid = rasterize_outlines(&outlines, &room, 0.05, Se2::new(-4.25, -2.25, 0.0), 170, 90);
    let (yaml, image) = save_map(&grid, MapMode::Trinary, 0.65, 0.196, "hall.pgm").unwrap();
    std::fs::create_dir_all(dir.join("maps")).unwrap();
    std::fs::create_dir_all(dir.join("runs")).unwrap();
    std::fs::write(dir.join("maps/hall.yaml"), yaml).unwrap();
    std::fs::write(dir.join("maps/hall.pgm"), image).unwrap();
    let scenario = format!(
        "map = \"../maps/hall.yaml\"\nspacing_m = 0.9\nlaps = 1\n\
         segments = [{{ straight_m = {straight_m} }}, {{ straight_m = {} }}]\n\
         [start]\nx_m = -2.0\ny_m = 0.0\nyaw_deg = 0.0\n\
         [limits]\nmax_speed_mps = 0.22\nmax_accel_mps2 = 0.05\nmax_yaw_rate_radps = 0.2\n",
        -straight_m
    );
    let file = dir.join("runs/hall-run.toml");
    std::fs::write(&file, scenario).unwrap();
    file
}

#[test]
fn a_scenario_file_runs_on_any_map_and_a_path_through_a_wall_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let config = tmp.path().join("config");
    short_config(&config);
    let eval_on = |scenario: &Path| {
        Command::new(env!("CARGO_BIN_EXE_amr"))
            .args(["eval", "--trials", "1", "--seed", "3", "--scenario"])
            .arg(scenario)
            .arg("--config")
            .arg(&config)
            .arg("--out")
            .arg(tmp.path().join("out"))
            .env_remove("RUST_LOG")
            .output()
            .unwrap()
    };
    let run = eval_on(&hall(tmp.path(), 0.6));
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    // Named after the file; every configuration localised on the hall (2.4–2.7 cm here; the world
    // ray-cast the map's cells: a world that saw nothing there would leave AMCL lost).
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(tmp.path().join("out/hall-run/report.json")).unwrap()).unwrap();
    assert_eq!(report["map"], "surveyed", "AMCL's map is a survey by default");
    assert!(report["site"].as_str().unwrap().ends_with("hall.yaml"), "{}", report["site"]);
    for s in report["summary"].as_array().unwrap() {
        let rmse = s["trial_rmse_2d"]["mean"].as_f64().unwrap();
        assert!(rmse < 0.06, "{}: {rmse} m", s["configuration"]);
    }
    // 7 m forward from x = -2 goes through the +x wall at x = 4.
    let run = eval_on(&hall(&tmp.path().join("b"), 7.0));
    let said = String::from_utf8_lossy(&run.stderr);
    assert!(
        !run.status.success() && said.contains("into a wall") && said.contains("hall-run.toml"),
        "{said}"
    );
}

/// The occlusion study on a map of one's own: every team and spacing is tried, the
/// ones that do not fit the site are listed with the reason, the others carry T1–T4 and what each
/// robot's neighbours hid from it; a plot per scenario.
#[test]
fn the_occlusion_study_runs_every_team_and_spacing_on_a_scenario_file() {
    let tmp = tempfile::tempdir().unwrap();
    let config = tmp.path().join("config");
    short_config(&config);
    let scenario = hall(tmp.path(), 0.3);
    let run = Command::new(env!("CARGO_BIN_EXE_amr"))
        .args(["eval", "--study", "occlusion", "--trials", "1", "--confirm-trials", "3", "--seed", "3"])
        .arg("--study-scenario")
        .arg(&scenario)
        .arg("--config")
        .arg(&config)
        .arg("--out")
        .arg(tmp.path().join("out"))
        .env_remove("RUST_LOG")
        .output()
        .unwrap();
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let dir = tmp.path().join("out/study-occlusion");
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("study.json")).unwrap()).unwrap();
    let rows = report["rows"].as_array().unwrap();
    let grid: Vec<(u64, f64)> =
        rows.iter().map(|r| (r["robots"].as_u64().unwrap(), r["spacing_m"].as_f64().unwrap())).collect();
    let mut expected = Vec::new();
    for n in [2, 3, 4] {
        for s in [0.5, 1.0, 1.5, 2.0] {
            expected.push((n, s));
        }
    }
    assert_eq!(grid, expected);
    // The hall is 4 m wide with boxes along +y: four robots 2 m apart do not fit; two 0.5 m apart do.
    let row = |n: u64, s: f64| rows.iter().find(|r| r["robots"] == n && r["spacing_m"] == s).unwrap();
    assert!(row(4, 2.0)["skipped"].as_str().unwrap().contains("into a wall"), "{}", row(4, 2.0));
    let (two, three) = (row(2, 0.5), row(3, 0.5));
    for r in [two, three] {
        assert!(r["skipped"].is_null(), "{r}");
        let figures = r["figures"].as_array().unwrap();
        assert_eq!(figures.len(), 4);
        for f in figures {
            let rmse = f[1]["rmse"]["mean"].as_f64().unwrap();
            assert!(rmse < 0.1, "{f}");
            // V errs by the robots' mean error, so the worst-placed robot errs at least as much
            // (per trial, and so in the mean over trials).
            let worst = f[1]["worst_robot"]["mean"].as_f64().unwrap();
            assert!(worst >= rmse - 1e-12 && worst < 0.15, "{f}");
        }
    }
    // Three abreast the middle robot loses about twice the beams to its neighbours.
    let occluded = |r: &serde_json::Value| r["occluded"][0].as_f64().unwrap();
    assert!(occluded(three) > 1.6 * occluded(two) && occluded(two) > 0.1, "{two} {three}");
    // One trial has no spread to leave the criterion open: no configuration ran the confirmation.
    for r in rows.iter().filter(|r| r["skipped"].is_null()) {
        assert_eq!(r["trials"], 1, "{r}");
    }
    let md = std::fs::read_to_string(dir.join("study.md")).unwrap();
    assert!(md.contains("| hall-run | straight | 2 | 0.5 |") && md.contains("hall-run.png"), "{md}");
    assert!(md.contains("runs 3 trials in all") && md.contains("0 of them on 3 trials"), "{md}");
    let worst_table = md.split("## The worst-placed robot").nth(1).unwrap_or_default();
    assert!(worst_table.contains("| hall-run | straight | 3 | 0.5 |"), "{md}");
    assert!(dir.join("hall-run.png").is_file());
}
