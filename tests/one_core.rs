//! One server core, three drivers: `amr eval`'s runner, `amr replay`'s engine (fed what a recording
//! gives back) and the same engine fed what the network link gives back produce the same estimates,
//! bit for bit, in every configuration. (That the live server's actors and a replay of their
//! recording agree is `record/tests/recording/record_replay.rs`.)
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code: a failed step fails the test")]

use amr_actors::config::{ConfigSource, load};
use amr_actors::server::{ServerSetup, formation_robots};
use amr_actors::supervisor::RestartPolicy;
use amr_core::config::value::Count;
use amr_msgs::{EstimateSource, Uplink};
use amr_net::wire::{Envelope, from_uplink, to_uplink, uplink_channel};
use amr_record::replay::Engine;
use amr_record::wire::{decode_uplink, encode_uplink};
use amr_sim::eval::{Setup, TrialFrame, run_trial_observed};
use hil_mocks::world::{Noise, paper_site};

const SEED: u64 = 11;

fn setups() -> (Setup, ServerSetup) {
    let config = load(&ConfigSource::Embedded).unwrap();
    let scenario = hil_tests::short_scenario("[{ straight_m = 0.6 }]");
    let mut amcl = config.amcl.clone();
    amcl.min_particles = Count::new(200).unwrap();
    amcl.max_particles = Count::new(200).unwrap();
    let map = config.maps[&scenario.map].clone();
    let eval = Setup {
        site: paper_site().unwrap().into(),
        map: amr_sim::eval::EvalMap::Given(map.clone()),
        robot: amr_sim::robot_spec(&config.robots[0]),
        vamr: config.vamr.clone(),
        amcl: amcl.clone(),
        noise: Noise::TYPICAL,
        scenario: scenario.clone(),
        physics_dt_s: 1.0 / 150.0,
        steps_per_scan: 10,
        oracle: amr_core::vamr::pipeline::Oracle::default(),
        robots: 2,
    };
    let server = ServerSetup {
        map,
        robots: formation_robots(&config.server, &config.robots).unwrap(),
        server: config.server.clone(),
        vamr: config.vamr.clone(),
        amcl,
        scenario,
        seed: SEED,
        auto_arm: amr_actors::server::AutoArm::Off,
        policy: RestartPolicy::default(),
        progress: std::sync::Arc::new(amr_actors::server::progress::PlanProgress::in_memory()),
    };
    (eval, server)
}

/// The message with its robot named as the server's formation names it.
fn renamed(u: &Uplink, ids: &[String]) -> Uplink {
    let mut u = u.clone();
    if let Uplink::Scan(s) = &mut u
        && let Some(i) = s.robot.strip_prefix("robot").and_then(|i| i.parse::<usize>().ok())
    {
        s.robot.clone_from(&ids[i]);
    }
    u
}

fn bits(v: Option<[f64; 3]>) -> Option<[u64; 3]> {
    v.map(|p| p.map(f64::to_bits))
}

#[test]
fn eval_replay_and_the_network_path_give_identical_estimates_in_every_configuration() {
    let (eval, server) = setups();
    let ids: Vec<String> = server.robots.iter().map(|r| r.id.as_str().to_owned()).collect();
    let mut steps: Vec<Vec<(Uplink, f64)>> = Vec::new();
    let trial = run_trial_observed(&eval, SEED, &mut |f: &TrialFrame<'_>| {
        steps.push(f.uplink.iter().map(|(u, rx)| (renamed(u, &ids), *rx)).collect());
    });
    assert_eq!(steps.len(), trial.scans);
    assert!(trial.scans > 40, "{} scans", trial.scans);
    for (c, series) in &trial.series {
        let mut recorded = Engine::new(&server, Some(*c));
        let mut networked = Engine::new(&server, Some(*c));
        let (mut from_record, mut from_network) = (Vec::new(), Vec::new());
        for step in &steps {
            let (mut a, mut b) = (None, None);
            for (u, rx) in step {
                // What a recording gives back.
                let r = decode_uplink(&encode_uplink(*rx, u).unwrap()).unwrap();
                // What the network link gives back.
                let (stamp, body) = from_uplink(u);
                let env = Envelope {
                    version: amr_msgs::SCHEMA_VERSION,
                    session: 1,
                    seq: 1,
                    origin: u.robot().to_owned(),
                    robot: u.robot().to_owned(),
                    stamp_s: stamp,
                    sent_s: stamp,
                    body,
                };
                let n = to_uplink(
                    Envelope::decode(&env.encode().unwrap()).unwrap(),
                    u.robot(),
                    uplink_channel(u),
                )
                .unwrap();
                let fused = |s: amr_record::replay::Step| {
                    s.estimates
                        .into_iter()
                        .find(|e| e.source == EstimateSource::Fused(*c))
                        .and_then(|e| e.v)
                        .map(|v| [v.x, v.y, v.theta])
                };
                a = fused(recorded.uplink(r.rx_s, &r.msg)).or(a);
                b = fused(networked.uplink(*rx, &n)).or(b);
            }
            from_record.push(a);
            from_network.push(b);
        }
        let eval_bits: Vec<_> = series.estimates.iter().copied().map(bits).collect();
        let record_bits: Vec<_> = from_record.into_iter().map(bits).collect();
        let network_bits: Vec<_> = from_network.into_iter().map(bits).collect();
        let estimated = eval_bits.iter().filter(|e| e.is_some()).count();
        assert!(estimated > trial.scans / 2, "{c:?}: {estimated} estimates of {} scans", trial.scans);
        assert_eq!(record_bits, eval_bits, "{c:?}: replay of the recorded uplink against eval");
        assert_eq!(network_bits, eval_bits, "{c:?}: the network path against eval");
    }
}
