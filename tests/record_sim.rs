//! Record a short simulation (the whole system against the mocks, in virtual time), read it back,
//! replay it: the estimates are identical.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "tests")]

use amr_actors::config::{ConfigSource, load};
use amr_actors::server::{ServerSetup, formation_robots};
use amr_actors::supervisor::RestartPolicy;
use amr_record::{FlushPolicy, RecordOptions, RecordSources, Recorder, replay};
use amr_sim::{Sim, SimCan};

#[test]
fn a_recorded_simulation_replays_to_the_same_estimates() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("sim.mcap");
    let config = load(&ConfigSource::Embedded).unwrap();
    let scenario = hil_tests::short_scenario("[{ straight_m = 1.0, turn_deg = 20.0 }]");
    let options = hil_tests::sim_options(scenario.clone(), 9, SimCan::VirtualTime, 40);
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().start_paused(true).build().unwrap();
    // The server as Sim::start builds it (for the replay).
    let setup = ServerSetup {
        server: config.server.clone(),
        vamr: config.vamr.clone(),
        amcl: config.amcl.clone(),
        map: config.maps[&scenario.map].clone(),
        robots: formation_robots(&config.server, &config.robots).unwrap(),
        scenario,
        seed: 9,
        auto_arm: amr_actors::server::AutoArm::Mock,
        policy: RestartPolicy::default(),
        progress: std::sync::Arc::new(amr_actors::server::progress::PlanProgress::in_memory()),
    };
    let stats = rt.block_on(async {
        let sim = Sim::start(&config, options).await.unwrap();
        // Started before virtual time moves: no scan has been taken yet.
        let sources = RecordSources::server(&sim.server.ports, &setup);
        let recorder = Recorder::start(
            RecordOptions {
                file: Some(path.clone()),
                live: None,
                flush: FlushPolicy::default(),
                ros2: false,
                ros2_live: None,
            },
            sources,
        )
        .await
        .unwrap();
        sim.run(|_| {}).await;
        let report = sim.report();
        assert_eq!(report.final_phase, "Finished", "{}", report.to_text());
        let stats = recorder.stop().await.unwrap();
        sim.shutdown().await;
        stats
    });
    assert!(stats.per_topic["/amr/uplink"] > 500, "{stats:?}");
    let report = replay(&path, Some(&dir.path().join("replayed.mcap")), &setup, None).unwrap();
    assert!(report.exact(), "{report:#?}");
    assert_eq!(report.fused_identical, report.recorded_fused);
}
