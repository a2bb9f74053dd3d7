//! `amr eval`: the paper's experiments in simulation, T1–T4 side by side, written to
//! `out/eval/<scenario>/` as Markdown and JSON.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use amr_actors::config::Config;
use amr_core::metrics::{AxisStats, MeanSd};
use amr_sim::eval::{
    ConfigSummary, EvalMap, Setup, Surveys, Trial, TrialFrame, run_trial, run_trial_observed, summarise,
};
use anyhow::Context as _;
use hil_mocks::world::Noise;
use serde::Serialize;

#[derive(Debug, Serialize)]
struct Report<'a> {
    scenario: &'a str,
    /// AMCL's map: `surveyed` or `true`.
    map: MapSource,
    /// What the world ray-casts: `the paper's site` or the map's path.
    site: &'a str,
    robots: usize,
    trials: usize,
    seed: u64,
    scans_per_trial: Vec<usize>,
    summary: &'a [ConfigSummary],
}

/// A progress bar on stderr when it is a terminal (hidden otherwise, so logs and CI stay clean).
pub fn progress(len: u64, what: &str) -> indicatif::ProgressBar {
    let bar = if std::io::IsTerminal::is_terminal(&std::io::stderr()) {
        indicatif::ProgressBar::new(len)
    } else {
        indicatif::ProgressBar::hidden()
    };
    if let Ok(style) =
        indicatif::ProgressStyle::with_template("{msg} [{bar:30}] {pos}/{len} ({elapsed}, about {eta} left)")
    {
        bar.set_style(style.progress_chars("=> "));
    }
    bar.set_message(what.to_owned());
    bar
}

/// AMCL's map in an evaluation (`--map`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum MapSource {
    /// A simulated survey of the site, as SLAM builds maps (the localiser never sees the world
    /// it is simulated in).
    Surveyed,
    /// The site's own map (the paper's site: the rendering of the polygons the world ray-casts).
    True,
}

/// What an evaluation runs: a scenario with AMCL's map, the formation's size, and `trials` trials,
/// trial k with seed `seed + k`. `amr eval`, its error budget and its sweeps take one.
#[derive(Debug, Clone, Copy)]
pub struct Plan<'a> {
    pub config: &'a Config,
    /// A scenario of the configuration, or a scenario file's path.
    pub scenario: &'a str,
    pub map: MapSource,
    /// Robots in the formation.
    pub robots: usize,
    pub trials: usize,
    /// Seed of the first trial.
    pub seed: u64,
}

/// What the world ray-casts, in words.
fn site_words(chosen: &amr_actors::config::ChosenScenario) -> String {
    if chosen.map_name == "paper-site" {
        "the paper's site".into()
    } else {
        format!("the map {}", chosen.map_name)
    }
}

pub fn setup(
    config: &Config,
    chosen: &amr_actors::config::ChosenScenario,
    robots: usize,
    map: MapSource,
) -> anyhow::Result<Setup> {
    let sc = &chosen.scenario;
    let robot = config.robots.first().context("the configuration has no robot")?;
    anyhow::ensure!(robots >= 2, "a formation needs at least 2 robots, not {robots}");
    let site = amr_sim::site_for(&chosen.map_name, &chosen.map)?;
    let formation: Vec<_> = std::iter::repeat_n(robot.clone(), robots).collect();
    amr_sim::check_formation(&site, sc, &formation).with_context(|| format!("scenario {}", chosen.name))?;
    let map = match map {
        MapSource::True => EvalMap::Given(chosen.map.clone()),
        MapSource::Surveyed => EvalMap::Surveyed(Surveys::new(
            site.clone(),
            chosen.map.clone(),
            amr_sim::survey::SurveyOptions::TYPICAL,
        )),
    };
    Ok(Setup {
        site,
        map,
        robot: amr_sim::robot_spec(robot),
        vamr: config.vamr.clone(),
        amcl: config.amcl.clone(),
        noise: Noise::TYPICAL,
        scenario: sc.clone(),
        physics_dt_s: 1.0 / 150.0,
        steps_per_scan: 10,
        oracle: amr_core::vamr::pipeline::Oracle::default(),
        robots,
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
        "# amr eval: {} ({} robots, {} trials, seed {})\n\nSimulated: {}, TiM551 model with {} m range noise, wheel slip and gyro bias \
         (hil_mocks::world::Noise::TYPICAL). AMCL's map: {}. Errors are of the virtual robot V's position in metres.\n",
        report.scenario,
        report.robots,
        report.trials,
        report.seed,
        report.site,
        Noise::TYPICAL.range_sigma_m,
        match report.map {
            MapSource::Surveyed => {
                "surveyed (each trial its own simulated SLAM-style survey of the site, its grid at a random sub-cell offset: amr_sim::survey)"
            }
            MapSource::True => "the site's own map",
        }
    );
    let _ = writeln!(out, "\n## Trial-level 2D RMSE against the true pose (Tables 15–16 layout)\n");
    let _ = writeln!(
        out,
        "| config | ours: mean ± SD (m) | paper: mean ± SD (m) | scans without an estimate | estimates not verified |"
    );
    let _ = writeln!(out, "|---|---|---|---|---|");
    for s in report.summary {
        let ours = s.trial_rmse_2d.map_or("—".into(), |m| format!("{:.4} ± {:.4}", m.mean, m.sd));
        let paper = s.paper_rmse_2d.map_or("—".into(), |(m, sd)| format!("{m:.4} ± {sd:.4}"));
        let _ =
            writeln!(out, "| {} | {ours} | {paper} | {} | {} |", s.configuration, s.missing, s.unverified);
    }
    let _ = writeln!(
        out,
        "\nThe paper's figures are against its own reference (planned path + encoders) on real robots; ours are against the simulator's truth."
    );
    let _ = writeln!(
        out,
        "\n## Each robot's own position\n\nV's error is the mean of the robots' errors (errors of opposite sign cancel in it; a robot whose \
         own estimate drifts counts 1/N). Here, where each configuration placed each robot, against that robot's true position: \
         trial-level 2D RMSE (m), mean ± SD over trials, and per trial the worst robot's.\n"
    );
    let n = report.summary.iter().map(|s| s.robot_rmse_2d.len()).max().unwrap_or(0);
    let _ = writeln!(
        out,
        "| config | {} | worst robot |\n|---|{}---|",
        (0..n).map(|i| format!("robot {i}")).collect::<Vec<_>>().join(" | "),
        "---|".repeat(n)
    );
    let ms = |m: &Option<MeanSd>| m.map_or("—".into(), |m| format!("{:.4} ± {:.4}", m.mean, m.sd));
    for s in report.summary {
        let cells: Vec<String> = s.robot_rmse_2d.iter().map(ms).collect();
        let _ =
            writeln!(out, "| {} | {} | {} |", s.configuration, cells.join(" | "), ms(&s.worst_robot_rmse_2d));
    }
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

/// Where `amr eval` writes: the report directory, and optionally a recording and a live view (the
/// hub of a Foxglove server that runs while the trials do).
#[derive(Debug, Clone)]
pub struct Outputs<'a> {
    pub dir: &'a Path,
    pub record: Option<&'a Path>,
    pub live: Option<amr_record::Hub>,
}

/// T1–T4 side by side on `plan`'s trials: `report.md`, `report.json`, `trials.json` and the first
/// trial's plots in the scenario's directory under `outputs.dir`, which it returns.
pub fn run(plan: &Plan<'_>, outputs: Outputs<'_>) -> anyhow::Result<PathBuf> {
    let Plan { config, scenario, map, robots, trials, seed } = *plan;
    let Outputs { dir: out_dir, record, live: hub } = outputs;
    let chosen = config.scenario(scenario)?;
    let setup = setup(config, &chosen, robots, map)?;
    let site = site_words(&chosen);
    // A scenario file's stem names its output directory and its report.
    let scenario = chosen.stem.as_str();
    let mut results: Vec<Trial> = Vec::with_capacity(trials);
    let bar = progress(trials as u64, &format!("{scenario}: trials"));
    for k in 0..trials {
        let trial_seed = seed.wrapping_add(k as u64);
        tracing::debug!(scenario, trial = k + 1, of = trials, seed = trial_seed, "running trial");
        let trial = match (record, &hub) {
            (None, None) => run_trial(&setup, trial_seed),
            _ => {
                let file =
                    record.map(|p| if trials == 1 { p.to_path_buf() } else { trial_file(p, trial_seed) });
                record_trial(config, &setup, scenario, trial_seed, file.as_deref(), hub.clone())?
            }
        };
        results.push(trial);
        bar.inc(1);
    }
    bar.finish_and_clear();
    let summary = summarise(scenario, &results);
    let report = Report {
        scenario,
        map,
        site: &site,
        robots,
        trials,
        seed,
        scans_per_trial: results.iter().map(|t| t.scans).collect(),
        summary: &summary,
    };
    let dir = if robots == 2 {
        out_dir.join(scenario)
    } else {
        out_dir.join(format!("{scenario}-{robots}-robots"))
    };
    std::fs::create_dir_all(&dir).with_context(|| format!("cannot create {}", dir.display()))?;
    std::fs::write(dir.join("report.json"), serde_json::to_string_pretty(&report)? + "\n")?;
    std::fs::write(dir.join("trials.json"), serde_json::to_string(&results)? + "\n")?;
    let mut md = markdown(&report);
    if let Some(first) = results.first() {
        let written = crate::plots::write_all(&dir, first, &setup.site.outlines())?;
        md += &format!(
            "\n## Plots (trial 1)\n\n{}\n",
            written
                .iter()
                .filter_map(|p| p.file_name())
                .map(|n| format!("- {}", n.to_string_lossy()))
                .collect::<Vec<_>>()
                .join("\n")
        );
    }
    std::fs::write(dir.join("report.md"), &md)?;
    Ok(dir)
}

/// Which parameter a sensitivity study varies (paper Tables 6–7).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Sweep {
    /// ε_d, the correspondence distance gate (Table 6).
    Eps,
    /// Δθ, the angular increment (Table 7).
    Step,
}

#[derive(Debug, Serialize)]
struct SweepRow {
    setting: String,
    /// T4 updates whose heading search failed, percent.
    failure_rate_pct: f64,
    /// T4 trial-level 2D RMSE against the truth, cm (mean over trials).
    rmse_2d_cm: f64,
    /// RMSE of T4's relative heading, degrees.
    heading_rmse_deg: f64,
    /// Mean wall-clock time of one T4 pipeline update (includes the heading search), ms.
    pipeline_ms: f64,
    /// The paper's row (failure %, 2D RMSE cm, heading RMSE °, KD-tree + refined search ms).
    paper: Option<[f64; 4]>,
}

/// `amr eval --sweep`: the sensitivity studies of Tables 6–7 on one scenario, always with the
/// paper's two robots (`plan.robots` is not used). Returns the Markdown report's path.
pub fn sweep(plan: &Plan<'_>, which: Sweep, out_dir: &Path) -> anyhow::Result<PathBuf> {
    let Plan { config, scenario, map, trials, seed, .. } = *plan;
    let chosen = config.scenario(scenario)?;
    let base = setup(config, &chosen, 2, map)?;
    let scenario = chosen.stem.as_str();
    let (label, settings, paper) = sweep_settings(which);
    let mut rows = Vec::new();
    for (value, paper_row) in settings.iter().zip(paper) {
        let mut s = base.clone();
        match which {
            Sweep::Eps => {
                s.vamr.heading.distance_gate_m =
                    amr_core::config::value::Positive::new(value / 1000.0).map_err(anyhow::Error::msg)?
            }
            Sweep::Step => {
                s.vamr.heading.step_deg =
                    amr_core::config::value::Positive::new(*value).map_err(anyhow::Error::msg)?
            }
        }
        let bar = progress(trials as u64, &format!("{label} = {value}"));
        let results: Vec<Trial> = (0..trials)
            .map(|k| {
                let t = run_trial(&s, seed.wrapping_add(k as u64));
                bar.inc(1);
                t
            })
            .collect();
        bar.finish_and_clear();
        rows.push(sweep_row(*value, &results, paper_row));
    }
    let name = match which {
        Sweep::Eps => "sweep-eps",
        Sweep::Step => "sweep-step",
    };
    let md = sweep_markdown(label, scenario, trials, seed, &rows);
    let dir = out_dir.join(scenario);
    std::fs::create_dir_all(&dir).with_context(|| format!("cannot create {}", dir.display()))?;
    std::fs::write(dir.join(format!("{name}.json")), serde_json::to_string_pretty(&rows)? + "\n")?;
    std::fs::write(dir.join(format!("{name}.md")), &md)?;
    Ok(dir.join(format!("{name}.md")))
}

/// The settings a sweep runs, its label, and the paper's figures at each (Table 6: ε_d in mm;
/// Table 7: Δθ in degrees): failure %, 2D RMSE cm, heading RMSE °, search ms.
fn sweep_settings(which: Sweep) -> (&'static str, Vec<f64>, Vec<[f64; 4]>) {
    match which {
        // Table 6 (ε_d in mm) and Table 7 (Δθ in degrees) of the paper.
        Sweep::Eps => (
            "ε_d (mm)",
            vec![1.0, 2.0, 3.0, 4.0, 5.0, 7.0],
            vec![
                [11.7, 5.2, 0.38, 141.0],
                [5.0, 4.1, 0.24, 144.0],
                [2.0, 3.5, 0.16, 150.0],
                [2.8, 3.7, 0.18, 171.0],
                [4.7, 4.2, 0.24, 184.0],
                [8.3, 5.0, 0.34, 205.0],
            ],
        ),
        Sweep::Step => (
            "Δθ (°)",
            vec![0.05, 0.1, 0.2, 0.5, 1.0],
            vec![
                [1.5, 3.4, 0.12, 310.0],
                [2.0, 3.5, 0.16, 150.0],
                [3.3, 3.8, 0.23, 90.0],
                [7.5, 4.6, 0.43, 48.0],
                [15.0, 5.8, 0.79, 32.0],
            ],
        ),
    }
}

/// T4's figures over one setting's trials.
fn sweep_row(value: f64, results: &[Trial], paper_row: [f64; 4]) -> SweepRow {
    let t4: Vec<&amr_sim::eval::Series> = results
        .iter()
        .filter_map(|t| {
            t.series.iter().find(|(c, _)| *c == amr_core::config::Configuration::T4).map(|(_, x)| x)
        })
        .collect();
    let updates: usize = t4.iter().map(|x| x.updates).sum();
    let failures: usize = t4.iter().map(|x| x.heading_failures).sum();
    let heading: Vec<f64> = t4.iter().flat_map(|x| x.heading_errors_rad.iter().copied()).collect();
    let per_trial: Vec<f64> = t4.iter().filter_map(|x| AxisStats::of(&x.truth).map(|a| a.d2.rmse)).collect();
    SweepRow {
        setting: format!("{value}"),
        failure_rate_pct: 100.0 * failures as f64 / updates.max(1) as f64,
        rmse_2d_cm: 100.0 * amr_core::metrics::MeanSd::of(&per_trial).map_or(f64::NAN, |m| m.mean),
        heading_rmse_deg: amr_core::metrics::ErrorStats::of(&heading)
            .map_or(f64::NAN, |e| e.rmse.to_degrees()),
        pipeline_ms: 1000.0 * t4.iter().map(|x| x.pipeline_s).sum::<f64>() / updates.max(1) as f64,
        paper: Some(paper_row),
    }
}

/// A sweep's table, ours beside the paper's.
fn sweep_markdown(label: &str, scenario: &str, trials: usize, seed: u64, rows: &[SweepRow]) -> String {
    let mut md = format!(
        "# amr eval --sweep: {label}, scenario {scenario}, {trials} trials from seed {seed}\n\nT4 (the complete method). Ours in simulation against the truth; the paper's on its robots (Tables 6–7). \
         Our time is the whole T4 pipeline update on this machine; the paper's is its KD-tree + refined search on a Pentium G4400.\n\n\
         | {label} | failure % | 2D RMSE cm | heading RMSE ° | pipeline ms | paper: failure % | 2D RMSE cm | heading RMSE ° | search ms |\n|---|---|---|---|---|---|---|---|---|\n"
    );
    for r in rows {
        let p = r.paper.unwrap_or([f64::NAN; 4]);
        let _ = writeln!(
            md,
            "| {} | {:.1} | {:.2} | {:.3} | {:.3} | {} | {} | {} | {} |",
            r.setting,
            r.failure_rate_pct,
            r.rmse_2d_cm,
            r.heading_rmse_deg,
            r.pipeline_ms,
            p[0],
            p[1],
            p[2],
            p[3]
        );
    }
    md
}

/// `--record FILE` with several trials: one file per trial, `FILE-<seed>.mcap`.
fn trial_file(path: &Path, seed: u64) -> PathBuf {
    let stem = path.file_stem().map_or_else(|| "eval".into(), |s| s.to_string_lossy().into_owned());
    path.with_file_name(format!("{stem}-{seed}.mcap"))
}

/// One trial, recorded as MCAP: each robot's scans and odometry, the true poses, and T1–T4's
/// estimates of V side by side (`/eval/<T>/V`), on simulated time.
fn record_trial(
    config: &Config,
    setup: &Setup,
    scenario: &str,
    seed: u64,
    file: Option<&Path>,
    live: Option<amr_record::Hub>,
) -> anyhow::Result<Trial> {
    use amr_msgs::OdomMsg;
    use amr_record::encode::Event;

    let names: Vec<String> = (0..setup.robots)
        .map(|i| {
            config.server.robots.get(i).map_or_else(|| format!("robot{i}"), |m| m.id.as_str().to_owned())
        })
        .collect();
    let mut meta = std::collections::BTreeMap::new();
    meta.insert("command".to_owned(), std::env::args().collect::<Vec<_>>().join(" "));
    meta.insert("scenario".to_owned(), scenario.to_owned());
    meta.insert("seed".to_owned(), seed.to_string());
    meta.insert("robots".to_owned(), names.join(","));
    let shown = file.map_or_else(|| "the live view".to_owned(), |f| f.display().to_string());
    let mut rec = amr_record::FileRecorder::to(file, live, names.clone(), meta)
        .with_context(|| format!("creating {shown}"))?;
    rec.put(0.0, &Event::Map(setup.map.for_trial(seed).into_owned()))?;
    let mount = setup.robot.lidar_mount;
    rec.put(0.0, &Event::Mounts(names.iter().map(|n| (n.clone(), mount)).collect()))?;
    let mut failed: Option<amr_record::RecordError> = None;
    let mut seq = 0u64;
    let trial = run_trial_observed(setup, seed, &mut |f: &TrialFrame<'_>| {
        if failed.is_some() {
            return;
        }
        seq += 1;
        let t = f.t_s;
        let mut events = Vec::new();
        for (i, name) in names.iter().enumerate() {
            if let Some(scan) = f.scans.get(i) {
                events.push(Event::Scan(amr_msgs::ScanMsg {
                    robot: name.clone(),
                    seq,
                    stamp_s: t,
                    received_s: t,
                    scan: std::sync::Arc::clone(scan),
                    odom: None,
                    odom_frame: 0,
                }));
            }
            if let Some(pose) = f.odom.get(i) {
                let o = OdomMsg { seq, frame: 1, stamp_s: t, pose: *pose, twist: (0.0, 0.0), gyro: false };
                events.push(Event::Odom(name.clone(), o));
            }
        }
        events.push(Event::Truth { stamp_s: t, v: amr_sim::eval::v_of(f.truth), robots: f.truth.to_vec() });
        for (c, est) in f.estimates {
            if let Some(v) = est {
                events.push(Event::EvalEstimate { stamp_s: t, configuration: *c, v: *v });
            }
        }
        for (c, points) in f.virtual_scans {
            if let Some(points) = points {
                events.push(Event::EvalVirtualScan {
                    stamp_s: t,
                    configuration: *c,
                    points: points.to_vec(),
                });
            }
        }
        // The complete method's particle cloud (the encoder keeps one a second).
        if let Some((c, filter)) = f.filters.iter().find(|(c, _)| *c == amr_core::config::Configuration::T4) {
            let poses: Vec<amr_core::se2::Se2> = filter.particles().iter().map(|p| p.pose).collect();
            events.push(Event::Particles(amr_msgs::ParticleCloud {
                source: amr_msgs::EstimateSource::Fused(*c),
                stamp_s: t,
                poses: std::sync::Arc::new(poses),
            }));
        }
        for e in &events {
            if let Err(err) = rec.put(t, e) {
                failed = Some(err);
                return;
            }
        }
    });
    if let Some(e) = failed {
        return Err(e).with_context(|| format!("recording to {shown}"));
    }
    let stats = rec.finish()?;
    if file.is_some() {
        tracing::info!(file = %shown, messages = stats.messages, "trial recorded");
    }
    Ok(trial)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// With several trials, each is recorded beside the file named, with its seed.
    #[test]
    fn each_trial_records_to_its_own_file() {
        assert_eq!(trial_file(Path::new("out/run.mcap"), 7), Path::new("out/run-7.mcap"));
        assert_eq!(trial_file(Path::new("run"), 12), Path::new("run-12.mcap"));
    }

    /// A pooled table: its title, its header, and nothing for a configuration without figures.
    #[test]
    fn a_pooled_table_heads_its_columns() {
        let mut out = String::new();
        table(&mut out, "Against the true pose", |s| s.pooled_truth, &[]);
        assert_eq!(
            out,
            "\n### Against the true pose\n\n| config | axis | MAE | RMSE | median | P95 | max | n |\n|---|---|---|---|---|---|---|---|\n"
        );
    }
}
