//! The likelihood-field sensor model (Thrun et al., Probabilistic Robotics §6.4; nav2_amcl
//! `likelihood_field_model.cpp` and `likelihood_field_model_prob.cpp`): the grid stores each cell's
//! final per-beam term so that a beam costs one lookup (as Beluga does).

use crate::config::{AmclParams, LaserModel};
use crate::map::{OccupancyGrid, euclidean_distance_m};
use crate::se2::Se2;

/// The per-beam term is nav2's `pz = z_hit·exp(−d²/2σ²) + z_rand/range_max` (without the
/// Gaussian's normalisation), stored as `pz³` for nav2's `1 + Σ pz³` aggregation or as `ln pz` for
/// the product model, with `d` capped at `laser_likelihood_max_dist`.
///
/// Where this differs from nav2 is `d`. nav2 (and a plain distance transform) takes the distance from
/// the endpoint's cell centre to the nearest occupied cell *centre*, and 0 anywhere inside an
/// obstacle. A LiDAR sees the obstacle's *surface*, the boundary between occupied and other cells.
/// With nav2's `d` the best-scoring place for an endpoint is anywhere inside the wall, so where the
/// faces that fix a direction are seen from one side only (a corridor looking ahead) the likelihood
/// is flat over the wall's thickness and the estimate slides up to a wall thickness beyond the truth.
/// Measured in our corridor (`scenarios.rs`): the maximum-likelihood shift along the corridor at the
/// true heading was up to +9.5 cm with nav2's `d`, 0 (±5 mm, the probe's step) with this one.
///
/// Here `d` is the distance to the surface: a signed distance at the map's cell centres (`+` outside
/// obstacles: distance to the nearest occupied centre − res/2; `−` inside: distance to the nearest
/// non-occupied centre − res/2), interpolated bilinearly, so that it is 0 on the face between an
/// occupied and a free cell and grows on both sides. To keep one lookup per beam, the factor of that
/// interpolated `|d|` is sampled on a grid [`SUBDIVISION`] times finer than the map (so 4 × 4 bytes
/// per map cell; the surface is placed to within a quarter cell).
#[derive(Debug, Clone)]
pub struct LikelihoodField {
    /// The factor grid, `SUBDIVISION` times finer than the map, row-major from the bottom row.
    fine_width: usize,
    fine_height: usize,
    inv_fine_resolution: f64,
    cells: Vec<f32>,
    world_to_map: Se2,
    /// The map's signed distances (m) at its cell centres plus a one-cell ring repeating the edge.
    padded_width: usize,
    padded_height: usize,
    signed: Vec<f32>,
    /// Off the map a point is as far as the cap (nav2 counts off-map as `max_occ_dist`).
    off_map: f32,
    /// Centres of the free cells (AMCL's "free": exactly 0), for random poses.
    free: Vec<[f64; 2]>,
    resolution: f64,
    model: LaserModel,
}

/// How many factor cells per map cell along each axis.
pub const SUBDIVISION: usize = 2;

impl LikelihoodField {
    /// `range_max_m` is the sensor's maximum range used in the `z_rand` term.
    #[must_use]
    pub fn new(grid: &OccupancyGrid, params: &AmclParams, range_max_m: f64) -> Self {
        let (w, h, res) = (grid.width, grid.height, grid.resolution_m);
        let occupied: Vec<bool> = grid.cells.iter().map(|&c| c == crate::map::OCCUPIED).collect();
        let not_occupied: Vec<bool> = occupied.iter().map(|o| !o).collect();
        let to_occupied = euclidean_distance_m(&occupied, w, h, res);
        let to_outside = euclidean_distance_m(&not_occupied, w, h, res);
        let max_d = params.laser_likelihood_max_dist.get();
        let (pw, ph) = (w + 2, h + 2);
        // The ring repeats the edge cells, so that interpolation at the map's border stays flat.
        let signed = (0..ph)
            .flat_map(|pj| (0..pw).map(move |pi| (pi, pj)))
            .map(|(pi, pj)| {
                let k = pj.clamp(1, h.max(1)).saturating_sub(1) * w + pi.clamp(1, w.max(1)).saturating_sub(1);
                let d = match occupied.get(k) {
                    Some(true) => -(to_outside[k] - res / 2.0).min(max_d),
                    Some(false) => (to_occupied[k] - res / 2.0).min(max_d),
                    None => max_d,
                };
                d as f32
            })
            .collect();
        let (z_hit, z_rand, sigma) = (params.z_hit.get(), params.z_rand.get(), params.sigma_hit.get());
        let rand_term = if range_max_m > 0.0 { z_rand / range_max_m } else { 0.0 };
        let model = params.laser_model_type;
        let factor = |d: f64| {
            let d = d.min(max_d);
            let pz = z_hit * (-(d * d) / (2.0 * sigma * sigma)).exp() + rand_term;
            match model {
                LaserModel::LikelihoodField => (pz * pz * pz) as f32,
                // pz > 0 is guaranteed by the config (z_hit + z_rand > 0); guard anyway.
                LaserModel::LikelihoodFieldProb => pz.max(f64::MIN_POSITIVE).ln() as f32,
            }
        };
        let free = (0..h)
            .flat_map(|j| (0..w).map(move |i| (i, j)))
            .filter(|&(i, j)| grid.is_free(i, j))
            .map(|(i, j)| grid.cell_center(i, j))
            .collect();
        let mut field = LikelihoodField {
            fine_width: w * SUBDIVISION,
            fine_height: h * SUBDIVISION,
            inv_fine_resolution: SUBDIVISION as f64 / res,
            cells: Vec::new(),
            world_to_map: grid.origin.inverse(),
            padded_width: pw,
            padded_height: ph,
            signed,
            off_map: factor(max_d),
            free,
            resolution: res,
            model,
        };
        let k = SUBDIVISION as f64;
        field.cells = (0..field.fine_height)
            .flat_map(|b| (0..field.fine_width).map(move |a| (a, b)))
            .map(|(a, b)| {
                // The fine cell's centre in map cells, then in the padded centres' index.
                let (x, y) = ((a as f64 + 0.5) / k, (b as f64 + 0.5) / k);
                field.signed_at(x + 0.5, y + 0.5).map_or(field.off_map, |d| factor(f64::from(d.abs())))
            })
            .collect();
        field
    }

    /// The distance (m, signed: negative inside obstacles) to the nearest obstacle surface at a world
    /// point, interpolated bilinearly between cell centres; `None` off the map.
    #[must_use]
    pub fn signed_distance(&self, p: [f64; 2]) -> Option<f32> {
        let q = self.world_to_map.transform_point(p);
        let r = 1.0 / self.resolution;
        self.signed_at(q[0] * r + 0.5, q[1] * r + 0.5)
    }

    /// Bilinear interpolation at the continuous index `(u, v)` of the padded grid's cell centres
    /// (map cell `(i, j)` is at `(i + 1, j + 1)`).
    fn signed_at(&self, u: f64, v: f64) -> Option<f32> {
        if !(u >= 0.0 && v >= 0.0) {
            return None;
        }
        let (i, j) = (u as usize, v as usize);
        if i + 1 >= self.padded_width || j + 1 >= self.padded_height {
            return None;
        }
        let (fx, fy) = ((u - i as f64) as f32, (v - j as f64) as f32);
        let k = j * self.padded_width + i;
        let bottom = &self.signed[k..k + 2];
        let top = &self.signed[k + self.padded_width..k + self.padded_width + 2];
        let b = bottom[0] + (bottom[1] - bottom[0]) * fx;
        let t = top[0] + (top[1] - top[0]) * fx;
        Some(b + (t - b) * fy)
    }

    /// The factor at the continuous fine-grid coordinates `(u, v)`: one lookup.
    #[inline]
    fn factor_at(&self, u: f64, v: f64) -> f32 {
        if u >= 0.0 && v >= 0.0 {
            let (i, j) = (u as usize, v as usize);
            if i < self.fine_width && j < self.fine_height {
                return self.cells[j * self.fine_width + i];
            }
        }
        self.off_map
    }

    /// The per-beam factor at a world point.
    #[must_use]
    pub fn at(&self, p: [f64; 2]) -> f32 {
        let q = self.world_to_map.transform_point(p);
        self.factor_at(q[0] * self.inv_fine_resolution, q[1] * self.inv_fine_resolution)
    }

    /// The log-likelihood of the points (base frame) seen from `pose`: `ln(1 + Σ pz³)` (nav2
    /// likelihood_field) or `Σ ln pz` (likelihood_field_prob). Logs keep a product over hundreds of
    /// virtual-scan points from underflowing.
    #[must_use]
    pub fn log_likelihood(&self, pose: &Se2, points: &[[f64; 2]]) -> f64 {
        // The pose in the map frame, scaled to fine cells: one transform per beam.
        let m = self.world_to_map * *pose;
        let (s, c) = m.theta.sin_cos();
        let r = self.inv_fine_resolution;
        let (u0, v0, cr, sr) = (m.x * r, m.y * r, c * r, s * r);
        let sum: f64 = points
            .iter()
            .map(|p| f64::from(self.factor_at(u0 + cr * p[0] - sr * p[1], v0 + sr * p[0] + cr * p[1])))
            .sum();
        match self.model {
            LaserModel::LikelihoodField => sum.ln_1p(),
            LaserModel::LikelihoodFieldProb => sum,
        }
    }

    #[must_use]
    pub fn free_cells(&self) -> &[[f64; 2]] {
        &self.free
    }

    #[must_use]
    pub fn resolution_m(&self) -> f64 {
        self.resolution
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::{FREE, OCCUPIED};

    #[test]
    fn factor_by_hand() {
        // 1 m × 0.3 m at 0.1 m; the left column is a wall whose surface is the line x = 0.1.
        let mut g = OccupancyGrid::filled(10, 3, 0.1, Se2::IDENTITY, FREE);
        for j in 0..3 {
            g.set(0, j, OCCUPIED);
        }
        let params = crate::amcl::tests::shipped_params();
        let f = LikelihoodField::new(&g, &params, 10.0);
        let pz = |d: f64| 0.5 * (-(d * d) / (2.0 * 0.2 * 0.2)).exp() + 0.5 / 10.0;
        let sd = |x: f64| f64::from(f.signed_distance([x, 0.15]).unwrap());
        // Cell 3's centre is 0.25 m from the surface (nav2 would say 0.3 m, centre to centre).
        assert!((sd(0.35) - 0.25).abs() < 1e-6);
        // Between centres the distance is interpolated: exact for a flat face.
        assert!((sd(0.3) - 0.2).abs() < 1e-6);
        assert!((sd(0.137) - 0.037).abs() < 1e-6);
        // On the face 0; inside the wall negative.
        assert!(sd(0.1).abs() < 1e-6);
        assert!((sd(0.05) + 0.05).abs() < 1e-6);
        assert!((sd(0.0) + 0.05).abs() < 1e-6, "flat at the map's border");
        // The factor is looked up on a grid twice as fine (0.05 m): the value at its cell centres.
        let at = |x: f64| f64::from(f.at([x, 0.15]));
        assert!((at(0.37) - pz(0.275).powi(3)).abs() < 1e-6);
        // Either side of the face alike (nav2: 0 anywhere inside, 0.1 m in the first free cell).
        assert!((at(0.11) - pz(0.025).powi(3)).abs() < 1e-6);
        assert!((at(0.09) - pz(0.025).powi(3)).abs() < 1e-6);
        assert!((at(0.02) - pz(0.05).powi(3)).abs() < 1e-6);
        assert!(at(0.11) > at(0.16) && at(0.09) > at(0.02), "largest at the surface");
        // Off the map: the cap, 2 m.
        assert!((f64::from(f.at([-5.0, 0.0])) - pz(2.0).powi(3)).abs() < 1e-9);
        assert_eq!(f.signed_distance([-5.0, 0.0]), None);
        assert_eq!(f.free_cells().len(), 27);
        let ll = f.log_likelihood(&Se2::IDENTITY, &[[0.11, 0.15], [0.37, 0.15]]);
        assert!((ll - (1.0 + pz(0.025).powi(3) + pz(0.275).powi(3)).ln()).abs() < 1e-6);
        // The product model stores ln pz.
        let mut prob = params.clone();
        prob.laser_model_type = LaserModel::LikelihoodFieldProb;
        let f = LikelihoodField::new(&g, &prob, 10.0);
        let ll = f.log_likelihood(&Se2::IDENTITY, &[[0.11, 0.15], [0.37, 0.15]]);
        assert!((ll - (pz(0.025).ln() + pz(0.275).ln())).abs() < 1e-6);
    }
}
