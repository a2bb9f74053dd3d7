//! Where the mock's ranges come from. The world simulator implements [`ScanSource`] later; the
//! static [`RectRoom`] is here so the mock is useful on its own.

use std::time::Duration;

/// Ranges (and optionally RSSI) for one scan.
#[derive(Debug, Clone, PartialEq)]
pub struct SourceScan {
    /// One per beam, metres; non-finite or ≤ 0 means no return (sent as 0, notes §3 field 22).
    pub ranges_m: Vec<f32>,
    /// One per beam when the source models remission.
    pub rssi: Option<Vec<u8>>,
}

/// Supplies the scan the mock sends.
pub trait ScanSource: Send + Sync + std::fmt::Debug + 'static {
    /// The scan ending `elapsed` after the device booted, for beams at `angles_rad` (robot frame,
    /// 0 = straight ahead, counter-clockwise positive).
    fn scan(&self, elapsed: Duration, angles_rad: &[f64]) -> SourceScan;
}

/// A static rectangular room around the sensor: walls at `x = -back_m / +front_m`,
/// `y = -right_m / +left_m`; beams beyond `max_range_m` get no return.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RectRoom {
    pub front_m: f64,
    pub back_m: f64,
    pub left_m: f64,
    pub right_m: f64,
    /// TiM551: 10 m (notes §3.1).
    pub max_range_m: f64,
}

impl Default for RectRoom {
    fn default() -> Self {
        Self { front_m: 4.0, back_m: 2.0, left_m: 1.5, right_m: 2.5, max_range_m: 10.0 }
    }
}

impl RectRoom {
    /// Distance from the sensor to the first wall along `angle_rad`.
    pub fn range_m(&self, angle_rad: f64) -> f64 {
        let (s, c) = angle_rad.sin_cos();
        let mut best = f64::INFINITY;
        if c > 1e-12 {
            best = best.min(self.front_m / c);
        }
        if c < -1e-12 {
            best = best.min(self.back_m / -c);
        }
        if s > 1e-12 {
            best = best.min(self.left_m / s);
        }
        if s < -1e-12 {
            best = best.min(self.right_m / -s);
        }
        best
    }
}

impl ScanSource for RectRoom {
    fn scan(&self, _elapsed: Duration, angles_rad: &[f64]) -> SourceScan {
        let ranges_m: Vec<f32> = angles_rad
            .iter()
            .map(|a| {
                let r = self.range_m(*a);
                if r <= self.max_range_m { r as f32 } else { 0.0 }
            })
            .collect();
        let rssi = Some(ranges_m.iter().map(|r| if *r > 0.0 { 200 } else { 0 }).collect());
        SourceScan { ranges_m, rssi }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn walls_are_where_the_room_says() {
        let room = RectRoom::default();
        assert!((room.range_m(0.0) - 4.0).abs() < 1e-12);
        assert!((room.range_m(std::f64::consts::FRAC_PI_2) - 1.5).abs() < 1e-12);
        assert!((room.range_m(-std::f64::consts::FRAC_PI_2) - 2.5).abs() < 1e-12);
        assert!((room.range_m(std::f64::consts::FRAC_PI_4) - 1.5 * 2f64.sqrt()).abs() < 1e-12);
    }
}
