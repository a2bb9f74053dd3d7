//! The fault-recovery drills as tests, on virtual time: each runs on tokio's paused clock with its
//! devices over in-memory pipes and must pass every expectation; the soak and the scan flood run
//! shortened. Nothing here waits on the wall clock, so the machine's speed and load decide no
//! outcome, and the same seed gives the same outcome, timings included (checked below). The drills
//! that need the wall clock, and one drill per real transport, run in real time in
//! `drills_real_time.rs`; `amr drill` runs every drill in real time.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code: a failed step fails the test")]

use std::time::Duration;

use amr_actors::config::{ConfigSource, load};
use amr_sim::drills::{DRILLS, DrillClock, DrillOutcome, run_on, table};

async fn drill(name: &str) -> DrillOutcome {
    let config = load(&ConfigSource::Embedded).unwrap();
    let outcome = run_on(name, &config, 5, DrillClock::Virtual).await.unwrap();
    assert!(outcome.passed, "{}\n{outcome:#?}", table(std::slice::from_ref(&outcome)));
    outcome
}

macro_rules! drills {
    ($($test:ident => $name:literal),* $(,)?) => {
        $(
            #[tokio::test(start_paused = true)]
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
    drive_bus_off => "drive-bus-off",
    drive_heartbeat => "drive-heartbeat",
    drive_reboot => "drive-reboot",
    drive_fault_moving => "drive-fault-moving",
    new_master_moving => "new-master-moving",
    estop_during_restart => "estop-during-restart",
    safety_crash_moving => "safety-crash-moving",
    robot_restart_odometry => "robot-restart-odometry",
    bad_scan => "bad-scan",
    drive_reboot_moving => "drive-reboot-moving",
    bad_data => "bad-data",
    link_lost => "link-lost",
    server_restart => "server-restart",
    estop => "estop",
    estop_input => "estop-input",
    late_scans => "late-scans",
}

/// One robot floods the server with scans, shortened from 60 s to 15 s.
#[tokio::test(start_paused = true)]
async fn scan_flood_shortened() {
    let config = load(&ConfigSource::Embedded).unwrap();
    let outcome = amr_sim::drills::scan_flood(&config, 5, Duration::from_secs(15), DrillClock::Virtual).await;
    assert!(outcome.passed, "{}\n{outcome:#?}", table(std::slice::from_ref(&outcome)));
}

/// The chaos soak, shortened from 10 minutes to 60 s (still several faults of several kinds, a
/// server crash among them), run twice: it passes, and the same seed gives the same outcome,
/// events, counters and every timing. (tokio picks at random among the branches of a `select!`
/// that are ready at the same instant unless it is `biased`, and on a paused clock many are: the
/// mock devices' and the link's selects have a fixed order, or two runs part, e.g. after the
/// server's crash.)
#[tokio::test(start_paused = true)]
async fn soak_shortened_passes_the_same_way_twice() {
    let config = load(&ConfigSource::Embedded).unwrap();
    let mut runs = Vec::new();
    for _ in 0..2 {
        let o = amr_sim::drills::soak(&config, 5, Duration::from_secs(60), DrillClock::Virtual).await;
        assert!(o.passed, "{}\n{o:#?}", table(std::slice::from_ref(&o)));
        assert!(o.counters.get("injected.server-crash").is_some_and(|n| *n >= 1), "{o:#?}");
        runs.push(format!("{o:?}"));
    }
    assert_eq!(runs[0], runs[1]);
}

/// Every drill is tested: on virtual time here, or in real time in `drills_real_time.rs`; a drill
/// that needs the wall clock refuses virtual time with its reason.
#[tokio::test(start_paused = true)]
async fn every_drill_in_the_list_has_a_test() {
    let here = include_str!("drills.rs");
    let real = include_str!("drills_real_time.rs");
    let config = load(&ConfigSource::Embedded).unwrap();
    for d in DRILLS {
        let quoted = format!("\"{}\"", d.name);
        // The soak and the scan flood run shortened, above.
        let shortened = ["soak", "scan-flood"].contains(&d.name);
        match d.real_time_only() {
            None => assert!(here.contains(&quoted) || shortened, "no virtual-time test for drill {}", d.name),
            Some(why) => {
                assert!(real.contains(&quoted), "no real-time test for drill {}", d.name);
                let o = run_on(d.name, &config, 1, DrillClock::Virtual).await.unwrap();
                assert!(!o.passed && o.failures.iter().any(|f| f.contains(why)), "{o:#?}");
            }
        }
    }
    assert!(run_on("no-such-drill", &config, 1, DrillClock::Virtual).await.is_none());
}
