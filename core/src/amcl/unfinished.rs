//! A search of the whole map that its budget stopped before it found a place explaining the scan
//! as a tracked place does, carried on over the next updates before the filter is called lost
//! (docs/integrity.md, "A search carried on").
//!
//! On a large map (an outdoor campus) a scan explained poorly asks little of a place and prunes
//! little, and the whole map's search stops at its budget (`search_budget`) long before it has
//! looked everywhere. Deciding then decides on nothing: the robot may stand at the estimate in
//! clutter the map does not hold (no place explains its scan better, and the filter is to be held)
//! or have been carried off (some place does, and the filter is lost). The search is carried on
//! instead, a budget per update, on the scan it started with; the filter is held `uncertain` while
//! it runs, and decides when it is complete, as on a search completed at once, on the places found
//! carried by the odometry to the scan then and judged on it.

use std::sync::Arc;

use super::likelihood::FixedPoints;
use super::{Amcl, IntegrityState, places, refine, rivals, subsample};
use crate::se2::Se2;

/// A search of the whole map under way, for the scan whose `beams` it searches, taken when the
/// odometry read `odom`; places found count if they explain `need` of a scan.
#[derive(Debug, Clone)]
pub(super) struct Unfinished {
    ongoing: places::Ongoing,
    beams: Vec<[f64; 2]>,
    odom: Se2,
    need: f64,
    updates: u32,
}

impl Unfinished {
    /// `ongoing`, the search of `beams` (taken at `odom`) at `need`, stopped by its first budget.
    pub(super) fn new(ongoing: places::Ongoing, beams: Vec<[f64; 2]>, odom: Se2, need: f64) -> Self {
        Unfinished { ongoing, beams, odom, need, updates: 0 }
    }
}

/// What carrying a search on decided.
pub(super) enum Carried {
    /// Still under way: the filter is held.
    Searching,
    /// Complete, or out of updates: the places found (carried to this scan, judged on it, kept if
    /// they explain it clearly better than the estimate, the best first), and whether it was
    /// complete.
    Done { found: Vec<(Se2, f64)>, complete: bool },
}

impl Amcl {
    /// The whole map's search `unfinished` carried on by one budget (`search_budget`) at this
    /// update (odometry `odom`, the scan's `points`); put back while it is under way and has
    /// updates left. Done, its places are climbed to the scan it searched, carried by the
    /// odometry to this one and judged on it; and where it stopped for good short of the whole
    /// map, the square around the anchor is searched on this scan as well
    /// ([`Amcl::with_square`]).
    pub(super) fn carry_search_on(
        &mut self,
        mut unfinished: Unfinished,
        odom: Se2,
        points: &[[f64; 2]],
    ) -> Carried {
        let p = *self.monitor.params();
        let budget = p.search_budget;
        let field = Arc::clone(&self.field);
        let search = field.place_search();
        search.carry_on(&mut unfinished.ongoing, budget);
        unfinished.updates += 1;
        let complete = unfinished.ongoing.complete();
        if !complete && unfinished.updates < p.search_carried_updates {
            self.unfinished = Some(unfinished);
            return Carried::Searching;
        }
        // Judged on this scan as places a complete search found are on the scan after theirs
        // (`Amcl::doubt_loss`): clearly better than the estimate explains it now.
        let need = self.search_need().unwrap_or(f64::INFINITY);
        let then = FixedPoints::new(&unfinished.beams);
        let now = FixedPoints::new(&subsample(points, self.params.max_beams.usize()));
        let judged = subsample(points, p.max_points);
        let mut found: Vec<(Se2, f64)> = unfinished
            .ongoing
            .places()
            .iter()
            .map(|q| rivals::Rival::found(refine(&self.field, &then, q.pose), unfinished.odom))
            .map(|place| self.carried_to(&place, odom, &now, &judged))
            .filter(|(_, share)| *share >= need)
            .collect();
        found.sort_by(|a, b| b.1.total_cmp(&a.1));
        if !complete {
            found = self.with_square(found, points, unfinished.need, Some(odom));
        }
        Carried::Done { found, complete }
    }

    /// A search under way is dropped: the filter tracks again, or stays lost (a rival won, or
    /// it was lost before the search started).
    pub(super) fn search_moot(&self, before: IntegrityState) -> bool {
        let now = self.monitor.state();
        now == IntegrityState::Tracking || (now == IntegrityState::Lost && before == IntegrityState::Lost)
    }
}
