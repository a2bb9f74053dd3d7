//! Determinism of the simulation (DEVELOPERS.md): in virtual time — every device over in-memory
//! pipes, tokio's clock paused on one thread — two runs with the same seed give identical results,
//! and another seed gives different ones.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code: a failed step fails the test")]

use amr_actors::config::{ConfigSource, load};
use amr_sim::{Sim, SimCan, SimReport};

/// One run in its own paused single-thread runtime.
fn run(seed: u64) -> SimReport {
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().start_paused(true).build().unwrap();
    rt.block_on(async {
        let config = load(&ConfigSource::Embedded).unwrap();
        let scenario = hil_tests::short_scenario("[{ straight_m = 1.0, turn_deg = 20.0 }]");
        let sim = Sim::start(&config, hil_tests::sim_options(scenario, seed, SimCan::VirtualTime, 40))
            .await
            .unwrap();
        sim.run(|_| {}).await;
        let report = sim.report();
        sim.shutdown().await;
        report
    })
}

#[test]
fn the_same_seed_gives_the_same_run_in_virtual_time() {
    let (a, b, other) = (run(9), run(9), run(10));
    assert_eq!(a.final_phase, "Finished", "{}", a.to_text());
    assert!(a.every_device_reached_ok(), "{}", a.to_text());
    assert!(a.samples.len() > 150, "{}", a.to_text());
    // Bit for bit: every scored estimate and the final true poses.
    assert_eq!(a.samples, b.samples);
    assert_eq!(a.final_truth, b.final_truth);
    assert_eq!(a.plan_s, b.plan_s);
    assert_ne!(a.samples, other.samples, "a different seed changes the noise");
}
