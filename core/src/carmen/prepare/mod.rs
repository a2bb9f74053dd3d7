//! A Radish "corrected" CARMEN log (`*-corrected.log`, SLAM-corrected by its authors) made into what
//! `amr bench localize` reads: the log with its raw odometry only, the reference trajectory, and a
//! map built from the scans at their corrected poses.
//!
//! A corrected log holds its answer: both pose triples of every FLASER line are the corrected pose,
//! and its ODOM lines are raw odometry re-anchored on the corrected poses:
//!
//! - the ODOM line right before a FLASER carries the scan's timestamp: the scan's odometry;
//! - the ODOM line right after a FLASER (NEFF lines and comments between do not count) is an anchor
//!   at the scan's corrected pose (its timestamp is 0 or garbage);
//! - every ODOM line after the anchor, up to the next FLASER, is `corrected(scan) ∘ odom(scan)⁻¹ ∘
//!   odom(t)`: raw odometry seen from the scan's corrected pose.
//!
//! So within a segment (an anchor and the ODOM lines after it) the increments between consecutive
//! lines are the raw odometry's increments, the anchor standing for the reading before the scan.
//! Chaining them from the first ODOM line of the file (raw odometry: no scan precedes it) rebuilds
//! the raw odometry in that line's frame ([`raw_odometry`]).
//!
//! The map ([`build_map`]): every beam with a range in `[min_range, max_range]` below the log's
//! no-return value (its largest reading) is cast from the scan's corrected pose, at the angles
//! [`parse_line`](super::parse_line) gives FLASER beams ([`flaser_beam_step`]); its endpoint's cell
//! counts a hit, every other cell it crosses (sampled every quarter of a cell) a pass. A cell with a
//! hit is occupied when hits are at least a quarter of its observations; any other observed cell is
//! free, the rest unknown.
//!
//! Pure: text in, text and a grid out; the caller reads and writes the files.

use std::f64::consts::FRAC_PI_2;
use std::fmt::Write as _;

use super::{CarmenError, Fields, flaser_beam_step};
use crate::map::{FREE, OCCUPIED, OccupancyGrid, UNKNOWN};
use crate::se2::Se2;

/// An ODOM line.
#[derive(Debug, Clone, PartialEq)]
pub struct OdometryLine {
    pub pose: Se2,
    /// `tv rv accel`, as logged.
    pub velocity: [f64; 3],
    pub timestamp_s: f64,
    pub logger_timestamp_s: f64,
    /// The line right after a FLASER: the scan's corrected pose, not a reading.
    pub anchor: bool,
}

/// A FLASER line.
#[derive(Debug, Clone, PartialEq)]
pub struct LaserLine {
    /// Every reading as logged, no-return values included.
    pub ranges_m: Vec<f64>,
    /// The laser pose (x y θ): the corrected pose.
    pub pose: Se2,
    /// The odometry fields (the corrected pose again in a corrected log).
    pub odometry: Se2,
    pub timestamp_s: f64,
    pub logger_timestamp_s: f64,
    /// Line number in the file, from 1.
    pub line: usize,
}

/// A line that carries a pose, in file order.
#[derive(Debug, Clone, PartialEq)]
pub enum Event {
    Odometry(OdometryLine),
    Laser(LaserLine),
}

/// A corrected log: its parameters (first-seen order, the last value of each) and its pose lines.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CorrectedLog {
    pub params: Vec<(String, String)>,
    pub events: Vec<Event>,
}

/// Why a log could not be prepared.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PrepareError {
    #[error("line {line}: {error}")]
    Line { line: usize, error: CarmenError },
    #[error("no FLASER line")]
    NoScans,
    #[error("not a corrected log: {0}")]
    NotCorrected(String),
    #[error("line {line}: a FLASER line before any ODOM line (no odometry to rebuild)")]
    ScanBeforeOdometry { line: usize },
    #[error("PARAM robot_frontlaser_offset `{0}` is not a number")]
    LaserOffset(String),
    #[error("the map would have {width} × {height} cells (at most {MAX_MAP_CELLS})")]
    MapTooLarge { width: usize, height: usize },
}

/// The most cells a map may have (at 5 cm, 410 m × 410 m; the largest of the public corrected logs
/// needs 28 M).
pub const MAX_MAP_CELLS: usize = 1 << 26;

/// `ipc_timestamp hostname logger_timestamp`; a missing logger timestamp is the IPC one.
fn stamps(f: &mut Fields<'_>) -> Result<(f64, f64), CarmenError> {
    let ipc = f.timestamp()?;
    let _host = f.it.next();
    let logger = if f.it.clone().next().is_some() { f.f64("logger_timestamp")? } else { ipc };
    Ok((ipc, logger))
}

impl CorrectedLog {
    /// Read the lines that matter (PARAM, ODOM, FLASER; NEFF, other messages and comments are
    /// skipped) and check that the log is a corrected one: every FLASER's two poses alike, and at
    /// least 95 % of them followed by an anchor at that pose.
    pub fn parse(text: &str) -> Result<Self, PrepareError> {
        let mut log = CorrectedLog::default();
        let mut after_scan = false;
        for (k, line) in text.lines().enumerate() {
            let at = |error| PrepareError::Line { line: k + 1, error };
            let mut it = line.split_ascii_whitespace();
            let Some(message) = it.next() else { continue };
            if message.starts_with('#') {
                continue;
            }
            let mut f = Fields { it, message };
            match message {
                "FLASER" => {
                    let n = f.count("num_readings").map_err(at)?;
                    let ranges_m = f.floats(n, "range").map_err(at)?;
                    let pose = f.pose("laser pose").map_err(at)?;
                    let odometry = f.pose("odometry").map_err(at)?;
                    let (timestamp_s, logger_timestamp_s) = stamps(&mut f).map_err(at)?;
                    log.events.push(Event::Laser(LaserLine {
                        ranges_m,
                        pose,
                        odometry,
                        timestamp_s,
                        logger_timestamp_s,
                        line: k + 1,
                    }));
                    after_scan = true;
                }
                "ODOM" => {
                    let pose = f.pose("pose").map_err(at)?;
                    let v = f.floats(3, "velocity").map_err(at)?;
                    let (timestamp_s, logger_timestamp_s) = stamps(&mut f).map_err(at)?;
                    log.events.push(Event::Odometry(OdometryLine {
                        pose,
                        velocity: [v[0], v[1], v[2]],
                        timestamp_s,
                        logger_timestamp_s,
                        anchor: after_scan,
                    }));
                    after_scan = false;
                }
                "NEFF" => {}
                "PARAM" => {
                    if let (Some(name), Some(value)) = (f.it.next(), f.it.next()) {
                        match log.params.iter_mut().find(|(n, _)| n == name) {
                            Some((_, v)) => value.clone_into(v),
                            None => log.params.push((name.to_owned(), value.to_owned())),
                        }
                    }
                    after_scan = false;
                }
                _ => after_scan = false,
            }
        }
        log.check()?;
        Ok(log)
    }

    fn check(&self) -> Result<(), PrepareError> {
        let mut scans = 0usize;
        let mut anchored = 0usize;
        let mut last_scan: Option<Se2> = None;
        for e in &self.events {
            match e {
                Event::Laser(l) => {
                    scans += 1;
                    let same =
                        [l.pose.x - l.odometry.x, l.pose.y - l.odometry.y, l.pose.theta - l.odometry.theta]
                            .iter()
                            .all(|d| d.abs() < 1e-9);
                    if !same {
                        return Err(PrepareError::NotCorrected(format!(
                            "the FLASER line at line {} carries two different poses (a raw log has its \
                             odometry in the FLASER lines already)",
                            l.line
                        )));
                    }
                    last_scan = Some(l.pose);
                }
                Event::Odometry(o) if o.anchor => {
                    anchored += usize::from(last_scan.is_some_and(|p| p.approx_eq(&o.pose, 1e-6, 1e-6)));
                }
                Event::Odometry(_) => {}
            }
        }
        if scans == 0 {
            return Err(PrepareError::NoScans);
        }
        if anchored * 20 < scans * 19 {
            return Err(PrepareError::NotCorrected(format!(
                "only {anchored} of {scans} FLASER lines are followed by an ODOM line at their pose"
            )));
        }
        Ok(())
    }

    /// The FLASER lines, in file order.
    pub fn scans(&self) -> impl Iterator<Item = &LaserLine> {
        self.events.iter().filter_map(|e| match e {
            Event::Laser(l) => Some(l),
            Event::Odometry(_) => None,
        })
    }

    /// The laser's offset ahead of the robot (`PARAM robot_frontlaser_offset`, default 0), m.
    pub fn laser_offset_m(&self) -> Result<f64, PrepareError> {
        match self.params.iter().find(|(n, _)| n == "robot_frontlaser_offset") {
            None => Ok(0.0),
            Some((_, v)) => v
                .parse::<f64>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or_else(|| PrepareError::LaserOffset(v.clone())),
        }
    }
}

/// The raw odometry at every event, rebuilt by chaining the increments between consecutive ODOM
/// lines of each segment (module documentation): per ODOM line its reading, per FLASER the reading
/// before it, `None` for anchors. The frame is the first ODOM line's.
pub fn raw_odometry(events: &[Event]) -> Result<Vec<Option<Se2>>, PrepareError> {
    let mut raw: Option<Se2> = None;
    // The previous line's pose, in the current segment's frame.
    let mut previous: Option<Se2> = None;
    events
        .iter()
        .map(|e| match e {
            Event::Odometry(o) if o.anchor => {
                previous = Some(o.pose);
                Ok(None)
            }
            Event::Odometry(o) => {
                let r = match (raw, previous) {
                    (Some(r), Some(p)) => r * (p.inverse() * o.pose),
                    _ => o.pose,
                };
                raw = Some(r);
                previous = Some(o.pose);
                Ok(Some(r))
            }
            Event::Laser(l) => raw.map(Some).ok_or(PrepareError::ScanBeforeOdometry { line: l.line }),
        })
        .collect()
}

fn pose_text(p: &Se2) -> String {
    format!("{:.6} {:.6} {:.6}", p.x, p.y, p.theta)
}

/// The log with its raw odometry only: PARAM lines, then every ODOM line but the anchors with its
/// raw reading, every FLASER line with the raw odometry of its scan (its laser pose: the odometry
/// moved by the laser's offset). `raw` is [`raw_odometry`]'s answer for `log.events`.
pub fn raw_log(log: &CorrectedLog, raw: &[Option<Se2>]) -> Result<String, PrepareError> {
    let laser = Se2::new(log.laser_offset_m()?, 0.0, 0.0);
    let mut out = String::from(
        "# CARMEN log with raw odometry only, rebuilt from a corrected log by `amr tools carmen-prepare`\n\
         # FLASER n r1..rn x y theta odom_x odom_y odom_theta ipc_ts host logger_ts (both poses: raw odometry)\n\
         # ODOM x y theta tv rv accel ipc_ts host logger_ts\n",
    );
    for (name, value) in &log.params {
        let _ = writeln!(out, "PARAM {name} {value} nohost 0");
    }
    for (e, r) in log.events.iter().zip(raw) {
        match (e, r) {
            (Event::Odometry(o), Some(r)) => {
                let [tv, rv, acc] = o.velocity;
                let _ = writeln!(
                    out,
                    "ODOM {} {tv:.6} {rv:.6} {acc:.6} {:.6} nohost {:.6}",
                    pose_text(r),
                    o.timestamp_s,
                    o.logger_timestamp_s
                );
            }
            (Event::Laser(l), Some(r)) => {
                let _ = write!(out, "FLASER {}", l.ranges_m.len());
                for v in &l.ranges_m {
                    let _ = write!(out, " {v}");
                }
                let _ = writeln!(
                    out,
                    " {} {} {:.6} nohost {:.6}",
                    pose_text(&(*r * laser)),
                    pose_text(r),
                    l.timestamp_s,
                    l.logger_timestamp_s
                );
            }
            // Anchors.
            (_, None) => {}
        }
    }
    Ok(out)
}

/// The reference trajectory: `scan,timestamp,x,y,theta`, the corrected pose of every scan.
#[must_use]
pub fn reference_csv(log: &CorrectedLog) -> String {
    let mut out = String::from("scan,timestamp,x,y,theta\n");
    for (k, l) in log.scans().enumerate() {
        let p = l.pose;
        let _ = writeln!(out, "{k},{:.6},{:.6},{:.6},{:.6}", l.timestamp_s, p.x, p.y, p.theta);
    }
    out
}

/// How the map is built.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MapOptions {
    pub resolution_m: f64,
    /// Beams shorter or longer than these are not used.
    pub min_range_m: f64,
    pub max_range_m: f64,
    /// Unknown border around the beams' endpoints and the poses.
    pub margin_m: f64,
}

impl Default for MapOptions {
    fn default() -> Self {
        MapOptions { resolution_m: 0.05, min_range_m: 0.1, max_range_m: 40.0, margin_m: 1.0 }
    }
}

/// A cell's state from its hits and passes: occupied when hit and hits are at least a quarter of
/// its observations, free when otherwise observed, else unknown.
#[must_use]
pub fn cell_state(hits: u32, passes: u32) -> i8 {
    let seen = u64::from(hits) + u64::from(passes);
    if seen == 0 {
        UNKNOWN
    } else if hits > 0 && 4 * u64::from(hits) >= seen {
        OCCUPIED
    } else {
        FREE
    }
}

/// The map of `scans` at their logged (corrected) poses (module documentation).
pub fn build_map(scans: &[&LaserLine], options: &MapOptions) -> Result<OccupancyGrid, PrepareError> {
    if scans.is_empty() {
        return Err(PrepareError::NoScans);
    }
    let res = options.resolution_m;
    let no_return = scans.iter().flat_map(|l| l.ranges_m.iter().copied()).fold(f64::NEG_INFINITY, f64::max);
    let used = |r: f64| r >= options.min_range_m && r <= options.max_range_m && r < no_return - 1e-6;
    // Every used beam: origin, direction (cos, sin), range.
    let beams = || {
        scans.iter().flat_map(move |l| {
            let step = flaser_beam_step(l.ranges_m.len());
            l.ranges_m.iter().enumerate().filter(move |(_, r)| used(**r)).map(move |(i, r)| {
                let (s, c) = (l.pose.theta + (-FRAC_PI_2 + step * i as f64)).sin_cos();
                (l.pose, c, s, *r)
            })
        })
    };
    let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
    let mut extend = |x: f64, y: f64| {
        lo = [lo[0].min(x), lo[1].min(y)];
        hi = [hi[0].max(x), hi[1].max(y)];
    };
    for l in scans {
        extend(l.pose.x, l.pose.y);
    }
    for (p, c, s, r) in beams() {
        extend(p.x + r * c, p.y + r * s);
    }
    let x0 = ((lo[0] - options.margin_m) / res).floor() * res;
    let y0 = ((lo[1] - options.margin_m) / res).floor() * res;
    let wf = ((hi[0] + options.margin_m - x0) / res).ceil().max(1.0);
    let hf = ((hi[1] + options.margin_m - y0) / res).ceil().max(1.0);
    if wf * hf > MAX_MAP_CELLS as f64 {
        return Err(PrepareError::MapTooLarge { width: wf as usize, height: hf as usize });
    }
    let (w, h) = (wf as usize, hf as usize);
    let cell = |x: f64, y: f64| -> Option<usize> {
        let (i, j) = (((x - x0) / res).floor(), ((y - y0) / res).floor());
        (i >= 0.0 && j >= 0.0 && i < wf && j < hf).then(|| j as usize * w + i as usize)
    };
    let mut hits = vec![0u32; w * h];
    let mut passes = vec![0u32; w * h];
    let sample = res / 4.0;
    for (p, c, s, r) in beams() {
        let end = cell(p.x + r * c, p.y + r * s);
        if let Some(e) = end {
            hits[e] = hits[e].saturating_add(1);
        }
        // The samples' cells are monotone in x and y along the beam: a cell left is never entered
        // again, so comparing with the previous cell counts each cell once per beam.
        let mut last = None;
        for k in 0..(r / sample).ceil() as usize {
            let d = k as f64 * sample;
            let Some(q) = cell(p.x + d * c, p.y + d * s) else { continue };
            if Some(q) != end && Some(q) != last {
                passes[q] = passes[q].saturating_add(1);
                last = Some(q);
            }
        }
    }
    let cells = hits.iter().zip(&passes).map(|(h, p)| cell_state(*h, *p)).collect();
    Ok(OccupancyGrid { width: w, height: h, resolution_m: res, origin: Se2::new(x0, y0, 0.0), cells })
}

/// What [`prepare`] made, and counts for the user.
#[derive(Debug, Clone, PartialEq)]
pub struct Prepared {
    pub raw_log: String,
    pub reference_csv: String,
    pub map: OccupancyGrid,
    pub scans: usize,
    /// ODOM lines kept (with their raw reading), anchors dropped.
    pub odometry_lines: usize,
    pub anchors: usize,
}

/// The raw-odometry log, the reference and the map of a corrected log's text.
pub fn prepare(text: &str, options: &MapOptions) -> Result<Prepared, PrepareError> {
    let log = CorrectedLog::parse(text)?;
    let raw = raw_odometry(&log.events)?;
    let scans: Vec<&LaserLine> = log.scans().collect();
    let anchors = raw.iter().filter(|r| r.is_none()).count();
    Ok(Prepared {
        raw_log: raw_log(&log, &raw)?,
        reference_csv: reference_csv(&log),
        map: build_map(&scans, options)?,
        scans: scans.len(),
        odometry_lines: log.events.len() - scans.len() - anchors,
        anchors,
    })
}

#[cfg(test)]
mod tests;
