//! The shipped configuration validates; every bad-config fixture fails with its documented error.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code: a failed step fails the test")]

use amr_actors::config::Config;
use amr_actors::config::{ConfigSource, load};
use hil_tests::{apply, config_dir, fixtures, without_line};

#[test]
fn shipped_configuration_is_valid() {
    let config = load(&ConfigSource::Dir(config_dir())).unwrap();
    let ids: Vec<&str> = config.robots.iter().map(|r| r.id.as_str()).collect();
    assert_eq!(ids, ["robot-a", "robot-b"]);
    // Spot-check values taken from the paper, nav2_amcl's defaults and the devices.
    let a = config.robot("robot-a").unwrap();
    assert_eq!(a.chassis.outline_m.bounds(), (-0.2, -0.2, 0.2, 0.2));
    assert_eq!(a.lidar_mount.to_se2(), amr_core::se2::Se2::new(0.175, 0.0, 0.0));
    assert_eq!(a.limits.max_speed_mps.get(), 0.22);
    assert_eq!(a.limits.max_accel_mps2.get(), 0.05);
    assert_eq!(a.limits.max_yaw_rate_radps.get(), 0.2);
    assert_eq!(a.devices.lidar.port, 2112);
    assert_eq!(a.devices.imu.baud, 115_200);
    assert_eq!(config.server.sync.max_stamp_spread_ms.ms(), 50);
    assert_eq!(config.server.sync.max_age_ms.ms(), 100);
    assert_eq!(config.server.sync.e2e_threshold_ms.ms(), 350);
    assert_eq!(config.vamr.tracker.measurement_var_m2.get(), 4.0e-4);
    assert_eq!(config.vamr.heading.distance_gate_m.get(), 0.003);
    assert_eq!(config.amcl.min_particles.get(), 500);
    assert_eq!(config.amcl.max_particles.get(), 2000);
}

#[test]
fn every_fixture_fails_with_its_documented_error() {
    let all = fixtures().unwrap();
    assert!(all.len() >= 20, "expected a fixture per rule, found {}", all.len());
    let mut failures = Vec::new();
    for fx in &all {
        let files = apply(fx).unwrap_or_else(|e| panic!("fixture {}: {e}", fx.name));
        match Config::from_files(files) {
            Ok(_) => failures.push(format!("{}: accepted, expected `{}`", fx.name, fx.expect)),
            Err(e) if without_line(&e) != fx.expect => {
                failures.push(format!(
                    "{}:\n   got    `{}`\n   expect `{}`",
                    fx.name,
                    without_line(&e),
                    fx.expect
                ));
            }
            Err(_) => {}
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

#[test]
fn fixture_names_are_unique_rules() {
    // Two fixtures with the same expected error test the same rule twice and leave another untested.
    let all = fixtures().unwrap();
    let mut seen = std::collections::BTreeMap::new();
    for fx in &all {
        if let Some(other) = seen.insert(fx.expect.clone(), fx.name.clone()) {
            panic!("fixtures {other} and {} expect the same error", fx.name);
        }
    }
}
