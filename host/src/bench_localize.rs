//! `amr bench localize`: AMCL on recorded real logs against their references, per log: tracking from
//! the first reference pose and global localisation, with the odometry alone and (when given) nav2's
//! figures beside them. Reads what `../shared/tools/carmen/regen.sh` writes: `<name>-raw.log`,
//! `<name>_map.yaml` (+ image), `<name>-gt.csv`. Measures; asserts nothing.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use amr_core::amcl::UpdateOutcome;
use amr_core::amcl::log::{LogLocalizer, RefPose, Score, Start, parse_reference, score};
use amr_core::carmen::{Record, parse_line};
use amr_core::config::AmclParams;
use amr_core::se2::Se2;
use anyhow::Context as _;
use serde::Serialize;

/// One way of running a log.
#[derive(Debug, Clone, Serialize)]
pub(crate) struct Run {
    pub score: Score,
    /// Per filter update (motion + sensor + resampling + estimate), milliseconds.
    pub update_median_ms: f64,
    pub update_p95_ms: f64,
    pub updates: usize,
}

#[derive(Debug, Clone, Serialize)]
pub(crate) struct LogReport {
    pub name: String,
    pub scans: usize,
    pub odometry_only: Score,
    /// Tracking from the first reference pose, one run per seed.
    pub tracking: Vec<Run>,
    /// Global localisation (no initial pose), one run per seed.
    pub global: Vec<Run>,
    /// nav2's scores on this log, from `<nav2-dir>/<name>.csv` if given.
    pub nav2: Option<Score>,
}

#[derive(Debug, Clone, Serialize)]
pub(crate) struct Report {
    pub seeds: Vec<u64>,
    pub logs: Vec<LogReport>,
}

/// The log names in `dir`: every `<name>-raw.log` with its map and reference beside it.
fn logs_in(dir: &Path) -> anyhow::Result<Vec<String>> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .with_context(|| format!("cannot list {}", dir.display()))?
        .filter_map(|e| e.ok()?.file_name().into_string().ok())
        .filter_map(|f| f.strip_suffix("-raw.log").map(str::to_owned))
        .filter(|n| dir.join(format!("{n}_map.yaml")).exists() && dir.join(format!("{n}-gt.csv")).exists())
        .collect();
    names.sort();
    anyhow::ensure!(
        !names.is_empty(),
        "{}: no <name>-raw.log with <name>_map.yaml and <name>-gt.csv beside it (see ../shared/tools/carmen)",
        dir.display()
    );
    Ok(names)
}

fn read(path: &Path) -> anyhow::Result<String> {
    std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))
}

/// Parse a pose CSV with `timestamp,x,y,theta` columns (ours, nav2 harness's, score.py's input).
fn read_poses(path: &Path) -> anyhow::Result<Vec<(f64, Se2)>> {
    let text = read(path)?;
    let refs = parse_reference(&text).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
    Ok(refs.into_iter().map(|r| (r.timestamp_s, r.pose)).collect())
}

fn percentile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    sorted[((sorted.len() - 1) as f64 * q).round() as usize]
}

/// One run of the filter over the log.
fn run_once(
    grid: &amr_core::map::OccupancyGrid,
    records: &[Record],
    params: &AmclParams,
    start: Start,
    seed: u64,
    reference: &[RefPose],
) -> Run {
    let mut loc = LogLocalizer::new(grid, params.clone(), start, seed);
    let mut est = Vec::new();
    let mut ms = Vec::new();
    for r in records {
        let t0 = Instant::now();
        let fed = loc.feed(r);
        let dt = t0.elapsed().as_secs_f64() * 1e3;
        if let Some(f) = fed {
            if matches!(f.outcome, UpdateOutcome::Updated { .. }) {
                ms.push(dt);
            }
            if let Some(p) = f.pose {
                est.push((p.timestamp_s, p.pose));
            }
        }
    }
    // The first update builds the field: not an update's cost.
    if !ms.is_empty() {
        ms.remove(0);
    }
    ms.sort_by(f64::total_cmp);
    Run {
        score: score(reference, &est),
        update_median_ms: percentile(&ms, 0.5),
        update_p95_ms: percentile(&ms, 0.95),
        updates: ms.len(),
    }
}

/// The odometry alone, rigidly aligned so that the first scan sits on the first reference pose.
fn odometry_only(records: &[Record], reference: &[RefPose]) -> Score {
    let mut est = Vec::new();
    let mut align: Option<Se2> = None;
    for r in records {
        if let Record::Laser(l) = r
            && let Some(o) = l.odometry
        {
            let a = *align
                .get_or_insert_with(|| reference.first().map_or(Se2::IDENTITY, |g| g.pose * o.inverse()));
            est.push((l.timestamp_s, a * o));
        }
    }
    score(reference, &est)
}

pub(crate) fn run(
    params: &AmclParams,
    dir: &Path,
    only: &[String],
    seeds: &[u64],
    nav2_dir: Option<&Path>,
) -> anyhow::Result<Report> {
    let names = if only.is_empty() { logs_in(dir)? } else { only.to_vec() };
    let mut logs = Vec::new();
    for name in names {
        let grid = crate::localize::read_map(&dir.join(format!("{name}_map.yaml")))?;
        let gt_path = dir.join(format!("{name}-gt.csv"));
        let reference =
            parse_reference(&read(&gt_path)?).map_err(|e| anyhow::anyhow!("{}: {e}", gt_path.display()))?;
        let first =
            reference.first().map(|r| r.pose).with_context(|| format!("{}: empty", gt_path.display()))?;
        let log_path = dir.join(format!("{name}-raw.log"));
        let records: Vec<Record> =
            read(&log_path)?.lines().filter_map(|l| parse_line(l).ok().flatten()).collect();
        let scans = records.iter().filter(|r| matches!(r, Record::Laser(_))).count();
        tracing::info!(log = %name, scans, "localising");
        let tracked = Start::resolve(Some(first), params);
        let tracking =
            seeds.iter().map(|&s| run_once(&grid, &records, params, tracked, s, &reference)).collect();
        let global =
            seeds.iter().map(|&s| run_once(&grid, &records, params, Start::Global, s, &reference)).collect();
        let nav2 = match nav2_dir {
            Some(d) => {
                let p: PathBuf = d.join(format!("{name}.csv"));
                if p.exists() { Some(score(&reference, &read_poses(&p)?)) } else { None }
            }
            None => None,
        };
        logs.push(LogReport {
            name,
            scans,
            odometry_only: odometry_only(&records, &reference),
            tracking,
            global,
            nav2,
        });
    }
    Ok(Report { seeds: seeds.to_vec(), logs })
}

fn cm(s: &Score) -> (f64, f64, f64) {
    s.translation.map_or((f64::NAN, f64::NAN, f64::NAN), |t| (t.rmse * 100.0, t.p95 * 100.0, t.max * 100.0))
}

fn row(out: &mut String, name: &str, what: &str, s: &Score, times: Option<(f64, f64)>) {
    let (rmse, p95, max) = cm(s);
    let t = times.map_or("–".to_owned(), |(m, p)| format!("{m:.2} / {p:.2}"));
    let conv = s.converged_from.map_or("never".to_owned(), |c| c.to_string());
    let _ = writeln!(
        out,
        "| {name} | {what} | {rmse:.1} | {p95:.1} | {max:.1} | {:.2} | {:.1} | {conv} | {t} |",
        s.heading_rmse_deg,
        s.diverged_share * 100.0
    );
}

pub(crate) fn markdown(r: &Report) -> String {
    let mut out = String::new();
    let _ = writeln!(
        out,
        "AMCL on recorded logs against their references (seeds {:?}; one row per seed). Errors in cm; \
         'off' is the share of scans more than 0.5 m off; 'from' is the first scan from which every \
         scan is within 0.5 m; times are per filter update (median / P95, ms).\n",
        r.seeds
    );
    let _ = writeln!(out, "| log | run | RMSE | P95 | max | heading RMSE (°) | off (%) | from | update ms |");
    let _ = writeln!(out, "|---|---|---|---|---|---|---|---|---|");
    for l in &r.logs {
        row(&mut out, &l.name, "odometry alone", &l.odometry_only, None);
        if let Some(n) = &l.nav2 {
            row(&mut out, &l.name, "nav2 (its CSV)", n, None);
        }
        for (s, run) in r.seeds.iter().zip(&l.tracking) {
            row(
                &mut out,
                &l.name,
                &format!("tracking, seed {s}"),
                &run.score,
                Some((run.update_median_ms, run.update_p95_ms)),
            );
        }
        for (s, run) in r.seeds.iter().zip(&l.global) {
            row(
                &mut out,
                &l.name,
                &format!("global, seed {s}"),
                &run.score,
                Some((run.update_median_ms, run.update_p95_ms)),
            );
        }
    }
    out
}
