//! `amr bench localize`: AMCL on recorded real logs against their references, per log: tracking from
//! the first reference pose and global localisation, with the odometry alone and (when given) nav2's
//! figures beside them. Reads Radish CARMEN logs (GitHub acschaefer/ple, data/carmen/) as `<name>-raw.log`,
//! `<name>_map.yaml` (+ image), `<name>-gt.csv`. Measures; asserts nothing.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use amr_core::amcl::integrity::{self, Judged as Banded};
use amr_core::amcl::log::{Kidnap, LogLocalizer, RefPose, Score, Start, parse_reference, score};
use amr_core::amcl::{IntegrityState, UpdateOutcome};
use amr_core::carmen::{Record, parse_line};
use amr_core::config::AmclParams;
use amr_core::se2::Se2;
use anyhow::Context as _;
use serde::Serialize;

mod report;
#[cfg(test)]
mod tests;

pub use report::markdown;

/// One way of running a log.
#[derive(Debug, Clone, Serialize)]
pub struct Run {
    pub score: Score,
    /// Per filter update (motion + sensor + resampling + estimate), milliseconds.
    pub update_median_ms: f64,
    pub update_p95_ms: f64,
    pub updates: usize,
    pub integrity: IntegrityCounts,
    /// With kidnappings written into the log: per kidnapping, the scans (from the kidnapping's on)
    /// until the filter reported `Lost`, and until it was tracking again (reported `Tracking` with
    /// the estimate on, [`PoseError::off`] not); `None`: not before the next kidnapping or the log's end.
    pub kidnaps: Vec<KidnapOutcome>,
}

#[derive(Debug, Clone, Copy, Serialize)]
pub struct KidnapOutcome {
    pub scan: usize,
    pub jump_m: f64,
    pub jump_deg: f64,
    /// Whether the estimate was carried off: off ([`PoseError::off`]) for at least [`DETECT_WITHIN`]
    /// scans in a row, a loss as [`IntegrityCounts`] counts them (a filter can absorb a jump, or
    /// come back from a short excursion by itself).
    pub carried_off: bool,
    /// Off on some scan, but never for [`DETECT_WITHIN`] in a row.
    pub brief: bool,
    /// Scans until the filter no longer reported `Tracking` (`Uncertain` or `Lost`: a server
    /// holds on either).
    pub doubted_after: Option<usize>,
    pub lost_after: Option<usize>,
    pub tracked_after: Option<usize>,
    /// Scans until the estimate was back: on for [`DETECT_WITHIN`] scans in a row after it had
    /// been off, whatever the state reported (what a localiser that reports
    /// no state, nav2's, can be compared on).
    pub back_after: Option<usize>,
}

/// Per laser record: its index, the error against the reference, and the state reported.
type Judged = (usize, Option<PoseError>, IntegrityState);

/// How far an estimate is from the reference pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseError {
    pub m: f64,
    pub rad: f64,
}

/// An estimate this far off in heading is off whatever its position: a kidnapping that turns the
/// odometry can leave the estimate within 0.5 m of the robot facing the wrong way, and a server
/// driving on it drives the wrong way. Degrees.
pub const OFF_HEADING_DEG: f64 = 10.0;

impl PoseError {
    /// More than 0.5 m ([`amr_core::amcl::log::DIVERGED_M`]) or [`OFF_HEADING_DEG`] from the
    /// reference.
    #[must_use]
    pub fn off(&self) -> bool {
        self.m > amr_core::amcl::log::DIVERGED_M || self.rad > OFF_HEADING_DEG.to_radians()
    }
}

fn kidnap_outcomes(judged: &[Judged], kidnaps: &[Kidnap]) -> Vec<KidnapOutcome> {
    kidnaps
        .iter()
        .enumerate()
        .map(|(n, k)| {
            let end = kidnaps.get(n + 1).map_or(usize::MAX, |x| x.scan);
            let window = || judged.iter().filter(|(i, _, _)| *i >= k.scan && *i < end);
            let lost_after =
                window().find(|(_, _, s)| *s == IntegrityState::Lost).map(|(i, _, _)| i - k.scan);
            let doubted_after =
                window().find(|(_, _, s)| *s != IntegrityState::Tracking).map(|(i, _, _)| i - k.scan);
            let tracked_after = window()
                .find(|(i, e, s)| {
                    *s == IntegrityState::Tracking
                        && e.is_some_and(|e| !e.off())
                        && lost_after.is_some_and(|l| *i >= k.scan + l)
                })
                .map(|(i, _, _)| i - k.scan);
            let off: Vec<bool> = window().map(|(_, e, _)| e.is_some_and(|e| e.off())).collect();
            let carried_off = off.windows(DETECT_WITHIN).any(|w| w.iter().all(|o| *o));
            let first_off = off.iter().position(|o| *o);
            let back_after = first_off
                .and_then(|f| {
                    off.windows(DETECT_WITHIN).enumerate().skip(f).find(|(_, w)| w.iter().all(|o| !*o))
                })
                .and_then(|(n, _)| window().nth(n))
                .map(|(i, _, _)| i - k.scan);
            KidnapOutcome {
                carried_off,
                brief: !carried_off && off.iter().any(|o| *o),
                scan: k.scan,
                jump_m: k.jump.translation_norm(),
                jump_deg: k.jump.theta.to_degrees(),
                doubted_after,
                lost_after,
                tracked_after,
                back_after,
            }
        })
        .collect()
}

/// How the integrity states matched the truth over one run. A scan is off when its estimate is
/// more than 0.5 m or [`OFF_HEADING_DEG`] from the reference ([`PoseError::off`]), else on; a
/// loss is a run of at least [`DETECT_WITHIN`] off scans (shorter runs are excursions the filter
/// came back from by itself).
#[derive(Debug, Clone, Default, Serialize)]
pub struct IntegrityCounts {
    /// Scans whose estimate is on.
    pub on: usize,
    /// Times the filter turned `Lost` with its estimate on, and on over the
    /// [`DETECT_WITHIN`] scans before (false alarms: not the hysteresis after a real loss).
    pub false_lost: usize,
    /// Scans on reported `Uncertain`.
    pub uncertain_on: usize,
    /// Scans on reported `Lost`: a server holds on them as on a loss (the hysteresis after a real
    /// loss, and a filter that doubts a right estimate for long, not only the false alarms).
    pub lost_on: usize,
    /// Scans off reported `Tracking`: what a server would drive on.
    pub tracking_off: usize,
    /// Runs of off scans shorter than a loss.
    pub excursions: usize,
    /// Losses, those reported lost within [`DETECT_WITHIN`] scans of their start, and those the
    /// filter came back from (the estimate on again before the log ended).
    pub losses: usize,
    pub detected: usize,
    pub recovered: usize,
    /// Updates that re-seeded particles because the filter was lost.
    pub reseeds: u64,
}

/// A loss counts as detected when the filter reports `Lost` within this many scans of its first
/// off scan; it is also the shortest run of off scans that counts as a loss.
pub const DETECT_WITHIN: usize = 3;

/// The integrity counts of a run: per scan, its error (None: no reference) and the state reported.
pub fn integrity_counts(per_scan: &[(Option<PoseError>, IntegrityState)], reseeds: u64) -> IntegrityCounts {
    let mut c = IntegrityCounts { reseeds, ..IntegrityCounts::default() };
    let scored: Vec<(PoseError, IntegrityState)> =
        per_scan.iter().filter_map(|(e, s)| e.map(|e| (e, *s))).collect();
    let off = |k: usize| scored[k].0.off();
    let mut k = 0;
    while k < scored.len() {
        if !off(k) {
            c.on += 1;
            let s = scored[k].1;
            c.uncertain_on += usize::from(s == IntegrityState::Uncertain);
            c.lost_on += usize::from(s == IntegrityState::Lost);
            let entered = s == IntegrityState::Lost && k > 0 && scored[k - 1].1 != IntegrityState::Lost;
            let settled = k >= DETECT_WITHIN && (k - DETECT_WITHIN..k).all(|j| !off(j));
            c.false_lost += usize::from(entered && settled);
            k += 1;
            continue;
        }
        let start = k;
        while k < scored.len() && off(k) {
            c.tracking_off += usize::from(scored[k].1 == IntegrityState::Tracking);
            k += 1;
        }
        if k - start < DETECT_WITHIN {
            c.excursions += 1;
            continue;
        }
        c.losses += 1;
        let seen = scored[start..start + DETECT_WITHIN].iter().any(|(_, s)| *s == IntegrityState::Lost);
        c.detected += usize::from(seen);
        c.recovered += usize::from(k < scored.len());
    }
    c
}

#[derive(Debug, Clone, Serialize)]
pub struct LogReport {
    pub name: String,
    pub scans: usize,
    pub odometry_only: Score,
    /// Tracking from the first reference pose, one run per seed.
    pub tracking: Vec<Run>,
    /// Global localisation (no initial pose), one run per seed.
    pub global: Vec<Run>,
    /// Tracking with kidnappings written into the log (`--kidnap`), one run per seed.
    pub kidnapped: Vec<Run>,
    /// nav2's scores on this log, from `<nav2-dir>/<name>.csv` if given.
    pub nav2: Option<Score>,
    /// nav2 on the kidnapped logs, per seed, from `<nav2-dir>/<name>-kidnap<every>-s<seed>.csv`
    /// (its estimates on the log `amr tools carmen-kidnap --every <every> --seed <seed>` writes)
    /// where there is one: the kidnappings scored as ours are, nav2 reporting no state.
    pub nav2_kidnapped: Vec<(u64, Vec<KidnapOutcome>)>,
    /// The integrity measure at the reference poses and displaced from them.
    pub separation: Vec<SeparationRow>,
    /// At the reference poses, the endpoints of each range band and the share of them explained.
    pub by_range: Vec<BandRow>,
}

/// One range band's endpoints over a log's scans at the reference poses.
#[derive(Debug, Clone, Serialize)]
pub struct BandRow {
    /// The band, `from–to m`.
    pub band: String,
    pub endpoints: u64,
    /// Share of them the map explains.
    pub explained: f64,
}

/// The endpoints of every scan at the reference poses, by range band.
fn band_rows(at_ref: &[Banded]) -> Vec<BandRow> {
    let bounds: Vec<f64> =
        std::iter::once(0.0).chain(integrity::RANGE_BANDS_M).chain(std::iter::once(f64::INFINITY)).collect();
    (0..integrity::BANDS)
        .map(|b| {
            let n: u64 = at_ref.iter().map(|j| u64::from(j.points[b])).sum();
            let e: u64 = at_ref.iter().map(|j| u64::from(j.explained[b])).sum();
            let band = match (bounds.get(b), bounds.get(b + 1)) {
                (Some(from), Some(to)) if to.is_finite() => format!("{from}–{to} m"),
                (Some(from), _) => format!("{from} m and beyond"),
                _ => String::new(),
            };
            BandRow { band, endpoints: n, explained: if n == 0 { 0.0 } else { e as f64 / n as f64 } }
        })
        .collect()
}

/// The explained share over one log's scans at one displacement from the reference, and how many
/// scans the monitor's thresholds would call uncertain or lost (taking as each range band's level
/// the share of that band's endpoints explained at the references, which the monitor's running
/// means learn, and as each scan's level what its bands explain as [`integrity::Monitor::expected`]
/// weighs them; without the monitor's pull of a little-seen band towards the whole scans' level).
#[derive(Debug, Clone, Serialize)]
pub struct SeparationRow {
    pub displacement: String,
    pub scans: usize,
    pub median: f64,
    pub p5: f64,
    pub p95: f64,
    /// Share of scans below `uncertain_ratio` × level, and below `lost_ratio` × level.
    pub below_uncertain: f64,
    pub below_lost: f64,
}

fn separation_rows(judged: &[Vec<Banded>], params: &AmclParams) -> Vec<SeparationRow> {
    let p = params.integrity;
    let at_ref = judged.first().map_or(&[][..], Vec::as_slice);
    let levels: Vec<f64> = band_rows(at_ref).iter().map(|b| b.explained).collect();
    let level_of = |j: &Banded| {
        let n = f64::from(j.total().max(1));
        let sum: f64 = j.points.iter().zip(&levels).map(|(&c, l)| f64::from(c) * l).sum();
        (sum / n).clamp(p.floor, 1.0)
    };
    let labels = std::iter::once("reference".to_owned()).chain(
        amr_core::amcl::log::DISPLACEMENTS
            .iter()
            .map(|(d, a)| if *a == 0.0 { format!("{d} m") } else { format!("{:.0}°", a.to_degrees()) }),
    );
    labels
        .zip(judged)
        .map(|(displacement, scans)| {
            let ratios: Vec<f64> = scans.iter().filter_map(|j| Some(j.share()? / level_of(j))).collect();
            let mut v: Vec<f64> = scans.iter().filter_map(Banded::share).collect();
            v.sort_by(f64::total_cmp);
            let n = ratios.len().max(1) as f64;
            let below = |r: f64| ratios.iter().filter(|s| **s < r).count() as f64 / n;
            SeparationRow {
                displacement,
                scans: v.len(),
                median: percentile(&v, 0.5),
                p5: percentile(&v, 0.05),
                p95: percentile(&v, 0.95),
                below_uncertain: below(p.uncertain_ratio),
                below_lost: below(p.lost_ratio),
            }
        })
        .collect()
}

#[derive(Debug, Clone, Serialize)]
pub struct Report {
    pub seeds: Vec<u64>,
    pub logs: Vec<LogReport>,
    /// Logs not run, and why.
    pub skipped: Vec<(String, String)>,
}

/// Why a log cannot be tracked on its odometry, if it cannot: the odometry pose changes between
/// fewer than half of its consecutive scans (a log without odometry messages carries one pose
/// for many scans).
fn without_usable_odometry(records: &[Record]) -> Option<String> {
    let odom: Vec<Se2> = records
        .iter()
        .filter_map(|r| match r {
            Record::Laser(l) => l.odometry,
            Record::Odometry { .. } => None,
        })
        .collect();
    let pairs = odom.len().saturating_sub(1);
    let moved = odom.windows(2).filter(|w| w[0] != w[1]).count();
    (pairs == 0 || moved * 2 < pairs).then(|| {
        format!("no usable odometry (the odometry pose changes between {moved} of {pairs} consecutive scans)")
    })
}

/// When the reference's stamps are not distinct (some logs stamp every scan alike, or with 2³²),
/// scans cannot be matched to it by time: if the log has as many scans as the reference has poses,
/// both are re-stamped with the scan's index and matched by their order. Whether it did.
fn by_index(records: &mut [Record], reference: &mut [RefPose]) -> bool {
    let mut stamps: Vec<f64> = reference.iter().map(|r| r.timestamp_s).collect();
    stamps.sort_by(f64::total_cmp);
    let distinct = stamps.windows(2).all(|w| w[1] - w[0] > 2.0 * amr_core::amcl::log::MATCH_TOLERANCE_S);
    let lasers = records.iter().filter(|r| matches!(r, Record::Laser(_))).count();
    if distinct || lasers != reference.len() {
        return false;
    }
    for (k, r) in reference.iter_mut().enumerate() {
        r.timestamp_s = k as f64;
    }
    let mut k = 0usize;
    for r in records.iter_mut() {
        if let Record::Laser(l) = r {
            l.timestamp_s = k as f64;
            k += 1;
        }
    }
    true
}

/// Another localiser's poses for a log matched to its reference by order ([`by_index`]): one row
/// per scan, re-stamped with the scan's index.
fn by_order(poses: &mut [(f64, Se2)], scans: usize) -> anyhow::Result<()> {
    anyhow::ensure!(
        poses.len() == scans,
        "{} rows for {scans} scans: the log's stamps are not distinct, so its rows are matched to the scans by their order, one row per scan",
        poses.len()
    );
    for (k, p) in poses.iter_mut().enumerate() {
        p.0 = k as f64;
    }
    Ok(())
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
        "{}: no <name>-raw.log with <name>_map.yaml and <name>-gt.csv beside it (make them from a Radish corrected CARMEN log, e.g. of github.com/acschaefer/ple, data/carmen/, with `amr tools carmen-prepare LOG --out DIR`)",
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
    kidnaps: &[Kidnap],
) -> Run {
    let mut loc = LogLocalizer::new(grid, params.clone(), start, seed);
    let mut est = Vec::new();
    let mut states: Vec<Judged> = Vec::new();
    let mut ms = Vec::new();
    let mut refs = reference.to_vec();
    refs.sort_by(|a, b| a.timestamp_s.total_cmp(&b.timestamp_s));
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
                let state = p.integrity.map_or(IntegrityState::Uncertain, |i| i.state);
                states.push((loc.scans.saturating_sub(1), error_at(&refs, p.timestamp_s, &p.pose), state));
            }
        }
    }
    let reseeds = loc.filter().map_or(0, amr_core::amcl::Amcl::reseeds);
    let per_scan: Vec<(Option<PoseError>, IntegrityState)> =
        states.iter().map(|(_, e, s)| (*e, *s)).collect();
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
        integrity: integrity_counts(&per_scan, reseeds),
        kidnaps: kidnap_outcomes(&states, kidnaps),
    }
}

/// The error of `pose` against the reference pose stamped `t` (sorted references).
fn error_at(refs: &[RefPose], t: f64, pose: &Se2) -> Option<PoseError> {
    let k = refs.partition_point(|g| g.timestamp_s < t - amr_core::amcl::log::MATCH_TOLERANCE_S);
    let g = refs.get(k).filter(|g| (g.timestamp_s - t).abs() <= amr_core::amcl::log::MATCH_TOLERANCE_S)?;
    Some(PoseError {
        m: (g.pose.x - pose.x).hypot(g.pose.y - pose.y),
        rad: amr_core::se2::angle_diff(g.pose.theta, pose.theta).abs(),
    })
}

/// Another localiser's poses judged as [`run_once`] judges ours, per laser record (the pose
/// stamped with the record's stamp, if any); it reports no state, so every scan counts as
/// `Tracking`.
fn judged_without_states(records: &[Record], reference: &[RefPose], poses: &[(f64, Se2)]) -> Vec<Judged> {
    let mut refs = reference.to_vec();
    refs.sort_by(|a, b| a.timestamp_s.total_cmp(&b.timestamp_s));
    let mut sorted = poses.to_vec();
    sorted.sort_by(|a, b| a.0.total_cmp(&b.0));
    let tol = amr_core::amcl::log::MATCH_TOLERANCE_S;
    records
        .iter()
        .filter_map(|r| match r {
            Record::Laser(l) => Some(l.timestamp_s),
            Record::Odometry { .. } => None,
        })
        .enumerate()
        .filter_map(|(i, t)| {
            let k = sorted.partition_point(|p| p.0 < t - tol);
            let (_, pose) = sorted.get(k).filter(|p| (p.0 - t).abs() <= tol)?;
            Some((i, error_at(&refs, t, pose), IntegrityState::Tracking))
        })
        .collect()
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

/// Which runs of each log and seed [`run`] makes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Runs {
    /// From the first reference pose.
    pub tracking: bool,
    /// With no initial pose.
    pub global: bool,
    /// With the odometry teleported every N scans, from the first reference pose.
    pub kidnapped: Option<usize>,
}

pub fn run(
    params: &AmclParams,
    dir: &Path,
    only: &[String],
    seeds: &[u64],
    nav2_dir: Option<&Path>,
    runs: Runs,
) -> anyhow::Result<Report> {
    let kidnap_every = runs.kidnapped;
    let names = if only.is_empty() { logs_in(dir)? } else { only.to_vec() };
    let mut logs = Vec::new();
    let mut skipped = Vec::new();
    for name in names {
        let grid = amr_actors::config::load_map_path(&dir.join(format!("{name}_map.yaml")))?;
        let gt_path = dir.join(format!("{name}-gt.csv"));
        let reference =
            parse_reference(&read(&gt_path)?).map_err(|e| anyhow::anyhow!("{}: {e}", gt_path.display()))?;
        let first =
            reference.first().map(|r| r.pose).with_context(|| format!("{}: empty", gt_path.display()))?;
        let log_path = dir.join(format!("{name}-raw.log"));
        let mut records: Vec<Record> =
            read(&log_path)?.lines().filter_map(|l| parse_line(l).ok().flatten()).collect();
        let scans = records.iter().filter(|r| matches!(r, Record::Laser(_))).count();
        if let Some(why) = without_usable_odometry(&records) {
            tracing::warn!(log = %name, "skipped: {why}");
            skipped.push((name, why));
            continue;
        }
        let mut reference = reference;
        let indexed = by_index(&mut records, &mut reference);
        if indexed {
            tracing::warn!(log = %name, "the log's stamps are not distinct: scans matched to the reference by their order");
        }
        tracing::info!(log = %name, scans, "localising");
        let tracked = Start::resolve(Some(first), params);
        let each = |start: Start, on: bool| -> Vec<Run> {
            let seeds = if on { seeds } else { &[][..] };
            seeds.iter().map(|&s| run_once(&grid, &records, params, start, s, &reference, &[])).collect()
        };
        let tracking = each(tracked, runs.tracking);
        let global = each(Start::Global, runs.global);
        // The same log with its odometry teleported every `kidnap_every` scans (jumps drawn from
        // the seed), tracked from the first reference pose.
        let mut kidnapped = Vec::new();
        let mut nav2_kidnapped = Vec::new();
        for &s in seeds {
            let Some(every) = kidnap_every else { break };
            let (recs, k) = amr_core::amcl::log::kidnapped(&records, every, s);
            kidnapped.push(run_once(&grid, &recs, params, tracked, s, &reference, &k));
            let Some(p) = nav2_dir.map(|d| d.join(format!("{name}-kidnap{every}-s{s}.csv"))) else {
                continue;
            };
            if p.exists() {
                let mut poses = read_poses(&p)?;
                if indexed {
                    by_order(&mut poses, reference.len()).with_context(|| p.display().to_string())?;
                }
                nav2_kidnapped
                    .push((s, kidnap_outcomes(&judged_without_states(&recs, &reference, &poses), &k)));
            }
        }
        let nav2 = match nav2_dir {
            Some(d) => {
                let p: PathBuf = d.join(format!("{name}.csv"));
                if p.exists() {
                    let mut poses = read_poses(&p)?;
                    if indexed {
                        by_order(&mut poses, reference.len()).with_context(|| p.display().to_string())?;
                    }
                    Some(score(&reference, &poses))
                } else {
                    None
                }
            }
            None => None,
        };
        let judged = amr_core::amcl::log::integrity_separation(&grid, &records, &reference, params, 1);
        logs.push(LogReport {
            name,
            scans,
            odometry_only: odometry_only(&records, &reference),
            tracking,
            global,
            kidnapped,
            nav2,
            nav2_kidnapped,
            separation: separation_rows(&judged, params),
            by_range: band_rows(judged.first().map_or(&[][..], Vec::as_slice)),
        });
    }
    Ok(Report { seeds: seeds.to_vec(), logs, skipped })
}
