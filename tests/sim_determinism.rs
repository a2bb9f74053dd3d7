//! The simulation in virtual time — every device over in-memory pipes, tokio's clock paused on one
//! thread: two runs with the same seed give identical results, and another seed gives different
//! ones; and a formation whose fusion cannot start does not drive on anything unverified.
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

/// One robot's scans reach the server 0.3 s late for the first 8 s (a loaded host: past the
/// fusion's 100 ms age gate, while its odometry and health arrive on time), so nothing can be
/// fused. The robots' own filters localise all along; the formation must not drive on them alone,
/// and V's filter must start where the robots are when fusion begins, not where the scenario
/// started. Once V is verified the plan runs and finishes, V within 10 cm of the truth whenever
/// it was verified.
#[test]
fn a_formation_whose_fusion_starts_late_waits_for_a_verified_v() {
    use std::time::Duration;
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().start_paused(true).build().unwrap();
    let (report, during) = rt.block_on(async {
        let config = load(&ConfigSource::Embedded).unwrap();
        let scenario = hil_tests::short_scenario("[{ straight_m = 2.0, turn_deg = 20.0 }]");
        let sim =
            Sim::start(&config, hil_tests::sim_options(scenario, 5, SimCan::VirtualTime, 90)).await.unwrap();
        let late = sim.robots[1].id.clone();
        sim.link.set_scan_delay(&late, Duration::from_millis(300));
        let mut during = Vec::new();
        let watch = async {
            for _ in 0..16 {
                tokio::time::sleep(Duration::from_millis(500)).await;
                during.push(sim.formation().map(|f| (f.phase, f.plan_s)));
            }
            sim.link.set_scan_delay(&late, Duration::ZERO);
        };
        tokio::join!(sim.run(|_| {}), watch);
        let report = sim.report();
        sim.shutdown().await;
        (report, during)
    });
    use amr_actors::server::formation::Phase;
    for d in &during {
        let ok = match d {
            None => true,
            Some((Phase::Waiting, plan_s)) => *plan_s == 0.0,
            Some(_) => false,
        };
        assert!(ok, "the formation moved while nothing could be fused: {during:?}");
    }
    assert!(during.iter().any(Option::is_some), "the formation started: {during:?}");
    assert_eq!(report.final_phase, "Finished", "{}", report.to_text());
    let failures = report.failures(0.10, true);
    assert!(failures.is_empty(), "{failures:?}\n{}", report.to_text());
    assert!(report.samples.iter().filter(|s| s.verified).count() > 100, "{}", report.to_text());
}

/// A job of laps, the server restarted in the second lap (crashed; a new one started and re-armed
/// by the operator). Every lap passes the same places, so the point of the plan nearest V alone
/// cannot tell the lap: the new formation resumes at the progress the old one reached (a few
/// seconds before it where V lags its plan in a turn, or just after where V coasted to), never a
/// lap later, and drives the rest of the job to its end.
#[test]
fn a_server_restarted_in_lap_two_resumes_there_and_drives_every_lap() {
    use std::time::Duration;
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().start_paused(true).build().unwrap();
    rt.block_on(async {
        let config = load(&ConfigSource::Embedded).unwrap();
        let text = hil_tests::short_scenario_text(
            "[{ straight_m = 0.8, turn_deg = 180.0 }, { straight_m = 0.8, turn_deg = 180.0 }]",
        )
        .replace("laps = 1", "laps = 3");
        let scenario = toml::from_str(&text).unwrap();
        let mut sim =
            Sim::start(&config, hil_tests::sim_options(scenario, 5, SimCan::VirtualTime, 600)).await.unwrap();
        let mut lap_s = 0.0;
        for _ in 0..600 {
            tokio::time::sleep(Duration::from_millis(500)).await;
            if let Some((_, plan_s, len_s)) = sim_plan(&sim) {
                lap_s = len_s / 3.0;
                if plan_s > 1.4 * lap_s {
                    break;
                }
            }
        }
        let (_, before, _) = sim_plan(&sim).unwrap();
        assert!(before > 1.4 * lap_s && before < 2.0 * lap_s, "in lap 2: {before} of laps of {lap_s} s");
        sim.restart_server().await.unwrap();
        assert!(sim.server.rearm().await);
        let mut seen = Vec::new();
        for _ in 0..1200 {
            tokio::time::sleep(Duration::from_millis(250)).await;
            let Some((phase, plan_s, _)) = sim_plan(&sim) else { continue };
            seen.push((phase.clone(), plan_s));
            if matches!(
                phase,
                amr_actors::server::formation::Phase::Finished
                    | amr_actors::server::formation::Phase::Stopped { .. }
            ) {
                break;
            }
        }
        let resumed = seen.iter().map(|(_, s)| *s).find(|s| *s > 0.0).expect("the new formation ran");
        let lap_of = |s: f64| (s / lap_s).floor();
        assert_eq!(lap_of(resumed), lap_of(before), "resumed in the lap the job was in");
        assert!(
            resumed >= before - 10.0 && resumed <= before + 3.0,
            "resumed at {resumed} s after {before} s (laps of {lap_s} s): {seen:?}"
        );
        let ran: Vec<f64> = seen.iter().map(|(_, s)| *s).filter(|s| *s > 0.0).collect();
        let steps: Vec<f64> = ran.windows(2).map(|w| w[1] - w[0]).collect();
        assert!(steps.iter().all(|d| (-1e-9..=1.5).contains(d)), "the plan jumped: {seen:?}");
        assert!(matches!(seen.last(), Some((amr_actors::server::formation::Phase::Finished, _))), "{seen:?}");
        sim.shutdown().await;
    });
}

/// The formation's phase, progress and plan length, s.
fn sim_plan(sim: &Sim) -> Option<(amr_actors::server::formation::Phase, f64, f64)> {
    sim.formation().map(|f| (f.phase, f.plan_s, f.plan_len_s))
}
