//! The place a lost filter's estimate left: when re-seeded particles take the estimate of a
//! lost filter elsewhere, the pose it left is carried on by the odometry and judged against the
//! new estimate on the scans after, and the particles go back there if it explains them clearly
//! better (docs/integrity.md, "The place left").
//!
//! A filter can be called lost on the robot (a stretch of scans its map explains poorly: parked
//! cars, people, a region mapped from elsewhere). Each re-seeded particle is the best of many
//! poses for one scan, and on such a scan a wrong place that happens to explain it beats the
//! truth, which explains little: the estimate followed such particles and every particle at the
//! truth was resampled away. The scans after tell the two apart at once (the wrong place explains
//! almost none of them), but nothing else looked back: a real outdoor log kept out of tuning
//! drove 32 m off for 37 scans this way, its estimate explaining under a tenth of each scan where
//! the place it left explained half or more.

use super::likelihood::FixedPoints;
use super::rivals::{RIVAL_SCANS, Rival, same_place};
use super::{Amcl, IntegrityState, subsample};
use crate::se2::Se2;

impl Amcl {
    /// Called after an update's estimate is taken, with the estimate before it carried by the
    /// odometry to this update (`carried`) and the state before it: a lost filter whose estimate
    /// went to another place (re-seeded particles won the weighting) keeps the place it left,
    /// unless it carries one already or is lost among twins (`rivals.rs` judges those).
    pub(super) fn remember_left(&mut self, carried: Option<Se2>, before: Option<IntegrityState>, odom: Se2) {
        if !self.monitor.params().return_to_left
            || self.left.is_some()
            || self.twins
            || before != Some(IntegrityState::Lost)
        {
            return;
        }
        let (Some(from), Some(now)) = (carried, self.estimate.as_ref().map(|e| e.pose)) else { return };
        if !same_place(&from, &now) {
            self.left = Some(Rival::found(from, odom));
        }
    }

    /// The place left judged on this scan (carried by the odometry, climbed to the scan) against
    /// the estimate, as a rival is (`rivals.rs`): dropped once the filter tracks, once the
    /// estimate is back there, when its evidence is `switch_margin` against it, or after
    /// [`RIVAL_SCANS`]. It wins when it explained `switch_margin` more of each of the last
    /// `confirm` scans than the estimate, and at least the lost bar: the particles are then placed
    /// around it as around a rival that won, and the filter, still lost, is judged on from there.
    pub(super) fn judge_left(&mut self, odom: Se2, points: &[[f64; 2]]) {
        let Some(left) = self.left.take() else { return };
        let p = *self.monitor.params();
        let (Some(last), Some(estimate)) = (self.monitor.last(), self.pose_at(&odom)) else { return };
        if self.twins || self.monitor.state() == IntegrityState::Tracking {
            return;
        }
        let beams = FixedPoints::new(&subsample(points, self.params.max_beams.usize()));
        let (pose, share) = self.carried_to(&left, odom, &beams, &subsample(points, p.max_points));
        let evidence = left.evidence + (share - last.explained);
        let judged = left.judged + 1;
        // The bar a place the search of the map finds must reach (`Amcl::search_need`).
        let beaten = self.search_need().is_some_and(|need| share >= need);
        let streak = if beaten { left.streak + 1 } else { 0 };
        if evidence <= -p.switch_margin || judged > RIVAL_SCANS || same_place(&pose, &estimate) {
            return;
        }
        if streak >= p.confirm {
            self.place_around(&[pose], odom);
            return;
        }
        self.left = Some(Rival { pose, odom, evidence, judged, streak });
    }
}
