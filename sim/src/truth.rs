//! The world's true poses over time, on the fleet clock, for scoring estimates at their stamps.

use std::collections::VecDeque;
use std::sync::{Arc, Mutex, PoisonError};

use amr_core::se2::Se2;

/// Seconds of history kept.
const KEEP_S: f64 = 10.0;

/// True poses of every robot, sampled at each world step.
#[derive(Debug, Clone, Default)]
pub struct TruthLog(Arc<Mutex<History>>);

/// `(time, every robot's pose)`, oldest first.
type History = VecDeque<(f64, Vec<Se2>)>;

impl TruthLog {
    pub fn push(&self, t_s: f64, poses: Vec<Se2>) {
        let mut q = self.0.lock().unwrap_or_else(PoisonError::into_inner);
        q.push_back((t_s, poses));
        while q.front().is_some_and(|(t, _)| t_s - t > KEEP_S) {
            q.pop_front();
        }
    }

    /// The poses at `t_s`, interpolated between the two samples around it; `None` outside the
    /// history.
    #[must_use]
    pub fn at(&self, t_s: f64) -> Option<Vec<Se2>> {
        let q = self.0.lock().unwrap_or_else(PoisonError::into_inner);
        let i = q.iter().position(|(t, _)| *t >= t_s)?;
        if i == 0 {
            return (q[0].0 == t_s).then(|| q[0].1.clone());
        }
        let ((ta, a), (tb, b)) = (&q[i - 1], &q[i]);
        let f = if tb > ta { (t_s - ta) / (tb - ta) } else { 1.0 };
        Some(
            a.iter()
                .zip(b)
                .map(|(pa, pb)| {
                    let d = pa.inverse() * *pb;
                    *pa * Se2::new(d.x * f, d.y * f, d.theta * f)
                })
                .collect(),
        )
    }

    /// The latest poses.
    #[must_use]
    pub fn latest(&self) -> Option<(f64, Vec<Se2>)> {
        self.0.lock().unwrap_or_else(PoisonError::into_inner).back().cloned()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn interpolates_between_samples_and_refuses_outside() {
        let log = TruthLog::default();
        log.push(1.0, vec![Se2::new(0.0, 0.0, 0.0)]);
        log.push(1.1, vec![Se2::new(0.01, 0.0, 0.0)]);
        let mid = log.at(1.05).unwrap_or_default();
        assert!(mid[0].approx_eq(&Se2::new(0.005, 0.0, 0.0), 1e-12, 1e-12));
        assert!(log.at(0.9).is_none());
        assert!(log.at(1.2).is_none());
        assert_eq!(log.at(1.0).map(|p| p[0]), Some(Se2::new(0.0, 0.0, 0.0)));
    }
}
