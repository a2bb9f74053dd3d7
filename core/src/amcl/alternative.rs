//! An uncertain filter's alternative: a place that explains the scan far better than the
//! estimate, searched for on the filter's updates and checked on the scans after, before the
//! filter believes it (docs/integrity.md, "An alternative while uncertain").

use std::sync::Arc;

use super::likelihood::{FixedPoints, LikelihoodField};
use super::{Amcl, IntegrityState, Particle, integrity, refine, subsample};
use crate::se2::Se2;

/// A candidate place for an uncertain filter: `pose` when the odometry read `odom`, and the judged
/// scans in a row on which it explained the scan far better than the estimate.
#[derive(Debug, Clone, Copy)]
pub(super) struct Alternative {
    pose: Se2,
    odom: Se2,
    wins: u32,
}

/// The spread of the particles placed around a confirmed alternative, m and rad.
const ALTERNATIVE_SPREAD_M: f64 = 0.05;
const ALTERNATIVE_SPREAD_RAD: f64 = 0.02;

impl Amcl {
    /// Uncertain, and no alternative pending: look for a place that explains this scan far better
    /// than the estimate (as `reseed` does, `alternative_draws` draws); the best found is checked
    /// on the next scans ([`Self::check_alternative`]). Placing particles there at once pulled a
    /// filter that was right, its scan full of unmapped people, to a place 27 m off that fitted
    /// that one scan better (the surveyed world). The draws are few and repeated on each update
    /// while uncertain: a cluttered site is uncertain for a third of its scans (acapulco), and 1 000
    /// draws an update put its update time's P95 at 60–80 ms, against 0.8 ms.
    pub(super) fn search_alternative(&mut self, odom: Se2, points: &[[f64; 2]]) {
        let p = *self.monitor.params();
        let k = p.alternative_draws;
        if k == 0 || self.replace_need().is_none() {
            return;
        }
        let judged = subsample(points, p.max_points);
        let share = |field: &LikelihoodField, at: &Se2, origin| {
            integrity::explained_share(field, at, &judged, origin, &p).unwrap_or(0.0)
        };
        let field = Arc::clone(&self.field);
        let origin = self.sensor_origin;
        self.alternative = self
            .better_places(points, k)
            .into_iter()
            .flatten()
            .map(|pose| (share(&field, &pose, origin), pose))
            .max_by(|a, b| a.0.total_cmp(&b.0))
            .map(|(_, pose)| Alternative { pose, odom, wins: 1 });
    }

    /// The pending alternative judged on this scan (carried by the odometry, climbed to the
    /// scan): it stays while it explains [`Self::replace_need`] of the scan, and after `confirm`
    /// more scans in a row the estimate is taken to be wrong: the filter turns `Lost` and the
    /// re-seeded share of its particles are placed around the alternative.
    pub(super) fn check_alternative(&mut self, odom: Se2, points: &[[f64; 2]]) {
        let Some(alt) = self.alternative.take() else { return };
        let p = *self.monitor.params();
        if self.monitor.state() != IntegrityState::Uncertain {
            return;
        }
        let Some(need) = self.replace_need() else { return };
        let beams = FixedPoints::new(&subsample(points, self.params.max_beams.usize()));
        let pose = refine(&self.field, &beams, alt.pose * (alt.odom.inverse() * odom));
        let judged = subsample(points, p.max_points);
        let share = integrity::explained_share(&self.field, &pose, &judged, self.sensor_origin, &p);
        if share.unwrap_or(0.0) < need {
            return;
        }
        let wins = alt.wins + 1;
        if wins <= p.confirm {
            self.alternative = Some(Alternative { pose, odom, wins });
            return;
        }
        self.monitor.declare_lost();
        let n = self.particles.len();
        let k = n.min(p.reseed_max_particles);
        let w = 1.0 / n as f64;
        // The particles are where the last update left them, at its odometry: the alternative is
        // placed there too.
        let at_update = self.last_odom.map_or(pose, |u| pose * (odom.inverse() * u));
        for _ in 0..k {
            let at = self.rng.below(n);
            let q = Se2::new(
                at_update.x + self.rng.gaussian(ALTERNATIVE_SPREAD_M),
                at_update.y + self.rng.gaussian(ALTERNATIVE_SPREAD_M),
                at_update.theta + self.rng.gaussian(ALTERNATIVE_SPREAD_RAD),
            );
            if let Some(slot) = self.particles.get_mut(at) {
                *slot = Particle { pose: q, weight: w };
            }
        }
        self.renormalise();
        self.reseeds += 1;
    }
}
