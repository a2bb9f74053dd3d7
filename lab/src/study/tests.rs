//! Tests of the study's statistics, verdicts and report.

use super::*;

/// The pairs are taken trial by trial: a difference the trials share cancels, a trial without an
/// estimate on either side is left out, and a margin missed by less than two standard errors is
/// told apart from one missed beyond the noise.
#[test]
fn the_criterion_pairs_trials_and_weighs_the_noise() {
    let t4 = [Some(0.030), Some(0.020), None, Some(0.041)];
    let best = [Some(0.024), Some(0.014), Some(0.010), Some(0.034)];
    let d = paired_difference_cm(&t4, &best).unwrap();
    assert_eq!(d.n, 3);
    assert!((d.mean - 0.6333).abs() < 1e-3, "{d:?}");
    // 0.6, 0.6, 0.7: SD 0.0577, standard error 0.0333; 0.63 − 0.07 > 0.5 is beyond the noise.
    assert!((standard_error(&d) - 0.0333).abs() < 1e-3, "{d:?}");
    assert_eq!(over_margin(&d), (true, true));
    assert_eq!(with_se(&d), "+0.63 ± 0.03");
    // The same mean with trials that disagree: over the margin, not beyond the noise.
    let noisy = paired_difference_cm(
        &[Some(0.040), Some(0.020), Some(0.031)],
        &[Some(0.024), Some(0.024), Some(0.024)],
    )
    .unwrap();
    assert!((noisy.mean - 0.6333).abs() < 1e-3, "{noisy:?}");
    assert_eq!(over_margin(&noisy), (true, false));
    assert_eq!(over_margin(&MeanSd { mean: 0.4, sd: 0.0, n: 5 }), (false, false));
    assert!(paired_difference_cm(&t4, &best[..3]).is_none());
}

/// A trial whose V errs by a constant `rmse_m[k]` in configuration `CONFIGS[k]`.
fn trial(seed: u64, rmse_m: [f64; 4]) -> Trial {
    let series = CONFIGS
        .iter()
        .zip(rmse_m)
        .map(|(c, r)| {
            let truth = vec![amr_core::metrics::Sample { e_x: r, e_y: 0.0 }; 3];
            (*c, amr_sim::eval::Series { robots: vec![truth.clone()], truth, ..Default::default() })
        })
        .collect();
    Trial {
        seed,
        scans: 3,
        series,
        times_s: vec![0.0; 3],
        truth_v: vec![[0.0; 3]; 3],
        truth_robots: Vec::new(),
        final_particles_t4: Vec::new(),
        visibility: Vec::new(),
    }
}

fn row() -> StudyRow {
    StudyRow::new("s".into(), "s".into(), "straight", 2, 1.0)
}

/// Only a configuration whose trials leave the criterion open runs the confirmation trials: the
/// same first seeds and the next, and its figures are of all of them.
#[test]
fn an_open_verdict_is_settled_on_more_trials_and_a_clear_one_is_not() {
    // T4 − T2 per trial, cm, by seed: the first three straddle the margin (+0.6 ± 0.32), the
    // next seven hold it.
    let d_cm = |seed: u64| match seed {
        100 => 1.2,
        101 => 0.1,
        102 => 0.5,
        _ => -0.3,
    };
    let mut calls = Vec::new();
    let mut r = row();
    let out = run_row(&mut r, 3, 10, 100, &mut |from, count| {
        calls.push((from, count));
        (from..from + count as u64).map(|s| trial(s, [0.05, 0.03, 0.04, 0.03 + d_cm(s) / 100.0])).collect()
    });
    assert_eq!(calls, [(100, 3), (103, 7)]);
    assert_eq!(r.trials, 10);
    assert_eq!(out.iter().map(|t| t.seed).collect::<Vec<_>>(), (100..110).collect::<Vec<_>>());
    let d = r.t4_over_best_paired_cm().unwrap();
    assert_eq!(d.n, 10);
    assert!((d.mean - (1.8 - 2.1) / 10.0).abs() < 1e-9, "{d:?}");
    assert!(!verdict_open(&d), "{d:?}");

    // Clearly held, and clearly missed: three trials say so, and no more run.
    for t4 in [0.028, 0.04] {
        let mut calls = 0;
        let mut r = row();
        run_row(&mut r, 3, 10, 100, &mut |from, count| {
            calls += 1;
            (from..from + count as u64).map(|s| trial(s, [0.05, 0.03, 0.04, t4 + s as f64 * 1e-5])).collect()
        });
        assert_eq!((calls, r.trials), (1, 3), "T4 {t4}");
    }
    // No confirmation asked for: none.
    let mut r = row();
    run_row(&mut r, 3, 0, 100, &mut |from, count| {
        (from..from + count as u64).map(|s| trial(s, [0.05, 0.03, 0.04, 0.03 + d_cm(s) / 100.0])).collect()
    });
    assert_eq!(r.trials, 3);
}

/// The criterion is open only while the margin lies within two standard errors of the mean,
/// and never on one trial.
#[test]
fn the_verdict_is_open_only_within_two_standard_errors_of_the_margin() {
    // SD 0.2 over 4 trials: a standard error of 0.1.
    let at = |mean: f64| MeanSd { mean, sd: 0.2, n: 4 };
    assert!(verdict_open(&at(0.6)), "0.4 ≤ 0.5 < 0.8");
    assert!(verdict_open(&at(0.7)), "0.5 ≤ 0.5 < 0.9");
    assert!(!verdict_open(&at(0.71)), "missed beyond the noise");
    assert!(!verdict_open(&at(0.3)), "held beyond the noise: 0.3 + 0.2 is not above 0.5");
    assert!(!verdict_open(&MeanSd { mean: 0.5, sd: 0.0, n: 1 }), "one trial");
    assert_eq!(over_margin(&at(0.71)), (true, true));
    assert_eq!(over_margin(&at(0.6)), (true, false));
}

/// Figures in cm with two decimals, a dash without any; shares in whole percent, per robot.
#[test]
fn cells_are_written_in_centimetres_and_percent() {
    let f = |rmse| Figures { rmse, trial_rmse: Vec::new(), diverged: 0, missing: 0, worst_robot: None };
    assert_eq!(cm(&f(Some(MeanSd { mean: 0.0123, sd: 0.0045, n: 3 }))), "1.23 ± 0.45");
    assert_eq!(cm(&f(None)), "—");
    assert_eq!(pct(&[0.125, 0.5, 1.0]), "12/50/100");
    assert_eq!(pct(&[]), "");
}

/// A trial diverged when V strays more than [`DIVERGED_M`] at some scan; the RMSE is of each
/// trial, then mean and SD over trials.
#[test]
fn figures_count_diverged_trials_and_average_their_rmse() {
    let trials = [trial(1, [0.01, 0.02, 0.03, 0.04]), trial(2, [0.03, 0.02, 0.6, 0.04])];
    let t1 = figures(&trials, Configuration::T1);
    let m = t1.rmse.unwrap();
    assert!((m.mean - 0.02).abs() < 1e-12, "{m:?}");
    assert_eq!((m.n, t1.diverged, t1.missing), (2, 0, 0));
    assert_eq!(figures(&trials, Configuration::T3).diverged, 1);
    let worst = figures(&trials, Configuration::T4).worst_robot.unwrap();
    assert!((worst.mean - 0.04).abs() < 1e-12 && worst.sd.abs() < 1e-12, "{worst:?}");
}

/// The study's table starts with its header and names the trials, the seed and the map.
#[test]
fn the_study_report_heads_its_table() {
    let rows = [row()];
    let report = StudyReport {
        map: MapSource::True,
        trials: 3,
        confirm_trials: 0,
        seed: 7,
        spacings_m: &SPACINGS_M,
        teams: &TEAMS,
        rows: &rows,
    };
    let md = study_markdown(&report);
    assert!(
        md.starts_with(
            "# amr eval --study occlusion: 3 trials per configuration from seed 7, AMCL's map true\n"
        ),
        "{md}"
    );
    assert!(md.contains(
        "\n| scenario | motion | robots | spacing m | T1 | T2 | T3 | T4 | Δ cm | occluded % | site left % | site % |\n"
    ));
    assert!(md.contains("| s | straight | 2 | 1 | — | — | — | — | — |  |  |  |\n"), "{md}");
    assert!(md.contains("\n1 configurations run, 0 skipped"), "{md}");
}
