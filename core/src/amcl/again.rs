//! The whole map searched again while the filter stays lost (`search_again_every`): the search
//! re-seeds around a place it singles out, and it verifies the estimate when the estimate is the
//! one place that explains the scan (docs/integrity.md, "Searched again while lost").

use std::sync::Arc;

use super::likelihood::FixedPoints;
use super::{Amcl, SEARCHED_PLACES, integrity, places, refine, rivals, subsample};
use crate::se2::Se2;

/// What a search made again while lost found.
#[derive(Debug, Clone, PartialEq)]
pub(super) enum Again {
    /// The estimate is the one place: the filter tracks again, nothing is re-seeded.
    Verified,
    /// Places to re-seed around: the one place the search singled out among those that explain
    /// the scan clearly better than the estimate, or none.
    Places(Vec<Se2>),
}

impl Amcl {
    /// The whole map searched for this scan (a filter still lost): first whether the estimate is
    /// the one place that explains it (`verify_margin`), then whether the search singles out a
    /// place that explains it clearly better ([`Amcl::search_need`]). Only a lone place is
    /// re-seeded around: in a building of look-alike rooms, a filter lost while the odometry
    /// failed (a real log kept out of tuning) was sent by a search made then to a look-alike room,
    /// where without it the particles it kept came back to the robot once the odometry did
    /// (docs/results.md).
    pub(super) fn search_again(&mut self, points: &[[f64; 2]]) -> Again {
        let p = *self.monitor.params();
        let reseed_bar = self.search_need();
        let estimate = self.estimate.as_ref().map(|e| e.pose);
        let verify_bar = p.tracking_ratio * p.floor;
        let verifiable = p.verify_margin > 0.0
            && !self.twins
            && self.monitor.last().is_some_and(|i| i.explained >= verify_bar - p.verify_margin);
        let bar = match (reseed_bar, verifiable) {
            (Some(r), true) => r.min(verify_bar),
            (Some(r), false) => r,
            (None, true) => verify_bar,
            (None, false) => return Again::Places(Vec::new()),
        };
        let (found, complete) = self.scored_places(points, bar, self.last_odom);
        if verifiable
            && complete
            && let Some(at) = estimate
            && let Some((own, share)) = found
                .iter()
                .filter(|(q, _)| rivals::same_place(q, &at))
                .max_by(|a, b| a.1.total_cmp(&b.1))
                .copied()
            && share >= verify_bar
            && found.iter().all(|(q, s)| rivals::same_place(q, &at) || *s < share - p.verify_margin)
        {
            // The estimate is matched to the place found at it (its optimum for this scan).
            self.move_estimate_to(&at, &own);
            let judged = subsample(points, p.max_points);
            let at_own = integrity::judge(&self.field, &own, &judged, self.sensor_origin, &p);
            self.monitor.verify(&at_own);
            return Again::Verified;
        }
        let Some(need) = reseed_bar else { return Again::Places(Vec::new()) };
        let better: Vec<Se2> =
            found.into_iter().filter(|(_, s)| *s >= need).map(|(q, _)| q).take(SEARCHED_PLACES).collect();
        Again::Places(if better.len() == 1 { better } else { Vec::new() })
    }

    /// The places the exhaustive search of the map ([`places::PlaceSearch`]) finds for this scan
    /// whose endpoints it counts as explained at `need` of them, each climbed to its optimum,
    /// with the share of the scan the integrity measure (judged as the estimate is) finds there,
    /// kept if at least `need`; the best first. And whether the search looked at the whole map
    /// (it stops at `search_budget`).
    ///
    /// Where it stopped, and with `near` (the odometry now) and an anchor
    /// ([`Amcl::near_centre`]), the square of `near_search_m` around the anchor is searched as
    /// well (a budget of its own), and its places (those not found already) join the others: on a large map
    /// (an outdoor campus) the whole map's search at the low bar of a scan explained poorly stops
    /// at its budget without having reached the robot, and a filter carried off its robot by a
    /// slip, a push or a missed turn has its robot near. Where the whole map was searched, the
    /// square adds nothing it could find.
    pub(super) fn scored_places(
        &mut self,
        points: &[[f64; 2]],
        need: f64,
        near: Option<Se2>,
    ) -> (Vec<(Se2, f64)>, bool) {
        let (found, ongoing) = self.scored_in(points, need, None);
        if ongoing.complete() {
            return (found, true);
        }
        (self.with_square(found, points, need, near), false)
    }

    /// `found` (places of a search of the whole map that stopped at its budget) and the places of
    /// the square around the anchor ([`Self::near_centre`], with `near` the odometry now) not
    /// found already, the best first.
    pub(super) fn with_square(
        &mut self,
        mut found: Vec<(Se2, f64)>,
        points: &[[f64; 2]],
        need: f64,
        near: Option<Se2>,
    ) -> Vec<(Se2, f64)> {
        if let Some(window) = near.and_then(|odom| self.near_centre(odom)) {
            let (near, _) = self.scored_in(points, need, Some(window));
            for (q, share) in near {
                if !found.iter().any(|(f, _)| rivals::same_place(f, &q)) {
                    found.push((q, share));
                }
            }
            found.sort_by(|a, b| b.1.total_cmp(&a.1));
        }
        found
    }

    /// The square the search looks in as well: `near_search_m` around the anchor (the pose of
    /// the last scan judged while tracking) carried on by the odometry to `odom`.
    fn near_centre(&self, odom: Se2) -> Option<([f64; 2], f64)> {
        let r = self.monitor.params().near_search_m;
        let (pose, at) = self.anchor?;
        let now = pose * (at.inverse() * odom);
        (r > 0.0).then_some(([now.x, now.y], r))
    }

    /// [`Self::scored_places`] within `window` (centre, half side), or the whole map; and the
    /// search, complete or stopped at its budget.
    pub(super) fn scored_in(
        &mut self,
        points: &[[f64; 2]],
        need: f64,
        window: Option<([f64; 2], f64)>,
    ) -> (Vec<(Se2, f64)>, places::Ongoing) {
        let p = *self.monitor.params();
        let field = Arc::clone(&self.field);
        let beams = subsample(points, self.params.max_beams.usize());
        let (max, apart) = (SEARCHED_PLACES * 4, places::PLACES_APART);
        let search = field.place_search();
        // The square has a budget of its own: it is searched because the whole map's ran out.
        let budget = if window.is_some() { places::SEARCH_BUDGET } else { p.search_budget };
        let mut ongoing = match window {
            Some((centre, half_side_m)) => search.start_within(&beams, need, max, apart, centre, half_side_m),
            None => search.start(&beams, need, max, apart),
        };
        search.carry_on(&mut ongoing, budget);
        let fixed = FixedPoints::new(&beams);
        let scored = self.scored(&ongoing.places(), &fixed, points, need);
        (scored, ongoing)
    }

    /// `found` (places of a scan whose beams are `beams`) climbed to their optimum for that scan,
    /// with the share of `points` (the scan) the integrity measure finds there, kept if at least
    /// `need`.
    pub(super) fn scored(
        &self,
        found: &[places::Place],
        beams: &FixedPoints,
        points: &[[f64; 2]],
        need: f64,
    ) -> Vec<(Se2, f64)> {
        let p = self.monitor.params();
        let judged = subsample(points, p.max_points);
        found
            .iter()
            .map(|q| refine(&self.field, beams, q.pose))
            .map(|pose| {
                let share = integrity::explained_share(&self.field, &pose, &judged, self.sensor_origin, p);
                (pose, share.unwrap_or(0.0))
            })
            .filter(|(_, share)| *share >= need)
            .collect()
    }
}
