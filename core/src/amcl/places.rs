//! An exhaustive search of the map for the places that explain a scan: branch and bound over the
//! translations at each heading, as in correlative scan matching (E. Olson, "Real-time correlative
//! scan matching", ICRA 2009) and Cartographer's fast correlative matcher (W. Hess et al., "Real-time
//! loop closure in 2D LIDAR SLAM", ICRA 2016), with the integrity measure's count of explained
//! endpoints as the score.
//!
//! Uniform draws (the re-seeding's best-of-many poses) find the robot's basin with a probability
//! that falls with the map's free area (docs/integrity.md, "The whole map searched": about one
//! draw in 100 × the area in m² indoors, one in 300 × outdoors). The search here looks at every
//! block of the map at every heading, and its cost grows with the places that nearly explain the
//! scan more than with the area.
//!
//! The map is cut into square blocks ([`BLOCK_M`]); a block is "near" when some point of it lies
//! within [`NEAR_M`] of a mapped surface. Level `l` of the precomputed grids holds, for block
//! `(i, j)`, whether any block of `[i, i + 2^l) × [j, j + 2^l)` is near, so that the endpoints
//! counted on level `l` at one translation bound the count at every translation of that square
//! (the bound Cartographer's precomputation grids give). A square whose bound is below the
//! count sought is not looked into.

use std::f64::consts::PI;

use super::likelihood::LikelihoodField;
use crate::se2::Se2;

/// The side of a block, m (rounded to whole map cells).
pub const BLOCK_M: f64 = 0.1;
/// An endpoint in a block that holds a point this close to a mapped surface is counted, m.
pub const NEAR_M: f64 = 0.15;
/// Places counting this share of the endpoints fewer than the best place found are not looked
/// for: the search's bar rises with the best it has found.
pub const SLACK: f64 = 0.1;
/// The filter's searches: places stand at least this far apart (or turned this much), m and rad.
pub const PLACES_APART: (f64, f64) = (1.0, 0.35);
/// The filter's searches count at most this many squares (bounds the update that turns lost).
pub const SEARCH_BUDGET: u64 = 4_000_000;
/// Levels above the blocks: the top level's squares are 2^6 blocks (12.8 m) a side.
const LEVELS: usize = 7;
/// Candidates kept while searching: past this, the better half is kept and the count sought
/// rises to the worst of them (memory stays bounded on a map where the scan fits everywhere).
const KEPT: usize = 20_000;
/// Headings: at least this step (the far endpoints of a scan whose farthest return is a metre
/// away would ask for thousands of headings), at most this one, rad.
const MIN_STEP_RAD: f64 = 0.007;
const MAX_STEP_RAD: f64 = 0.035;

/// The precomputed grids of one map (built once per map, shared by its filters).
#[derive(Debug, Clone)]
pub struct PlaceSearch {
    block_m: f64,
    width: usize,
    height: usize,
    /// `levels[l][j * width + i]`: some block of `[i, i + 2^l) × [j, j + 2^l)` is near.
    levels: Vec<Vec<bool>>,
    /// Whether block `(i, j)` holds free space (a robot can stand there).
    free: Vec<bool>,
    /// The blocks holding free space lie within `[x0, x1] × [y0, y1]`.
    bounds: Option<(usize, usize, usize, usize)>,
    map_to_world: Se2,
}

/// A place the search found: a pose and the share of the scan's endpoints it counts.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Place {
    pub pose: Se2,
    pub share: f64,
}

/// What one search looked at, for benchmarks and tests.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SearchCost {
    pub headings: usize,
    /// Squares whose bound was counted, all levels.
    pub squares: u64,
    /// The search stopped at its budget of squares before it looked at every heading.
    pub cut: bool,
}

/// A search of the map under way ([`PlaceSearch::start`]): where it stands, what it has found.
/// Carried on a budget at a time ([`PlaceSearch::carry_on`]), so that an update that searches a
/// large map is bounded and the search completes over the updates after it.
#[derive(Debug, Clone)]
pub struct Ongoing {
    /// The scan's endpoints.
    n: usize,
    /// The blocks searched, `(x0, y0, x1, y1)`.
    bounds: (usize, usize, usize, usize),
    /// The count sought (rises with the best found), the slack below the best, the best.
    need: usize,
    slack: usize,
    best: usize,
    /// The heading step, rad, and every heading's endpoints as block offsets.
    step: f64,
    offsets: Vec<Vec<(isize, isize)>>,
    /// The next top-level square to bound (heading, row, column in one index).
    next_top: usize,
    /// The top-level squares bounded at `need` or more: `(bound, i, j, heading)`, the best first
    /// once all are bounded.
    tops: Vec<(usize, usize, usize, usize)>,
    /// The next of `tops` to descend into.
    next_descent: usize,
    /// Squares to look into: `(bound, i, j, level, heading)`.
    stack: Vec<(usize, usize, usize, usize, usize)>,
    /// Blocks found: `(count, i, j, heading)`.
    found: Vec<(usize, usize, usize, usize)>,
    max_places: usize,
    apart: (f64, f64),
    block_m: f64,
    map_to_world: Se2,
    cost: SearchCost,
    complete: bool,
}

impl Ongoing {
    /// Whether the search has looked at everything it was started on.
    #[must_use]
    pub fn complete(&self) -> bool {
        self.complete
    }

    /// What it has counted so far (`cut` while it is not complete and stopped at a budget).
    #[must_use]
    pub fn cost(&self) -> SearchCost {
        self.cost
    }

    /// The places found so far: at most `max_places`, the best first, each at least `apart` from
    /// those before it; all of them, once the search is complete.
    #[must_use]
    pub fn places(&self) -> Vec<Place> {
        let mut found: Vec<_> = self.found.iter().filter(|f| f.0 >= self.need).copied().collect();
        found.sort_by(|a, b| b.0.cmp(&a.0).then((a.3, a.2, a.1).cmp(&(b.3, b.2, b.1))));
        let mut places: Vec<Place> = Vec::new();
        for (count, i, j, hk) in found {
            if places.len() >= self.max_places {
                break;
            }
            let in_map = Se2::new(
                (i as f64 + 0.5) * self.block_m,
                (j as f64 + 0.5) * self.block_m,
                hk as f64 * self.step,
            );
            let pose = self.map_to_world * in_map;
            let distinct = places.iter().all(|q| {
                let d = q.pose.inverse() * pose;
                d.translation_norm() >= self.apart.0 || d.theta.abs() >= self.apart.1
            });
            if distinct {
                places.push(Place { pose, share: count as f64 / self.n as f64 });
            }
        }
        places
    }
}

impl PlaceSearch {
    /// The grids for `field`'s map.
    #[must_use]
    pub fn new(field: &LikelihoodField) -> Self {
        let res = field.resolution_m();
        let k = if res > 0.0 { ((BLOCK_M / res).round() as usize).max(1) } else { 1 };
        let block_m = k as f64 * res;
        let (width, height, near, free) = field.blocks(k, NEAR_M);
        let mut levels = vec![near];
        for l in 1..=LEVELS {
            let s = 1usize << (l - 1);
            let below = &levels[l - 1];
            let at = |i: usize, j: usize| i < width && j < height && below[j * width + i];
            let mut grid = vec![false; width * height];
            for j in 0..height {
                for i in 0..width {
                    grid[j * width + i] = at(i, j) || at(i + s, j) || at(i, j + s) || at(i + s, j + s);
                }
            }
            levels.push(grid);
        }
        let mut bounds: Option<(usize, usize, usize, usize)> = None;
        for (idx, _) in free.iter().enumerate().filter(|(_, f)| **f) {
            let (i, j) = (idx % width, idx / width);
            bounds = Some(match bounds {
                None => (i, j, i, j),
                Some((x0, y0, x1, y1)) => (x0.min(i), y0.min(j), x1.max(i), y1.max(j)),
            });
        }
        PlaceSearch { block_m, width, height, levels, free, bounds, map_to_world: field.map_to_world() }
    }

    /// Bytes held by the grids.
    #[must_use]
    pub fn heap_bytes(&self) -> usize {
        (self.levels.len() + 1) * self.width * self.height
    }

    /// The places (robot poses in the world) at which at least `min_share` of `points` (the scan's
    /// endpoints in the robot's frame) land in near blocks, standing in a free block: at most
    /// `max_places`, the best first, each at least `apart_m` or `apart_rad` from those before it.
    /// At most `budget` squares are counted (the search then returns what it found so far, and
    /// says so). The whole map, or `within` a square: the robot positions within `half_side_m`
    /// of `centre` (a point of the world) along each axis of the map's grid.
    #[must_use]
    pub fn search(
        &self,
        points: &[[f64; 2]],
        min_share: f64,
        max_places: usize,
        apart: (f64, f64),
        budget: u64,
        within: Option<([f64; 2], f64)>,
    ) -> (Vec<Place>, SearchCost) {
        let bounds = match within {
            None => self.bounds,
            Some((centre, half_side_m)) => self.window(centre, half_side_m),
        };
        self.search_in(bounds, points, min_share, max_places, apart, budget)
    }

    /// The blocks of `bounds` within `half_side_m` of `centre` along each axis of the grid; `None`
    /// where they hold no free block's bounds, or the window is no number.
    fn window(&self, centre: [f64; 2], half_side_m: f64) -> Option<(usize, usize, usize, usize)> {
        let (x0, y0, x1, y1) = self.bounds?;
        let m = self.map_to_world.inverse().transform_point(centre);
        let (lo_x, lo_y) = ((m[0] - half_side_m) / self.block_m, (m[1] - half_side_m) / self.block_m);
        let (hi_x, hi_y) = ((m[0] + half_side_m) / self.block_m, (m[1] + half_side_m) / self.block_m);
        if ![lo_x, lo_y, hi_x, hi_y].iter().all(|v| v.is_finite()) || half_side_m < 0.0 {
            return None;
        }
        // Clamped to the free blocks' bounds before the cast: a window far off the map is empty.
        let clamp = |v: f64, lo: usize, hi: usize| v.floor().clamp(lo as f64, hi as f64) as usize;
        let (wx0, wx1) = (clamp(lo_x, x0, x1), clamp(hi_x, x0, x1));
        let (wy0, wy1) = (clamp(lo_y, y0, y1), clamp(hi_y, y0, y1));
        let inside =
            hi_x >= x0 as f64 && lo_x <= x1 as f64 + 1.0 && hi_y >= y0 as f64 && lo_y <= y1 as f64 + 1.0;
        inside.then_some((wx0, wy0, wx1, wy1))
    }

    fn search_in(
        &self,
        bounds: Option<(usize, usize, usize, usize)>,
        points: &[[f64; 2]],
        min_share: f64,
        max_places: usize,
        apart: (f64, f64),
        budget: u64,
    ) -> (Vec<Place>, SearchCost) {
        let mut ongoing = self.start_in(bounds, points, min_share, max_places, apart);
        self.carry_on(&mut ongoing, budget);
        (ongoing.places(), ongoing.cost)
    }

    /// A search of the whole map for the places [`Self::search`] finds, not yet run: run it with
    /// [`Self::carry_on`], a budget at a time, until it is complete ([`Ongoing::complete`]).
    #[must_use]
    pub fn start(
        &self,
        points: &[[f64; 2]],
        min_share: f64,
        max_places: usize,
        apart: (f64, f64),
    ) -> Ongoing {
        self.start_in(self.bounds, points, min_share, max_places, apart)
    }

    /// As [`Self::start`], within a square: the robot positions within `half_side_m` of `centre`
    /// (a point of the world) along each axis of the map's grid.
    #[must_use]
    pub fn start_within(
        &self,
        points: &[[f64; 2]],
        min_share: f64,
        max_places: usize,
        apart: (f64, f64),
        centre: [f64; 2],
        half_side_m: f64,
    ) -> Ongoing {
        self.start_in(self.window(centre, half_side_m), points, min_share, max_places, apart)
    }

    fn start_in(
        &self,
        bounds: Option<(usize, usize, usize, usize)>,
        points: &[[f64; 2]],
        min_share: f64,
        max_places: usize,
        apart: (f64, f64),
    ) -> Ongoing {
        // Endpoints that are no place (not finite) are left out.
        let points: Vec<[f64; 2]> =
            points.iter().filter(|p| p[0].is_finite() && p[1].is_finite()).copied().collect();
        let n = points.len();
        let mut ongoing = Ongoing {
            n,
            bounds: (0, 0, 0, 0),
            need: 0,
            slack: 0,
            best: 0,
            step: 0.0,
            offsets: Vec::new(),
            next_top: 0,
            tops: Vec::new(),
            next_descent: 0,
            stack: Vec::new(),
            found: Vec::new(),
            max_places,
            apart,
            block_m: self.block_m,
            map_to_world: self.map_to_world,
            cost: SearchCost::default(),
            complete: true,
        };
        let Some(bounds) = bounds else { return ongoing };
        if n == 0 || max_places == 0 || !(min_share.is_finite()) {
            return ongoing;
        }
        // The heading step moves the farthest endpoint by about a block.
        let far = points.iter().map(|p| p[0].hypot(p[1])).fold(0.0, f64::max);
        let step =
            if far > 0.0 { (self.block_m / far).clamp(MIN_STEP_RAD, MAX_STEP_RAD) } else { MAX_STEP_RAD };
        let headings = (2.0 * PI / step).ceil() as usize;
        let step = 2.0 * PI / headings as f64;
        // Every heading's endpoints as block offsets from the robot's block.
        ongoing.offsets = (0..headings)
            .map(|hk| {
                let (s, c) = (hk as f64 * step).sin_cos();
                points
                    .iter()
                    .map(|p| {
                        let u = (c * p[0] - s * p[1]) / self.block_m;
                        let v = (s * p[0] + c * p[1]) / self.block_m;
                        ((0.5 + u).floor() as isize, (0.5 + v).floor() as isize)
                    })
                    .collect()
            })
            .collect();
        ongoing.bounds = bounds;
        ongoing.need = ((min_share.clamp(0.0, 1.0) * n as f64).ceil() as usize).max(1);
        ongoing.slack = (SLACK * n as f64).ceil() as usize;
        ongoing.step = step;
        ongoing.cost.headings = headings;
        ongoing.complete = false;
        ongoing
    }

    /// Runs `ongoing` on (a search [`Self::start`]ed on this map's grids) until it is complete or
    /// has counted `budget` more squares (at least 4: a square stopped among its four children is
    /// looked into again, its children counted anew, and a run counts them all). The places it
    /// finds are the same, in the same order, whether it runs on one budget or on many.
    pub fn carry_on(&self, ongoing: &mut Ongoing, budget: u64) {
        if ongoing.complete {
            return;
        }
        let limit = ongoing.cost.squares.saturating_add(budget.max(4));
        let o = ongoing;
        let top = self.levels.len() - 1;
        let (x0, y0, x1, y1) = o.bounds;
        // The top level's squares at every heading, the best bound first: the best places are met
        // early, and the bar rises with them (as Cartographer's matcher orders its candidates).
        let side = 1usize << top;
        let (ni, nj) = ((x1 - x0) / side + 1, (y1 - y0) / side + 1);
        let all_tops = o.offsets.len() * nj * ni;
        if o.next_top < all_tops {
            while o.next_top < all_tops {
                if o.cost.squares >= limit {
                    o.cost.cut = true;
                    return;
                }
                let k = o.next_top;
                let (hk, j, i) = (k / (nj * ni), y0 + (k / ni % nj) * side, x0 + (k % ni) * side);
                o.next_top += 1;
                o.cost.squares += 1;
                let bound = self.count(top, i, j, &o.offsets[hk], o.need);
                if bound >= o.need {
                    o.tops.push((bound, i, j, hk));
                }
            }
            o.tops.sort_by(|a, b| b.0.cmp(&a.0).then((a.3, a.2, a.1).cmp(&(b.3, b.2, b.1))));
        }
        let mut children: Vec<(usize, usize, usize)> = Vec::with_capacity(4);
        loop {
            let Some((bound, i, j, l, hk)) = o.stack.pop() else {
                match o.tops.get(o.next_descent) {
                    Some(&(bound, i, j, hk)) if bound >= o.need => {
                        o.next_descent += 1;
                        o.stack.push((bound, i, j, top, hk));
                        continue;
                    }
                    _ => break,
                }
            };
            if bound < o.need {
                continue;
            }
            if l == 0 {
                if bound > o.best {
                    o.best = bound;
                    o.need = o.need.max(o.best.saturating_sub(o.slack));
                }
                o.found.push((bound, i, j, hk));
                if o.found.len() >= KEPT {
                    o.found.sort_by_key(|f| std::cmp::Reverse(f.0));
                    o.found.truncate(KEPT / 2);
                    o.need = o.need.max(o.found.last().map_or(o.need, |f| f.0));
                }
                continue;
            }
            let s = 1usize << (l - 1);
            children.clear();
            for (di, dj) in [(0, 0), (s, 0), (0, s), (s, s)] {
                let (ci, cj) = (i + di, j + dj);
                if ci > x1 || cj > y1 || (l == 1 && !self.free[cj * self.width + ci]) {
                    continue;
                }
                if o.cost.squares >= limit {
                    // Looked into again when the search carries on (its children counted anew).
                    o.stack.push((bound, i, j, l, hk));
                    o.cost.cut = true;
                    return;
                }
                o.cost.squares += 1;
                let b = self.count(l - 1, ci, cj, &o.offsets[hk], o.need);
                if b >= o.need {
                    children.push((b, ci, cj));
                }
            }
            // The best child popped first.
            children.sort_by_key(|c| c.0);
            o.stack.extend(children.iter().map(|&(b, ci, cj)| (b, ci, cj, l - 1, hk)));
        }
        o.cost.cut = false;
        o.complete = true;
    }

    /// The endpoints (at `offsets` from block `(i, j)`) that land in near squares of level `l`,
    /// counted until `need` is out of reach.
    fn count(&self, l: usize, i: usize, j: usize, offsets: &[(isize, isize)], need: usize) -> usize {
        let grid = &self.levels[l];
        // A square that starts left of (below) the map but reaches into it is bounded by the
        // map's first square on that side, which covers all of its part on the map.
        let side = 1isize << l;
        let clamp = |a: isize| if a < 0 && a + side > 0 { 0 } else { a };
        let mut hits = 0;
        for (k, (du, dv)) in offsets.iter().enumerate() {
            let (u, v) = (clamp((i as isize).saturating_add(*du)), clamp((j as isize).saturating_add(*dv)));
            if u >= 0
                && v >= 0
                && (u as usize) < self.width
                && (v as usize) < self.height
                && grid[v as usize * self.width + u as usize]
            {
                hits += 1;
            } else if hits + (offsets.len() - k - 1) < need {
                return hits;
            }
        }
        hits
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::*;
    use crate::map::{FREE, OCCUPIED, OccupancyGrid};

    /// A 30 m × 20 m map at 0.05 m of rooms and corridors drawn as walls, none symmetric; its origin
    /// turned, so that the search's map frame is not the world's.
    fn rooms() -> OccupancyGrid {
        let mut g = OccupancyGrid::filled(600, 400, 0.05, Se2::new(-3.0, 2.0, 0.3), FREE);
        let mut wall = |a: [f64; 2], b: [f64; 2]| {
            let steps = ((b[0] - a[0]).hypot(b[1] - a[1]) / 0.02).ceil() as usize;
            for s in 0..=steps {
                let t = s as f64 / steps as f64;
                let (x, y) = (a[0] + (b[0] - a[0]) * t, a[1] + (b[1] - a[1]) * t);
                g.set((x / 0.05) as usize, (y / 0.05) as usize, OCCUPIED);
            }
        };
        wall([0.5, 0.5], [29.5, 0.5]);
        wall([29.5, 0.5], [29.5, 19.5]);
        wall([29.5, 19.5], [0.5, 19.5]);
        wall([0.5, 19.5], [0.5, 0.5]);
        wall([8.0, 0.5], [8.0, 12.0]);
        wall([8.0, 14.0], [8.0, 19.5]);
        wall([8.0, 7.0], [14.0, 7.0]);
        wall([17.0, 7.0], [29.5, 7.0]);
        wall([20.0, 7.0], [20.0, 15.5]);
        wall([12.0, 12.0], [16.0, 16.0]);
        wall([3.0, 4.0], [5.0, 4.0]);
        wall([24.0, 13.0], [26.5, 11.0]);
        g
    }

    /// Endpoints of a 360° scan of `beams` rays from `pose` (world), in the robot's frame: each
    /// ray marched to the first occupied cell, up to 25 m.
    fn scan(g: &OccupancyGrid, pose: &Se2, beams: usize) -> Vec<[f64; 2]> {
        let mut out = Vec::new();
        for b in 0..beams {
            let a = -PI + 2.0 * PI * b as f64 / beams as f64;
            let mut r = 0.1;
            while r < 25.0 {
                let w = pose.transform_point([r * a.cos(), r * a.sin()]);
                let m = g.origin.inverse().transform_point(w);
                let (i, j) = ((m[0] / g.resolution_m).floor(), (m[1] / g.resolution_m).floor());
                if i < 0.0 || j < 0.0 || i >= g.width as f64 || j >= g.height as f64 {
                    break;
                }
                if g.cells[j as usize * g.width + i as usize] == OCCUPIED {
                    out.push([r * a.cos(), r * a.sin()]);
                    break;
                }
                r += 0.01;
            }
        }
        out
    }

    fn field(g: &OccupancyGrid) -> Arc<LikelihoodField> {
        Arc::new(LikelihoodField::new(g, &crate::amcl::tests::shipped_params(), 25.0))
    }

    /// The truth is among the places found, whatever its heading, and the count at the truth's
    /// place is the whole scan.
    #[test]
    fn the_robot_is_among_the_places_found() {
        let g = rooms();
        let f = field(&g);
        let search = PlaceSearch::new(&f);
        for in_map in [Se2::new(4.7, 3.3, 0.4), Se2::new(23.1, 7.6, -2.6), Se2::new(12.4, 14.2, 1.9)] {
            let truth = g.origin * in_map;
            let points = scan(&g, &truth, 90);
            assert!(points.len() > 60, "{}", points.len());
            let (places, cost) = search.search(&points, 0.9, 20, (1.0, 0.35), u64::MAX, None);
            assert!(!cost.cut);
            // Found to the search's grain (blocks, and endpoints counted within `NEAR_M`: the
            // count is level over a few blocks around the truth) ...
            let off = |q: &Se2| {
                let d = truth.inverse() * *q;
                (d.translation_norm(), d.theta.abs())
            };
            let at = places.iter().position(|q| off(&q.pose).0 < 0.4 && off(&q.pose).1 < 0.07);
            let Some(at) = at else { panic!("truth {truth:?} not among {places:?}") };
            assert!(places[at].share > 0.97, "{:?}", places[at]);
            // ... and from there the likelihood's climb reaches it.
            let beams = crate::amcl::FixedPoints::new(&points);
            let (m, rad) = off(&crate::amcl::refine(&f, &beams, places[at].pose));
            assert!(m < 0.05 && rad < 0.01, "climbed to {m} m, {rad} rad off");
            eprintln!("truth {truth:?}: rank {at} of {}, {} squares", places.len(), cost.squares);
        }
    }

    /// A search within a square around a pose finds the robot there, with fewer squares counted than
    /// the whole map takes, and only places within the square; one around a pose 10 m away does not.
    #[test]
    fn a_search_within_a_square_finds_only_what_is_in_it() {
        let g = rooms();
        let search = PlaceSearch::new(&field(&g));
        let truth = g.origin * Se2::new(23.1, 7.6, -2.6);
        let points = scan(&g, &truth, 90);
        let within = |q: &Se2, at: &Se2, r: f64| {
            let (a, b) = (g.origin.inverse() * *q, g.origin.inverse() * *at);
            (a.x - b.x).abs() <= r + 0.1 && (a.y - b.y).abs() <= r + 0.1
        };
        let (all, whole) = search.search(&points, 0.6, 20, (1.0, 0.35), u64::MAX, None);
        let carried_off = truth * Se2::new(2.0, -3.0, 1.0);
        let centre = [carried_off.x, carried_off.y];
        let (near, cost) = search.search(&points, 0.6, 20, (1.0, 0.35), u64::MAX, Some((centre, 5.0)));
        assert!(!cost.cut && cost.squares < whole.squares, "{cost:?} against {whole:?}");
        let at =
            |places: &[Place]| places.iter().any(|q| (truth.inverse() * q.pose).translation_norm() < 0.4);
        assert!(at(&all) && at(&near), "near {near:?}");
        assert!(near.iter().all(|q| within(&q.pose, &carried_off, 5.0)), "{near:?}");
        let away = g.origin * Se2::new(10.0, 16.0, 0.0);
        let (far, _) = search.search(&points, 0.6, 20, (1.0, 0.35), u64::MAX, Some(([away.x, away.y], 3.0)));
        assert!(!at(&far) && far.iter().all(|q| within(&q.pose, &away, 3.0)), "{far:?}");
        // A window off the map, or no number, holds nothing.
        let off_map = search.search(&points, 0.6, 20, (1.0, 0.35), u64::MAX, Some(([500.0, -400.0], 5.0)));
        let nan = search.search(&points, 0.6, 20, (1.0, 0.35), u64::MAX, Some(([f64::NAN, 0.0], 5.0)));
        assert!(off_map.0.is_empty() && nan.0.is_empty() && nan.1.squares == 0);
    }

    /// The bound prunes nothing it should not: on a small map every block and heading whose count
    /// reaches the bar (counted directly, all blocks: the asked share, or a tenth of the endpoints
    /// below the best count where that is higher) is found by the search.
    #[test]
    fn the_search_finds_what_counting_every_block_finds() {
        let g = rooms();
        let f = field(&g);
        let search = PlaceSearch::new(&f);
        let truth = g.origin * Se2::new(27.3, 1.1, 2.2);
        let points = scan(&g, &truth, 40);
        let (places, cost) = search.search(&points, 0.7, usize::MAX, (0.0, 0.0), u64::MAX, None);
        // Every block and heading counted directly.
        let n = points.len();
        let need = (0.7 * n as f64).ceil() as usize;
        let step = 2.0 * PI / cost.headings as f64;
        let mut counts: Vec<usize> = Vec::new();
        for hk in 0..cost.headings {
            let (s, c) = (hk as f64 * step).sin_cos();
            let offsets: Vec<(isize, isize)> = points
                .iter()
                .map(|p| {
                    let (u, v) =
                        ((c * p[0] - s * p[1]) / search.block_m, (s * p[0] + c * p[1]) / search.block_m);
                    ((0.5 + u).floor() as isize, (0.5 + v).floor() as isize)
                })
                .collect();
            for j in 0..search.height {
                for i in 0..search.width {
                    if search.free[j * search.width + i] {
                        // Below the asked share it is not counted to the end.
                        counts.push(search.count(0, i, j, &offsets, need));
                    }
                }
            }
        }
        let best = counts.iter().copied().max().unwrap_or(0);
        let bar = need.max(best.saturating_sub((SLACK * n as f64).ceil() as usize));
        let direct = counts.iter().filter(|c| **c >= bar).count();
        assert!(direct > 0 && bar > need, "best {best} of {n}, bar {bar}");
        assert_eq!(places.len(), direct, "the search and the direct count disagree");
        assert!(places.iter().all(|q| q.share >= 0.7));
        let all = (search.width * search.height * cost.headings) as u64;
        assert!(cost.squares < all / 4, "pruned too little: {} of {all}", cost.squares);
    }

    /// A budget stops the search and says so; an empty scan finds nothing.
    #[test]
    fn a_search_is_bounded() {
        let g = rooms();
        let search = PlaceSearch::new(&field(&g));
        let points = scan(&g, &(g.origin * Se2::new(5.0, 10.0, 0.3)), 60);
        let (_, cost) = search.search(&points, 0.8, 10, (1.0, 0.35), 1_000, None);
        assert!(cost.cut && cost.squares == 1_000, "{cost:?}");
        assert!(search.search(&[], 0.8, 10, (1.0, 0.35), u64::MAX, None).0.is_empty());
        assert!(search.search(&points, f64::NAN, 10, (1.0, 0.35), u64::MAX, None).0.is_empty());
        // Endpoints that are no place, or far off any map, are not a reason to fail.
        let odd = [[f64::NAN, 1.0], [f64::INFINITY, 0.0], [1e300, -1e300], [3.0, 4.0], [-2.0, 0.5]];
        let (_, cost) = search.search(&odd, 0.5, 10, (1.0, 0.35), 100_000, None);
        assert!(cost.squares > 0);
    }

    /// A search carried on a budget at a time (budgets that stop it while it bounds the top
    /// level's squares, and while it descends) finds the places one run finds, in the same order;
    /// each run counts no more than its budget (at least 4) and, stopped, says so.
    #[test]
    fn a_search_carried_on_finds_what_one_run_finds() {
        let g = rooms();
        let search = PlaceSearch::new(&field(&g));
        for (k, at) in [Se2::new(5.0, 10.0, 0.3), Se2::new(21.0, 4.0, -2.0)].iter().enumerate() {
            let points = scan(&g, &(g.origin * *at), 60);
            for bar in [0.5, 0.8] {
                let (once, cost) = search.search(&points, bar, 20, (1.0, 0.35), u64::MAX, None);
                assert!(!cost.cut && !once.is_empty(), "place {k} at {bar}: {cost:?}");
                for budget in [1u64, 777, 20_000] {
                    let most = budget.max(4);
                    let mut ongoing = search.start(&points, bar, 20, (1.0, 0.35));
                    let mut runs = 0u64;
                    while !ongoing.complete() {
                        let before = ongoing.cost().squares;
                        search.carry_on(&mut ongoing, budget);
                        let counted = ongoing.cost().squares - before;
                        assert!(counted <= most, "counted {counted} on a budget of {budget}");
                        assert_eq!(ongoing.cost().cut, !ongoing.complete());
                        runs += 1;
                        assert!(runs <= cost.squares + 1, "no end on a budget of {budget}");
                    }
                    assert!(runs > 1, "place {k} at {bar}: one budget of {budget} sufficed");
                    assert_eq!(ongoing.places(), once, "place {k} at {bar} on a budget of {budget}");
                }
            }
        }
    }
}
