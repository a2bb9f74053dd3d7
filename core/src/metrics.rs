//! The paper's error statistics (§5, Eq. 21–22; docs/method.md §10): per axis and in 2D, MAE, RMSE,
//! median, P95 and max over all samples, and trial-level RMSE as mean ± sample standard deviation.

use serde::Serialize;

/// Statistics of absolute errors.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ErrorStats {
    pub count: usize,
    pub mae: f64,
    pub rmse: f64,
    pub median: f64,
    /// 95th percentile, linear interpolation between order statistics.
    pub p95: f64,
    pub max: f64,
}

/// The `q` quantile (0..=1) of sorted values, interpolating linearly between neighbours.
fn quantile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let pos = q * (sorted.len() - 1) as f64;
    let (lo, hi) = (pos.floor() as usize, pos.ceil() as usize);
    sorted[lo] + (sorted[hi] - sorted[lo]) * (pos - lo as f64)
}

impl ErrorStats {
    /// Of the absolute values of `errors` (NaN entries are skipped). `None` for no samples.
    #[must_use]
    pub fn of(errors: &[f64]) -> Option<Self> {
        let mut a: Vec<f64> = errors.iter().filter(|e| !e.is_nan()).map(|e| e.abs()).collect();
        if a.is_empty() {
            return None;
        }
        a.sort_by(f64::total_cmp);
        let n = a.len() as f64;
        Some(ErrorStats {
            count: a.len(),
            mae: a.iter().sum::<f64>() / n,
            rmse: (a.iter().map(|e| e * e).sum::<f64>() / n).sqrt(),
            median: quantile(&a, 0.5),
            p95: quantile(&a, 0.95),
            max: a[a.len() - 1],
        })
    }
}

/// Errors of one sample: `e_x`, `e_y` and `e_2D = hypot(e_x, e_y)`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Sample {
    pub e_x: f64,
    pub e_y: f64,
}

impl Sample {
    #[must_use]
    pub fn e_2d(&self) -> f64 {
        self.e_x.hypot(self.e_y)
    }
}

/// X, Y and 2D statistics of a set of samples (the layout of Tables 8 and 13–14).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct AxisStats {
    pub x: ErrorStats,
    pub y: ErrorStats,
    pub d2: ErrorStats,
}

impl AxisStats {
    #[must_use]
    pub fn of(samples: &[Sample]) -> Option<Self> {
        Some(AxisStats {
            x: ErrorStats::of(&samples.iter().map(|s| s.e_x).collect::<Vec<_>>())?,
            y: ErrorStats::of(&samples.iter().map(|s| s.e_y).collect::<Vec<_>>())?,
            d2: ErrorStats::of(&samples.iter().map(Sample::e_2d).collect::<Vec<_>>())?,
        })
    }
}

/// Mean and sample standard deviation (n − 1) of per-trial values (Tables 15–16).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct MeanSd {
    pub mean: f64,
    pub sd: f64,
    pub n: usize,
}

impl MeanSd {
    #[must_use]
    pub fn of(values: &[f64]) -> Option<Self> {
        let n = values.len();
        if n == 0 {
            return None;
        }
        let mean = values.iter().sum::<f64>() / n as f64;
        let sd = if n > 1 {
            (values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1) as f64).sqrt()
        } else {
            0.0
        };
        Some(MeanSd { mean, sd, n })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn by_hand() {
        let s = ErrorStats::of(&[3.0, -1.0, 2.0, -4.0, f64::NAN]).unwrap();
        assert_eq!(s.count, 4);
        assert_eq!(s.mae, 2.5);
        assert!((s.rmse - (30.0f64 / 4.0).sqrt()).abs() < 1e-12);
        assert_eq!(s.median, 2.5, "between 2 and 3");
        // P95 of [1, 2, 3, 4]: position 0.95·3 = 2.85 → 3 + 0.85·1.
        assert!((s.p95 - 3.85).abs() < 1e-12);
        assert_eq!(s.max, 4.0);
        assert_eq!(ErrorStats::of(&[]), None);
        let m = MeanSd::of(&[0.2, 0.4]).unwrap();
        assert!((m.mean - 0.3).abs() < 1e-12 && (m.sd - 0.02f64.sqrt()).abs() < 1e-12);
        let a = AxisStats::of(&[Sample { e_x: 3.0, e_y: 4.0 }, Sample { e_x: 0.0, e_y: 0.0 }]).unwrap();
        assert_eq!(a.d2.max, 5.0);
        assert_eq!(a.d2.mae, 2.5);
    }
}
