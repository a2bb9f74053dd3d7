//! CARMEN robot logs (`.log`, `.clf`): the format of many classic 2D LiDAR datasets (Intel Research
//! Lab, MIT CSAIL, Freiburg). One message per line, each ending in
//! `ipc_timestamp ipc_hostname logger_timestamp`. Pure: lines in, records out.
//!
//! Read: `ODOM x y θ tv rv accel`, `FLASER n r… x y θ odom_x odom_y odom_θ`,
//! `RAWLASER1..4 type start fov res max acc remission n r… m rem…`, and
//! `ROBOTLASER1 type start fov res max acc remission n r… m rem… laser_x laser_y laser_θ robot_x
//! robot_y robot_θ tv rv fwd side turn`. Other messages (PARAM, SYNC, TRUEPOS, NEFF, RLASER…) and
//! comments are skipped.
//!
//! [`prepare`] turns a Radish "corrected" log into a raw-odometry log, its reference trajectory and
//! its map.

pub mod prepare;

use crate::scan::Scan;
use crate::se2::Se2;

/// A laser message.
#[derive(Debug, Clone, PartialEq)]
pub struct LaserRecord {
    pub scan: Scan,
    /// The odometry pose carried by the line itself (FLASER's odom fields, ROBOTLASER1's robot pose).
    pub odometry: Option<Se2>,
    /// The laser in the robot frame (ROBOTLASER1: robot⁻¹ ∘ laser; otherwise at the robot's origin).
    pub laser_in_robot: Se2,
    /// The pose the log gives for the laser (FLASER x, y, θ: in corrected logs a pseudo ground truth).
    pub logged_pose: Option<Se2>,
    /// `ipc_timestamp`, seconds.
    pub timestamp_s: f64,
}

/// One parsed line.
#[derive(Debug, Clone, PartialEq)]
pub enum Record {
    Odometry { pose: Se2, timestamp_s: f64 },
    Laser(Box<LaserRecord>),
}

/// Why a line could not be read.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{message}: {reason}")]
pub struct CarmenError {
    pub message: String,
    pub reason: String,
}

/// Readings at or beyond this are "no return" for FLASER, whose lines carry no maximum (SICK LMS
/// logs use ~81.9 m for it).
pub const FLASER_MAX_RANGE_M: f64 = 80.0;

struct Fields<'a> {
    it: std::str::SplitAsciiWhitespace<'a>,
    message: &'a str,
}

impl Fields<'_> {
    fn err(&self, reason: impl Into<String>) -> CarmenError {
        CarmenError { message: self.message.to_owned(), reason: reason.into() }
    }

    fn f64(&mut self, what: &str) -> Result<f64, CarmenError> {
        let t = self.it.next().ok_or_else(|| self.err(format!("missing {what}")))?;
        let v: f64 = t.parse().map_err(|_| self.err(format!("{what} `{t}` is not a number")))?;
        if v.is_finite() { Ok(v) } else { Err(self.err(format!("{what} is not finite"))) }
    }

    fn count(&mut self, what: &str) -> Result<usize, CarmenError> {
        let v = self.f64(what)?;
        if v < 0.0 || v.fract() != 0.0 || v > 100_000.0 {
            return Err(self.err(format!("{what} {v} is not a count")));
        }
        Ok(v as usize)
    }

    fn floats(&mut self, n: usize, what: &str) -> Result<Vec<f64>, CarmenError> {
        (0..n).map(|_| self.f64(what)).collect()
    }

    fn pose(&mut self, what: &str) -> Result<Se2, CarmenError> {
        Ok(Se2::new(self.f64(what)?, self.f64(what)?, self.f64(what)?))
    }

    /// The trailing `ipc_timestamp hostname logger_timestamp`.
    fn timestamp(&mut self) -> Result<f64, CarmenError> {
        self.f64("ipc_timestamp")
    }
}

/// The angle between the beams of a FLASER line of `n` readings, which start at −90°: 180° ahead,
/// 181/361/721 readings include both ends, other counts split 180° evenly (180 and 360: the SICK's
/// last beam dropped).
#[must_use]
pub fn flaser_beam_step(n: usize) -> f64 {
    if matches!(n, 181 | 361 | 721) {
        std::f64::consts::PI / (n - 1) as f64
    } else {
        std::f64::consts::PI / n.max(1) as f64
    }
}

/// Parse one line. `Ok(None)` for comments, blank lines and messages this reader does not use.
pub fn parse_line(line: &str) -> Result<Option<Record>, CarmenError> {
    let mut it = line.split_ascii_whitespace();
    let Some(message) = it.next() else { return Ok(None) };
    let mut f = Fields { it, message };
    match message {
        "ODOM" => {
            let pose = f.pose("pose")?;
            f.floats(3, "velocity")?;
            Ok(Some(Record::Odometry { pose, timestamp_s: f.timestamp()? }))
        }
        "FLASER" => {
            let n = f.count("num_readings")?;
            let ranges = f.floats(n, "range")?;
            let logged = f.pose("laser pose")?;
            let odom = f.pose("odometry")?;
            let timestamp_s = f.timestamp()?;
            let scan = Scan::new(
                -std::f64::consts::FRAC_PI_2,
                flaser_beam_step(n),
                0.0,
                FLASER_MAX_RANGE_M - 1e-9,
                ranges,
            );
            Ok(Some(Record::Laser(Box::new(LaserRecord {
                scan,
                odometry: Some(odom),
                laser_in_robot: Se2::IDENTITY,
                logged_pose: Some(logged),
                timestamp_s,
            }))))
        }
        m if m.starts_with("RAWLASER") || m == "ROBOTLASER1" => {
            let _laser_type = f.f64("laser_type")?;
            let (start, fov, res, max) = (
                f.f64("start_angle")?,
                f.f64("field_of_view")?,
                f.f64("angular_resolution")?,
                f.f64("maximum_range")?,
            );
            let _accuracy = f.f64("accuracy")?;
            let _remission_mode = f.f64("remission_mode")?;
            let n = f.count("num_readings")?;
            let ranges = f.floats(n, "range")?;
            let m_rem = f.count("num_remissions")?;
            f.floats(m_rem, "remission")?;
            // Both are finite (checked when read).
            if res <= 0.0 || fov <= 0.0 {
                return Err(f.err(format!("angular resolution {res} / field of view {fov} must be positive")));
            }
            let scan = Scan::new(start, res, 0.0, max - 1e-9, ranges);
            let (odometry, laser_in_robot) = if m == "ROBOTLASER1" {
                let laser = f.pose("laser pose")?;
                let robot = f.pose("robot pose")?;
                f.floats(5, "velocity and safety fields")?;
                (Some(robot), robot.inverse() * laser)
            } else {
                (None, Se2::IDENTITY)
            };
            let timestamp_s = f.timestamp()?;
            Ok(Some(Record::Laser(Box::new(LaserRecord {
                scan,
                odometry,
                laser_in_robot,
                logged_pose: None,
                timestamp_s,
            }))))
        }
        _ => Ok(None),
    }
}

/// Format a FLASER line (for writing logs, e.g. from the simulator or in tests).
#[must_use]
pub fn flaser_line(ranges: &[f64], laser_pose: &Se2, odometry: &Se2, timestamp_s: f64) -> String {
    let mut s = format!("FLASER {}", ranges.len());
    for r in ranges {
        s += &format!(" {:.3}", if r.is_finite() { *r } else { 81.91 });
    }
    s += &format!(
        " {:.6} {:.6} {:.6} {:.6} {:.6} {:.6} {timestamp_s:.6} sim {timestamp_s:.6}",
        laser_pose.x, laser_pose.y, laser_pose.theta, odometry.x, odometry.y, odometry.theta
    );
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flaser_by_hand() {
        let line = "FLASER 3 1.0 2.5 81.9 0.5 0.25 0.1 1.0 2.0 0.2 1234.5 host 32.9";
        let Some(Record::Laser(l)) = parse_line(line).unwrap() else { panic!() };
        assert_eq!(l.scan.len(), 3);
        assert_eq!(l.scan.valid_count(), 2, "81.9 m is no return");
        assert!((l.scan.angle(0) + std::f64::consts::FRAC_PI_2).abs() < 1e-12);
        assert!((l.scan.angle_increment_rad - std::f64::consts::PI / 3.0).abs() < 1e-12);
        assert_eq!(l.odometry, Some(Se2::new(1.0, 2.0, 0.2)));
        assert_eq!(l.logged_pose, Some(Se2::new(0.5, 0.25, 0.1)));
        assert_eq!(l.timestamp_s, 1234.5);
        // 181 readings over 180° are 1° apart, ends included.
        let ranges = vec!["1.0"; 181].join(" ");
        let Some(Record::Laser(l)) = parse_line(&format!("FLASER 181 {ranges} 0 0 0 0 0 0 1 h 1")).unwrap()
        else {
            panic!()
        };
        assert!((l.scan.angle(180) - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
    }

    #[test]
    fn robotlaser_gives_the_laser_offset() {
        let line = "ROBOTLASER1 0 -1.5708 3.14159 0.0174533 50.0 0.01 0 2 1.0 2.0 0 1.1 0.0 0.0 1.0 0.0 0.0 0 0 0 0 0 7.5 h 8";
        let Some(Record::Laser(l)) = parse_line(line).unwrap() else { panic!() };
        assert!(l.laser_in_robot.approx_eq(&Se2::new(0.1, 0.0, 0.0), 1e-12, 1e-12));
        assert_eq!(l.odometry, Some(Se2::new(1.0, 0.0, 0.0)));
        assert_eq!(l.scan.range_max_m, 50.0 - 1e-9);
        assert_eq!(l.timestamp_s, 7.5);
    }

    #[test]
    fn odom_and_skipped_lines() {
        assert_eq!(
            parse_line("ODOM 1 2 0.5 0 0 0 3.25 h 1").unwrap(),
            Some(Record::Odometry { pose: Se2::new(1.0, 2.0, 0.5), timestamp_s: 3.25 })
        );
        assert_eq!(parse_line("# comment").unwrap(), None);
        assert_eq!(parse_line("PARAM robot_front_laser_max 81.9").unwrap(), None);
        assert_eq!(parse_line("").unwrap(), None);
    }

    #[test]
    fn bad_lines_are_errors_not_panics() {
        for line in [
            "ODOM 1 2",
            "FLASER 5 1 2 3",
            "FLASER x",
            "FLASER -1",
            "ODOM 1 nan 0 0 0 0 1 h 1",
            "ROBOTLASER1 0 0 0 0 50 0 0 1 1.0 0",
            "FLASER 1e9",
        ] {
            assert!(parse_line(line).is_err(), "{line}");
        }
    }

    #[test]
    fn written_lines_read_back() {
        let line =
            flaser_line(&[1.0, f64::NAN, 3.0], &Se2::new(1.0, 2.0, 0.3), &Se2::new(1.1, 2.1, 0.31), 12.0);
        let Some(Record::Laser(l)) = parse_line(&line).unwrap() else { panic!() };
        assert_eq!(l.scan.valid_count(), 2);
        assert!(l.odometry.unwrap().approx_eq(&Se2::new(1.1, 2.1, 0.31), 1e-6, 1e-6));
    }
}
