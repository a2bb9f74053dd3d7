//! `amr eval --budget` and `amr eval --study occlusion`: where the Virtual-AMR
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

use crate::eval::{MapSource, Plan, progress, setup};

mod report;
#[cfg(test)]
mod tests;

use report::{study_markdown, study_plots};

/// Trials `seed, seed + 1, …` of `setup`, on every core (each trial is deterministic in its seed,
/// so the result does not depend on the number of threads).
pub fn run_trials(setup: &Setup, seed: u64, trials: usize, what: &str) -> Vec<Trial> {
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
#[derive(Debug, Clone, Serialize)]
pub struct Figures {
    /// Trial-level 2D RMSE against the truth, m: mean and SD over trials.
    pub rmse: Option<MeanSd>,
    /// Per trial, in trial order, its 2D RMSE against the truth, m (none if the trial gave no
    /// estimate): what a comparison of two configurations on the same trials pairs.
    pub trial_rmse: Vec<Option<f64>>,
    /// Trials whose error exceeded [`DIVERGED_M`] at any scan, or that never gave an estimate.
    pub diverged: usize,
    /// Scans without an estimate, over all trials.
    pub missing: usize,
    /// Per trial, the worst-placed robot's own 2D RMSE (where the configuration placed it), m:
    /// mean and SD over trials.
    pub worst_robot: Option<MeanSd>,
}

/// A trial whose estimate strays this far from the truth has diverged, m.
pub const DIVERGED_M: f64 = 0.5;

pub fn figures(trials: &[Trial], c: Configuration) -> Figures {
    let series: Vec<&amr_sim::eval::Series> =
        trials.iter().filter_map(|t| t.series.iter().find(|(k, _)| *k == c).map(|(_, s)| s)).collect();
    let trial_rmse: Vec<Option<f64>> =
        series.iter().map(|s| AxisStats::of(&s.truth).map(|a| a.d2.rmse)).collect();
    let per_trial: Vec<f64> = trial_rmse.iter().flatten().copied().collect();
    let diverged = series
        .iter()
        .filter(|s| s.truth.is_empty() || s.truth.iter().any(|e| e.e_x.hypot(e.e_y) > DIVERGED_M))
        .count();
    let worst: Vec<f64> = series
        .iter()
        .filter_map(|s| s.robots.iter().filter_map(|e| AxisStats::of(e).map(|a| a.d2.rmse)).reduce(f64::max))
        .collect();
    Figures {
        rmse: MeanSd::of(&per_trial),
        trial_rmse,
        diverged,
        missing: series.iter().map(|s| s.missing).sum(),
        worst_robot: MeanSd::of(&worst),
    }
}

/// Per trial `a − b` in cm over the trials where both gave an estimate (none if the two are of
/// different trials, or no trial has both).
fn paired_difference_cm(a: &[Option<f64>], b: &[Option<f64>]) -> Option<MeanSd> {
    if a.len() != b.len() {
        return None;
    }
    let d: Vec<f64> =
        a.iter().zip(b).filter_map(|(x, y)| Some(100.0 * (x.as_ref()? - y.as_ref()?))).collect();
    MeanSd::of(&d)
}

/// A paired difference as `+0.55 ± 0.12`: its mean and the standard error of that mean.
fn with_se(d: &MeanSd) -> String {
    format!("{:+.2} ± {:.2}", d.mean, standard_error(d))
}

fn standard_error(d: &MeanSd) -> f64 {
    d.sd / (d.n.max(1) as f64).sqrt()
}

/// The never-worse criterion (T4 ≤ min(T1, T2, T3) + 0.5 cm: the complete method localises at most
/// the margin worse than the best of the configurations it builds on) as the study judges it:
/// missed when the mean difference is above the margin, and missed beyond the trials' noise when it
/// is above it by more than two standard errors of the paired differences.
fn over_margin(d: &MeanSd) -> (bool, bool) {
    (d.mean > MARGIN_CM, d.mean - 2.0 * standard_error(d) > MARGIN_CM)
}

/// The never-worse criterion's margin: how much worse than the best of T1–T3 T4 may be, cm.
const MARGIN_CM: f64 = 0.5;

/// Whether the trials leave the criterion open: the margin lies within two standard errors of the
/// paired difference's mean, so these trials can say neither that T4 holds it nor that it misses
/// it. (One trial has no spread to judge by: never open.)
fn verdict_open(d: &MeanSd) -> bool {
    let se = standard_error(d);
    d.n > 1 && d.mean - 2.0 * se <= MARGIN_CM && d.mean + 2.0 * se > MARGIN_CM
}

/// T1–T4 of one configuration on `trials` trials from `seed` (`run(first seed, count)`), and on
/// `confirm` in all (the same first ones and the next) when those leave the criterion open: the
/// trials' spread, not the configurations', decided it. Sets the row's figures and trial count.
fn run_row(
    row: &mut StudyRow,
    trials: usize,
    confirm: usize,
    seed: u64,
    run: &mut dyn FnMut(u64, usize) -> Vec<Trial>,
) -> Vec<Trial> {
    let mut results = run(seed, trials);
    row.figures = CONFIGS.iter().map(|k| (*k, figures(&results, *k))).collect();
    if confirm > trials && row.t4_over_best_paired_cm().is_some_and(|d| verdict_open(&d)) {
        results.extend(run(seed.wrapping_add(trials as u64), confirm - trials));
        row.figures = CONFIGS.iter().map(|k| (*k, figures(&results, *k))).collect();
    }
    row.trials = results.len();
    results
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
/// Returns the Markdown report's path.
pub fn budget(plan: &Plan<'_>, out_dir: &Path) -> anyhow::Result<PathBuf> {
    let Plan { config, scenario, map, robots, trials, seed } = *plan;
    let chosen = config.scenario(scenario)?;
    let base = setup(config, &chosen, robots, map)?;
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

/// The occlusion study's scenarios by default: the paper's site, the one-sided hall, the
/// corridor and the hall with its racks behind the formation (`config/maps/README.md`), straight
/// and turning where the site allows.
pub const STUDY_SCENARIOS: [&str; 6] =
    ["straight", "turning", "hall-straight", "hall-turning", "corridor", "short-racks"];
/// Centre-to-centre spacing between neighbours, m.
pub const SPACINGS_M: [f64; 4] = [0.5, 1.0, 1.5, 2.0];
/// Team sizes.
pub const TEAMS: [usize; 3] = [2, 3, 4];
/// Laps of a looping scenario in the study (the paper's turning runs 30).
const STUDY_LAPS: i64 = 2;

const CONFIGS: [Configuration; 4] =
    [Configuration::T1, Configuration::T2, Configuration::T3, Configuration::T4];

/// One configuration of the study: a scenario, a team and a spacing.
#[derive(Debug, Serialize)]
struct StudyRow {
    scenario: String,
    site: String,
    motion: &'static str,
    robots: usize,
    spacing_m: f64,
    /// Why the configuration was not run (the formation does not fit the site), if it was not.
    skipped: Option<String>,
    /// Trials run: the study's count, or its confirmation count where those left the criterion
    /// open ([`verdict_open`]).
    trials: usize,
    /// T1–T4.
    figures: Vec<(Configuration, Figures)>,
    /// Per robot, mean over trials: share of its beams on other robots' bodies.
    occluded: Vec<f64>,
    /// Per robot: share of the site returns it would have alone that are left.
    site_left: Vec<f64>,
    /// Per robot: share of its beams that return from the site.
    site_share: Vec<f64>,
}

impl StudyRow {
    /// A configuration not yet run.
    fn new(scenario: String, site: String, motion: &'static str, robots: usize, spacing_m: f64) -> Self {
        StudyRow {
            scenario,
            site,
            motion,
            robots,
            spacing_m,
            skipped: None,
            trials: 0,
            figures: Vec::new(),
            occluded: Vec::new(),
            site_left: Vec::new(),
            site_share: Vec::new(),
        }
    }

    /// One of configuration `c`'s figures (`pick`: V's RMSE or the worst robot's), mean, cm.
    fn mean_cm(&self, c: Configuration, pick: fn(&Figures) -> Option<MeanSd>) -> Option<f64> {
        self.figures.iter().find(|(k, _)| *k == c).and_then(|(_, f)| pick(f)).map(|m| 100.0 * m.mean)
    }

    fn rmse_cm(&self, c: Configuration) -> Option<f64> {
        self.mean_cm(c, |f| f.rmse)
    }

    /// T4 − min(T1, T2, T3) of a figure, cm.
    fn t4_over_best(&self, pick: fn(&Figures) -> Option<MeanSd>) -> Option<f64> {
        let best = CONFIGS[..3].iter().filter_map(|c| self.mean_cm(*c, pick)).fold(f64::INFINITY, f64::min);
        Some(self.mean_cm(Configuration::T4, pick)? - best).filter(|d| d.is_finite())
    }

    /// T4 − the best of T1–T3 (the lowest mean RMSE of V), trial by trial on the same trials, cm:
    /// when every trial gave both an estimate, its mean is T4's mean RMSE less the best one's (a
    /// trial without one is left out of the pairs), and its SD is what says whether a difference is
    /// the configurations' or the trials' (the trials share the sensor streams, so the pairs' spread
    /// is well below either column's).
    fn t4_over_best_paired_cm(&self) -> Option<MeanSd> {
        let best = CONFIGS[..3]
            .iter()
            .filter_map(|c| Some((*c, self.rmse_cm(*c)?)))
            .min_by(|a, b| a.1.total_cmp(&b.1))?
            .0;
        let trials =
            |c: Configuration| self.figures.iter().find(|(k, _)| *k == c).map(|(_, f)| &f.trial_rmse);
        paired_difference_cm(trials(Configuration::T4)?, trials(best)?)
    }

    /// T4 − min(T1, T2, T3) of the worst-placed robot's RMSE, cm.
    fn t4_worst_over_best_cm(&self) -> Option<f64> {
        self.t4_over_best(|f| f.worst_robot)
    }

    /// The first cells of the row's line in a table: scenario, motion, robots, spacing.
    fn lead(&self) -> String {
        format!("| {} | {} | {} | {} |", self.scenario, self.motion, self.robots, self.spacing_m)
    }
}

#[derive(Debug, Serialize)]
struct StudyReport<'a> {
    map: MapSource,
    trials: usize,
    /// Trials of a configuration whose first `trials` left the criterion open.
    confirm_trials: usize,
    seed: u64,
    spacings_m: &'a [f64],
    teams: &'a [usize],
    rows: &'a [StudyRow],
}

fn motion(sc: &amr_core::config::ScenarioConfig) -> &'static str {
    if sc.segments.iter().any(|s| s.turn_deg.is_some_and(|t| t.get() != 0.0)) {
        "turning"
    } else {
        "straight"
    }
}

fn pct(v: &[f64]) -> String {
    v.iter().map(|x| format!("{:.0}", 100.0 * x)).collect::<Vec<_>>().join("/")
}

/// What the occlusion study runs: every scenario of `scenarios` with every team of [`TEAMS`] at
/// every spacing of [`SPACINGS_M`], `trials` trials each from `seed`, and `confirm_trials` in all
/// where those leave the never-worse criterion open (0: none).
#[derive(Debug, Clone, Copy)]
pub struct Occlusion<'a> {
    pub config: &'a Config,
    /// Scenarios (names or files); [`STUDY_SCENARIOS`] by default.
    pub scenarios: &'a [String],
    pub map: MapSource,
    pub trials: usize,
    pub confirm_trials: usize,
    pub seed: u64,
}

/// `amr eval --study occlusion`: T1–T4 over robot spacing, team size and sites. Returns the
/// Markdown report's path.
pub fn occlusion(plan: &Occlusion<'_>, out_dir: &Path) -> anyhow::Result<PathBuf> {
    let Occlusion { config, scenarios, map, trials, confirm_trials, seed } = *plan;
    let mut rows = Vec::new();
    for name in scenarios {
        let chosen = config.scenario(name)?;
        let site =
            if chosen.map_name == "paper-site" { "paper site".to_owned() } else { chosen.map_name.clone() };
        let mut surveys = None;
        for robots in TEAMS {
            for spacing in SPACINGS_M {
                let mut c = chosen.clone();
                c.scenario.spacing_m =
                    amr_core::config::value::Positive::new(spacing).map_err(anyhow::Error::msg)?;
                if c.scenario.laps.get() > STUDY_LAPS as u32 {
                    c.scenario.laps =
                        amr_core::config::value::Count::new(STUDY_LAPS).map_err(anyhow::Error::msg)?;
                }
                let mut row =
                    StudyRow::new(chosen.stem.clone(), site.clone(), motion(&c.scenario), robots, spacing);
                match setup(config, &c, robots, map) {
                    Err(e) => row.skipped = Some(format!("{e:#}")),
                    Ok(mut s) => {
                        // One site, so one survey per trial seed for all its configurations.
                        match &surveys {
                            Some(m) => s.map = amr_sim::eval::EvalMap::clone(m),
                            None => surveys = Some(s.map.clone()),
                        }
                        let what = format!("{} · {robots} robots · {spacing} m", chosen.stem);
                        let results = run_row(&mut row, trials, confirm_trials, seed, &mut |from, count| {
                            let what =
                                if from == seed { what.clone() } else { format!("{what} · confirming") };
                            run_trials(&s, from, count, &what)
                        });
                        let n = results.len().max(1) as f64;
                        let mean = |f: fn(&amr_sim::eval::View) -> f64| -> Vec<f64> {
                            (0..robots)
                                .map(|i| {
                                    results.iter().filter_map(|t| t.visibility.get(i)).map(f).sum::<f64>() / n
                                })
                                .collect()
                        };
                        row.occluded = mean(|v| v.occluded);
                        row.site_left = mean(|v| v.site_left);
                        row.site_share = mean(|v| v.site);
                    }
                }
                tracing::info!(
                    scenario = %row.scenario,
                    robots,
                    spacing,
                    t1_cm = ?row.rmse_cm(Configuration::T1),
                    t4_cm = ?row.rmse_cm(Configuration::T4),
                    skipped = row.skipped.is_some(),
                    "study configuration done"
                );
                rows.push(row);
            }
        }
    }
    let dir = out_dir.join("study-occlusion");
    std::fs::create_dir_all(&dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let report = StudyReport {
        map,
        trials,
        confirm_trials,
        seed,
        spacings_m: &SPACINGS_M,
        teams: &TEAMS,
        rows: &rows,
    };
    std::fs::write(dir.join("study.json"), serde_json::to_string_pretty(&report)? + "\n")?;
    let mut md = study_markdown(&report);
    study_plots(&dir, scenarios, &rows, &mut md)?;
    std::fs::write(dir.join("study.md"), &md)?;
    Ok(dir.join("study.md"))
}
