//! Degradation instead of failure, in a simulation on virtual time (tokio's paused clock, the
//! devices over in-memory pipes: the same run from the same seed): one robot's scans stop mid-run. The
//! server declares it lost, keeps localising the other robot on its own AMCL and stops the
//! formation (the shipped `on_robot_lost = "stop"`); when the scans return the track is re-acquired
//! with a full heading search, and the formation resumes only after an explicit re-arm.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code: a failed step fails the test")]

use std::time::Duration;

use amr_actors::config::{ConfigSource, load};
use amr_actors::server::formation::Phase;
use amr_actors::server::ports::ServerStats;
use amr_msgs::{DisarmReason, SafetyState};
use amr_sim::{Sim, SimCan};
use hil_mocks::tim551::Fault;

async fn wait_until(what: &str, timeout: Duration, mut cond: impl FnMut() -> bool) {
    let start = tokio::time::Instant::now();
    while !cond() {
        assert!(start.elapsed() < timeout, "timed out waiting for {what}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

#[tokio::test(start_paused = true)]
async fn a_robot_whose_scans_stop_stops_the_formation_until_it_is_back_and_rearmed() {
    let config = load(&ConfigSource::Embedded).unwrap();
    let scenario = hil_tests::short_scenario("[{ straight_m = 3.0 }]");
    let sim =
        Sim::start(&config, hil_tests::sim_options(scenario, 11, SimCan::VirtualTime, 90)).await.unwrap();
    let stats = &sim.server.ports.stats;
    let phase = || sim.formation().map(|f| f.phase);
    wait_until("the formation 4 s into its plan", Duration::from_secs(30), || {
        sim.formation().is_some_and(|f| f.phase == Phase::Running && f.plan_s > 4.0)
    })
    .await;
    let full_before = ServerStats::get(&stats.full_searches);
    assert!(full_before >= 1, "the first acquisition searched the full circle");

    // Robot B's LiDAR goes silent (connected, sending nothing).
    sim.mocks[1].lidar.handle.inject(Fault::Stall);
    wait_until("robot-b declared lost", Duration::from_secs(3), || ServerStats::get(&stats.robots_lost) == 1)
        .await;
    wait_until("the formation stopped", Duration::from_secs(3), || {
        matches!(phase(), Some(Phase::Stopped { .. }))
    })
    .await;
    // Both robots disarmed: they ramp to zero on their own.
    wait_until("both robots disarmed", Duration::from_secs(3), || {
        sim.robots.iter().all(|r| matches!(*r.ports.safety_now.borrow(), Some(SafetyState::Disarmed(_))))
    })
    .await;
    // Robot A is still localised, by its own AMCL.
    let own_a = ServerStats::get(&stats.own_estimates[0]);
    tokio::time::sleep(Duration::from_secs(2)).await;
    assert!(ServerStats::get(&stats.own_estimates[0]) >= own_a + 20, "robot-a's own AMCL kept running");
    let fused_during = ServerStats::get(&stats.fused);
    tokio::time::sleep(Duration::from_secs(1)).await;
    assert_eq!(ServerStats::get(&stats.fused), fused_during, "nothing fused while robot-b is silent");

    // The scans return: the track is re-acquired with the full heading search.
    sim.mocks[1].lidar.handle.inject(Fault::Resume);
    wait_until("robot-b back", Duration::from_secs(10), || ServerStats::get(&stats.robots_back) == 1).await;
    wait_until("a full heading search", Duration::from_secs(5), || {
        ServerStats::get(&stats.full_searches) > full_before
    })
    .await;
    // Still stopped: nothing resumes by itself.
    tokio::time::sleep(Duration::from_secs(1)).await;
    assert!(matches!(phase(), Some(Phase::Stopped { .. })), "{:?}", phase());
    assert_eq!(
        *sim.robots[0].ports.safety_now.borrow(),
        Some(SafetyState::Disarmed(DisarmReason::Requested))
    );

    // The operator re-arms: the formation finishes its plan.
    assert!(sim.server.rearm().await);
    // The re-arm is a message to the formation actor: `run` returns on a stopped formation, so
    // it starts once the formation has left Stopped.
    wait_until("the formation re-armed", Duration::from_secs(3), || {
        !matches!(phase(), Some(Phase::Stopped { .. }))
    })
    .await;
    sim.run(|_| {}).await;
    let report = sim.report();
    sim.shutdown().await;
    let text = report.to_text();
    assert_eq!(report.final_phase, "Finished", "{text}");
    for e in &report.final_formation_error_m {
        assert!(*e < 0.08, "a robot ended {e:.3} m from its slot\n{text}");
    }
}
