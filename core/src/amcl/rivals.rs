//! Rivals to the estimate: places that explain a scan far better than the estimate, searched for
//! while the filter is uncertain or a scan explains poorly, carried beside the estimate and judged
//! against it on the scans after, before the filter believes one (docs/integrity.md, "Rivals").

use std::sync::Arc;

use super::likelihood::{FixedPoints, LikelihoodField};
use super::{Amcl, IntegrityState, Particle, integrity, refine, subsample};
use crate::se2::Se2;

/// A rival to the estimate: `pose` when the odometry read `odom`, found because it explained a
/// scan far better than the estimate (or the place a lost estimate left, `left.rs`), then judged
/// against it on every scan after: `evidence` is
/// the sum over those scans of its share less the estimate's, `judged` their number, `streak` the
/// last of them in a row on which it explained `switch_margin` more than the estimate. A filter
/// keeps up to [`RIVALS`] of them, distinct places, so that twins (places the scan cannot tell
/// apart) are carried side by side until the scans tell them apart.
#[derive(Debug, Clone, Copy)]
pub(super) struct Rival {
    pub(super) pose: Se2,
    pub(super) odom: Se2,
    pub(super) evidence: f64,
    pub(super) judged: u32,
    pub(super) streak: u32,
}

impl Rival {
    /// A rival just found at `pose` when the odometry read `odom`, judged on no scan yet.
    pub(super) fn found(pose: Se2, odom: Se2) -> Self {
        Rival { pose, odom, evidence: 0.0, judged: 0, streak: 0 }
    }
}

/// A rival this close to the estimate is the same place: the estimate went there, m and rad.
const SAME_PLACE_M: f64 = 0.5;
const SAME_PLACE_RAD: f64 = 0.175;

/// Scans a rival is judged on at most: two places that explain the scans alike for this long
/// are twins the scans cannot tell, and the filter keeps its estimate (the rival is dropped).
pub(super) const RIVAL_SCANS: u32 = 50;

/// Rivals carried at most.
const RIVALS: usize = 3;

/// Whether `a` is where `b` is: within [`SAME_PLACE_M`] and [`SAME_PLACE_RAD`].
pub(super) fn same_place(a: &Se2, b: &Se2) -> bool {
    within(a, b, SAME_PLACE_M, SAME_PLACE_RAD)
}

/// Whether `a` seen from `b` is within `m` and `rad` of it. In `b`'s frame, not the map's: the
/// map-frame difference `a · b⁻¹` also holds the turn between them about the map's origin, metres
/// far from it.
fn within(a: &Se2, b: &Se2, m: f64, rad: f64) -> bool {
    let apart = b.inverse() * *a;
    apart.translation_norm() < m && apart.theta.abs() < rad
}

/// The estimate has gone to a rival when it is this close to it, m and rad: a rival is climbed to
/// each scan, and an estimate at the same optimum stands within a few centimetres of it. One
/// farther off but at the same place (a drift, a turn the odometry missed) is left to the rival
/// to correct.
const WENT_THERE_M: f64 = 0.1;
const WENT_THERE_RAD: f64 = 0.035;

/// The spread of the particles placed around a rival that won, m and rad.
const RIVAL_SPREAD_M: f64 = 0.05;
const RIVAL_SPREAD_RAD: f64 = 0.02;

impl Amcl {
    /// Uncertain, or this scan explained poorly, and fewer than [`RIVALS`] carried: look for
    /// places that explain this scan far better than the estimate, or as a tracked place does
    /// where the estimate explains it below the uncertain bar (`rival_need`; as `reseed` does,
    /// `alternative_draws` draws); the best distinct ones join the rivals, judged on the next
    /// scans ([`Self::judge_rivals`]), and the estimate is ambiguous from now. A place found at
    /// the estimate's place ([`same_place`]: the estimate a little off) joins first: in a room
    /// whose corners look alike, with the estimate put 0.3 m off by an odometry glitch, the
    /// search finds the four corners explaining the scan fully, and three kept by share alone
    /// can be the other corners, one of which the filter then goes to. The draws are few
    /// and repeated on each such update: a cluttered site is uncertain for a third of its scans
    /// (acapulco), and 1 000 draws an update put its update time's P95 at 60–80 ms, against 0.8 ms.
    pub(super) fn search_rivals(&mut self, odom: Se2, points: &[[f64; 2]]) {
        let p = *self.monitor.params();
        let k = p.alternative_draws;
        let need = self.rival_need();
        if k == 0 || self.rivals.len() >= RIVALS || need.is_none() {
            return;
        }
        let judged = subsample(points, p.max_points);
        let share = |field: &LikelihoodField, at: &Se2, origin| {
            integrity::explained_share(field, at, &judged, origin, &p).unwrap_or(0.0)
        };
        let field = Arc::clone(&self.field);
        let origin = self.sensor_origin;
        let mut found: Vec<(f64, Se2)> = self
            .better_places(points, k, super::Stream::Search, need)
            .into_iter()
            .flatten()
            .map(|pose| (share(&field, &pose, origin), pose))
            .collect();
        found.sort_by(|a, b| b.0.total_cmp(&a.0));
        if let Some(estimate) = self.pose_at(&odom) {
            found.sort_by_key(|(_, pose)| !same_place(pose, &estimate));
        }
        for (_, pose) in found {
            if self.rivals.len() < RIVALS && !self.rivals.iter().any(|r| same_place(&r.pose, &pose)) {
                self.rivals.push(Rival::found(pose, odom));
            }
        }
        // A place that explains this scan far better: the estimate is in doubt from now.
        self.monitor.set_ambiguous(!self.rivals.is_empty());
    }

    /// Not tracking, the estimate explaining this scan between the uncertain and the tracking bar,
    /// no rival carried: look for any other place that explains the scan nearly as well
    /// (`unique_margin` less, `alternative_draws` draws of the search's stream); if there is
    /// none, the estimate is the only candidate for where the robot is, and the monitor counts
    /// the scan towards `Tracking` ([`integrity::Monitor::vouch`]). What the bar alone cannot
    /// tell: a filter that came back to the robot after a loss, in a place whose scans the map
    /// explains less well than it usually does (clutter, people), is at the only place that
    /// explains them; a filter at a twin of that place is not.
    pub(super) fn vouch_if_unique(&mut self, estimate: &Se2, points: &[[f64; 2]]) {
        let p = *self.monitor.params();
        let Some(last) = self.monitor.last() else { return };
        if p.alternative_draws == 0
            || p.unique_margin <= 0.0
            || !self.monitor.vouchable()
            || !self.rivals.is_empty()
        {
            return;
        }
        let need = last.explained - p.unique_margin;
        let away = |place: &Se2| !same_place(place, estimate);
        let elsewhere = self
            .places_explaining(points, p.alternative_draws, super::Stream::Search, need, away)
            .into_iter()
            .flatten()
            .any(|place| away(&place));
        if !elsewhere {
            self.monitor.vouch();
        }
    }

    /// Each rival judged on this scan (carried by the odometry, climbed to the scan) against the
    /// estimate, the two as hypotheses whose evidence adds up scan by scan (the sum of the
    /// rival's share less the estimate's). While none has won, the filter is not `Tracking`
    /// (the monitor is told the estimate is ambiguous). A rival is dropped when it no longer
    /// explains the scan as a tracked place does (`uncertain_ratio` of the level), when the
    /// estimate has gone there ([`WENT_THERE_M`], [`WENT_THERE_RAD`]), when the evidence is
    /// `switch_margin` against it, or after [`RIVAL_SCANS`]. One wins when it beat the estimate on each of the last `confirm` scans
    /// (explained `switch_margin` more of the scan, or, where the estimate explained the scan
    /// below the uncertain bar, explained it as a tracked place does: an estimate carried into an
    /// office still explains about 70 % of a scan, many endpoints landing near some wall at any
    /// pose, and the margin alone asked the truth for all of it), its evidence leads the
    /// runner-up rival's by `switch_margin`, and it explains this scan as well as a tracked place
    /// does (never less than a single rival needed before rivals were carried side by side: a
    /// lead summed over many scans of small differences carried filters to wrong places along a
    /// featureless corridor). The estimate is then taken to be wrong, the filter turns `Lost` and
    /// places the re-seeded share of its particles around the rival; but a winner at the
    /// estimate's place ([`same_place`]) corrects the estimate instead, the cloud moved onto it.
    /// The scan that found it does not count: a best-of-many pose fits the scan it was chosen on
    /// better than the truth does (placing particles there at once pulled a filter that was
    /// right, its scan full of unmapped people, to a place 27 m off). Where none wins but two or
    /// more have each beaten the estimate on the last `confirm` scans, explain the scan as a
    /// tracked place does and stand away from it (twins: a place and its mirror image), the
    /// filter turns `Lost`, places the particles around all of them (and around a rival at the
    /// estimate's place that beat it too: the estimate corrected is one of the twins, and the
    /// likeliest after a glitch of the odometry) and carries them on as twins: judged on their
    /// own shares while `Lost`, dropped when they explain less than a tracked place does or trail
    /// the best twin's evidence by `switch_margin`, and the estimate ambiguous (never
    /// `Tracking`) while two remain.
    pub(super) fn judge_rivals(&mut self, odom: Se2, points: &[[f64; 2]]) {
        let rivals = std::mem::take(&mut self.rivals);
        self.monitor.set_ambiguous(false);
        let p = *self.monitor.params();
        let (Some(last), Some(estimate)) = (self.monitor.last(), self.pose_at(&odom)) else { return };
        if rivals.is_empty() {
            self.twins = false;
            return;
        }
        if self.monitor.state() == IntegrityState::Lost && !self.twins {
            return;
        }
        let beams = FixedPoints::new(&subsample(points, self.params.max_beams.usize()));
        let judged_points = subsample(points, p.max_points);
        let mut kept: Vec<(Rival, f64)> = Vec::new();
        for rival in rivals {
            let (pose, share) = self.carried_to(&rival, odom, &beams, &judged_points);
            let evidence = rival.evidence + (share - last.explained);
            let judged = rival.judged + 1;
            // A scan counts towards the rival when it explains `switch_margin` more of it than the
            // estimate, or, on a scan the estimate explains below the uncertain bar, when it
            // explains the scan as a tracked place does.
            let beaten = share >= last.explained + p.switch_margin
                || (last.explained < p.uncertain_ratio * last.level
                    && share >= p.tracking_ratio * last.level);
            let streak = if beaten { rival.streak + 1 } else { 0 };
            // Twins are judged on their own shares: the estimate, lost, moves among them.
            let dropped = share < p.uncertain_ratio * last.level
                || (!self.twins && within(&pose, &estimate, WENT_THERE_M, WENT_THERE_RAD))
                || (!self.twins && evidence <= -p.switch_margin)
                || judged > RIVAL_SCANS
                || kept.iter().any(|(k, _)| same_place(&k.pose, &pose));
            if !dropped {
                kept.push((Rival { pose, odom, evidence, judged, streak }, share));
            }
        }
        kept.sort_by(|a, b| b.0.evidence.total_cmp(&a.0.evidence));
        if self.twins {
            // Lost among twins: not `tracking` while two of them still explain the scans as a
            // tracked place does and neither leads the other by `switch_margin` (the evidence
            // of each holds the same estimate's shares: their difference is theirs alone).
            let best = kept.first().map_or(0.0, |(r, _)| r.evidence);
            kept.retain(|(r, _)| best - r.evidence < p.switch_margin);
            if kept.len() >= 2 {
                self.rivals = kept.into_iter().map(|(r, _)| r).collect();
                self.monitor.set_ambiguous(true);
            } else {
                self.twins = false;
            }
            return;
        }
        let runner_up = kept.get(1).map_or(0.0, |(r, _)| r.evidence.max(0.0));
        let winner = kept.first().filter(|(lead, share)| {
            lead.streak >= p.confirm
                && lead.evidence - runner_up >= p.switch_margin
                && *share >= p.tracking_ratio * last.level
        });
        // Those that beat the estimate, apart from it and at its place.
        let (beaters, beaten_here): (Vec<Rival>, Vec<Rival>) = kept
            .iter()
            .filter(|(r, share)| r.streak >= p.confirm && *share >= p.tracking_ratio * last.level)
            .map(|(r, _)| *r)
            .partition(|r| !same_place(&r.pose, &estimate));
        let targets: Vec<Se2> = match winner {
            Some(&(Rival { pose, .. }, _)) => {
                // A rival at the estimate's place corrects it: the cloud is moved onto it, as a
                // match to the map moves it, and the estimate was not lost.
                if same_place(&pose, &estimate) {
                    self.move_pose_at(odom, pose);
                    return;
                }
                self.monitor.declare_lost();
                vec![pose]
            }
            // Two or more beat the estimate from elsewhere and none leads: it is wrong whichever
            // is right, or a little off if one that beat it stands at its place.
            None if beaters.len() >= 2 => {
                let beaters: Vec<Rival> = beaters.into_iter().chain(beaten_here).collect();
                let poses = beaters.iter().map(|r| r.pose).collect();
                self.monitor.declare_lost();
                self.rivals = beaters;
                self.twins = true;
                self.monitor.set_ambiguous(true);
                poses
            }
            // None has won: the estimate is in doubt while a rival has explained more of the
            // scans since it was found, or beat it on this one, or the estimate explains this
            // scan below the tracking bar. A rival that only matches an estimate explaining the
            // scans as a tracked place does (the other corner of a room, found on the one scan
            // the estimate explained poorly) is carried on, but leaves the estimate unambiguous.
            None => {
                let doubted = last.explained < p.tracking_ratio * last.level
                    || kept.iter().any(|(r, _)| r.evidence > 0.0 || r.streak > 0);
                self.rivals = kept.into_iter().map(|(r, _)| r).collect();
                self.monitor.set_ambiguous(doubted && !self.rivals.is_empty());
                return;
            }
        };
        self.place_around(&targets, odom);
    }

    /// `rival` carried by the odometry to `odom`, climbed to this scan (`beams`), and the share of
    /// the scan (`judged`, the integrity measure's points) explained there.
    pub(super) fn carried_to(
        &self,
        rival: &Rival,
        odom: Se2,
        beams: &FixedPoints,
        judged: &[[f64; 2]],
    ) -> (Se2, f64) {
        let p = self.monitor.params();
        let pose = refine(&self.field, beams, rival.pose * (rival.odom.inverse() * odom));
        let share =
            integrity::explained_share(&self.field, &pose, judged, self.sensor_origin, p).unwrap_or(0.0);
        (pose, share)
    }

    /// Up to `reseed_max_particles` particles, drawn at random, placed around `targets` (poses at
    /// odometry `odom`), in turn: a rival that won, twins, the place a lost estimate left.
    pub(super) fn place_around(&mut self, targets: &[Se2], odom: Se2) {
        let n = self.particles.len();
        if targets.is_empty() || n == 0 {
            return;
        }
        let k = n.min(self.monitor.params().reseed_max_particles);
        let w = 1.0 / n as f64;
        for i in 0..k {
            // The particles are where the last update left them, at its odometry: the target is
            // placed there too.
            let pose = targets[i % targets.len()];
            let at_update = self.last_odom.map_or(pose, |u| pose * (odom.inverse() * u));
            let at = self.rng.below(n);
            let q = Se2::new(
                at_update.x + self.rng.gaussian(RIVAL_SPREAD_M),
                at_update.y + self.rng.gaussian(RIVAL_SPREAD_M),
                at_update.theta + self.rng.gaussian(RIVAL_SPREAD_RAD),
            );
            if let Some(slot) = self.particles.get_mut(at) {
                *slot = Particle { pose: q, weight: w };
            }
        }
        self.renormalise();
        self.reseeds += 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two poses are compared in their own frame, not the map's: far from the map's origin a turn
    /// of 3° is still the same place (composed the other way round, the 3° about the origin moved
    /// it 12 m), and 0.6 m away is another, whatever the heading.
    #[test]
    fn places_are_compared_where_they_stand() {
        for at in [[0.0, 0.0], [150.0, -200.0], [-220.0, 30.0]] {
            let a = Se2::new(at[0], at[1], 1.0);
            let turned = Se2::new(at[0], at[1], 1.0 + 3f64.to_radians());
            assert!(same_place(&a, &turned) && same_place(&turned, &a), "{at:?}");
            let moved = Se2::new(at[0] + 0.36, at[1] - 0.48, 1.0);
            assert!(!same_place(&a, &moved) && !same_place(&moved, &a), "{at:?}");
            let near = Se2::new(at[0] + 0.3, at[1], 1.0 + 5f64.to_radians());
            assert!(same_place(&a, &near) && same_place(&near, &a), "{at:?}");
            let facing = Se2::new(at[0], at[1], 1.0 + 12f64.to_radians());
            assert!(!same_place(&a, &facing), "{at:?}");
        }
    }
}
