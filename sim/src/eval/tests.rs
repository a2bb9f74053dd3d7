use super::*;
use amr_actors::config::{Config, ConfigFile};
use amr_core::config::value::Count;
use hil_mocks::world::paper_site;

fn shipped() -> Config {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../config");
    let mut files = Vec::new();
    let mut stack = vec![root.clone()];
    while let Some(dir) = stack.pop() {
        for e in std::fs::read_dir(&dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                let rel = p.strip_prefix(&root).unwrap().to_string_lossy().replace('\\', "/");
                files.push(ConfigFile { path: rel, bytes: std::fs::read(&p).unwrap() });
            }
        }
    }
    Config::from_files(files).unwrap()
}

/// The straight scenario shortened to 0.6 m and back, with few particles so it runs quickly in a
/// debug build.
fn short_setup() -> Setup {
    let config = shipped();
    let mut scenario = config.scenarios["straight"].clone();
    scenario.segments = vec![
        amr_core::config::Segment {
            straight_m: Some(amr_core::config::value::Finite::new(0.6).unwrap()),
            turn_deg: None,
        },
        amr_core::config::Segment {
            straight_m: Some(amr_core::config::value::Finite::new(-0.6).unwrap()),
            turn_deg: None,
        },
    ];
    let mut amcl = config.amcl.clone();
    amcl.min_particles = Count::new(200).unwrap();
    amcl.max_particles = Count::new(200).unwrap();
    Setup {
        site: paper_site().unwrap().into(),
        map: EvalMap::Given(config.maps["paper-site"].clone()),
        robot: crate::robot_spec(&config.robots[0]),
        vamr: config.vamr.clone(),
        amcl,
        noise: Noise::TYPICAL,
        scenario,
        physics_dt_s: 1.0 / 150.0,
        steps_per_scan: 10,
        oracle: amr_core::vamr::pipeline::Oracle::default(),
        robots: 2,
    }
}

/// Each robot is placed wherever V is, and against its own truth: V (the robots' centroid) errs by
/// the mean of their errors at every scan, and no robot is compared with its neighbour's pose
/// (0.9 m away).
fn assert_robots_placed(c: Configuration, s: &Series, robots: usize) {
    assert_eq!(s.robots.len(), robots, "{c:?}");
    for r in &s.robots {
        assert_eq!(r.len(), s.truth.len(), "{c:?}: a robot placed with every estimate of V");
        let rmse = AxisStats::of(r).unwrap().d2.rmse;
        assert!(rmse < 0.3, "{c:?}: a robot's 2D RMSE {rmse:.3} m");
    }
    let n = robots as f64;
    for (k, v) in s.truth.iter().enumerate() {
        let mx = s.robots.iter().map(|r| r[k].e_x).sum::<f64>() / n;
        let my = s.robots.iter().map(|r| r[k].e_y).sum::<f64>() / n;
        assert!(
            (mx - v.e_x).abs() < 1e-9 && (my - v.e_y).abs() < 1e-9,
            "{c:?} scan {k}: V {v:?}, robots' mean ({mx}, {my})"
        );
    }
}

#[test]
fn slots_put_the_reference_robot_where_it_sees_the_others() {
    assert_eq!(slots(2, 0.9), vec![0.45, -0.45]);
    assert_eq!(slots(3, 0.9), vec![0.0, 0.9, -0.9]);
    assert_eq!(slots(4, 0.5), vec![0.0, 0.5, -0.5, 1.0]);
}

#[test]
fn three_robots_run_through_the_same_pipeline() {
    let mut setup = short_setup();
    setup.robots = 3;
    setup.scenario.segments.truncate(1);
    let trial = run_trial(&setup, 2);
    for (c, s) in &trial.series {
        assert_eq!(s.truth.len() + s.missing, trial.scans, "{c:?}");
        assert!(s.truth.len() > trial.scans / 2, "{c:?}: {} of {} scans", s.truth.len(), trial.scans);
        let rmse = AxisStats::of(&s.truth).unwrap().d2.rmse;
        assert!(rmse < 0.3, "{c:?}: 2D RMSE {rmse:.3} m");
        assert_robots_placed(*c, s, 3);
    }
}

#[test]
fn the_reference_respects_the_limits_and_comes_back() {
    let config = shipped();
    let sc = &config.scenarios["straight"];
    let dt = 0.01;
    let r = reference(sc, 2, dt);
    let start = sc.start_pose();
    let end = r.last().unwrap().pose;
    assert!(end.approx_eq(&start, 1e-3, 1e-9), "back where it started: {end:?}");
    let far = r.iter().map(|x| x.pose.x - start.x).fold(f64::NEG_INFINITY, f64::max);
    assert!((far - 4.0).abs() < 0.01, "4 m out: {far}");
    assert!(r.iter().all(|x| x.v_mps.abs() <= 0.22 + 1e-12));
    assert!(
        r.windows(2).all(|w| (w[1].v_mps - w[0].v_mps).abs() <= 0.05 * dt + 1e-12),
        "acceleration ≤ 0.05 m/s²"
    );
}

/// Turning on the spot, every robot of the formation can follow the plan inside the limits: its
/// outer wheel (0.2 m beyond its slot) never needs more than the speed or acceleration limit, for
/// teams of 2–4 at every spacing of the occlusion study.
#[test]
fn every_robot_can_follow_the_turns_of_the_reference() {
    let config = shipped();
    let mut sc = config.scenarios["turning"].clone();
    let dt = 0.01;
    for robots in 2..=4 {
        for spacing in [0.5, 1.0, 2.0] {
            sc.spacing_m = amr_core::config::value::Positive::new(spacing).unwrap();
            let r = reference(&sc, robots, dt);
            let (v_max, a_max) = (sc.limits.max_speed_mps.get(), sc.limits.max_accel_mps2.get());
            for y in slots(robots, spacing) {
                let wheels: Vec<[f64; 2]> = r
                    .iter()
                    .map(|x| {
                        let v = x.v_mps - x.w_radps * y;
                        [v - x.w_radps * 0.2, v + x.w_radps * 0.2]
                    })
                    .collect();
                let what = format!("{robots} robots {spacing} m apart, the one at {y} m");
                assert!(wheels.iter().flatten().all(|w| w.abs() <= v_max + 1e-9), "{what}: speed");
                assert!(
                    wheels.windows(2).all(|w| (0..2).all(|k| (w[1][k] - w[0][k]).abs() <= a_max * dt + 1e-9)),
                    "{what}: acceleration"
                );
            }
        }
    }
}

#[test]
fn a_short_trial_runs_all_four_configurations_on_the_same_scans() {
    let setup = short_setup();
    let trial = run_trial(&setup, 1);
    assert!(trial.scans > 100, "{} scans", trial.scans);
    assert_eq!((trial.times_s.len(), trial.truth_v.len()), (trial.scans, trial.scans));
    assert!(trial.truth_robots.iter().all(|t| t.len() == trial.scans));
    assert_eq!(trial.final_particles_t4.len(), 200, "T4's cloud at the end");
    assert_eq!(trial.series.iter().map(|(c, _)| *c).collect::<Vec<_>>(), CONFIGS.to_vec());
    for (c, s) in &trial.series {
        assert_eq!(s.truth.len() + s.missing, trial.scans, "{c:?}: every scan is a sample or a miss");
        assert_eq!(s.truth.len(), s.reference.len());
        assert_eq!(s.estimates.len(), trial.scans, "{c:?}: one entry per scan");
        assert_eq!(s.estimates.iter().filter(|e| e.is_some()).count(), s.truth.len());
        // Localisation works in every configuration on this short run (a loose bound: this is not
        // the paper's comparison, which `amr eval` reports).
        let rmse = AxisStats::of(&s.truth).unwrap().d2.rmse;
        assert!(rmse < 0.3, "{c:?}: 2D RMSE {rmse:.3} m");
        assert_robots_placed(*c, s, 2);
        // Every filter given a pose is unverified until it has judged a few scans, and then
        // verified for the rest of this quiet run.
        eprintln!("{c:?}: {} of {} estimates not verified", s.unverified, s.truth.len());
        assert!(
            s.unverified >= 1 && s.unverified * 10 < s.truth.len(),
            "{c:?}: {} of {}",
            s.unverified,
            s.truth.len()
        );
    }
    // The summary's statistics are those of the raw errors.
    let summary = summarise("straight", std::slice::from_ref(&trial));
    for (sum, (_, s)) in summary.iter().zip(&trial.series) {
        let raw = AxisStats::of(&s.truth).unwrap();
        assert_eq!(sum.pooled_truth.unwrap(), raw);
        assert_eq!(sum.trial_rmse_2d.unwrap().mean, raw.d2.rmse);
        assert_eq!(sum.unverified, s.unverified);
        assert_eq!(sum.trial_rmse_2d.unwrap().n, 1);
        let robots: Vec<f64> = s.robots.iter().map(|r| AxisStats::of(r).unwrap().d2.rmse).collect();
        assert_eq!(sum.robot_rmse_2d.iter().map(|m| m.unwrap().mean).collect::<Vec<_>>(), robots);
        assert_eq!(sum.worst_robot_rmse_2d.unwrap().mean, robots[0].max(robots[1]));
    }
    assert_eq!(summary[3].paper_rmse_2d, Some((0.0412, 0.0083)));
}

/// With `fusion.amcl_motion = reference` the virtual-scan filters sample V's motion as the
/// reference robot, 0.45 m beside V, drove it: through a turn on the spot T2–T4 still place V and
/// each robot, and T4's cloud stands around V.
#[test]
fn with_the_reference_robots_motion_the_filters_still_place_v() {
    let mut setup = short_setup();
    let finite = |v: f64| Some(amr_core::config::value::Finite::new(v).unwrap());
    setup.scenario.segments = vec![
        amr_core::config::Segment { straight_m: finite(0.3), turn_deg: finite(90.0) },
        amr_core::config::Segment { straight_m: finite(0.3), turn_deg: None },
    ];
    setup.vamr.fusion.amcl_motion = amr_core::config::AmclMotion::Reference;
    let trial = run_trial(&setup, 3);
    let turned = trial.truth_v.iter().map(|v| v[2]).fold(0.0f64, f64::max);
    assert!(turned > 80f64.to_radians(), "V turned {:.1}°", turned.to_degrees());
    for (c, s) in trial.series.iter().skip(1) {
        let rmse = AxisStats::of(&s.truth).unwrap().d2.rmse;
        assert!(rmse < 0.06, "{c:?}: 2D RMSE {rmse:.3} m");
        assert_robots_placed(*c, s, 2);
    }
    let v = trial.truth_v.last().unwrap();
    let n = trial.final_particles_t4.len() as f64;
    let mean = trial.final_particles_t4.iter().fold([0.0, 0.0], |m, p| [m[0] + p[0] / n, m[1] + p[1] / n]);
    let off = (mean[0] - v[0]).hypot(mean[1] - v[1]);
    assert!(off < 0.06, "T4's cloud is centred {off:.3} m from V");
    // The setting reaches the filters: with V's own motion the same seed gives other estimates.
    setup.vamr.fusion.amcl_motion = amr_core::config::AmclMotion::Virtual;
    let own = run_trial(&setup, 3);
    let t4 = |t: &Trial| t.series[3].1.estimates.clone();
    assert_ne!(t4(&trial), t4(&own), "T4 the same with either motion");
    assert_eq!(trial.series[0].1.estimates, own.series[0].1.estimates, "T1 has no virtual-scan filter");
}

/// Each trial surveys the site afresh from its own seed (and the same seed, the same map); a
/// given map is every trial's.
#[test]
fn each_trial_has_its_own_survey() {
    let setup = short_setup();
    let EvalMap::Given(truth) = &setup.map else { panic!("the short setup gives the site's map") };
    assert_eq!(setup.map.for_trial(4).as_ref(), truth);
    let surveyed = EvalMap::Surveyed(Surveys::new(setup.site.clone(), truth.clone(), SurveyOptions::TYPICAL));
    let a = surveyed.for_trial(4);
    // Made once: a clone (another configuration of a study) gets the same map; a fresh survey of
    // the same seed makes the same map again.
    assert_eq!(a, surveyed.clone().for_trial(4));
    let fresh = EvalMap::Surveyed(Surveys::new(setup.site.clone(), truth.clone(), SurveyOptions::TYPICAL));
    assert_eq!(a, fresh.for_trial(4));
    assert_ne!(a, surveyed.for_trial(5));
    assert_ne!(a.as_ref(), truth);
}

#[test]
fn same_seed_same_trial() {
    let setup = short_setup();
    let mut shorter = setup.clone();
    shorter.scenario.segments.truncate(1);
    if let EvalMap::Given(truth) = &setup.map {
        shorter.map =
            EvalMap::Surveyed(Surveys::new(setup.site.clone(), truth.clone(), SurveyOptions::TYPICAL));
    }
    let a = serde_json::to_string(&run_trial(&shorter, 4)).unwrap();
    let b = serde_json::to_string(&run_trial(&shorter, 4)).unwrap();
    let c = serde_json::to_string(&run_trial(&shorter, 5)).unwrap();
    assert_eq!(a, b);
    assert_ne!(a, c);
}

/// The oracle replaces what it names by the truth, and nothing else: with the true relative
/// heading T2–T4's heading errors vanish while the scans (and T1) stay exactly as without it.
#[test]
fn the_oracle_replaces_the_heading_and_only_in_the_fusion() {
    let mut setup = short_setup();
    setup.scenario.segments.truncate(1);
    let plain = run_trial(&setup, 4);
    setup.oracle = amr_core::vamr::pipeline::Oracle { heading: true, ..Default::default() };
    let oracle = run_trial(&setup, 4);
    let series = |t: &Trial, c: Configuration| t.series.iter().find(|(k, _)| *k == c).unwrap().1.clone();
    let t4 = series(&plain, Configuration::T4);
    assert!(t4.heading_errors_rad.iter().any(|e| e.abs() > 1e-4), "the search has errors of its own");
    for c in [Configuration::T2, Configuration::T4] {
        let s = series(&oracle, c);
        assert!(!s.heading_errors_rad.is_empty());
        assert!(s.heading_errors_rad.iter().all(|e| e.abs() < 1e-9), "{c:?}: {:?}", s.heading_errors_rad);
    }
    // The world does not know about the oracle: the same true path; and T1's V, where the relative
    // heading sets only V's heading, has the same positions (from the robots' own AMCL).
    assert_eq!(plain.truth_v, oracle.truth_v);
    let xy = |t: &Trial| -> Vec<Option<[f64; 2]>> {
        series(t, Configuration::T1).estimates.iter().map(|e| e.map(|p| [p[0], p[1]])).collect()
    };
    assert_eq!(xy(&plain), xy(&oracle));
}

/// Visibility in a trial: beside a neighbour 0.9 m away each robot loses about a tenth of its
/// beams to the other's body (as many site returns), and three abreast the middle robot twice that.
#[test]
fn each_trial_counts_what_the_neighbours_hide() {
    let mut setup = short_setup();
    setup.scenario.segments.truncate(1);
    let two = run_trial(&setup, 5);
    assert_eq!(two.visibility.len(), 2);
    for v in &two.visibility {
        assert!((0.08..0.15).contains(&v.occluded), "{v:?}");
        assert!((v.site_left + v.occluded - 1.0).abs() < 0.02, "{v:?}");
    }
    setup.robots = 3;
    let three = run_trial(&setup, 5);
    let middle = three.visibility[0].occluded;
    assert!(middle > 1.8 * two.visibility[0].occluded, "{:?}", three.visibility);
}

/// On a shipped site's own map (`--map true`) AMCL is as exact as the map: the world ray-casts the
/// site's polygons, which the map renders. Ray-cast as that rendering, whose occupied cells reach a
/// cell in front of every face, the robots stood nearer the racks than the map said, and every
/// configuration placed them about 5 cm towards the racks (+y).
#[test]
fn on_a_shipped_sites_own_map_the_robots_are_placed_where_they_stand() {
    let mut setup = short_setup();
    let config = shipped();
    let map = config.maps["short-racks"].clone();
    setup.site = crate::site_for("short-racks", &map).unwrap();
    setup.map = EvalMap::Given(map);
    setup.scenario = config.scenarios["short-racks"].clone();
    setup.scenario.segments = vec![amr_core::config::Segment {
        straight_m: Some(amr_core::config::value::Finite::new(0.6).unwrap()),
        turn_deg: None,
    }];
    for name in ["paper-site", "one-sided-hall", "corridor", "short-racks"] {
        let site = crate::site_for(name, &config.maps[name]).unwrap();
        assert!(site.grid.is_none() && !site.polygons.is_empty(), "{name} is ray-cast as its polygons");
    }
    // A map of another building that shares the name is ray-cast as its own cells.
    let mut other = config.maps["short-racks"].clone();
    let (i, j) = other.cell_of([0.0, 0.0]).unwrap();
    other.set(i, j, amr_core::map::OCCUPIED);
    assert!(crate::site_for("short-racks", &other).unwrap().grid.is_some(), "not our rendering");
    let trial = run_trial(&setup, 1);
    for (c, s) in &trial.series {
        let stats = AxisStats::of(&s.truth).unwrap();
        let mean_y = s.truth.iter().map(|e| e.e_y).sum::<f64>() / s.truth.len() as f64;
        assert!(mean_y.abs() < 0.015, "{c:?}: V placed {mean_y:+.3} m off in y on average");
        assert!(stats.d2.rmse < 0.025, "{c:?}: 2D RMSE {:.3} m", stats.d2.rmse);
    }
}

/// A shipped scenario on its site's own map with the robots 0.5 m apart and the shipped AMCL.
fn close_formation(scenario: &str) -> Setup {
    let mut setup = short_setup();
    let config = shipped();
    setup.scenario = config.scenarios[scenario].clone();
    let grid = config.maps[&setup.scenario.map].clone();
    setup.site = crate::site_for(&setup.scenario.map, &grid).unwrap();
    setup.map = EvalMap::Given(grid);
    setup.amcl = config.amcl.clone();
    setup.scenario.spacing_m = amr_core::config::value::Positive::new(0.5).unwrap();
    setup
}

/// In the hall two robots 0.5 m apart hide much of each other's view of the racks: the
/// neighbour's body is about half of what each robot's LiDAR returns, and the map does not hold
/// it. Each robot's own filter must not take that for being lost and re-seed itself to a place
/// whose racks explain the body's returns (where it stood metres off for the rest of the run).
#[test]
fn robots_side_by_side_in_the_hall_keep_their_own_filters() {
    let mut setup = close_formation("hall-straight");
    setup.scenario.segments = vec![amr_core::config::Segment {
        straight_m: Some(amr_core::config::value::Finite::new(3.0).unwrap()),
        turn_deg: None,
    }];
    for seed in [7, 8] {
        let trial = run_trial(&setup, seed);
        let (_, t1) = trial.series.iter().find(|(c, _)| *c == Configuration::T1).unwrap();
        assert_eq!(t1.robots.len(), 2);
        for (i, r) in t1.robots.iter().enumerate() {
            assert_eq!(r.len(), t1.truth.len(), "seed {seed}: robot {i} placed at every scan");
            let worst = r.iter().map(|e| e.e_x.hypot(e.e_y)).fold(0.0, f64::max);
            assert!(worst < 0.15, "seed {seed}: robot {i}'s own filter {worst:.2} m off at worst");
        }
    }
}

/// On `short-racks` two robots 0.5 m apart: the far one sees nothing of the site but its
/// neighbour, and its own estimate drifts. A virtual scan assembled with that estimate (T2 takes
/// the relative position from the robots' own filters) fits the map poorly; V's filter, judged
/// lost, must start again from the robots' own estimates, not re-localise anywhere on the map (a
/// place 11 m off explained that scan better).
#[test]
fn a_virtual_scan_assembled_with_a_drifting_robot_does_not_carry_v_off() {
    let setup = close_formation("short-racks");
    let trial = run_trial(&setup, 7);
    for (c, s) in &trial.series {
        assert!(
            s.truth.len() + 20 > trial.scans,
            "{c:?}: V placed on {} of {} scans",
            s.truth.len(),
            trial.scans
        );
        let worst = s.truth.iter().map(|e| e.e_x.hypot(e.e_y)).fold(0.0, f64::max);
        assert!(worst < 1.0, "{c:?}: V {worst:.2} m off at worst");
    }
}
