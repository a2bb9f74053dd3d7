//! A short hardware-in-the-loop run: both robot trees, the server tree and the world, on virtual
//! time (tokio's paused clock, the devices over in-memory pipes: the same run from the same seed,
//! whatever the machine's load). About 22 s of motion: 2 m forward, then a 45° turn of the whole
//! formation on the spot. The whole system over its real transports (SOPAS over TCP, CANopen
//! behind socketcand, LPBUS on a pty, the fleet over Zenoh) runs in real time in `host/tests/fleet.rs`.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code: a failed step fails the test")]

use amr_actors::config::{ConfigSource, load};
use amr_actors::supervisor::EventKind;
use amr_sim::{Sim, SimCan, v_of};

#[tokio::test(start_paused = true)]
async fn both_robots_follow_the_formation_and_v_is_localised() {
    let config = load(&ConfigSource::Embedded).unwrap();
    let scenario = hil_tests::short_scenario("[{ straight_m = 2.0, turn_deg = 45.0 }]");
    let start_v = scenario.start_pose();
    let sim =
        Sim::start(&config, hil_tests::sim_options(scenario, 7, SimCan::VirtualTime, 60)).await.unwrap();
    sim.run(|_| {}).await;
    let report = sim.report();
    let events: Vec<_> = sim.robots.iter().flat_map(|r| r.events.snapshot()).collect();
    let truth = sim.truth.latest().unwrap().1;
    sim.shutdown().await;
    let text = report.to_text();

    // The plan ran to its end, every device of both robots came up, nothing failed.
    assert_eq!(report.final_phase, "Finished", "{text}");
    assert!(report.every_device_reached_ok(), "{text}");
    assert!(
        !events.iter().any(|e| matches!(e.kind, EventKind::Failed { .. } | EventKind::StartFailed { .. })),
        "{events:?}"
    );
    // The formation moved as planned: V 2 m ahead, turned 45°, each robot at its slot. The
    // controller closes on AMCL (about 5 cm RMSE in this site, see amr eval): the bounds leave room
    // for that, not for a broken loop (which ends metres or tens of degrees off).
    let v = v_of(&truth).unwrap();
    let moved = start_v.inverse() * v;
    assert!((moved.x - 2.0).abs() < 0.25 && moved.y.abs() < 0.25, "V moved by {moved:?}\n{text}");
    assert!(
        (moved.theta.to_degrees() - 45.0).abs() < 8.0,
        "V turned {:.1}°\n{text}",
        moved.theta.to_degrees()
    );
    for e in &report.final_formation_error_m {
        assert!(*e < 0.08, "a robot ended {e:.3} m from its slot\n{text}");
    }
    // Localisation of V against the true pose stays bounded throughout.
    let err = report.error_2d.expect("fused estimates");
    assert!(err.count >= 200, "{text}");
    assert!(err.rmse < 0.12 && err.max < 0.30, "{text}");
    // The latency table: the paper's seven stages, from every fused update.
    assert_eq!(report.latency.len(), 7);
    let e2e = report.latency.last().unwrap();
    assert_eq!(e2e.stage, "end to end");
    assert!(
        e2e.count >= 200 && e2e.median_ms.is_finite() && e2e.median_ms >= report.latency[0].median_ms,
        "{text}"
    );
    assert!(report.latency[5].count >= 1, "AMCL ran at least once while moving 2 m\n{text}");
}
