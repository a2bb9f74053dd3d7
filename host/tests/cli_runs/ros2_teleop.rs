//! `amr sim --ros2-live zenoh --ros2-cmd-vel` driven as a ROS 2 operator would (an independent
//! rmw_zenoh peer, `peers/ros2_teleop_peer.py`): a pose on `/initialpose` restarts the filters
//! there, then `/cmd_vel` turns the formation, which its plan (straight ahead) never does, and
//! when the twists stop V comes to a stand. Loopback only.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code: a failed step fails the test")]

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use hil_tests::config_dir;

/// V's estimate nearest to `t` (peer time, s): (x, y, theta).
fn at(estimates: &[Vec<f64>], t: f64) -> (f64, f64, f64) {
    let e = estimates.iter().min_by(|a, b| (a[0] - t).abs().total_cmp(&(b[0] - t).abs())).unwrap();
    (e[1], e[2], e[3])
}

fn angle(a: f64) -> f64 {
    (a + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU) - std::f64::consts::PI
}

#[test]
fn a_ros2_operator_sets_vs_pose_and_drives_the_formation_and_its_silence_stops_it() {
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let router = format!("tcp/127.0.0.1:{port}");
    let config = config_dir();
    let mut sim = Command::new(env!("CARGO_BIN_EXE_amr"))
        .args(["sim", "--quiet", "--duration", "30", "--config", config.to_str().unwrap()])
        .args(["--ros2-live", "zenoh", "--ros2-router", &router, "--ros2-domain", "11", "--ros2-cmd-vel"])
        .env("RUST_LOG", "info")
        .env_remove("ROS_DOMAIN_ID")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let (w, drive_s) = (0.3, 6.0);
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/cli_runs/peers/ros2_teleop_peer.py");
    let peer = Command::new("python3")
        .args([script, &port.to_string(), "11", "0.2", &w.to_string(), &drive_s.to_string()])
        .output()
        .expect("python3 (the CI installs eclipse-zenoh and rosbags)");
    let _ = sim.kill();
    let deadline = Instant::now() + Duration::from_secs(30);
    while sim.try_wait().unwrap().is_none() {
        assert!(Instant::now() < deadline, "amr sim did not end");
        std::thread::sleep(Duration::from_millis(100));
    }
    let mut err = String::new();
    std::io::Read::read_to_string(sim.stderr.as_mut().unwrap(), &mut err).unwrap();
    assert!(peer.status.success(), "peer: {}", String::from_utf8_lossy(&peer.stderr));
    let v: serde_json::Value = serde_json::from_slice(&peer.stdout).unwrap();
    assert!(v["error"].is_null(), "{v}\n{err}");
    assert!(err.contains("the filters start again there"), "the server did not take the pose:\n{err}");

    let estimates: Vec<Vec<f64>> = serde_json::from_value(v["estimates"].clone()).unwrap();
    let phase = |p: &str| v["phases"][p].as_f64().unwrap();
    let (drive, silent, end) = (phase("drive"), phase("silent"), phase("end"));
    // Driven: V turned the way the twist said (the plan goes straight).
    let (a, b) = (at(&estimates, drive), at(&estimates, silent));
    let turned = angle(b.2 - a.2);
    assert!(turned > 0.3, "V turned {turned} rad under {w} rad/s for {drive_s} s\n{err}");
    // Silent: V stops (the robots brake at their comfort limit, 0.05 m/s², and the formation
    // closes up on its slots) and then stands.
    let (c, d) = (at(&estimates, silent + 6.0), at(&estimates, end));
    assert!(end - silent > 7.5);
    let moved = (d.0 - c.0).hypot(d.1 - c.1);
    assert!(moved < 0.05 && angle(d.2 - c.2).abs() < 0.03, "V went on {moved} m, {} rad", angle(d.2 - c.2));
}
