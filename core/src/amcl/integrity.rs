//! Localisation integrity: whether the estimate is right, judged from the scan and the map, not
//! from the particles' spread. A filter carried into the wrong place (a kidnapping, a missed turn,
//! a start from a wrong pose) can be as tight as a tracking one; what changes is that the map no
//! longer explains the scan at the estimate.
//!
//! The measure is the share of the scan's endpoints that the map explains at the estimate
//! ([`explained_share`]). It is compared with what this sensor explains where it is tracked:
//! clutter that the map does not hold (people, moved furniture) lowers the share on a real robot
//! in a way a threshold fitted to a perfect simulation would call lost. That level is learned while
//! the filter is not lost (a slow running mean), and learned by range band
//! ([`RANGE_BANDS_M`]): a far endpoint is explained less often than a near one (a small heading
//! error moves it further, it grazes surfaces, it meets what the map left out), so a scan of the
//! open street expects less than one of a corridor. A scan's level is what the bands of its
//! endpoints explain, weighted by their counts, never below `floor` nor above 1; the state follows
//! the share relative to it, with hysteresis:
//!
//! - any state → `Lost` after `confirm` updates in a row below `lost_ratio` × level (a robot
//!   carried off: the map explains little of the scan at once), unless the filter
//!   (`lost_needs_place`) finds no place of the map that explains the scan better, or only
//!   places the next scan does not confirm, and holds it `Uncertain` ([`Monitor::hold`]);
//! - `Tracking` → `Uncertain` when the median of the last `window` updates' shares, each relative
//!   to its scan's level, falls below `uncertain_ratio` (a filter that settled on a plausible
//!   wrong place, say a corridor a few metres off, explains most of the scan, but persistently
//!   less than where it is right; a scan or two full of people do not move the median);
//! - `Uncertain`/`Lost` → `Tracking` after `recover` updates in a row at or above
//!   `tracking_ratio` × level, or when the median of the `window` updates since the state last
//!   changed is at that bar (a filter back at the robot where people or clutter take a scan or
//!   two below the bar now and then: the run alone held it `lost` for 26 scans, within 0.2 m
//!   of the reference, on a development log);
//! - `Lost` also when the filter found a place that explains the scan far better than the
//!   estimate ([`Monitor::declare_lost`]).
//!
//! (An "update" here is one judged scan: the filter judges every scan, between its own updates
//! too.) The filter acts on the state ([`super::Amcl`]): while `Uncertain` or `Lost` it re-seeds
//! part of its particles from the scan.

use serde::{Deserialize, Serialize};

use super::likelihood::{FixedPoints, LikelihoodField};
use crate::se2::Se2;

/// What the filter believes of its own estimate.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum IntegrityState {
    /// The map explains the scan at the estimate as well as it does where the sensor is tracked.
    #[default]
    Tracking,
    /// It explains clearly less: the estimate may be wrong (or the scene is not the map's).
    Uncertain,
    /// It explains so little that the estimate is taken to be wrong: the filter re-localises.
    Lost,
}

impl IntegrityState {
    #[must_use]
    pub fn as_str(self) -> &'static str {
        match self {
            IntegrityState::Tracking => "tracking",
            IntegrityState::Uncertain => "uncertain",
            IntegrityState::Lost => "lost",
        }
    }
}

impl std::fmt::Display for IntegrityState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// The integrity of one estimate: the state, and the numbers it was judged by.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Integrity {
    pub state: IntegrityState,
    /// Share of the scan's endpoints explained by the map at the estimate (0..=1).
    pub explained: f64,
    /// The share this sensor explains where it is tracked, for this scan's ranges (the learned
    /// level by range band, [`Monitor::expected`]).
    pub level: f64,
    /// Another place explains the scans about as well as the estimate, or better, and the scans
    /// have not yet told them apart (the filter carries it as a rival): the state is not
    /// `Tracking` however much of the scan the estimate explains.
    #[serde(default)]
    pub ambiguous: bool,
}

/// Settings of the integrity monitor (`[integrity]` in `amcl.toml`).
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct IntegrityParams {
    /// Off, no estimate is ever judged (`Uncertain` throughout: a server never drives on it) and
    /// nothing is re-seeded; for measuring what the monitor costs (`amr bench amcl`).
    pub enabled: bool,
    /// An endpoint closer than this to a mapped surface is explained, m.
    pub hit_m: f64,
    /// A beam that passes a mapped surface more than this before its endpoint went through a
    /// wall: not explained, m.
    pub through_m: f64,
    /// Endpoints looked at per update, evenly spread over the scan (at most).
    pub max_points: usize,
    /// A scan with fewer valid endpoints is not judged (the state stays as it was): a robot
    /// facing open space sees one or two returns, and their share says nothing.
    pub min_points: usize,
    /// A scan's level never falls below this (a filter that starts lost must not learn a low
    /// level), share; above 0 (the level divides the scan's share).
    pub floor: f64,
    /// Where the level of every range band starts, share.
    pub initial_level: f64,
    /// Weight of each update in the level's running mean (after the first `1 / level_alpha`
    /// updates, which it averages alike); a range band holding fewer than ten of the update's
    /// endpoints learns in proportion to them.
    pub level_alpha: f64,
    /// Updates whose median share (each relative to its scan's level) `uncertain_ratio` is
    /// judged on.
    pub window: usize,
    pub uncertain_ratio: f64,
    pub lost_ratio: f64,
    pub tracking_ratio: f64,
    /// Updates in a row that a worse state needs.
    pub confirm: u32,
    /// Updates in a row that `Tracking` needs again.
    pub recover: u32,
    /// While `Lost`, the share of the particles re-seeded at each update from the scan.
    pub reseed_share: f64,
    /// While `Uncertain` (or on a scan explained poorly) and carrying fewer rivals than it keeps:
    /// draws per filter update (each the best of `reseed_candidates`) looking for places that
    /// explain the scan far better than the estimate (rivals, judged on the next scans). 0: no
    /// search.
    pub alternative_draws: usize,
    /// On turning `Lost`, half the re-seeded particles go around the places an exhaustive search
    /// of the whole map finds for the scan ([`super::places::PlaceSearch`]), the other half to
    /// uniform draws; off, all of them to uniform draws, which find the robot's basin with a
    /// chance that falls with the map's area.
    pub place_search: bool,
    /// While still `lost` (with `place_search`), every this many lost updates the whole map is
    /// searched again with that update's scan, and half the particles re-seeded then go around
    /// the place found if the search singles one out (two or more: none, see `Amcl::reseed`):
    /// the scan that turned the filter lost may be one the robot's place explains poorly
    /// (clutter, a half view), and uniform draws rarely reach a place on a large map. 0: searched
    /// only on turning lost.
    pub search_again_every: u32,
    /// The search of the whole map (`place_search`) counts at most this many squares: it bounds
    /// what the update that searches costs (36-512 ms for the whole search on the real logs'
    /// maps, docs/results.md). A search stopped by it returns what it found so far.
    pub search_budget: u64,
    /// Where the search of the whole map made on turning lost stops at `search_budget` having
    /// found no place that explains the scan clearly better than the estimate (not even in the
    /// square of `near_search_m`), it is carried on, one budget per update, over at most this many
    /// updates after it, on the scan it started with, and the filter is held `uncertain` until it
    /// is complete; then it decides as a complete search does (`amcl/unfinished.rs`). 0 (the
    /// default): it decides at once, on the places found so far (none), and the filter turns
    /// lost. Measured on the two large real logs kept out of tuning (docs/results.md, "A search
    /// carried on"): at 4, far fewer false alarms outdoors, more scans off reported `tracking`
    /// along a long corridor.
    pub search_carried_updates: u32,
    /// Where the search of the whole map stops at `search_budget` (a large map, a scan explained
    /// so poorly that the bar is low and little is pruned), the square within this distance (m,
    /// along each axis of the map) of the last pose the filter held while tracking, carried on by
    /// the odometry since, is searched as well, with a budget of its own
    /// (`places::SEARCH_BUDGET`), and its places join those found: a robot that slipped, was
    /// pushed or was carried a few metres is near where it was believed.
    /// 0: not searched.
    pub near_search_m: f64,
    /// The search made again while lost also checks the estimate: if the estimate is among the
    /// places it finds, explains the scan at least as a tracked place does at the lowest level
    /// (`tracking_ratio` × `floor`), and no place elsewhere explains it within this share of
    /// what the estimate does, the whole map holds no other answer and the filter is `Tracking`
    /// again ([`Monitor::verify`]). 0 (the default): the estimate is never verified so, only by
    /// its share. Measured in docs/results.md: faster returns to `Tracking` indoors; outdoors,
    /// where the right place often explains far less than the level, a verified filter turns
    /// lost again scans later, and each turn re-seeds and searches (more false alarms, larger
    /// errors, slower updates).
    pub verify_margin: f64,
    /// Uniform candidate poses per re-seeded particle; the best-fitting is kept.
    pub reseed_candidates: usize,
    /// At most this many particles are re-seeded in one update: bounds what an update costs
    /// while lost (each costs `reseed_candidates` likelihood evaluations).
    pub reseed_max_particles: usize,
    /// A re-seeded pose must explain this much more of the scan than the estimate does, share.
    pub switch_margin: f64,
    /// Not tracking, and the estimate between the uncertain and the tracking bar: if no other
    /// place explains the scan within this share of what the estimate explains (a search of
    /// `alternative_draws` draws), the scan counts towards `Tracking` as one above the bar would.
    /// 0 (the default): no such search, `Tracking` needs the bar. Measured in docs/results.md:
    /// faster returns to `Tracking` indoors, more false alarms on an outdoor log.
    pub unique_margin: f64,
    /// While `lost`, when re-seeded particles take the estimate to another place, the place it
    /// left is carried on by the odometry and judged against the new estimate: if it explains
    /// `switch_margin` more of each of `confirm` scans in a row (and at least the lost bar), the
    /// particles go back there (`left.rs`). Off: the place left is forgotten.
    pub return_to_left: bool,
    /// A filter turns `lost` on its shares only when the whole map holds a place that explains
    /// the scan clearly better than the estimate (the search made on turning lost finds one at
    /// the bar its re-seeding uses); when a search that covered the whole map finds none, the
    /// scan is one the map explains poorly anywhere (clutter, people, a region mapped from
    /// elsewhere), and the filter is held `uncertain` ([`Monitor::hold`]) for one judged scan, then
    /// searched again if its scans are still below the lost bar; each hold in a row lasts twice as
    /// long as the one before, up to 4 scans. Places found that explain the scan less than a
    /// tracked place does hold it too, and are judged on the next scan: one that explains that
    /// scan clearly better than the estimate as well turns it lost. Off: the shares alone turn it
    /// lost. Measured in docs/results.md ("Lost needs a better place"): on a cluttered log kept
    /// out of tuning, scans on the robot reported `lost` 613 → 43 and false alarms 24 → 4; the
    /// development logs' kidnappings are found as before.
    pub lost_needs_place: bool,
}

impl Default for IntegrityParams {
    fn default() -> Self {
        IntegrityParams {
            enabled: true,
            hit_m: 0.15,
            through_m: 0.3,
            max_points: 180,
            min_points: 30,
            floor: 0.6,
            initial_level: 0.75,
            level_alpha: 0.005,
            window: 5,
            uncertain_ratio: 0.88,
            lost_ratio: 0.6,
            tracking_ratio: 0.92,
            confirm: 2,
            recover: 3,
            reseed_share: 0.5,
            alternative_draws: 100,
            place_search: true,
            search_again_every: 5,
            search_budget: super::places::SEARCH_BUDGET,
            search_carried_updates: 0,
            near_search_m: 8.0,
            verify_margin: 0.0,
            reseed_candidates: 200,
            reseed_max_particles: 500,
            switch_margin: 0.3,
            unique_margin: 0.0,
            return_to_left: true,
            lost_needs_place: true,
        }
    }
}

impl IntegrityParams {
    /// Why these settings cannot work, if they cannot.
    pub fn check(&self) -> Result<(), String> {
        let share = |v: f64| v.is_finite() && (0.0..=1.0).contains(&v);
        if !(self.hit_m.is_finite() && self.hit_m > 0.0) {
            return Err(format!("hit_m must be > 0 (got {})", self.hit_m));
        }
        if !(self.through_m.is_finite() && self.through_m > 0.0) {
            return Err(format!("through_m must be > 0 (got {})", self.through_m));
        }
        if self.min_points < 10 || self.max_points < self.min_points {
            return Err(format!(
                "need 10 <= min_points <= max_points (got {} and {})",
                self.min_points, self.max_points
            ));
        }
        // The level is a divisor ([`Monitor::observe`]): never below `floor`, which must be
        // above 0.
        if !(self.floor.is_finite() && self.floor > 0.0 && self.floor <= 1.0) {
            return Err(format!("floor must be within 0 < floor <= 1 (got {})", self.floor));
        }
        for (name, v) in [
            ("initial_level", self.initial_level),
            ("level_alpha", self.level_alpha),
            ("reseed_share", self.reseed_share),
            ("switch_margin", self.switch_margin),
            ("unique_margin", self.unique_margin),
            ("verify_margin", self.verify_margin),
        ] {
            if !share(v) {
                return Err(format!("{name} must be within 0..=1 (got {v})"));
            }
        }
        if self.search_budget == 0 {
            return Err("search_budget must be > 0".to_owned());
        }
        if !(self.near_search_m.is_finite() && self.near_search_m >= 0.0) {
            return Err(format!("near_search_m must be >= 0 (got {})", self.near_search_m));
        }
        if !(self.lost_ratio > 0.0
            && self.lost_ratio < self.uncertain_ratio
            && self.uncertain_ratio < self.tracking_ratio
            && self.tracking_ratio <= 1.0)
        {
            return Err(format!(
                "need 0 < lost_ratio < uncertain_ratio < tracking_ratio <= 1 (got {}, {}, {})",
                self.lost_ratio, self.uncertain_ratio, self.tracking_ratio
            ));
        }
        if !(1..=50).contains(&self.window) {
            return Err(format!("window must be within 1..=50 (got {})", self.window));
        }
        if self.confirm == 0 || self.recover == 0 {
            return Err("confirm and recover must be at least 1".to_owned());
        }
        if self.reseed_candidates == 0 || self.reseed_max_particles == 0 {
            return Err("reseed_candidates and reseed_max_particles must be at least 1".to_owned());
        }
        Ok(())
    }
}

/// The ranges from the sensor that band a scan's endpoints for the level (m): a band holds the
/// endpoints from one bound to the next, the last everything beyond 40 m.
pub const RANGE_BANDS_M: [f64; 5] = [2.0, 5.0, 10.0, 20.0, 40.0];
/// Range bands ([`RANGE_BANDS_M`]).
pub const BANDS: usize = RANGE_BANDS_M.len() + 1;
/// A band holding this many of a judged scan's endpoints learns from it with the update's whole
/// weight (`level_alpha`); one holding fewer, in proportion.
const BAND_FULL_POINTS: f64 = 10.0;
/// What a band's level is drawn to the level of whole scans by, in endpoints
/// ([`Monitor::expected`]).
pub const BAND_PRIOR_POINTS: f64 = 50.0;

/// Endpoints of a scan by range band ([`RANGE_BANDS_M`]), and how many of them the map explains at
/// a pose.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Judged {
    pub points: [u32; BANDS],
    pub explained: [u32; BANDS],
}

impl Judged {
    /// A scan of `points` endpoints in one band (the nearest), `explained` of them explained.
    #[must_use]
    pub fn in_one_band(points: u32, explained: u32) -> Self {
        let mut j = Judged::default();
        j.points[0] = points;
        j.explained[0] = explained.min(points);
        j
    }

    #[must_use]
    pub fn total(&self) -> u32 {
        self.points.iter().sum()
    }

    /// The share explained; `None` without points.
    #[must_use]
    pub fn share(&self) -> Option<f64> {
        let n = self.total();
        (n > 0).then(|| f64::from(self.explained.iter().sum::<u32>()) / f64::from(n))
    }
}

/// The range band of an endpoint `end` seen from the sensor at `origin` (base frame; the base's
/// origin when not known).
#[must_use]
pub fn band_of(end: [f64; 2], origin: Option<[f64; 2]>) -> usize {
    let o = origin.unwrap_or([0.0, 0.0]);
    let r = (end[0] - o[0]).hypot(end[1] - o[1]);
    RANGE_BANDS_M.iter().take_while(|&&b| r >= b).count()
}

/// How many of `points` (base frame) fall in each range band.
#[must_use]
pub fn bands(points: &[[f64; 2]], origin: Option<[f64; 2]>) -> [u32; BANDS] {
    let mut out = [0u32; BANDS];
    for &end in points {
        if let Some(c) = out.get_mut(band_of(end, origin)) {
            *c += 1;
        }
    }
    out
}

/// The share of `points` (base frame, seen from `pose`) that the map explains: the endpoint lands
/// within `hit_m` of a mapped surface and, when the sensor's position `origin` (base frame) is
/// known, the beam did not pass through a mapped surface more than `through_m` before its
/// endpoint. The second test is what tells a corridor's right place from one a few metres along
/// it: there the endpoints still land on the walls, but the beams along the corridor reach
/// through its end wall (or stop short of it). `None` without points.
#[must_use]
pub fn explained_share(
    field: &LikelihoodField,
    pose: &Se2,
    points: &[[f64; 2]],
    origin: Option<[f64; 2]>,
    p: &IntegrityParams,
) -> Option<f64> {
    judge(field, pose, points, origin, p).share()
}

/// [`explained_share`]'s count, by range band.
#[must_use]
pub fn judge(
    field: &LikelihoodField,
    pose: &Se2,
    points: &[[f64; 2]],
    origin: Option<[f64; 2]>,
    p: &IntegrityParams,
) -> Judged {
    let mut out = Judged::default();
    if points.is_empty() {
        return out;
    }
    let near = field.quantum_of(p.hit_m);
    let mut q = vec![0u8; points.len()];
    field.quantised_distances(pose, &FixedPoints::new(points), &mut q);
    for (&d, &end) in q.iter().zip(points) {
        let band = band_of(end, origin);
        let hit = u16::from(d) < near
            && origin.is_none_or(|o| !field.ray_crosses_surface(pose, o, end, p.through_m));
        if let (Some(n), Some(e)) = (out.points.get_mut(band), out.explained.get_mut(band)) {
            *n += 1;
            *e += u32::from(hit);
        }
    }
    out
}

/// The monitor: the learned level and the hysteresis.
#[derive(Debug, Clone)]
pub struct Monitor {
    params: IntegrityParams,
    state: IntegrityState,
    /// The learned level of each range band.
    levels: [f64; BANDS],
    /// The level learned from whole scans, whatever their ranges: what a band that has learned
    /// little is drawn to ([`Monitor::expected`]).
    overall: f64,
    /// Updates `overall` has learned from.
    updates: u64,
    /// The last judged scan's level ([`Monitor::expected`]).
    level: f64,
    /// The last `window` shares relative to their scan's level.
    recent: std::collections::VecDeque<f64>,
    /// Endpoints each band's level has learned from.
    learned: [f64; BANDS],
    below_uncertain: u32,
    below_lost: u32,
    above_tracking: u32,
    /// The last judgement fell between the uncertain and the tracking bar while not tracking:
    /// the run of good updates before it, which [`Monitor::vouch`] may carry on.
    vouchable: Option<u32>,
    /// Another place explains the scans about as well as the estimate (one of `Amcl`'s rivals):
    /// not `Tracking` until the scans tell them apart.
    ambiguous: bool,
    last: Option<Integrity>,
    /// Judged scans for which shares below the lost bar do not turn the filter lost
    /// ([`Monitor::hold`]).
    held: u32,
}

impl Monitor {
    #[must_use]
    pub fn new(params: IntegrityParams) -> Self {
        Monitor {
            params,
            state: IntegrityState::Tracking,
            levels: [params.initial_level; BANDS],
            overall: params.initial_level,
            updates: 0,
            level: params.initial_level.max(params.floor),
            recent: std::collections::VecDeque::new(),
            learned: [0.0; BANDS],
            below_uncertain: 0,
            below_lost: 0,
            above_tracking: 0,
            vouchable: None,
            ambiguous: false,
            last: None,
            held: 0,
        }
    }

    #[must_use]
    pub fn params(&self) -> &IntegrityParams {
        &self.params
    }

    /// The last judged scan's level: what this sensor explains where it is tracked, for that
    /// scan's ranges (share); before any, where the levels start.
    #[must_use]
    pub fn level(&self) -> f64 {
        self.level
    }

    /// The level of a scan whose endpoints fall in the range bands so (`bands`): what the learned
    /// bands explain, weighted by their counts, within `floor..=1`. A band that has learned from
    /// few endpoints is drawn to the level learned from whole scans (as if that level had been
    /// seen on [`BAND_PRIOR_POINTS`] endpoints of it): a band the robot had not yet seen, judged at
    /// the starting level, held a robot found again among clutter (where the whole scans had
    /// taught a level below the start) `lost` 10 updates longer on the synthetic site.
    #[must_use]
    pub fn expected(&self, bands: &[u32; BANDS]) -> f64 {
        let n: u32 = bands.iter().sum();
        if n == 0 {
            return self.level;
        }
        let memory = BAND_FULL_POINTS / self.params.level_alpha.max(1e-6);
        let sum: f64 = bands
            .iter()
            .zip(self.levels.iter().zip(&self.learned))
            .map(|(&c, (level, learned))| {
                let m = learned.min(memory);
                f64::from(c) * (m * level + BAND_PRIOR_POINTS * self.overall) / (m + BAND_PRIOR_POINTS)
            })
            .sum();
        (sum / f64::from(n)).clamp(self.params.floor, 1.0)
    }

    #[must_use]
    pub fn state(&self) -> IntegrityState {
        self.state
    }

    /// The last judgement, if any update has been judged.
    #[must_use]
    pub fn last(&self) -> Option<Integrity> {
        self.last
    }

    /// Start over as if the filter had just been given a pose: the state is not known to be
    /// wrong, and the counters restart; the learned level is kept (it belongs to the sensor).
    pub fn restart(&mut self, state: IntegrityState) {
        self.state = state;
        self.recent.clear();
        self.below_uncertain = 0;
        self.below_lost = 0;
        self.above_tracking = 0;
        self.vouchable = None;
        self.ambiguous = false;
        self.held = 0;
    }

    /// The filter just turned `lost` on its shares, and no place of the map explains the scan
    /// clearly better than the estimate (or the search for one is still under way): `uncertain`
    /// instead, and shares below the lost bar do not turn it lost for the next `scans` judged
    /// scans (then one more does, and the map is searched again). A filter `uncertain` is held
    /// alike; one `tracking` is not. Nothing else changes: the level, the window, the runs.
    pub fn hold(&mut self, scans: u32) {
        match self.state {
            IntegrityState::Tracking => return,
            IntegrityState::Uncertain => {}
            IntegrityState::Lost => {
                self.state = IntegrityState::Uncertain;
                if let Some(last) = &mut self.last {
                    last.state = IntegrityState::Uncertain;
                }
            }
        }
        self.held = scans;
    }

    /// The last judgement was below the lost ratio: one more confirms a loss.
    #[must_use]
    pub fn loss_pending(&self) -> bool {
        self.below_lost > 0 && self.state != IntegrityState::Lost
    }

    /// The last judged scan, alone, was below the uncertain ratio (the state may still be
    /// `Tracking`: the window's median decides that).
    #[must_use]
    pub fn last_below_uncertain(&self) -> bool {
        self.last.is_some_and(|i| i.explained < self.params.uncertain_ratio * i.level)
    }

    /// Whether another place explains the scans about as well as the estimate. While it does the
    /// state is at best `Uncertain` (a `Tracking` state turns `Uncertain` at once); when it no
    /// longer does, `recover` good updates in a row bring `Tracking` back as usual.
    pub fn set_ambiguous(&mut self, ambiguous: bool) {
        self.ambiguous = ambiguous;
        if ambiguous && self.state == IntegrityState::Tracking {
            self.state = IntegrityState::Uncertain;
            self.recent.clear();
        }
        if let Some(last) = &mut self.last {
            last.state = self.state;
            last.ambiguous = ambiguous;
        }
    }

    #[must_use]
    pub fn ambiguous(&self) -> bool {
        self.ambiguous
    }

    /// The estimate is known to be wrong by other evidence than its share (a place that explains
    /// the scan far better): `Lost` now, and `recover` good updates in a row to track again.
    pub fn declare_lost(&mut self) {
        self.state = IntegrityState::Lost;
        self.recent.clear();
        self.held = 0;
        self.ambiguous = false;
        self.below_lost = self.params.confirm;
        self.above_tracking = 0;
        self.vouchable = None;
        if let Some(last) = &mut self.last {
            last.state = IntegrityState::Lost;
            last.ambiguous = false;
        }
    }

    /// Judge one update: its estimate explains `judged` of the scan (none judged: nothing
    /// changes, the last judgement is returned as it was, or a fresh one at the starting level).
    pub fn observe(&mut self, judged: &Judged) -> Integrity {
        let p = self.params;
        let Some(explained) = judged.share() else {
            return self.last.unwrap_or(Integrity {
                state: self.state,
                explained: 0.0,
                level: self.level,
                ambiguous: self.ambiguous,
            });
        };
        // The level this scan is judged by, reported with it (the learning below is for the next).
        self.level = self.expected(&judged.points);
        let ratio = explained / self.level;
        self.recent.push_back(ratio);
        while self.recent.len() > p.window {
            self.recent.pop_front();
        }
        let mut sorted: Vec<f64> = self.recent.iter().copied().collect();
        sorted.sort_by(f64::total_cmp);
        let median = sorted.get(sorted.len() / 2).copied().unwrap_or(ratio);
        self.below_lost = if ratio < p.lost_ratio { self.below_lost + 1 } else { 0 };
        self.below_uncertain = u32::from(median < p.uncertain_ratio);
        let run = self.above_tracking;
        self.above_tracking = if ratio >= p.tracking_ratio { run + 1 } else { 0 };
        // A full window whose median is at the tracking bar: the scans at the estimate are
        // explained as where it is tracked, but for one or two (people walking by).
        let settled = self.recent.len() >= p.window && median >= p.tracking_ratio;
        let before = self.state;
        let held = self.held > 0;
        self.held = self.held.saturating_sub(1);
        self.state = match self.state {
            _ if self.below_lost >= p.confirm && !held => IntegrityState::Lost,
            IntegrityState::Tracking if self.below_uncertain > 0 || self.ambiguous => {
                IntegrityState::Uncertain
            }
            IntegrityState::Uncertain | IntegrityState::Lost
                if (self.above_tracking >= p.recover || settled) && !self.ambiguous =>
            {
                IntegrityState::Tracking
            }
            s => s,
        };
        // The window holds the judgements since the state last changed: back to tracking, the
        // median starts again from the good updates, not the bad ones; out of it, the median
        // that would bring it back is of the scans since (those before were of an estimate now
        // in doubt, or re-seeded away).
        if before != self.state {
            self.recent.clear();
            self.recent.push_back(ratio);
        }
        // The level learns while the filter is not lost from updates at or above the uncertain
        // bar, and while `Tracking` from any above the lost bar: the mean of the first updates,
        // then a slow running mean. Learning only while `Tracking` kept a site whose scans the map
        // explains less than the start level (a cluttered one) `Uncertain` for good: it could
        // never reach the level it was judged against. Learning only above the uncertain bar
        // learns from the upper part of a broad spread of shares, and the bar follows the level
        // up (on an outdoor log a level of 0.88 where the references explain 0.74 on average).
        // Each band learns from its own endpoints, with the update's weight if it holds at least
        // `BAND_FULL_POINTS` of them, in proportion if fewer. While the first `1 / level_alpha`
        // updates are averaged alike, so are a band's endpoints; a band first seen later starts at
        // the whole scans' level and learns at the running mean's pace from then on (one scan of a
        // new range, maybe a robot carried off, does not set its level).
        let learns = (self.state == IntegrityState::Tracking && ratio >= p.lost_ratio)
            || (self.state != IntegrityState::Lost && ratio >= p.uncertain_ratio);
        if learns {
            self.updates += 1;
            let warming = (self.updates as f64) < 1.0 / p.level_alpha.max(1e-6);
            let w = p.level_alpha.max(1.0 / self.updates as f64);
            self.overall = (self.overall + w * (explained - self.overall)).clamp(p.floor, 1.0);
            for b in 0..BANDS {
                let (Some(&c), Some(&e)) = (judged.points.get(b), judged.explained.get(b)) else { continue };
                if c == 0 {
                    continue;
                }
                let c = f64::from(c);
                let (Some(learned), Some(level)) = (self.learned.get_mut(b), self.levels.get_mut(b)) else {
                    continue;
                };
                let slow = p.level_alpha * (c / BAND_FULL_POINTS).min(1.0);
                let w = if warming {
                    slow.max(c / (*learned + c))
                } else {
                    if *learned == 0.0 {
                        *level = self.overall;
                    }
                    slow
                };
                *learned += c;
                *level = (*level + w * (f64::from(e) / c - *level)).clamp(0.0, 1.0);
            }
        }
        self.vouchable = (self.state != IntegrityState::Tracking
            && ratio >= p.uncertain_ratio
            && ratio < p.tracking_ratio)
            .then_some(run);
        let out = Integrity { state: self.state, explained, level: self.level, ambiguous: self.ambiguous };
        self.last = Some(out);
        out
    }

    /// Whether the last judgement may be vouched for ([`Monitor::vouch`]): not tracking, and the
    /// estimate explained the scan between the uncertain and the tracking bar.
    #[must_use]
    pub fn vouchable(&self) -> bool {
        self.vouchable.is_some()
    }

    /// The last judgement fell short of the tracking bar, but no other place explains the scan
    /// nearly as well as the estimate (the caller searched): it counts towards `Tracking` as an
    /// update above the bar would. Scans that the map explains less well than the learned level
    /// at the right place (clutter, an unmapped crowd) keep a filter that recovered from a loss
    /// out of `Tracking` by the bar alone, where one that never lost the robot stays tracking.
    pub fn vouch(&mut self) {
        let Some(run) = self.vouchable.take() else { return };
        self.above_tracking = run + 1;
        if self.above_tracking >= self.params.recover && !self.ambiguous {
            self.state = IntegrityState::Tracking;
            self.below_uncertain = 0;
            self.recent.clear();
            if let Some(last) = &mut self.last {
                last.state = IntegrityState::Tracking;
                self.recent.push_back(last.explained / last.level);
            }
        }
    }

    /// The whole map was searched for the scan and the estimate is the one place that explains
    /// it, as `judged` there (the caller's search, [`IntegrityParams::verify_margin`]): `Tracking`
    /// now. The level is left as it was learned: the scans that follow are judged against it as
    /// any other (a verified robot among clutter that explains much less than the level turns
    /// `uncertain` or `lost` again, and is verified again by a later search). A level brought
    /// down to what the verified place explains let a filter kidnapped later report `tracking`
    /// 61 m off on an outdoor log, three scans in a row over the lowered bar (docs/results.md).
    pub fn verify(&mut self, judged: &Judged) {
        let p = self.params;
        let Some(explained) = judged.share() else { return };
        self.level = self.expected(&judged.points);
        self.state = IntegrityState::Tracking;
        self.ambiguous = false;
        self.below_lost = 0;
        self.below_uncertain = 0;
        self.above_tracking = p.recover;
        self.vouchable = None;
        self.recent.clear();
        self.recent.push_back(explained / self.level);
        self.last = Some(Integrity { state: self.state, explained, level: self.level, ambiguous: false });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A scan of 1 000 endpoints in one range band, `share` of them explained.
    fn one(share: f64) -> Judged {
        Judged::in_one_band(1000, (share.clamp(0.0, 1.0) * 1000.0).round() as u32)
    }

    /// A monitor with the shipped settings after ten scans explained at 0.9 (`Tracking`), its
    /// settings and its level.
    fn tracking_at_0_9() -> (IntegrityParams, Monitor, f64) {
        let p = IntegrityParams::default();
        let mut m = Monitor::new(p);
        for _ in 0..10 {
            m.observe(&one(0.9));
        }
        let level = m.last().map_or(f64::NAN, |i| i.level);
        (p, m, level)
    }

    #[test]
    fn shipped_defaults_are_consistent() {
        IntegrityParams::default().check().unwrap();
    }

    #[test]
    fn a_floor_of_zero_is_refused_with_the_reason() {
        for floor in [0.0, -0.1, 1.5, f64::NAN] {
            let e = IntegrityParams { floor, ..IntegrityParams::default() }.check().unwrap_err();
            assert!(e.contains("floor must be within 0 < floor <= 1"), "{floor}: {e}");
        }
        IntegrityParams { floor: 1.0, ..IntegrityParams::default() }.check().unwrap();
    }

    #[test]
    fn a_search_without_budget_or_with_a_negative_square_is_refused() {
        let e = IntegrityParams { search_budget: 0, ..IntegrityParams::default() }.check().unwrap_err();
        assert!(e.contains("search_budget must be > 0"), "{e}");
        for near_search_m in [-1.0, f64::NAN, f64::INFINITY] {
            let e = IntegrityParams { near_search_m, ..IntegrityParams::default() }.check().unwrap_err();
            assert!(e.contains("near_search_m must be >= 0"), "{near_search_m}: {e}");
        }
        IntegrityParams { near_search_m: 0.0, ..IntegrityParams::default() }.check().unwrap();
    }

    #[test]
    fn a_drop_needs_confirming_and_recovery_needs_a_run_of_good_updates() {
        let mut m = Monitor::new(IntegrityParams::default());
        for _ in 0..10 {
            m.observe(&one(0.9));
        }
        let level = m.last().unwrap().level;
        // One bad update is not enough (a person in front of the sensor).
        assert_eq!(m.observe(&one(0.1)).state, IntegrityState::Tracking);
        for _ in 0..10 {
            assert_eq!(m.observe(&one(0.9)).state, IntegrityState::Tracking);
        }
        // Two in a row below the lost ratio: lost.
        m.observe(&one(0.1));
        assert_eq!(m.observe(&one(0.1)).state, IntegrityState::Lost);
        // The level is not learned while lost.
        assert!((m.last().unwrap().level - level).abs() < 1e-3);
        // Two good updates are not enough, three are.
        assert_eq!(m.observe(&one(0.9)).state, IntegrityState::Lost);
        assert_eq!(m.observe(&one(0.9)).state, IntegrityState::Lost);
        assert_eq!(m.observe(&one(0.9)).state, IntegrityState::Tracking);
        // A persistent fit between the lost and the uncertain ratio: uncertain within a few
        // updates, never lost.
        for _ in 0..10 {
            assert_eq!(m.observe(&one(0.9)).state, IntegrityState::Tracking);
        }
        let mid = level * 0.75;
        let turned = (1..=10).find(|_| m.observe(&one(mid)).state == IntegrityState::Uncertain);
        assert_eq!(turned, Some(3), "the median of 5 turns at the third");
        for _ in 0..20 {
            assert_eq!(m.observe(&one(mid)).state, IntegrityState::Uncertain);
        }
    }

    #[test]
    fn a_window_at_the_tracking_bar_since_a_loss_tracks_though_scans_dip_below_it() {
        let (p, mut m, level) = tracking_at_0_9();
        m.observe(&one(0.1));
        assert_eq!(m.observe(&one(0.1)).state, IntegrityState::Lost);
        // Back at the robot among people: every other scan below the uncertain bar, so never
        // `recover` good ones in a row. The window since the loss (its first scan the lost one)
        // is not at the bar until the lost scan has left it and three of five are.
        let (good, dip) = (level * (p.tracking_ratio + 0.02), level * (p.uncertain_ratio - 0.05));
        for share in [good, dip, good, dip] {
            assert_eq!(m.observe(&one(share)).state, IntegrityState::Lost);
        }
        assert_eq!(m.observe(&one(good)).state, IntegrityState::Tracking);
        // A window mostly below the bar does not: lost again, then two of five good.
        m.observe(&one(0.1));
        assert_eq!(m.observe(&one(0.1)).state, IntegrityState::Lost);
        for share in [good, dip, dip, good, dip, dip, good, dip, dip] {
            assert_eq!(m.observe(&one(share)).state, IntegrityState::Lost);
        }
    }

    /// A hold keeps a filter that turned lost `uncertain`, and one already `uncertain` from
    /// turning lost, for its scans; then one more scan below the lost bar turns it lost. A filter
    /// `tracking` is not held.
    #[test]
    fn a_hold_keeps_a_filter_from_turning_lost_for_its_scans() {
        let (_, mut m, _) = tracking_at_0_9();
        m.hold(3);
        assert_eq!(m.observe(&one(0.1)).state, IntegrityState::Tracking);
        assert_eq!(m.observe(&one(0.1)).state, IntegrityState::Lost, "a hold while tracking counted");
        m.hold(2);
        assert_eq!(
            (m.state(), m.last().map(|i| i.state)),
            (IntegrityState::Uncertain, Some(IntegrityState::Uncertain))
        );
        for _ in 0..2 {
            assert_eq!(m.observe(&one(0.1)).state, IntegrityState::Uncertain);
        }
        // Uncertain still, held again (a search under way): as long again.
        m.hold(1);
        assert_eq!(m.observe(&one(0.1)).state, IntegrityState::Uncertain);
        assert_eq!(m.observe(&one(0.1)).state, IntegrityState::Lost);
    }

    #[test]
    fn a_loss_declared_on_other_evidence_holds_until_a_run_of_good_updates() {
        let p = IntegrityParams::default();
        let mut m = Monitor::new(p);
        for _ in 0..10 {
            m.observe(&one(0.9));
        }
        // Uncertain on a persistent middling fit, then declared lost (a far better place exists).
        let mid = m.last().unwrap().level * 0.75;
        while m.observe(&one(mid)).state != IntegrityState::Uncertain {}
        m.declare_lost();
        assert_eq!(m.state(), IntegrityState::Lost);
        assert_eq!(m.last().map(|i| i.state), Some(IntegrityState::Lost));
        // The middling fit does not bring it back; `recover` good updates in a row do.
        assert_eq!(m.observe(&one(mid)).state, IntegrityState::Lost);
        for _ in 1..p.recover {
            assert_eq!(m.observe(&one(0.9)).state, IntegrityState::Lost);
        }
        assert_eq!(m.observe(&one(0.9)).state, IntegrityState::Tracking);
    }

    #[test]
    fn an_ambiguous_estimate_is_not_tracking_until_the_rival_is_gone() {
        let p = IntegrityParams::default();
        let mut m = Monitor::new(p);
        for _ in 0..10 {
            m.observe(&one(0.9));
        }
        assert_eq!(m.state(), IntegrityState::Tracking);
        // A rival turns a tracking estimate uncertain at once, its last judgement too.
        m.set_ambiguous(true);
        assert_eq!(m.state(), IntegrityState::Uncertain);
        assert_eq!(m.last().map(|i| i.state), Some(IntegrityState::Uncertain));
        // However well the estimate explains the scans, not tracking while the rival stands.
        for _ in 0..10 {
            assert_eq!(m.observe(&one(0.95)).state, IntegrityState::Uncertain);
        }
        // The rival gone: the good updates in a row count again.
        m.set_ambiguous(false);
        assert_eq!(m.observe(&one(0.95)).state, IntegrityState::Tracking);
        // A loss clears the ambiguity: recovering from it needs only the good updates.
        m.set_ambiguous(true);
        m.declare_lost();
        assert!(!m.ambiguous());
        for _ in 1..p.recover {
            assert_eq!(m.observe(&one(0.9)).state, IntegrityState::Lost);
        }
        assert_eq!(m.observe(&one(0.9)).state, IntegrityState::Tracking);
        // A restart forgets it.
        m.set_ambiguous(true);
        m.restart(IntegrityState::Uncertain);
        assert!(!m.ambiguous());
    }

    #[test]
    fn a_unique_estimate_between_the_bars_tracks_after_a_run_of_vouched_updates() {
        let (p, mut m, level) = tracking_at_0_9();
        m.declare_lost();
        let between = level * (p.uncertain_ratio + p.tracking_ratio) / 2.0;
        // Between the bars, unvouched: lost however long it lasts.
        for _ in 0..10 {
            assert_eq!(m.observe(&one(between)).state, IntegrityState::Lost);
            assert!(m.vouchable());
        }
        // Vouched for: `recover` of them in a row track, an update above the bar counting alike.
        m.observe(&one(between));
        m.vouch();
        assert_eq!(m.state(), IntegrityState::Lost);
        assert!(!m.vouchable(), "once per judgement");
        m.observe(&one(level));
        assert_eq!(m.state(), IntegrityState::Lost);
        m.observe(&one(between));
        m.vouch();
        assert_eq!(m.state(), IntegrityState::Tracking);
        assert_eq!(m.last().map(|i| i.state), Some(IntegrityState::Tracking));
        // Tracking: nothing to vouch for. Below the uncertain bar: nothing either.
        m.observe(&one(between));
        assert!(!m.vouchable());
        m.declare_lost();
        m.observe(&one(level * p.uncertain_ratio * 0.95));
        assert!(!m.vouchable());
        // A run broken by an unvouched update between the bars starts again.
        m.observe(&one(between));
        m.vouch();
        m.observe(&one(between));
        m.observe(&one(between));
        m.vouch();
        assert_eq!(m.state(), IntegrityState::Lost);
        // While a rival stands, vouching never brings tracking.
        m.set_ambiguous(true);
        for _ in 0..5 {
            m.observe(&one(between));
            m.vouch();
        }
        assert_eq!(m.state(), IntegrityState::Lost);
    }

    #[test]
    fn a_verified_estimate_tracks_and_is_judged_on_against_the_learned_level() {
        let p = IntegrityParams::default();
        let mut m = Monitor::new(p);
        for _ in 0..300 {
            m.observe(&one(0.95));
        }
        let level = m.level();
        assert!(level > 0.9, "{level}");
        // Among clutter the right place explains 0.8: lost after a drop, and lost it stays by the
        // share (below the tracking bar).
        for _ in 0..p.confirm {
            m.observe(&one(0.3));
        }
        for _ in 0..20 {
            m.observe(&one(0.8));
        }
        assert_eq!(m.state(), IntegrityState::Lost);
        m.verify(&one(0.8));
        assert_eq!(m.state(), IntegrityState::Tracking);
        assert_eq!(m.last().map(|i| (i.state, i.explained)), Some((IntegrityState::Tracking, 0.8)));
        assert!((m.level() - level).abs() < 1e-12, "the level is left as learned");
        // Judged on against that level: scans like it do not bring it down, a kidnapping does.
        for _ in 0..20 {
            assert_eq!(m.observe(&one(0.85)).state, IntegrityState::Tracking);
        }
        for _ in 0..p.confirm {
            m.observe(&one(0.3));
        }
        assert_eq!(m.state(), IntegrityState::Lost);
        // Leaving `lost` by the share alone still needs the bar.
        for _ in 0..10 {
            assert_eq!(m.observe(&one(level * p.tracking_ratio * 0.97)).state, IntegrityState::Lost);
        }
    }

    #[test]
    fn the_level_follows_the_sensor_but_not_below_its_floor() {
        let p = IntegrityParams::default();
        let mut m = Monitor::new(p);
        // A cluttered site whose scans the map explains at 0.66, well below where the level
        // starts: learned from the first updates on, tracking within a few of a pose being given.
        m.restart(IntegrityState::Uncertain);
        let turned = (1..=20).find(|_| m.observe(&one(0.66)).state == IntegrityState::Tracking);
        assert_eq!(turned, Some(4), "the first update teaches the level, three at it follow");
        for _ in 0..2000 {
            m.observe(&one(0.66));
        }
        let l = m.last().unwrap();
        assert_eq!(l.state, IntegrityState::Tracking);
        assert!((l.level - 0.66).abs() < 0.01, "{l:?}");
        // A filter that starts lost cannot teach it a low level.
        let mut m = Monitor::new(p);
        for _ in 0..2000 {
            m.observe(&one(0.2));
        }
        let l = m.last().unwrap();
        assert_eq!(l.state, IntegrityState::Lost);
        assert!(l.level >= p.floor, "{l:?}");
    }

    /// A scan of `near` endpoints 1–2 m away and `far` 20–40 m away, `near_share` and `far_share`
    /// of them explained.
    fn mixed(near: u32, near_share: f64, far: u32, far_share: f64) -> Judged {
        let mut j = Judged::default();
        j.points[band_of([1.5, 0.0], None)] = near;
        j.explained[band_of([1.5, 0.0], None)] = (f64::from(near) * near_share).round() as u32;
        j.points[band_of([30.0, 0.0], None)] = far;
        j.explained[band_of([30.0, 0.0], None)] = (f64::from(far) * far_share).round() as u32;
        j
    }

    #[test]
    fn endpoints_are_banded_by_their_range_from_the_sensor() {
        assert_eq!(band_of([1.9, 0.0], None), 0);
        assert_eq!(band_of([2.0, 0.0], None), 1);
        assert_eq!(band_of([0.0, -7.0], None), 2);
        assert_eq!(band_of([39.9, 0.0], None), 4);
        assert_eq!(band_of([40.0, 0.0], None), BANDS - 1);
        assert_eq!(band_of([1e9, f64::NAN], None), 0, "no range: the nearest band, never out of bounds");
        // From the sensor, not the base: 1.5 m ahead of a sensor mounted 1 m forward.
        assert_eq!(band_of([2.5, 0.0], Some([1.0, 0.0])), 0);
        assert_eq!(bands(&[[1.0, 0.0], [3.0, 0.0], [3.0, 1.0], [50.0, 0.0]], None), [1, 2, 0, 0, 0, 1]);
    }

    /// Far endpoints are explained less often than near ones where the robot is tracked (a small
    /// heading error moves them further; they graze surfaces and meet what the map left out). A
    /// scan of far endpoints is judged against what far endpoints explain, so the open street
    /// does not look lost; a scan of near ones explaining as little is a robot carried off.
    #[test]
    fn a_scan_is_judged_against_what_its_ranges_explain() {
        let p = IntegrityParams::default();
        let mut banded = Monitor::new(p);
        for _ in 0..400 {
            banded.observe(&mixed(90, 0.95, 90, 0.55));
        }
        assert_eq!(banded.state(), IntegrityState::Tracking);
        // All far, as far endpoints explain: tracking; one level for all ranges (the mean, 0.75)
        // would hold it uncertain.
        for _ in 0..20 {
            assert_eq!(banded.observe(&mixed(0, 0.0, 180, 0.55)).state, IntegrityState::Tracking);
        }
        let far = banded.expected(&bands(&[[30.0, 0.0]], None));
        assert!((far - p.floor).abs() < 1e-9, "0.55 learned, judged at the floor: {far}");
        let near = banded.expected(&bands(&[[1.5, 0.0]], None));
        assert!((near - 0.95).abs() < 0.01, "{near}");
        // All near, explaining what the far ones do: lost within `confirm`.
        banded.observe(&mixed(180, 0.55, 0, 0.0));
        assert_eq!(banded.observe(&mixed(180, 0.55, 0, 0.0)).state, IntegrityState::Lost);
    }

    /// A band the robot has not seen yet is judged at the level of the whole scans learned so far,
    /// not at the starting level: on a cluttered site, a scan of a new range is not doubted for it.
    #[test]
    fn a_band_not_yet_seen_is_judged_at_the_level_learned_from_whole_scans() {
        let p = IntegrityParams::default();
        let mut m = Monitor::new(p);
        for _ in 0..300 {
            m.observe(&mixed(180, 0.66, 0, 0.0));
        }
        let unseen = m.expected(&bands(&[[30.0, 0.0]], None));
        assert!((unseen - 0.66).abs() < 0.01, "{unseen}");
        // Given a pose again: `recover` scans of the new range at 0.64 bring `Tracking` (at the
        // starting level, 0.75, they would stay below the tracking bar, 0.69).
        m.restart(IntegrityState::Uncertain);
        for k in 1..=p.recover {
            let state = m.observe(&mixed(0, 0.0, 180, 0.64)).state;
            let want = if k < p.recover { IntegrityState::Uncertain } else { IntegrityState::Tracking };
            assert_eq!(state, want, "scan {k}");
        }
        // One scan of a range first seen after the level was learned does not set that band's
        // level: a robot carried off among far endpoints is lost as anywhere else.
        let mut m = Monitor::new(p);
        for _ in 0..500 {
            m.observe(&mixed(180, 0.85, 0, 0.0));
        }
        let mut far = Judged::default();
        far.points[3] = 180;
        far.explained[3] = 112;
        assert_eq!(m.observe(&far).state, IntegrityState::Tracking, "0.62 of 0.85: one scan, still tracking");
        far.explained[3] = 90;
        m.observe(&far);
        assert_eq!(m.observe(&far).state, IntegrityState::Lost, "0.50 of about 0.85, twice: lost");
    }
}
