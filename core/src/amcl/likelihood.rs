//! The likelihood-field sensor model (Thrun et al., Probabilistic Robotics §6.4; nav2_amcl
//! `likelihood_field_model.cpp` and `likelihood_field_model_prob.cpp`): the grid stores each cell's
//! final per-beam term so that a beam costs one lookup (as Beluga does).

use crate::config::{AmclParams, LaserModel};
use crate::map::{OccupancyGrid, capped_distance_q};
use crate::se2::Se2;

/// The per-beam term is nav2's `pz = z_hit·exp(−d²/2σ²) + z_rand/range_max` (without the
/// Gaussian's normalisation), stored as `pz³` for nav2's `1 + Σ pz³` aggregation or as `ln pz` for
/// the product model, with `d` capped at `laser_likelihood_max_dist`.
///
/// `d` is the distance from the endpoint to the nearest *surface cell*'s centre: an occupied cell
/// with a free cell among its 8 neighbours, a face a beam can reach. A wall that the mapping saw
/// from one side is a band of occupied cells with unknown ones behind it; the band's far side is no
/// surface (counting it puts a second optimum behind every such wall).
/// Measured on four public CARMEN logs (`amr bench localize`, seeds 1–5, tracking RMSE, to the
/// boundary / to surface cells): aces 8.1–9.2 / 8.2–9.2 cm, freiburg-079 7.0–7.3 / 6.2–6.4,
/// freiburg-101 6.1–6.5 / 5.9–6.5, intel 6.8–6.9 / 6.5–6.6; freiburg-079's global run with seed 4
/// 9.4 m (lost) / 7.3 cm.
/// Why the surface and not either of the two obvious choices:
///
/// - nav2 (and a plain distance transform) measures to the nearest occupied centre, so `d` is 0
///   anywhere inside an obstacle. Where the faces that fix a direction are seen from one side only
///   (a corridor looking ahead) and the obstacle is thick, the likelihood is flat over the thickness
///   and the estimate slides into the wall (measured on our polygon corridor: up to +9.5 cm).
///   Measuring to surface cells keeps `d` growing inside thick obstacles.
/// - The distance to the occupied/free *boundary* is right only for a
///   map whose walls are drawn exactly on cell faces. A map built the way SLAM builds maps marks the
///   cell an endpoint falls in, so the surface lies, on average, at that cell's centre, not on its
///   face: the boundary distance is res/2 off on every beam and has two optima per one-cell wall.
///   Measured on three public CARMEN logs (maximum-likelihood pose offset at the reference poses, 60
///   beams, σ 0.1 m): 5.6–6.3 cm RMS with the boundary distance, 3.7–4.2 cm with the centre one.
///
/// For one lookup per beam the capped `d` is quantised to a byte (steps of `max_dist/255`, 7.8 mm at
/// nav2's 2 m) and interpolated bilinearly between the map's cell centres onto a grid [`SUBDIVISION`]
/// times finer than the map (for maps of up to [`FINE_MAP_CELLS`]; larger ones keep the map's
/// resolution); the factor comes from a 256-entry table. That is 4 bytes per map cell (1 for large
/// maps), where f32 factors at twice the resolution took 16 (plus 4 for the distances).
#[derive(Debug, Clone)]
pub struct LikelihoodField {
    /// Quantised distances, `SUBDIVISION` times finer than the map, row-major from the bottom row.
    fine_width: usize,
    fine_height: usize,
    inv_fine_resolution: f64,
    cells: Vec<u8>,
    /// The factor of each quantised distance.
    table: [f64; 256],
    /// Metres per quantisation step.
    step_m: f64,
    world_to_map: Se2,
    /// `sin_cos` of `world_to_map`'s rotation.
    map_rotation: (f64, f64),
    map_to_world: Se2,
    /// The free cells (AMCL's "free": exactly 0), for random poses.
    free: FreeCells,
    width: usize,
    resolution: f64,
    model: LaserModel,
    /// The exhaustive place search's grids, built when first asked for (a filter that is never
    /// lost never needs them).
    places: std::sync::OnceLock<super::places::PlaceSearch>,
}

/// Points in a robot's frame as fixed-point metres (× 2¹⁶, 15 µm), converted once per scan for the
/// field's integer lookups ([`LikelihoodField::log_likelihood_of`]).
#[derive(Debug, Clone, Default)]
pub struct FixedPoints {
    xy: Vec<(i64, i64)>,
}

impl FixedPoints {
    #[must_use]
    pub fn new(points: &[[f64; 2]]) -> Self {
        let f = |v: f64| (v * 65_536.0).round() as i64;
        FixedPoints { xy: points.iter().map(|p| (f(p[0]), f(p[1]))).collect() }
    }

    #[must_use]
    pub fn len(&self) -> usize {
        self.xy.len()
    }

    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.xy.is_empty()
    }
}

/// How many factor cells per map cell along each axis, for maps of at most [`FINE_MAP_CELLS`].
pub const SUBDIVISION: usize = 2;
/// Larger maps get one factor cell per map cell (a nearest-cell lookup as nav2's), so that a
/// 200 m × 600 m map at 0.05 m (48 M cells) needs 48 MB, not 192.
pub const FINE_MAP_CELLS: usize = 16_000_000;

fn subdivision(width: usize, height: usize) -> usize {
    if width.saturating_mul(height) <= FINE_MAP_CELLS { SUBDIVISION } else { 1 }
}

/// The distances interpolated bilinearly between map cell centres onto a grid `sub` times finer.
fn refine(dist: &[u8], w: usize, h: usize, sub: usize) -> Vec<u8> {
    let (fw, fh) = (w * sub, h * sub);
    let mut cells = vec![OFF_MAP; fw * fh];
    if w == 0 || h == 0 {
        return cells;
    }
    // The quantised distance at map cell (i, j), clamped to the map (flat beyond its border).
    let d_at = |i: isize, j: isize| -> f64 {
        let i = i.clamp(0, w as isize - 1) as usize;
        let j = j.clamp(0, h as isize - 1) as usize;
        f64::from(dist[j * w + i])
    };
    let k = sub as f64;
    for b in 0..fh {
        // The fine cell's centre in map-cell units, relative to the centre of cell 0.
        let v = (b as f64 + 0.5) / k - 0.5;
        let (j, fy) = (v.floor() as isize, v - v.floor());
        for a in 0..fw {
            let u = (a as f64 + 0.5) / k - 0.5;
            let (i, fx) = (u.floor() as isize, u - u.floor());
            let bottom = d_at(i, j) + (d_at(i + 1, j) - d_at(i, j)) * fx;
            let top = d_at(i, j + 1) + (d_at(i + 1, j + 1) - d_at(i, j + 1)) * fx;
            cells[b * fw + a] = (bottom + (top - bottom) * fy).round().clamp(0.0, f64::from(OFF_MAP)) as u8;
        }
    }
    cells
}

/// The free cells as runs along rows: a uniform draw is a binary search, and a map of 48 M cells
/// with half of them free holds a few hundred thousand runs instead of 24 M indices.
#[derive(Debug, Clone, Default)]
struct FreeCells {
    /// First cell (row-major index) of each run.
    starts: Vec<u32>,
    /// Free cells before the end of each run.
    ends: Vec<u64>,
}

impl FreeCells {
    fn of(grid: &OccupancyGrid) -> Self {
        let mut f = FreeCells::default();
        let mut total = 0u64;
        let mut run: Option<usize> = None;
        let w = grid.width.max(1);
        for (k, c) in grid.cells.iter().enumerate() {
            let free = *c == crate::map::FREE;
            // Runs stop at row ends, so that a run is a stretch of one row.
            if let Some(s) = run
                && (!free || k % w == 0)
            {
                total += (k - s) as u64;
                f.starts.push(s as u32);
                f.ends.push(total);
                run = None;
            }
            if free && run.is_none() {
                run = Some(k);
            }
        }
        if let Some(s) = run {
            total += (grid.cells.len() - s) as u64;
            f.starts.push(s as u32);
            f.ends.push(total);
        }
        f
    }

    fn count(&self) -> usize {
        self.ends.last().map_or(0, |e| *e as usize)
    }

    /// The row-major index of the `n`-th free cell.
    fn nth(&self, n: usize) -> usize {
        let r = self.ends.partition_point(|e| *e <= n as u64).min(self.starts.len().saturating_sub(1));
        let before = if r == 0 { 0 } else { self.ends[r - 1] };
        self.starts[r] as usize + (n as u64 - before) as usize
    }

    fn bytes(&self) -> usize {
        self.starts.len() * 4 + self.ends.len() * 8
    }
}

/// Where [`LikelihoodField::ray_crosses_surface`] starts looking, from the sensor, m.
const RAY_START_M: f64 = 0.1;

/// The index of the largest quantised distance, which is also the value off the map.
const OFF_MAP: u8 = u8::MAX;

impl LikelihoodField {
    /// `range_max_m` is the sensor's maximum range used in the `z_rand` term.
    #[must_use]
    pub fn new(grid: &OccupancyGrid, params: &AmclParams, range_max_m: f64) -> Self {
        let (w, h, res) = (grid.width, grid.height, grid.resolution_m);
        let max_d = params.laser_likelihood_max_dist.get();
        let surface = surface_cells(grid);
        let dist = capped_distance_q(&surface, w, h, res, max_d);
        drop(surface);
        let (z_hit, z_rand, sigma) = (params.z_hit.get(), params.z_rand.get(), params.sigma_hit.get());
        let rand_term = if range_max_m > 0.0 { z_rand / range_max_m } else { 0.0 };
        let model = params.laser_model_type;
        let step_m = max_d / f64::from(OFF_MAP);
        let mut table = [0f64; 256];
        for (q, t) in table.iter_mut().enumerate() {
            let d = q as f64 * step_m;
            let pz = z_hit * (-(d * d) / (2.0 * sigma * sigma)).exp() + rand_term;
            *t = match model {
                LaserModel::LikelihoodField => pz * pz * pz,
                // pz > 0 is guaranteed by the config (z_hit + z_rand > 0); guard anyway.
                LaserModel::LikelihoodFieldProb => pz.max(f64::MIN_POSITIVE).ln(),
            };
        }
        let sub = subdivision(w, h);
        let cells = if sub == 1 { dist } else { refine(&dist, w, h, sub) };
        LikelihoodField {
            fine_width: w * sub,
            fine_height: h * sub,
            inv_fine_resolution: sub as f64 / res,
            cells,
            table,
            step_m,
            world_to_map: grid.origin.inverse(),
            map_rotation: grid.origin.inverse().theta.sin_cos(),
            map_to_world: grid.origin,
            free: FreeCells::of(grid),
            width: w,
            resolution: res,
            model,
            places: std::sync::OnceLock::new(),
        }
    }

    /// The (capped, quantised) distance in metres from a world point to the nearest surface cell's
    /// centre, as the field stores it; `None` off the map.
    #[must_use]
    pub fn distance(&self, p: [f64; 2]) -> Option<f64> {
        self.world_index(p).map(|k| f64::from(self.cells[k]) * self.step_m)
    }

    /// The fine cell holding a world point, by the same arithmetic as the filter's lookups.
    fn world_index(&self, p: [f64; 2]) -> Option<usize> {
        let (u0, v0, cr, sr) = self.fixed_pose(&Se2::IDENTITY);
        let &(x, y) = FixedPoints::new(&[p]).xy.first()?;
        self.fixed_index(u0, v0, cr, sr, x, y)
    }

    /// A pose in the map frame scaled to fine cells, as `(u0, v0, cos·k, sin·k)`: a base-frame point
    /// `p` lands at `(u0 + cos·k·p.x − sin·k·p.y, v0 + sin·k·p.x + cos·k·p.y)`. One `sin_cos` per
    /// pose (composing `Se2`s would take two and a normalisation).
    #[inline]
    fn fine_pose(&self, pose: &Se2) -> (f64, f64, f64, f64) {
        let (sp, cp) = pose.theta.sin_cos();
        let (s0, c0) = self.map_rotation;
        let m = &self.world_to_map;
        let r = self.inv_fine_resolution;
        let (x, y) = (m.x + c0 * pose.x - s0 * pose.y, m.y + s0 * pose.x + c0 * pose.y);
        (x * r, y * r, (c0 * cp - s0 * sp) * r, (s0 * cp + c0 * sp) * r)
    }

    /// The per-beam factor at a world point.
    #[must_use]
    pub fn at(&self, p: [f64; 2]) -> f64 {
        self.table[usize::from(self.world_index(p).map_or(OFF_MAP, |k| self.cells[k]))]
    }

    /// The log-likelihood of the points (base frame) seen from `pose`: `ln(1 + Σ pz³)` (nav2
    /// likelihood_field) or `Σ ln pz` (likelihood_field_prob). Logs keep a product over hundreds of
    /// virtual-scan points from underflowing.
    #[must_use]
    pub fn log_likelihood(&self, pose: &Se2, points: &[[f64; 2]]) -> f64 {
        self.log_likelihood_of(pose, &FixedPoints::new(points))
    }

    /// [`Self::log_likelihood`] of points converted once (for many poses).
    #[must_use]
    pub fn log_likelihood_of(&self, pose: &Se2, points: &FixedPoints) -> f64 {
        let (u0, v0, cr, sr) = self.fixed_pose(pose);
        let sum: f64 = points
            .xy
            .iter()
            .map(|&(x, y)| self.table[usize::from(self.fixed_lookup(u0, v0, cr, sr, x, y))])
            .sum();
        match self.model {
            LaserModel::LikelihoodField => sum.ln_1p(),
            LaserModel::LikelihoodFieldProb => sum,
        }
    }

    /// The quantised distances of the points seen from `pose`, into `out` (one per point);
    /// [`Self::factor`] turns them into per-beam factors.
    pub fn quantised_distances(&self, pose: &Se2, points: &FixedPoints, out: &mut [u8]) {
        let (u0, v0, cr, sr) = self.fixed_pose(pose);
        for (&(x, y), o) in points.xy.iter().zip(out) {
            *o = self.fixed_lookup(u0, v0, cr, sr, x, y);
        }
    }

    /// A pose as fixed-point numbers for [`Self::fixed_lookup`]: the origin in fine cells × 2³², the
    /// rotation's cosine and sine in fine cells per metre × 2¹⁶.
    #[inline]
    fn fixed_pose(&self, pose: &Se2) -> (i64, i64, i64, i64) {
        let (u0, v0, cr, sr) = self.fine_pose(pose);
        let (hi, lo) = (4_294_967_296.0, 65_536.0);
        ((u0 * hi) as i64, (v0 * hi) as i64, (cr * lo) as i64, (sr * lo) as i64)
    }

    /// The quantised distance where a point (metres × 2¹⁶) lands from a fixed-point pose. Integer
    /// arithmetic: an arithmetic shift is a floor, one unsigned compare per axis rejects both sides,
    /// and nothing can overflow into a panic (wrapping; a wrapped index is off the map). This is the
    /// inner loop of every filter update: a float-to-int conversion with Rust's saturation costs
    /// five instructions per axis on x86-64, and `floor` is a library call without SSE4.1.
    #[inline]
    fn fixed_lookup(&self, u0: i64, v0: i64, cr: i64, sr: i64, x: i64, y: i64) -> u8 {
        self.fixed_index(u0, v0, cr, sr, x, y).map_or(OFF_MAP, |k| self.cells[k])
    }

    /// The fine cell a point lands in, if on the map. A row index outside the map (either side)
    /// gives a cell index beyond the grid, so one compare on the column and the slice's own bound
    /// check reject everything off the map.
    #[inline]
    fn fixed_index(&self, u0: i64, v0: i64, cr: i64, sr: i64, x: i64, y: i64) -> Option<usize> {
        let u = u0.wrapping_add(cr.wrapping_mul(x)).wrapping_sub(sr.wrapping_mul(y));
        let v = v0.wrapping_add(sr.wrapping_mul(x)).wrapping_add(cr.wrapping_mul(y));
        let (i, j) = ((u >> 32) as u64, (v >> 32) as u64);
        if i >= self.fine_width as u64 || j >= self.fine_height as u64 {
            return None;
        }
        Some(j as usize * self.fine_width + i as usize)
    }

    /// Whether the straight line from `from` to `to` (base-frame points seen from `pose`) comes
    /// within half a map cell of a mapped surface before it is `stop_short_m` from `to`: a beam
    /// from a sensor at `from` that passed through a wall to reach `to`. Sphere tracing on the
    /// field's distances (each step as long as the distance to the nearest surface, at least half
    /// a cell), so a ray costs a few dozen lookups; off the map ends the search (nothing mapped
    /// there to cross). Distances beyond the field's cap are taken as the cap.
    #[must_use]
    pub fn ray_crosses_surface(&self, pose: &Se2, from: [f64; 2], to: [f64; 2], stop_short_m: f64) -> bool {
        let (u0, v0, cr, sr) = self.fine_pose(pose);
        let fine = |p: [f64; 2]| (u0 + cr * p[0] - sr * p[1], v0 + sr * p[0] + cr * p[1]);
        let (a, b) = (fine(from), fine(to));
        let length_m = (to[0] - from[0]).hypot(to[1] - from[1]);
        let end_m = length_m - stop_short_m;
        if !(end_m > 0.0 && end_m.is_finite()) {
            return false;
        }
        let (dx, dy) = ((b.0 - a.0) / length_m, (b.1 - a.1) / length_m);
        let near = self.resolution * 0.5;
        let step_min = self.resolution * 0.5;
        // Clear of the sensor itself (a pose a little off may stand it in a wall's cell).
        let mut t = RAY_START_M;
        // At most one step per half cell over the ray: bounded for any input.
        let cap = (end_m / step_min).ceil().min(1e6) as usize + 1;
        for _ in 0..cap {
            if t >= end_m {
                return false;
            }
            let (u, v) = (a.0 + dx * t, a.1 + dy * t);
            if !(u >= 0.0 && v >= 0.0 && u < self.fine_width as f64 && v < self.fine_height as f64) {
                return false;
            }
            let idx = v as usize * self.fine_width + u as usize;
            let Some(&q) = self.cells.get(idx) else { return false };
            let d = f64::from(q) * self.step_m;
            if d < near {
                return true;
            }
            t += d.max(step_min);
        }
        false
    }

    /// The per-beam factor of a quantised distance (`pz³` or `ln pz`, by model).
    #[must_use]
    pub fn factor(&self, q: u8) -> f64 {
        self.table[usize::from(q)]
    }

    /// The quantised distances strictly below `distance_m` are those `< quantum_of(distance_m)`.
    #[must_use]
    pub fn quantum_of(&self, distance_m: f64) -> u16 {
        (distance_m / self.step_m).ceil().clamp(0.0, 256.0) as u16
    }

    /// Number of free cells.
    #[must_use]
    pub fn free_count(&self) -> usize {
        self.free.count()
    }

    /// The world centre of the `n`-th free cell (`n < free_count()`).
    #[must_use]
    pub fn free_cell(&self, n: usize) -> [f64; 2] {
        let k = self.free.nth(n);
        let (i, j) = (k % self.width.max(1), k / self.width.max(1));
        self.map_to_world
            .transform_point([(i as f64 + 0.5) * self.resolution, (j as f64 + 0.5) * self.resolution])
    }

    #[must_use]
    pub fn resolution_m(&self) -> f64 {
        self.resolution
    }

    /// The map in square blocks of `k` map cells, for the exhaustive place search
    /// ([`super::places::PlaceSearch`]): the block grid's width and height, and per block
    /// (row-major from the bottom row, as the map) whether some point in it is within `tol_m` of a
    /// mapped surface by the field's distances, and whether it holds a free cell.
    pub(super) fn blocks(&self, k: usize, tol_m: f64) -> (usize, usize, Vec<bool>, Vec<bool>) {
        let k = k.max(1);
        let w = self.width;
        let sub = self.fine_width.checked_div(w).unwrap_or(1).max(1);
        let h = self.fine_height / sub;
        let (bw, bh) = (w.div_ceil(k), h.div_ceil(k));
        let mut near = vec![false; bw * bh];
        let mut free = vec![false; bw * bh];
        let q = self.quantum_of(tol_m);
        let fine_k = k * sub;
        for (idx, &d) in self.cells.iter().enumerate() {
            if u16::from(d) <= q {
                let (a, b) = (idx % self.fine_width, idx / self.fine_width);
                if let Some(cell) = near.get_mut((b / fine_k) * bw + a / fine_k) {
                    *cell = true;
                }
            }
        }
        let mut before = 0u64;
        for (&start, &end) in self.free.starts.iter().zip(&self.free.ends) {
            let len = (end - before) as usize;
            before = end;
            let start = start as usize;
            let (i0, j) = (start % w.max(1), start / w.max(1));
            for bi in i0 / k..=(i0 + len.max(1) - 1) / k {
                if let Some(cell) = free.get_mut((j / k) * bw + bi) {
                    *cell = true;
                }
            }
        }
        (bw, bh, near, free)
    }

    /// The map's origin: map-frame poses to the world.
    pub(super) fn map_to_world(&self) -> Se2 {
        self.map_to_world
    }

    /// The exhaustive place search over this map (its grids built on the first call).
    pub fn place_search(&self) -> &super::places::PlaceSearch {
        self.places.get_or_init(|| super::places::PlaceSearch::new(self))
    }

    /// Bytes held by the field's grids (the resident cost of a map; the place search's once built).
    #[must_use]
    pub fn heap_bytes(&self) -> usize {
        self.cells.len()
            + self.free.bytes()
            + self.places.get().map_or(0, super::places::PlaceSearch::heap_bytes)
    }
}

/// Occupied cells with a free cell among their 8 neighbours: the faces a beam can reach.
fn surface_cells(grid: &OccupancyGrid) -> Vec<bool> {
    let (w, h) = (grid.width, grid.height);
    let free = |i: usize, j: usize| grid.cells[j * w + i] == crate::map::FREE;
    (0..w * h)
        .map(|k| {
            let (i, j) = (k % w, k / w);
            grid.cells[k] == crate::map::OCCUPIED
                && (j.saturating_sub(1)..(j + 2).min(h))
                    .any(|jj| (i.saturating_sub(1)..(i + 2).min(w)).any(|ii| free(ii, jj)))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::{FREE, OCCUPIED, UNKNOWN};

    #[test]
    fn factor_by_hand() {
        // 1 m × 0.3 m at 0.1 m; the left column is a one-cell wall, as SLAM marks the cells that
        // endpoints fall in: the surface is (on average) at the cell centre, x = 0.05.
        let mut g = OccupancyGrid::filled(10, 3, 0.1, Se2::IDENTITY, FREE);
        for j in 0..3 {
            g.set(0, j, OCCUPIED);
        }
        let mut params = crate::amcl::tests::shipped_params();
        params.laser_model_type = LaserModel::LikelihoodField;
        let f = LikelihoodField::new(&g, &params, 10.0);
        let step = params.laser_likelihood_max_dist.get() / 255.0;
        let d = |x: f64| f.distance([x, 0.15]).unwrap();
        // Fine cells are 0.05 m; each holds the distance at its centre (interpolated between map
        // cell centres, exact for a flat wall), to within half a quantisation step.
        let near = |a: f64, b: f64| (a - b).abs() <= step / 2.0 + 1e-9;
        assert!(near(d(0.36), 0.375 - 0.05), "{}", d(0.36));
        assert!(near(d(0.11), 0.125 - 0.05));
        // Zero at the wall cell's centre, not on its face (the boundary distance said 0 at 0.1).
        assert!(near(d(0.06), 0.025));
        assert!(near(d(0.04), 0.0), "flat at the map's border");
        assert!(d(0.04) < d(0.11), "the face is not the surface");
        let pz = |d: f64| 0.5 * (-(d * d) / (2.0 * 0.2 * 0.2)).exp() + 0.5 / 10.0;
        let q = |d: f64| (d / step).round() * step;
        let at = |x: f64| f.at([x, 0.15]);
        assert!((at(0.36) - pz(q(0.325)).powi(3)).abs() < 1e-6);
        // Off the map: the cap, 2 m.
        assert!((f.at([-5.0, 0.0]) - pz(2.0).powi(3)).abs() < 1e-6);
        assert_eq!(f.distance([-5.0, 0.0]), None);
        assert_eq!(f.free_count(), 27);
        let c = f.free_cell(0);
        assert!((c[0] - 0.15).abs() < 1e-12 && (c[1] - 0.05).abs() < 1e-12, "{c:?}");
        let ll = f.log_likelihood(&Se2::IDENTITY, &[[0.06, 0.15], [0.36, 0.15]]);
        assert!((ll - (1.0 + pz(q(0.025)).powi(3) + pz(q(0.325)).powi(3)).ln()).abs() < 1e-6);
        // The product model stores ln pz.
        let mut prob = params.clone();
        prob.laser_model_type = LaserModel::LikelihoodFieldProb;
        let f = LikelihoodField::new(&g, &prob, 10.0);
        let ll = f.log_likelihood(&Se2::IDENTITY, &[[0.06, 0.15], [0.36, 0.15]]);
        assert!((ll - (pz(q(0.025)).ln() + pz(q(0.325)).ln())).abs() < 1e-5);
        let mut qd = [0u8; 2];
        f.quantised_distances(&Se2::IDENTITY, &FixedPoints::new(&[[0.06, 0.15], [-3.0, 0.0]]), &mut qd);
        assert_eq!(qd, [3, 255]);
        assert!((f.factor(3) - pz(q(0.025)).ln()).abs() < 1e-6);
    }

    #[test]
    fn the_unseen_side_of_a_wall_is_no_surface() {
        // A wall two cells thick (columns 4 and 5), seen from the left as a survey sees it: free
        // before it, unknown behind. Only column 4 borders free space; column 5 borders unknown
        // cells, which no beam has crossed, so an endpoint there is a cell behind the surface.
        let mut g = OccupancyGrid::filled(10, 5, 0.1, Se2::IDENTITY, UNKNOWN);
        for j in 0..5 {
            for i in 0..4 {
                g.set(i, j, FREE);
            }
            g.set(4, j, OCCUPIED);
            g.set(5, j, OCCUPIED);
        }
        // An occupied cell that touches free space only at a corner is a surface: (8, 1) with
        // (9, 0) free.
        g.set(8, 1, OCCUPIED);
        g.set(9, 0, FREE);
        // An occupied cell with no free cell anywhere around it is none: (8, 4).
        g.set(8, 4, OCCUPIED);
        let surface = surface_cells(&g);
        let at = |i: usize, j: usize| surface[j * 10 + i];
        assert!((0..5).all(|j| at(4, j) && !at(5, j)));
        assert!(at(8, 1) && !at(8, 4));
        let f = LikelihoodField::new(&g, &crate::amcl::tests::shipped_params(), 10.0);
        let d = |x: f64| f.distance([x, 0.25]).unwrap();
        // Fine cells are 0.05 m; the one centred at 0.575 is a cell behind the surface's centre.
        assert!(d(0.46) < 0.03, "{}", d(0.46));
        assert!((d(0.56) - 0.125).abs() < 0.01, "{}", d(0.56));
        assert!(d(0.56) > d(0.46));
    }

    #[test]
    fn inside_a_thick_obstacle_the_distance_grows_again() {
        // A block of columns 3..8 (x 0.3–0.8) and rows 2..11: its surface cells are its outer ring,
        // e.g. columns 3 and 7 at row 6.
        let mut g = OccupancyGrid::filled(12, 13, 0.1, Se2::IDENTITY, FREE);
        for i in 3..8 {
            for j in 2..11 {
                g.set(i, j, OCCUPIED);
            }
        }
        let f = LikelihoodField::new(&g, &crate::amcl::tests::shipped_params(), 10.0);
        let d = |x: f64| f.distance([x, 0.65]).unwrap();
        // nav2 (distance to any occupied centre) says 0 everywhere in 0.3..0.8. Fine cell centres
        // are at x = 0.375, 0.475, 0.575, …, interpolated between the map's cell centres.
        assert!((d(0.36) - 0.025).abs() < 0.01 && (d(0.74) - 0.025).abs() < 0.01);
        assert!((d(0.56) - 0.175).abs() < 0.01, "{}", d(0.56));
        assert!(d(0.46) > d(0.36) && d(0.56) > d(0.46) && d(0.66) < d(0.56));
    }
}
