//! The fault-recovery drills as tests: each runs against real mock devices in real time
//! and must pass every expectation; the soak runs shortened. `amr drill all` runs the same drills
//! and prints the table.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code: a failed step fails the test")]

use std::time::Duration;

use amr_actors::config::{ConfigSource, load};
use amr_sim::drills::{DrillOutcome, run, table};

/// Drills measure deadlines of a few hundred milliseconds in real time: on a 2-core machine two
/// simulations side by side starve each other, so the drills of this binary run one at a time.
static ONE_AT_A_TIME: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

async fn drill(name: &str) -> DrillOutcome {
    let _turn = ONE_AT_A_TIME.lock().await;
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
    drive_fault_moving => "drive-fault-moving",
    new_master_moving => "new-master-moving",
    estop_during_restart => "estop-during-restart",
    safety_crash_moving => "safety-crash-moving",
    robot_restart_odometry => "robot-restart-odometry",
    bad_scan => "bad-scan",
    command_burst => "command-burst",
    robot_freeze => "robot-freeze",
    drive_reboot_moving => "drive-reboot-moving",
    bad_data => "bad-data",
    absent_at_start => "absent-at-start",
    link_lost => "link-lost",
    server_restart => "server-restart",
    slow_consumer => "slow-consumer",
    estop => "estop",
    estop_input => "estop-input",
    estop_restart => "estop-restart",
    late_scans => "late-scans",
}

/// One robot floods the server with scans, shortened from 60 s to 15 s.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn scan_flood_shortened() {
    let _turn = ONE_AT_A_TIME.lock().await;
    let config = load(&ConfigSource::Embedded).unwrap();
    let outcome = amr_sim::drills::scan_flood(&config, 5, Duration::from_secs(15)).await;
    assert!(outcome.passed, "{}\n{outcome:#?}", table(std::slice::from_ref(&outcome)));
}

/// The chaos soak, shortened from 10 minutes to 40 s: still several faults of several kinds.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn soak_shortened() {
    let _turn = ONE_AT_A_TIME.lock().await;
    let config = load(&ConfigSource::Embedded).unwrap();
    let outcome = amr_sim::drills::soak(&config, 5, Duration::from_secs(40)).await;
    assert!(outcome.passed, "{}\n{outcome:#?}", table(std::slice::from_ref(&outcome)));
}

#[tokio::test]
async fn every_drill_in_the_list_has_a_test_here() {
    let names: Vec<&str> = amr_sim::drills::DRILLS.iter().map(|d| d.name).collect();
    let here = include_str!("drills.rs");
    for n in &names {
        // The soak and the scan flood run shortened, above.
        let shortened = ["soak", "scan-flood"].contains(n);
        assert!(here.contains(&format!("\"{n}\"")) || shortened, "no test for drill {n}");
    }
    let config = load(&ConfigSource::Embedded).unwrap();
    assert!(run("no-such-drill", &config, 1).await.is_none());
}

/// The main command's job in real time with two threads spinning beside it on this 2-core
/// machine (the case where a starved run once drove its whole plan on a V 4 m off and reported
/// success): the run either finishes with every verified estimate of V within 10 cm of the truth,
/// or ends short of its plan with a reason; never "Finished" off target.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_run_starved_by_busy_threads_never_finishes_off_target() {
    use std::sync::Arc;
    use std::sync::atomic::{AtomicBool, Ordering};
    let _turn = ONE_AT_A_TIME.lock().await;
    let config = load(&ConfigSource::Embedded).unwrap();
    let scenario = hil_tests::short_scenario("[{ straight_m = 1.5, turn_deg = 45.0 }]");
    let stop = Arc::new(AtomicBool::new(false));
    let busy: Vec<_> = (0..2)
        .map(|_| {
            let stop = Arc::clone(&stop);
            std::thread::spawn(move || {
                let mut x = 0u64;
                // Bounded by the flag, which the test sets after the run (itself bounded: 60 s).
                while !stop.load(Ordering::Relaxed) {
                    x = std::hint::black_box(x.wrapping_mul(6364136223846793005).wrapping_add(1));
                }
                x
            })
        })
        .collect();
    let options = hil_tests::sim_options(scenario, 5, amr_sim::SimCan::InProcess, 60);
    let sim = amr_sim::Sim::start(&config, options).await.unwrap();
    sim.run(|_| {}).await;
    let report = sim.report();
    sim.shutdown().await;
    stop.store(true, Ordering::Relaxed);
    for b in busy {
        b.join().unwrap();
    }
    eprintln!("{}", report.to_text());
    // Ended short of its plan, `amr sim` exits non-zero with the reason (`SimReport::failures`);
    // finished, it must be on target.
    if report.final_phase == "Finished" {
        let off_target = report.failures(0.10, false);
        assert!(off_target.is_empty(), "finished off target: {off_target:?}");
    }
}
