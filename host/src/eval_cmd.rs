//! `amr eval`: the paper's experiments in simulation, T1–T4 side by side, written to
//! `out/eval/<scenario>/` as Markdown and JSON.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use amr_core::config::Config;
use amr_core::metrics::AxisStats;
use anyhow::Context as _;
use hil_mocks::eval::{ConfigSummary, Setup, Trial, run_trial, summarise};
use hil_mocks::world::{Noise, RobotSpec, paper_site};
use serde::Serialize;

#[derive(Debug, Serialize)]
struct Report<'a> {
    scenario: &'a str,
    trials: usize,
    seed: u64,
    scans_per_trial: Vec<usize>,
    summary: &'a [ConfigSummary],
}

pub(crate) fn setup(config: &Config, scenario: &str) -> anyhow::Result<Setup> {
    let sc = config.scenarios.get(scenario).with_context(|| {
        format!("no scenario `{scenario}` (have: {:?})", config.scenarios.keys().collect::<Vec<_>>())
    })?;
    anyhow::ensure!(
        sc.map == "paper-site",
        "the simulated world knows the paper's site only, not map `{}`",
        sc.map
    );
    let robot = config.robots.first().context("the configuration has no robot")?;
    Ok(Setup {
        site: paper_site()?,
        map: config.maps.get(&sc.map).with_context(|| format!("no map `{}`", sc.map))?.clone(),
        robot: RobotSpec::from_config(robot),
        vamr: config.vamr.clone(),
        amcl: config.amcl.clone(),
        noise: Noise::TYPICAL,
        scenario: sc.clone(),
        physics_dt_s: 1.0 / 150.0,
        steps_per_scan: 10,
    })
}

fn table(
    out: &mut String,
    title: &str,
    pick: fn(&ConfigSummary) -> Option<AxisStats>,
    summary: &[ConfigSummary],
) {
    let _ = writeln!(out, "\n### {title}\n");
    let _ = writeln!(out, "| config | axis | MAE | RMSE | median | P95 | max | n |");
    let _ = writeln!(out, "|---|---|---|---|---|---|---|---|");
    for s in summary {
        if let Some(a) = pick(s) {
            for (axis, e) in [("X", a.x), ("Y", a.y), ("2D", a.d2)] {
                let _ = writeln!(
                    out,
                    "| {} | {axis} | {:.4} | {:.4} | {:.4} | {:.4} | {:.4} | {} |",
                    s.configuration, e.mae, e.rmse, e.median, e.p95, e.max, e.count
                );
            }
        }
    }
}

fn markdown(report: &Report<'_>) -> String {
    let mut out = format!(
        "# amr eval: {} ({} trials, seed {})\n\nSimulated: the paper's site, TiM551 model with {} m range noise, wheel slip and gyro bias \
         (hil_mocks::world::Noise::TYPICAL). Errors are of the virtual robot V's position in metres.\n",
        report.scenario,
        report.trials,
        report.seed,
        Noise::TYPICAL.range_sigma_m
    );
    let _ = writeln!(out, "\n## Trial-level 2D RMSE against the true pose (Tables 15–16 layout)\n");
    let _ =
        writeln!(out, "| config | ours: mean ± SD (m) | paper: mean ± SD (m) | scans without an estimate |");
    let _ = writeln!(out, "|---|---|---|---|");
    for s in report.summary {
        let ours = s.trial_rmse_2d.map_or("—".into(), |m| format!("{:.4} ± {:.4}", m.mean, m.sd));
        let paper = s.paper_rmse_2d.map_or("—".into(), |(m, sd)| format!("{m:.4} ± {sd:.4}"));
        let _ = writeln!(out, "| {} | {ours} | {paper} | {} |", s.configuration, s.missing);
    }
    let _ = writeln!(
        out,
        "\nThe paper's figures are against its own reference (planned path + encoders) on real robots; ours are against the simulator's truth."
    );
    let _ = writeln!(out, "\n## Pooled statistics (Tables 8, 13–14 layout)");
    table(&mut out, "Against the true pose", |s| s.pooled_truth, report.summary);
    table(
        &mut out,
        "Against the paper-style reference (odometry: planned path + encoders)",
        |s| s.pooled_reference,
        report.summary,
    );
    out
}

pub(crate) fn run(
    config: &Config,
    scenario: &str,
    trials: usize,
    seed: u64,
    out_dir: &Path,
) -> anyhow::Result<PathBuf> {
    let setup = setup(config, scenario)?;
    let mut results: Vec<Trial> = Vec::with_capacity(trials);
    for k in 0..trials {
        let trial_seed = seed.wrapping_add(k as u64);
        tracing::info!(scenario, trial = k + 1, of = trials, seed = trial_seed, "running trial");
        results.push(run_trial(&setup, trial_seed));
    }
    let summary = summarise(scenario, &results);
    let report = Report {
        scenario,
        trials,
        seed,
        scans_per_trial: results.iter().map(|t| t.scans).collect(),
        summary: &summary,
    };
    let dir = out_dir.join(scenario);
    std::fs::create_dir_all(&dir).with_context(|| format!("cannot create {}", dir.display()))?;
    std::fs::write(dir.join("report.json"), serde_json::to_string_pretty(&report)? + "\n")?;
    std::fs::write(dir.join("trials.json"), serde_json::to_string(&results)? + "\n")?;
    let md = markdown(&report);
    std::fs::write(dir.join("report.md"), &md)?;
    Ok(dir)
}
