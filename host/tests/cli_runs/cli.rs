//! The `amr` binary as a user runs it.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code: a failed step fails the test")]

use std::path::Path;
use std::process::{Command, Output};

use hil_tests::{apply, config_dir, fixtures, write_dir};

fn amr(args: &[&str], cwd: &Path, envs: &[(&str, &str)]) -> Output {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_amr"));
    cmd.args(args).current_dir(cwd).env_remove("RUST_LOG");
    for (k, v) in envs {
        cmd.env(k, v);
    }
    cmd.output().unwrap()
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

/// `file:LINE: rest` → (`file: rest`, LINE).
fn split_line_number(msg: &str) -> (String, Option<usize>) {
    let parts: Vec<&str> = msg.splitn(3, ':').collect();
    match parts[..] {
        [file, num, rest] if num.parse::<usize>().is_ok() => (format!("{file}:{rest}"), num.parse().ok()),
        _ => (msg.to_owned(), None),
    }
}

#[test]
fn check_accepts_the_shipped_configuration() {
    let out = amr(&["config", "check", config_dir().to_str().unwrap()], Path::new("."), &[]);
    assert!(out.status.success(), "stderr: {}", text(&out.stderr));
    let stdout = text(&out.stdout);
    assert!(stdout.contains("robot robot-a"), "{stdout}");
    assert!(stdout.contains("robot robot-b"), "{stdout}");
    assert!(stdout.contains("configuration T4, formation [robot-a (w 1), robot-b (w 1)]"), "{stdout}");
    assert!(stdout.contains("map paper-site: 210 × 76 cells at 0.05 m"), "{stdout}");
    assert!(stdout.trim_end().ends_with("ok: 2 robots, server, vamr, amcl and 4 maps are valid"), "{stdout}");
}

#[test]
fn check_without_a_directory_uses_config_here_or_the_embedded_defaults() {
    let repo = config_dir().join("..");
    let here = amr(&["config", "check"], &repo, &[]);
    assert!(here.status.success());
    assert!(text(&here.stdout).starts_with("configuration: config\n"), "{}", text(&here.stdout));

    let empty = tempfile::tempdir().unwrap();
    let embedded = amr(&["config", "check"], empty.path(), &[]);
    assert!(embedded.status.success(), "stderr: {}", text(&embedded.stderr));
    let stdout = text(&embedded.stdout);
    assert!(stdout.starts_with("configuration: embedded defaults"), "{stdout}");
    // The embedded copy is the same configuration: the report after the first line matches.
    let rest = |s: &str| s.split_once('\n').map(|(_, r)| r.to_owned()).unwrap_or_default();
    assert_eq!(rest(&stdout), rest(&text(&here.stdout)));
}

#[test]
fn check_rejects_every_fixture_with_its_documented_error() {
    let mut failures = Vec::new();
    for fx in fixtures().unwrap() {
        let dir = tempfile::tempdir().unwrap();
        write_dir(&apply(&fx).unwrap(), dir.path()).unwrap();
        let out = amr(&["config", "check", dir.path().to_str().unwrap()], Path::new("."), &[]);
        let stderr = text(&out.stderr);
        let last = stderr.lines().last().unwrap_or_default();
        let (msg, _) = split_line_number(last.strip_prefix("error: ").unwrap_or(last));
        if out.status.code() != Some(1) || msg != fx.expect || !out.stdout.is_empty() {
            failures.push(format!(
                "{}: exit {:?}, stdout {} bytes\n   got    `{last}`\n   expect `error: {}`",
                fx.name,
                out.status.code(),
                out.stdout.len(),
                fx.expect
            ));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

#[test]
fn errors_point_at_the_line_of_the_key() {
    // Break values in place in the shipped files (no re-serialisation), so line numbers are the user's.
    let cases = [
        ("robot-a.toml", "wheel_radius_m = 0.065", "wheel_radius_m = -0.065", "kinematics.wheel_radius_m"),
        ("robot-a.toml", "right = { node_id = 2", "right = { node_id = 1", "devices.drives.right.node_id"),
        ("server.toml", "max_stamp_spread_ms = 50", "max_stamp_spread_ms = 150", "sync.max_stamp_spread_ms"),
        ("amcl.toml", "min_particles = 500", "min_particles = 5000", "min_particles"),
        ("vamr.toml", "step_deg = 0.1", "step_deg = 11.0", "heading.step_deg"),
    ];
    for (file, from, to, key) in cases {
        let dir = tempfile::tempdir().unwrap();
        let shipped =
            amr_actors::config::read_files(&amr_actors::config::ConfigSource::Dir(config_dir())).unwrap();
        write_dir(&shipped, dir.path()).unwrap();
        let path = dir.path().join(file);
        let original = std::fs::read_to_string(&path).unwrap();
        let line = original.lines().position(|l| l.contains(from)).expect("shipped line") + 1;
        std::fs::write(&path, original.replacen(from, to, 1)).unwrap();

        let out = amr(&["config", "check", dir.path().to_str().unwrap()], Path::new("."), &[]);
        assert_eq!(out.status.code(), Some(1));
        let stderr = text(&out.stderr);
        let expected_prefix = format!("error: {file}:{line}: {key}: ");
        assert!(stderr.contains(&expected_prefix), "expected `{expected_prefix}` in `{stderr}`");
    }
}

#[test]
fn log_filter_follows_rust_log() {
    let repo = config_dir().join("..");
    let quiet = amr(&["config", "check"], &repo, &[]);
    assert!(!text(&quiet.stderr).contains("loading configuration"), "{}", text(&quiet.stderr));
    let verbose = amr(&["config", "check"], &repo, &[("RUST_LOG", "amr=debug")]);
    let stderr = text(&verbose.stderr);
    assert!(stderr.contains("DEBUG") && stderr.contains("loading configuration"), "{stderr}");
    // Logs go to stderr; the report on stdout is the same either way.
    assert_eq!(quiet.stdout, verbose.stdout);
}

#[test]
fn version_and_help() {
    let out = amr(&["--version"], Path::new("."), &[]);
    assert_eq!(text(&out.stdout).trim(), format!("amr {}", env!("CARGO_PKG_VERSION")));
    let help = text(&amr(&["--help"], Path::new("."), &[]).stdout);
    assert!(help.contains("config") && help.contains("Inspect the configuration"), "{help}");
    let usage = amr(&["config", "frobnicate"], Path::new("."), &[]);
    assert_eq!(usage.status.code(), Some(2), "clap's usage error");
}

#[test]
fn a_soak_too_short_to_mean_anything_is_refused_before_any_drill_runs() {
    let out = amr(&["drill", "all", "--soak-seconds", "5"], Path::new("."), &[("RUST_LOG", "info")]);
    let err = text(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(err.contains("--soak-seconds 5 is too short") && err.contains("30 s"), "{err}");
    // Refused up front, not after the other drills' minutes: none started.
    assert!(!err.contains("running"), "{err}");
    assert!(text(&out.stdout).is_empty(), "{}", text(&out.stdout));
    // The soak's floor is not a hurdle for one of the other drills.
    let list = amr(&["drill", "list", "--soak-seconds", "5"], Path::new("."), &[]);
    assert!(list.status.success(), "{}", text(&list.stderr));
}
