//! AMCL over a recorded log, and its score against a reference trajectory: what `amr localize` and
//! `amr bench localize` share. Pure: lines and poses in, poses and statistics out; the caller times.

use std::sync::Arc;

use serde::Serialize;

use super::{Amcl, LikelihoodField, UpdateOutcome, scan_points};
use crate::carmen::{LaserRecord, Record};
use crate::config::AmclParams;
use crate::metrics::ErrorStats;
use crate::se2::{Se2, angle_diff};

/// Where the filter starts.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Start {
    /// Gaussian around a pose (nav2 `/initialpose`).
    Pose { pose: Se2, std_xy_m: f64, std_yaw_rad: f64 },
    /// Uniform over the free space (global localisation).
    Global,
}

impl Start {
    /// From a pose given on the command line (spread from the parameters' `initial_pose`, else
    /// [`CLI_SPREAD`]), else the parameters' `initial_pose`, else global localisation.
    #[must_use]
    pub fn resolve(cli: Option<Se2>, params: &AmclParams) -> Start {
        match (cli, params.initial_pose) {
            (Some(pose), spread) => {
                let (std_xy_m, std_yaw_rad) =
                    spread.map_or(CLI_SPREAD, |s| (s.std_xy_m.get(), s.std_yaw_rad.get()));
                Start::Pose { pose, std_xy_m, std_yaw_rad }
            }
            (None, Some(ip)) => Start::Pose {
                pose: ip.pose(),
                std_xy_m: ip.std_xy_m.get(),
                std_yaw_rad: ip.std_yaw_rad.get(),
            },
            (None, None) => Start::Global,
        }
    }
}

/// The spread (m, rad) of a pose given without one: RViz's "2D Pose Estimate" sends nav2 variances
/// of 0.25 m² in x and y and (π/12)² in yaw.
pub const CLI_SPREAD: (f64, f64) = (0.5, std::f64::consts::PI / 12.0);

/// The pose reported for one laser record.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LogPose {
    pub timestamp_s: f64,
    pub pose: Se2,
    /// Of the last filter update, `[x, y, θ]`.
    pub covariance: [[f64; 3]; 3],
    /// The last judged update's integrity (`None` before the first).
    pub integrity: Option<super::Integrity>,
}

/// AMCL fed one log record at a time. The filter (and its field) is built at the first laser
/// record, so that a field needing the sensor's maximum range can take the scan's own.
#[derive(Debug)]
pub struct LogLocalizer<'g> {
    grid: std::borrow::Cow<'g, crate::map::OccupancyGrid>,
    params: AmclParams,
    start: Start,
    seed: u64,
    amcl: Option<Amcl>,
    last_odom: Option<Se2>,
    /// Laser records seen, and those without any odometry (skipped).
    pub scans: usize,
    pub scans_without_odometry: usize,
}

/// What one laser record gave.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fed {
    pub outcome: UpdateOutcome,
    pub pose: Option<LogPose>,
}

impl<'g> LogLocalizer<'g> {
    #[must_use]
    pub fn new(grid: &'g crate::map::OccupancyGrid, params: AmclParams, start: Start, seed: u64) -> Self {
        Self::on(std::borrow::Cow::Borrowed(grid), params, start, seed)
    }

    fn on(
        grid: std::borrow::Cow<'g, crate::map::OccupancyGrid>,
        params: AmclParams,
        start: Start,
        seed: u64,
    ) -> Self {
        LogLocalizer {
            grid,
            params,
            start,
            seed,
            amcl: None,
            last_odom: None,
            scans: 0,
            scans_without_odometry: 0,
        }
    }

    /// A localiser that owns its map (a live node's, replaced when a new map comes).
    #[must_use]
    pub fn owning(
        grid: crate::map::OccupancyGrid,
        params: AmclParams,
        start: Start,
        seed: u64,
    ) -> LogLocalizer<'static> {
        LogLocalizer::on(std::borrow::Cow::Owned(grid), params, start, seed)
    }

    /// Start again from `start` (an operator's initial pose, or global localisation): the filter
    /// at once if it is built, else when the first scan builds it.
    pub fn restart(&mut self, start: Start) {
        self.start = start;
        if let Some(f) = &mut self.amcl {
            match start {
                Start::Pose { pose, std_xy_m, std_yaw_rad } => f.init_pose(pose, std_xy_m, std_yaw_rad),
                Start::Global => f.init_global(),
            }
        }
    }

    /// The filter, once the first laser record has built it.
    #[must_use]
    pub fn filter(&self) -> Option<&Amcl> {
        self.amcl.as_ref()
    }

    /// Feed one record. Odometry records only update the odometry pose; a laser record runs the
    /// filter (if it moved far enough) and gives the pose at its stamp: the last estimate moved on by
    /// the odometry since (nav2's map→odom transform between updates).
    pub fn feed(&mut self, record: &Record) -> Option<Fed> {
        let laser: &LaserRecord = match record {
            Record::Odometry { pose, .. } => {
                self.last_odom = Some(*pose);
                return None;
            }
            Record::Laser(l) => l,
        };
        self.scans += 1;
        let Some(odom) = laser.odometry.or(self.last_odom) else {
            self.scans_without_odometry += 1;
            return None;
        };
        let (grid, params, start, seed) = (&*self.grid, &self.params, self.start, self.seed);
        let filter = self.amcl.get_or_insert_with(|| {
            let range_max = params.max_range_m().unwrap_or(laser.scan.range_max_m);
            let field = Arc::new(LikelihoodField::new(grid, params, range_max));
            let mut f = Amcl::new(params.clone(), field, seed);
            f.set_sensor_origin(Some([laser.laser_in_robot.x, laser.laser_in_robot.y]));
            match start {
                Start::Pose { pose, std_xy_m, std_yaw_rad } => f.init_pose(pose, std_xy_m, std_yaw_rad),
                Start::Global => f.init_global(),
            }
            f
        });
        let points = scan_points(&laser.scan, &laser.laser_in_robot, params);
        let outcome = filter.update(odom, &points, false);
        let pose = match (filter.estimate(), filter.pose_at(&odom)) {
            (Some(e), Some(pose)) => Some(LogPose {
                timestamp_s: laser.timestamp_s,
                pose,
                covariance: e.covariance,
                integrity: filter.integrity(),
            }),
            _ => None,
        };
        Some(Fed { outcome, pose })
    }
}

/// One reference pose (`scan,timestamp,x,y,theta`, as the shared CARMEN scripts write it).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RefPose {
    pub timestamp_s: f64,
    pub pose: Se2,
}

/// Parse a reference CSV with a header naming at least `timestamp,x,y,theta` (any order, other
/// columns ignored). Errors name the line.
pub fn parse_reference(text: &str) -> Result<Vec<RefPose>, String> {
    let mut lines = text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty());
    let (_, header) = lines.next().ok_or("empty reference file")?;
    let cols: Vec<&str> = header.split(',').map(str::trim).collect();
    let col = |name: &str| {
        cols.iter()
            .position(|c| *c == name)
            .ok_or_else(|| format!("line 1: no `{name}` column in `{header}`"))
    };
    let (ct, cx, cy, cth) = (col("timestamp")?, col("x")?, col("y")?, col("theta")?);
    lines
        .map(|(n, line)| {
            let f: Vec<&str> = line.split(',').map(str::trim).collect();
            let get = |c: usize| -> Result<f64, String> {
                let t = f.get(c).ok_or_else(|| format!("line {}: too few columns", n + 1))?;
                let v: f64 = t.parse().map_err(|_| format!("line {}: `{t}` is not a number", n + 1))?;
                if v.is_finite() { Ok(v) } else { Err(format!("line {}: `{t}` is not finite", n + 1)) }
            };
            Ok(RefPose { timestamp_s: get(ct)?, pose: Se2::new(get(cx)?, get(cy)?, get(cth)?) })
        })
        .collect()
}

/// Scores of an estimated trajectory against a reference, matched by timestamp.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Score {
    /// Reference poses, and those with an estimate within [`MATCH_TOLERANCE_S`].
    pub reference: usize,
    pub matched: usize,
    pub translation: Option<ErrorStats>,
    pub heading_rmse_deg: f64,
    pub heading_max_deg: f64,
    /// Share of matched poses more than [`DIVERGED_M`] off.
    pub diverged_share: f64,
    /// The first matched index from which every pose is within [`DIVERGED_M`] (global localisation's
    /// convergence); `None` if the last one is off.
    pub converged_from: Option<usize>,
}

/// An estimate farther than this from the reference counts as lost.
pub const DIVERGED_M: f64 = 0.5;
/// Estimates are matched to reference poses whose stamps differ by at most this.
pub const MATCH_TOLERANCE_S: f64 = 1e-3;

/// Score `estimate` (sorted or not) against `reference`. Every reference pose is matched to the
/// estimate with the nearest stamp; farther than [`MATCH_TOLERANCE_S`] it counts as unmatched.
#[must_use]
pub fn score(reference: &[RefPose], estimate: &[(f64, Se2)]) -> Score {
    let mut est: Vec<(f64, Se2)> = estimate.to_vec();
    est.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut trans = Vec::new();
    let mut head = Vec::new();
    for r in reference {
        let k = est.partition_point(|e| e.0 < r.timestamp_s);
        let best = [k.checked_sub(1), Some(k)]
            .into_iter()
            .flatten()
            .filter_map(|i| est.get(i))
            .min_by(|a, b| (a.0 - r.timestamp_s).abs().total_cmp(&(b.0 - r.timestamp_s).abs()));
        if let Some((t, p)) = best
            && (t - r.timestamp_s).abs() <= MATCH_TOLERANCE_S
        {
            trans.push((p.x - r.pose.x).hypot(p.y - r.pose.y));
            head.push(angle_diff(p.theta, r.pose.theta).to_degrees());
        }
    }
    let matched = trans.len();
    let diverged = trans.iter().filter(|e| **e > DIVERGED_M).count();
    let converged_from = match trans.iter().rposition(|e| *e > DIVERGED_M) {
        None if matched > 0 => Some(0),
        Some(i) if i + 1 < matched => Some(i + 1),
        _ => None,
    };
    let hs = ErrorStats::of(&head);
    Score {
        reference: reference.len(),
        matched,
        translation: ErrorStats::of(&trans),
        heading_rmse_deg: hs.map_or(f64::NAN, |s| s.rmse),
        heading_max_deg: hs.map_or(f64::NAN, |s| s.max),
        diverged_share: if matched > 0 { diverged as f64 / matched as f64 } else { f64::NAN },
        converged_from,
    }
}

/// A kidnapping written into a log: from laser record `scan` on (counting laser records), the
/// odometry reports a jump `jump` (in the robot's frame) that the robot did not make.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Kidnap {
    pub scan: usize,
    pub jump: Se2,
}

/// The log with its odometry teleported every `every` laser records (the first at `every`): each
/// jump 1–5 m in a direction and with a heading change drawn uniformly from `seed`'s generator.
/// Between the laser record before a kidnapping and the one at it, the odometry reports the jump
/// followed by what the robot really drove; every later pose carries the jump on. Odometry lines
/// between laser records take the same treatment. The robot's scans and the reference are
/// untouched: the filter is carried away by its odometry, as when a robot is lifted or slips far.
#[must_use]
pub fn kidnapped(records: &[Record], every: usize, seed: u64) -> (Vec<Record>, Vec<Kidnap>) {
    let (fixes, kidnaps) = kidnap_fixes(records, every, seed);
    let out = records
        .iter()
        .zip(fixes)
        .map(|(r, fix)| match r {
            Record::Odometry { pose, timestamp_s } => {
                Record::Odometry { pose: fix * *pose, timestamp_s: *timestamp_s }
            }
            Record::Laser(l) => {
                let mut l = l.clone();
                l.odometry = l.odometry.map(|o| fix * o);
                Record::Laser(l)
            }
        })
        .collect();
    (out, kidnaps)
}

/// [`kidnapped`] as the transform each record's odometry takes (reported = fix ∘ raw), one per
/// record, and the kidnappings.
fn kidnap_fixes(records: &[Record], every: usize, seed: u64) -> (Vec<Se2>, Vec<Kidnap>) {
    let mut rng = crate::rng::Rng::seed(seed);
    let mut fixes = Vec::with_capacity(records.len());
    let mut kidnaps = Vec::new();
    let mut fix = Se2::IDENTITY;
    let mut last_raw: Option<Se2> = None;
    let mut lasers = 0usize;
    for r in records {
        match r {
            Record::Odometry { pose, .. } => last_raw = Some(*pose),
            Record::Laser(l) => {
                if every > 0 && lasers > 0 && lasers.is_multiple_of(every) {
                    let base = l.odometry.or(last_raw);
                    if let Some(prev) = last_raw.or(base) {
                        let d = rng.range(1.0, 5.0);
                        let dir = rng.range(-std::f64::consts::PI, std::f64::consts::PI);
                        let turn = rng.range(-std::f64::consts::PI, std::f64::consts::PI);
                        let jump = Se2::new(d * dir.cos(), d * dir.sin(), turn);
                        // The reported previous pose P = fix ∘ prev; after the jump the reported
                        // pose is P ∘ jump ∘ (prev⁻¹ ∘ raw): fix' = fix ∘ prev ∘ jump ∘ prev⁻¹.
                        fix = fix * prev * jump * prev.inverse();
                        kidnaps.push(Kidnap { scan: lasers, jump });
                    }
                }
                if l.odometry.is_some() {
                    last_raw = l.odometry;
                }
                lasers += 1;
            }
        }
        fixes.push(fix);
    }
    (fixes, kidnaps)
}

/// A CARMEN log's text with the kidnappings of [`kidnapped`] written into it, for another
/// localiser to read the same log (nav2's core beside ours): every line [`crate::carmen::parse_line`]
/// reads as a record counts as one, as in [`kidnapped`]; the poses of its ODOM and FLASER lines
/// (FLASER's laser pose and odometry) are moved by the kidnappings so far, every other field and
/// line kept as it was. An error for a line with a pose this cannot move (ROBOTLASER1).
pub fn kidnapped_text(text: &str, every: usize, seed: u64) -> Result<(String, Vec<Kidnap>), String> {
    let parsed: Vec<Option<Record>> =
        text.lines().map(|l| crate::carmen::parse_line(l).ok().flatten()).collect();
    let records: Vec<Record> = parsed.iter().flatten().cloned().collect();
    let (fixes, kidnaps) = kidnap_fixes(&records, every, seed);
    let mut fixes = fixes.into_iter();
    let mut out = String::with_capacity(text.len() + text.len() / 8);
    for (n, (line, record)) in text.lines().zip(&parsed).enumerate() {
        let Some(fix) = record.as_ref().and_then(|_| fixes.next()) else {
            out.push_str(line);
            out.push('\n');
            continue;
        };
        let mut fields: Vec<String> = line.split_ascii_whitespace().map(str::to_owned).collect();
        // Where the poses stand: ODOM x y θ; FLASER n r1..rn laser_x laser_y laser_θ odom_x odom_y odom_θ.
        let at: Vec<usize> = match fields.first().map(String::as_str) {
            Some("ODOM") => vec![1],
            Some("FLASER") => {
                let n = fields.get(1).and_then(|f| f.parse::<usize>().ok()).unwrap_or(0);
                vec![2 + n, 5 + n]
            }
            Some(m) if m.starts_with("RAWLASER") => Vec::new(),
            Some(m) => return Err(format!("line {}: {m} carries a pose this cannot move", n + 1)),
            None => Vec::new(),
        };
        for k in at {
            let pose = match fields.get(k..k + 3) {
                Some([x, y, t]) => match (x.parse::<f64>(), y.parse::<f64>(), t.parse::<f64>()) {
                    (Ok(x), Ok(y), Ok(t)) => Se2::new(x, y, t),
                    _ => return Err(format!("line {}: a pose that is not three numbers", n + 1)),
                },
                _ => return Err(format!("line {}: a pose that is not three numbers", n + 1)),
            };
            let moved = fix * pose;
            for (slot, v) in fields[k..k + 3].iter_mut().zip([moved.x, moved.y, moved.theta]) {
                *slot = format!("{v:.6}");
            }
        }
        out.push_str(&fields.join(" "));
        out.push('\n');
    }
    Ok((out, kidnaps))
}

/// The displacements the integrity measure is tested against (translation m, rotation rad): the
/// estimate the map should call wrong.
pub const DISPLACEMENTS: [(f64, f64); 4] =
    [(0.3, 0.0), (0.5, 0.0), (1.0, 0.0), (0.0, 10.0 * std::f64::consts::PI / 180.0)];

/// The integrity measure ([`super::integrity::judge`]: the endpoints explained, by range band) of
/// every scan that has a reference pose, at that pose and at each of [`DISPLACEMENTS`] from it
/// (each in a direction drawn from `seed`'s generator, a rotation of either sign): `judged[0]` at
/// the references, `judged[1 + k]` displaced by `DISPLACEMENTS[k]`, scan for scan.
#[must_use]
pub fn integrity_separation(
    grid: &crate::map::OccupancyGrid,
    records: &[Record],
    reference: &[RefPose],
    params: &AmclParams,
    seed: u64,
) -> Vec<Vec<super::integrity::Judged>> {
    let mut out = vec![Vec::new(); 1 + DISPLACEMENTS.len()];
    let mut field: Option<LikelihoodField> = None;
    let mut rng = crate::rng::Rng::seed(seed);
    let p = params.integrity;
    let mut refs: Vec<RefPose> = reference.to_vec();
    refs.sort_by(|a, b| a.timestamp_s.total_cmp(&b.timestamp_s));
    for r in records {
        let Record::Laser(l) = r else { continue };
        let k = refs.partition_point(|g| g.timestamp_s < l.timestamp_s - MATCH_TOLERANCE_S);
        let Some(g) = refs.get(k).filter(|g| (g.timestamp_s - l.timestamp_s).abs() <= MATCH_TOLERANCE_S)
        else {
            continue;
        };
        let field = field.get_or_insert_with(|| {
            LikelihoodField::new(grid, params, params.max_range_m().unwrap_or(l.scan.range_max_m))
        });
        let points = super::subsample(&scan_points(&l.scan, &l.laser_in_robot, params), p.max_points);
        if points.len() < p.min_points {
            continue;
        }
        let origin = Some([l.laser_in_robot.x, l.laser_in_robot.y]);
        let judge = |pose: &Se2| super::integrity::judge(field, pose, &points, origin, &p);
        out[0].push(judge(&g.pose));
        for (k, &(d, a)) in DISPLACEMENTS.iter().enumerate() {
            let dir = rng.range(-std::f64::consts::PI, std::f64::consts::PI);
            let sign = if rng.below(2) == 0 { -1.0 } else { 1.0 };
            let moved = Se2::new(g.pose.x + d * dir.cos(), g.pose.y + d * dir.sin(), g.pose.theta + sign * a);
            out[1 + k].push(judge(&moved));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        /// Any text: rows or an error naming the line, never a panic.
        #[test]
        fn reference_parser_never_panics(text in "(timestamp,x,y,theta\n)?([-0-9.,a-z ]{0,40}\n){0,8}") {
            match parse_reference(&text) {
                Ok(rows) => prop_assert!(rows.iter().all(|r| r.timestamp_s.is_finite() && r.pose.x.is_finite())),
                Err(e) => prop_assert!(e.contains("line") || e.contains("empty"), "{e}"),
            }
        }
    }

    /// The log written with the kidnappings reads back as the kidnapped records: another
    /// localiser given the written log sees the odometry ours sees.
    #[test]
    fn a_kidnapped_log_written_out_reads_as_the_kidnapped_records() {
        let mut text = String::from("# comment\nPARAM robot_length 0.5 nohost 0\n");
        let mut pose = Se2::IDENTITY;
        for k in 0..25 {
            pose = pose * Se2::new(0.3, 0.0, 0.05);
            text +=
                &format!("ODOM {:.6} {:.6} {:.6} 0.3 0.05 0 {k}.5 host {k}.5\n", pose.x, pose.y, pose.theta);
            text += &crate::carmen::flaser_line(&[1.0, 2.0, 81.9, 3.5], &pose, &pose, f64::from(k) + 0.6);
            text.push('\n');
        }
        let records: Vec<Record> =
            text.lines().filter_map(|l| crate::carmen::parse_line(l).ok().flatten()).collect();
        let (want, kidnaps) = kidnapped(&records, 10, 3);
        assert_eq!(kidnaps.iter().map(|k| k.scan).collect::<Vec<_>>(), [10, 20]);
        let (written, same) = kidnapped_text(&text, 10, 3).unwrap();
        assert_eq!(same, kidnaps);
        assert!(written.starts_with("# comment\nPARAM robot_length 0.5 nohost 0\n"));
        let got: Vec<Record> =
            written.lines().filter_map(|l| crate::carmen::parse_line(l).ok().flatten()).collect();
        assert_eq!(got.len(), want.len());
        let close = |a: &Se2, b: &Se2| {
            (a.x - b.x).abs() < 2e-6 && (a.y - b.y).abs() < 2e-6 && angle_diff(a.theta, b.theta).abs() < 2e-6
        };
        for (g, w) in got.iter().zip(&want) {
            match (g, w) {
                (
                    Record::Odometry { pose: a, timestamp_s: s },
                    Record::Odometry { pose: b, timestamp_s: t },
                ) => {
                    assert!(close(a, b) && s == t, "{a:?} {b:?}");
                }
                (Record::Laser(a), Record::Laser(b)) => {
                    assert!(close(&a.odometry.unwrap(), &b.odometry.unwrap()));
                    // No return (81.9 m) reads as NaN, which no `==` matches: compared as printed.
                    assert_eq!(
                        format!("{:?}", (a.timestamp_s, &a.scan)),
                        format!("{:?}", (b.timestamp_s, &b.scan))
                    );
                    // The laser pose moves with the odometry (here the laser sits at the robot's origin).
                    assert!(close(&a.logged_pose.unwrap(), &a.odometry.unwrap()));
                }
                _ => panic!("records out of order"),
            }
        }
        // The odometry jumps at the kidnappings and nowhere else.
        let odom: Vec<Se2> = got
            .iter()
            .filter_map(|r| match r {
                Record::Laser(l) => l.odometry,
                Record::Odometry { .. } => None,
            })
            .collect();
        let steps: Vec<f64> = odom.windows(2).map(|w| (w[0].inverse() * w[1]).translation_norm()).collect();
        for (k, d) in steps.iter().enumerate() {
            assert_eq!(*d > 0.5, k + 1 == 10 || k + 1 == 20, "step {k}: {d}");
        }
        assert!(
            kidnapped_text(
                "ROBOTLASER1 0 -1.5 3.1 0.01 80 0.1 0 1 2.0 0 0 0 0 0 0 0 0 0 0 0 0 1.0 h 1.0\n",
                1,
                1
            )
            .is_err()
        );
    }

    #[test]
    fn reference_parse_and_score_by_hand() {
        let r =
            parse_reference("scan,timestamp,x,y,theta\n0,1.0,0,0,0\n1,2.0,1,0,0.1\n2,3.0,2,0,0\n").unwrap();
        assert_eq!(r.len(), 3);
        assert!(parse_reference("t,x\n1,2\n").unwrap_err().contains("timestamp"));
        assert!(parse_reference("timestamp,x,y,theta\n1,2,x,4\n").unwrap_err().contains("line 2"));
        // Off by 0.6 m at the first, exact after; the third has no estimate close enough in time.
        let est = [(1.0, Se2::new(0.6, 0.0, 0.0)), (2.0004, Se2::new(1.0, 0.0, 0.1)), (3.1, Se2::IDENTITY)];
        let s = score(&r, &est);
        assert_eq!((s.reference, s.matched), (3, 2));
        let t = s.translation.unwrap();
        assert!((t.rmse - (0.36f64 / 2.0).sqrt()).abs() < 1e-12 && (t.max - 0.6).abs() < 1e-12);
        assert!((s.diverged_share - 0.5).abs() < 1e-12);
        assert_eq!(s.converged_from, Some(1));
        assert!(s.heading_rmse_deg.abs() < 1e-9);
        // Diverged at the end: never converged.
        let s = score(&r[..2], &[(1.0, Se2::IDENTITY), (2.0, Se2::new(3.0, 0.0, 0.1))]);
        assert_eq!(s.converged_from, None);
    }
}
