//! Planar range scans: per-beam angles and validity, conversion to points (paper Eq. 1–2;
//! docs/method.md §2).

use serde::{Deserialize, Serialize};

use crate::se2::Se2;

/// A 2D range scan in its sensor frame. Beam `i` points at `angle_min_rad + i·angle_increment_rad`
/// (Eq. 1, with the increment taken from the device rather than `(θ_max − θ_min)/ID_total`, which is
/// off by one for a TiM551's 271 beams over 270°). Invalid beams (no return, NaN, outside
/// `[range_min_m, range_max_m]`) are stored as NaN, so validity travels with the data.
#[derive(Debug, Clone, PartialEq)]
pub struct Scan {
    pub angle_min_rad: f64,
    pub angle_increment_rad: f64,
    pub range_min_m: f64,
    pub range_max_m: f64,
    ranges_m: Vec<f64>,
}

/// Where the beams of a scan point: `count` beams `step_rad` apart, centred on `mid_angle_rad`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BeamGeometry {
    pub mid_angle_rad: f64,
    pub step_rad: f64,
    pub count: usize,
}

impl BeamGeometry {
    /// The index of the beam nearest to `angle_rad` (wrapped around the middle of the sweep), which
    /// lies outside `0..count` for angles outside the sweep.
    #[must_use]
    pub fn nearest_beam(&self, angle_rad: f64) -> i64 {
        let rel = crate::se2::normalize_angle(angle_rad - self.mid_angle_rad);
        let half = (self.count.max(1) - 1) as f64 / 2.0;
        (rel / self.step_rad + half).round() as i64
    }
}

/// A valid beam as a point, with the beam index it came from.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BeamPoint {
    pub index: usize,
    pub p: [f64; 2],
}

impl Scan {
    /// Build a scan; ranges outside `[range_min_m, range_max_m]`, zero or non-finite become invalid.
    #[must_use]
    pub fn new(
        angle_min_rad: f64,
        angle_increment_rad: f64,
        range_min_m: f64,
        range_max_m: f64,
        ranges_m: Vec<f64>,
    ) -> Self {
        let ranges_m =
            ranges_m
                .into_iter()
                .map(|r| {
                    if r.is_finite() && r > 0.0 && r >= range_min_m && r <= range_max_m {
                        r
                    } else {
                        f64::NAN
                    }
                })
                .collect();
        Scan { angle_min_rad, angle_increment_rad, range_min_m, range_max_m, ranges_m }
    }

    /// The same beam geometry with other ranges (validity rules applied again).
    #[must_use]
    pub fn with_ranges(&self, ranges_m: Vec<f64>) -> Self {
        Scan::new(self.angle_min_rad, self.angle_increment_rad, self.range_min_m, self.range_max_m, ranges_m)
    }

    #[must_use]
    pub fn len(&self) -> usize {
        self.ranges_m.len()
    }

    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.ranges_m.is_empty()
    }

    /// Ranges, NaN where invalid.
    #[must_use]
    pub fn ranges_m(&self) -> &[f64] {
        &self.ranges_m
    }

    #[must_use]
    pub fn is_valid(&self, i: usize) -> bool {
        self.ranges_m.get(i).is_some_and(|r| !r.is_nan())
    }

    /// Eq. 1: the angle of beam `i`.
    #[must_use]
    pub fn angle(&self, i: usize) -> f64 {
        self.angle_min_rad + self.angle_increment_rad * i as f64
    }

    /// The beam whose angle is nearest to `angle_rad` (any real angle; wrapped into the scan's
    /// sweep), or `None` if it falls outside the sweep by more than half a step.
    #[must_use]
    pub fn beam_index(&self, angle_rad: f64) -> Option<usize> {
        usize::try_from(self.geometry().nearest_beam(angle_rad)).ok().filter(|&i| i < self.len())
    }

    /// The beam layout alone, for lookups without the ranges.
    #[must_use]
    pub fn geometry(&self) -> BeamGeometry {
        let n = self.len();
        BeamGeometry {
            mid_angle_rad: self.angle_min_rad + self.angle_increment_rad * (n.max(1) - 1) as f64 / 2.0,
            step_rad: self.angle_increment_rad,
            count: n,
        }
    }

    /// Eq. 2: beam `i` as a point in the sensor frame, if valid.
    #[must_use]
    pub fn point(&self, i: usize) -> Option<[f64; 2]> {
        let r = *self.ranges_m.get(i)?;
        if r.is_nan() {
            return None;
        }
        let (s, c) = self.angle(i).sin_cos();
        Some([r * c, r * s])
    }

    /// Every valid beam as a point, transformed by `sensor_to_frame` (e.g. `T_L^B`).
    #[must_use]
    pub fn points_in(&self, sensor_to_frame: &Se2) -> Vec<BeamPoint> {
        (0..self.len())
            .filter_map(|i| {
                self.point(i).map(|p| BeamPoint { index: i, p: sensor_to_frame.transform_point(p) })
            })
            .collect()
    }

    /// Number of valid beams.
    #[must_use]
    pub fn valid_count(&self) -> usize {
        self.ranges_m.iter().filter(|r| !r.is_nan()).count()
    }
}

/// On the wire and in recordings a scan is its geometry and its ranges, an invalid beam as `null`
/// (`None`), so JSON can carry it and every valid range comes back bit for bit. Decoding goes
/// through [`Scan::new`]: a scan from outside obeys the same validity rules as one built here.
#[derive(Serialize)]
#[serde(rename = "Scan")]
struct ScanOut<'a> {
    angle_min_rad: f64,
    angle_increment_rad: f64,
    range_min_m: f64,
    range_max_m: f64,
    ranges_m: RangesOut<'a>,
}

struct RangesOut<'a>(&'a [f64]);

impl Serialize for RangesOut<'_> {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_seq(self.0.iter().map(|r| (!r.is_nan()).then_some(*r)))
    }
}

#[derive(Deserialize)]
#[serde(rename = "Scan", deny_unknown_fields)]
struct ScanIn {
    angle_min_rad: f64,
    angle_increment_rad: f64,
    range_min_m: f64,
    range_max_m: f64,
    ranges_m: Vec<Option<f64>>,
}

impl Serialize for Scan {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        ScanOut {
            angle_min_rad: self.angle_min_rad,
            angle_increment_rad: self.angle_increment_rad,
            range_min_m: self.range_min_m,
            range_max_m: self.range_max_m,
            ranges_m: RangesOut(&self.ranges_m),
        }
        .serialize(s)
    }
}

impl<'de> Deserialize<'de> for Scan {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let s = ScanIn::deserialize(d)?;
        Ok(Scan::new(
            s.angle_min_rad,
            s.angle_increment_rad,
            s.range_min_m,
            s.range_max_m,
            s.ranges_m.into_iter().map(|r| r.unwrap_or(f64::NAN)).collect(),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::FRAC_PI_2;

    fn tim551(ranges: Vec<f64>) -> Scan {
        // 271 beams, 1°, from −135° to +135° in the robot convention.
        Scan::new(-135f64.to_radians(), 1f64.to_radians(), 0.05, 10.0, ranges)
    }

    #[test]
    fn angles_and_points_by_eq_1_and_2() {
        let s = tim551(vec![1.0; 271]);
        assert!((s.angle(0) + 135f64.to_radians()).abs() < 1e-12);
        assert!((s.angle(270) - 135f64.to_radians()).abs() < 1e-12);
        let ahead = s.point(135).unwrap();
        assert!((ahead[0] - 1.0).abs() < 1e-12 && ahead[1].abs() < 1e-12);
        let left = s.point(225).unwrap();
        assert!(left[0].abs() < 1e-12 && (left[1] - 1.0).abs() < 1e-12);
        assert_eq!(s.beam_index(FRAC_PI_2), Some(225));
        assert_eq!(s.beam_index(FRAC_PI_2 + 0.4f64.to_radians()), Some(225));
        assert_eq!(s.beam_index(180f64.to_radians()), None, "behind the sensor, outside the 270° sweep");
        assert_eq!(s.beam_index(-135f64.to_radians()), Some(0));
    }

    #[test]
    fn invalid_ranges_are_never_points() {
        let mut r = vec![2.0; 271];
        r[0] = 0.0;
        r[1] = f64::NAN;
        r[2] = 0.01; // below range_min
        r[3] = 12.0; // above range_max
        r[4] = f64::INFINITY;
        let s = tim551(r);
        assert_eq!(s.valid_count(), 266);
        assert!((0..5).all(|i| s.point(i).is_none() && !s.is_valid(i)));
        assert_eq!(s.points_in(&Se2::IDENTITY).first().map(|b| b.index), Some(5));
    }

    #[test]
    fn points_follow_the_mount() {
        let s = tim551(vec![1.0; 271]);
        let mount = Se2::from_degrees(0.175, 0.0, 0.0);
        let ahead = s.points_in(&mount).into_iter().find(|b| b.index == 135).unwrap();
        assert!((ahead.p[0] - 1.175).abs() < 1e-12);
    }
}
