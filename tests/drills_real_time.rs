//! The drills that keep the real transports and the wall clock honest, in real time: one per
//! transport (the LiDAR over TCP, the IMU over a pty, CAN over socketcand), the drills that need
//! the wall clock (a robot on a thread of its own, frozen or killed; a blocked worker of the
//! multi-thread runtime; a TCP port nobody listens on), and the main command's job starved by busy
//! threads. The other drills run on virtual time (`drills.rs`).
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code: a failed step fails the test")]

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
    // One per real transport.
    lidar_reset_over_tcp => "lidar-reset",
    imu_unplug_on_a_pty => "imu-unplug",
    can_link_reset_over_socketcand => "can-link-reset",
    // The wall clock's own.
    absent_at_start => "absent-at-start",
    command_burst => "command-burst",
    robot_freeze => "robot-freeze",
    estop_restart => "estop-restart",
    slow_consumer => "slow-consumer",
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
