//! `amr eval --budget` and `amr eval --study occlusion` (issue 18 §3–§4): where the Virtual-AMR
//! fusion's error comes from, and where fusion wins over each robot localising alone.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use amr_actors::config::Config;
use amr_core::config::Configuration;
use amr_core::metrics::{AxisStats, MeanSd};
use amr_core::vamr::pipeline::Oracle;
use amr_sim::eval::{Setup, Trial, run_trial};
use anyhow::Context as _;
use serde::Serialize;

use crate::eval_cmd::{MapSource, progress, setup};

/// Trials `seed, seed + 1, …` of `setup`, on every core (each trial is deterministic in its seed,
/// so the result does not depend on the number of threads).
pub(crate) fn run_trials(setup: &Setup, seed: u64, trials: usize, what: &str) -> Vec<Trial> {
    let threads =
        std::thread::available_parallelism().map_or(1, std::num::NonZeroUsize::get).min(trials.max(1));
    let bar = progress(trials as u64, what);
    let next = std::sync::atomic::AtomicUsize::new(0);
    let mut done: Vec<(usize, Trial)> = std::thread::scope(|s| {
        let handles: Vec<_> = (0..threads)
            .map(|_| {
                s.spawn(|| {
                    let mut mine = Vec::new();
                    loop {
                        let k = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                        if k >= trials {
                            break mine;
                        }
                        mine.push((k, run_trial(setup, seed.wrapping_add(k as u64))));
                        bar.inc(1);
                    }
                })
            })
            .collect();
        handles.into_iter().flat_map(|h| h.join().unwrap_or_default()).collect()
    });
    bar.finish_and_clear();
    done.sort_by_key(|(k, _)| *k);
    done.into_iter().map(|(_, t)| t).collect()
}

/// One configuration's trial-level figures.
#[derive(Debug, Clone, Copy, Serialize)]
pub(crate) struct Figures {
    /// Trial-level 2D RMSE against the truth, m: mean and SD over trials.
    pub rmse: Option<MeanSd>,
    /// Trials whose error exceeded [`DIVERGED_M`] at any scan, or that never gave an estimate.
    pub diverged: usize,
    /// Scans without an estimate, over all trials.
    pub missing: usize,
}

/// A trial whose estimate strays this far from the truth has diverged, m.
pub(crate) const DIVERGED_M: f64 = 0.5;

pub(crate) fn figures(trials: &[Trial], c: Configuration) -> Figures {
    let series: Vec<&amr_sim::eval::Series> =
        trials.iter().filter_map(|t| t.series.iter().find(|(k, _)| *k == c).map(|(_, s)| s)).collect();
    let per_trial: Vec<f64> =
        series.iter().filter_map(|s| AxisStats::of(&s.truth).map(|a| a.d2.rmse)).collect();
    let diverged = series
        .iter()
        .filter(|s| s.truth.is_empty() || s.truth.iter().any(|e| e.e_x.hypot(e.e_y) > DIVERGED_M))
        .count();
    Figures { rmse: MeanSd::of(&per_trial), diverged, missing: series.iter().map(|s| s.missing).sum() }
}

fn cm(f: &Figures) -> String {
    f.rmse.map_or("—".into(), |m| format!("{:.2} ± {:.2}", 100.0 * m.mean, 100.0 * m.sd))
}

#[derive(Debug, Serialize)]
struct BudgetRow {
    /// What was replaced by the truth.
    replaced: &'static str,
    oracle: Oracle,
    t4: Figures,
}

#[derive(Debug, Serialize)]
struct BudgetReport<'a> {
    scenario: &'a str,
    map: MapSource,
    robots: usize,
    trials: usize,
    seed: u64,
    t1: Figures,
    rows: Vec<BudgetRow>,
}

/// `amr eval --budget`: T4's error with each of its sources replaced by the truth in turn, on the
/// same sensor streams (the world is seeded, so every row sees the same scans).
pub(crate) fn budget(
    config: &Config,
    scenario: &str,
    map: MapSource,
    robots: usize,
    trials: usize,
    seed: u64,
    out_dir: &Path,
) -> anyhow::Result<PathBuf> {
    let chosen = config.scenario(scenario)?;
    let base = setup(config, &chosen, robots, map, seed)?;
    let stem = chosen.stem.as_str();
    let none = Oracle::default();
    let rows: [(&'static str, Oracle); 5] = [
        ("nothing (T4 as it runs)", none),
        ("the tracker's relative position", Oracle { position: true, ..none }),
        ("the heading search's relative heading", Oracle { heading: true, ..none }),
        ("the relative pose (position and heading)", Oracle { position: true, heading: true, ..none }),
        (
            "the relative pose, and V's odometry composed with it",
            Oracle { position: true, heading: true, odometry: true },
        ),
    ];
    let mut out = Vec::new();
    let mut t1 = None;
    for (replaced, oracle) in rows {
        let mut s = base.clone();
        s.oracle = oracle;
        let results = run_trials(&s, seed, trials, replaced);
        if oracle == none {
            t1 = Some(figures(&results, Configuration::T1));
        }
        out.push(BudgetRow { replaced, oracle, t4: figures(&results, Configuration::T4) });
    }
    let report = BudgetReport {
        scenario: stem,
        map,
        robots,
        trials,
        seed,
        t1: t1.context("no baseline row")?,
        rows: out,
    };
    let mut md = format!(
        "# amr eval --budget: {stem}, {robots} robots, {trials} trials from seed {seed}, AMCL's map {}\n\n\
         T4's trial-level 2D RMSE of V against the truth (cm, mean ± SD over trials) with one source of its error \
         replaced by the truth at a time, on the same seeded sensor streams. A row's drop from the first is that \
         source's share; the last row is what remains: AMCL on the virtual scan itself (map, range noise, the \
         robots' own odometry). In this simulation every robot scans at the same instant, so time alignment \
         contributes nothing by construction.\n\n\
         T1 (each robot's own AMCL, V from both): {} cm, {} diverged.\n\n\
         | replaced by the truth | T4 2D RMSE (cm) | diverged (> {DIVERGED_M} m) | scans without an estimate |\n|---|---|---|---|\n",
        match map {
            MapSource::Surveyed => "surveyed",
            MapSource::True => "true",
        },
        cm(&report.t1),
        report.t1.diverged,
    );
    for r in &report.rows {
        let _ = writeln!(md, "| {} | {} | {} | {} |", r.replaced, cm(&r.t4), r.t4.diverged, r.t4.missing);
    }
    let dir = out_dir.join(stem);
    std::fs::create_dir_all(&dir).with_context(|| format!("cannot create {}", dir.display()))?;
    std::fs::write(dir.join("budget.json"), serde_json::to_string_pretty(&report)? + "\n")?;
    std::fs::write(dir.join("budget.md"), &md)?;
    Ok(dir.join("budget.md"))
}
