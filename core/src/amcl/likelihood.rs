//! The likelihood-field sensor model (Thrun et al., Probabilistic Robotics §6.4; nav2_amcl
//! `likelihood_field_model.cpp` and `likelihood_field_model_prob.cpp`): the grid stores each cell's
//! final per-beam term so that a beam costs one lookup (as Beluga does).

use crate::config::{AmclParams, LaserModel};
use crate::map::{OccupancyGrid, euclidean_distance_m};
use crate::se2::Se2;

/// With `pz = z_hit·exp(−d²/2σ²) + z_rand/range_max` (`d` the distance to the nearest occupied cell,
/// capped at `laser_likelihood_max_dist`; nav2's formula, without the Gaussian's normalisation), each
/// cell stores `pz³` for nav2's `1 + Σ pz³` aggregation, or `ln pz` for the product model.
#[derive(Debug, Clone)]
pub struct LikelihoodField {
    width: usize,
    height: usize,
    inv_resolution: f64,
    world_to_map: Se2,
    cells: Vec<f32>,
    /// Off the map a point is as far as the cap (nav2 counts off-map as `max_occ_dist`).
    off_map: f32,
    /// Centres of the free cells (AMCL's "free": exactly 0), for random poses.
    free: Vec<[f64; 2]>,
    resolution: f64,
    model: LaserModel,
}

impl LikelihoodField {
    /// `range_max_m` is the sensor's maximum range used in the `z_rand` term.
    #[must_use]
    pub fn new(grid: &OccupancyGrid, params: &AmclParams, range_max_m: f64) -> Self {
        let seed: Vec<bool> = grid.cells.iter().map(|&c| c == crate::map::OCCUPIED).collect();
        let dist = euclidean_distance_m(&seed, grid.width, grid.height, grid.resolution_m);
        let max_d = params.laser_likelihood_max_dist.get();
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
        let free = (0..grid.height)
            .flat_map(|j| (0..grid.width).map(move |i| (i, j)))
            .filter(|&(i, j)| grid.is_free(i, j))
            .map(|(i, j)| grid.cell_center(i, j))
            .collect();
        LikelihoodField {
            width: grid.width,
            height: grid.height,
            inv_resolution: 1.0 / grid.resolution_m,
            world_to_map: grid.origin.inverse(),
            cells: dist.into_iter().map(factor).collect(),
            off_map: factor(max_d),
            free,
            resolution: grid.resolution_m,
            model,
        }
    }

    /// The factor at a world point: one lookup.
    #[inline]
    #[must_use]
    pub fn at(&self, p: [f64; 2]) -> f32 {
        let q = self.world_to_map.transform_point(p);
        let (fi, fj) = (q[0] * self.inv_resolution, q[1] * self.inv_resolution);
        if fi >= 0.0 && fj >= 0.0 {
            let (i, j) = (fi as usize, fj as usize);
            if i < self.width && j < self.height {
                return self.cells[j * self.width + i];
            }
        }
        self.off_map
    }

    /// The log-likelihood of the points (base frame) seen from `pose`: `ln(1 + Σ pz³)` (nav2
    /// likelihood_field) or `Σ ln pz` (likelihood_field_prob). Logs keep a product over hundreds of
    /// virtual-scan points from underflowing.
    #[must_use]
    pub fn log_likelihood(&self, pose: &Se2, points: &[[f64; 2]]) -> f64 {
        let (s, c) = pose.theta.sin_cos();
        let sum: f64 = points
            .iter()
            .map(|p| f64::from(self.at([pose.x + c * p[0] - s * p[1], pose.y + s * p[0] + c * p[1]])))
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
        let mut g = OccupancyGrid::filled(10, 1, 0.1, Se2::IDENTITY, FREE);
        g.set(0, 0, OCCUPIED);
        let params = crate::amcl::tests::shipped_params();
        let f = LikelihoodField::new(&g, &params, 10.0);
        // Cell 3 is 0.3 m from the occupied cell: pz = 0.5·exp(−0.09/0.08) + 0.5/10.
        let pz = 0.5 * (-0.09f64 / (2.0 * 0.2 * 0.2)).exp() + 0.05;
        assert!((f64::from(f.at([0.35, 0.05])) - pz.powi(3)).abs() < 1e-6);
        // On the obstacle: (0.5 + 0.05)³.
        assert!((f64::from(f.at([0.05, 0.05])) - 0.55f64.powi(3)).abs() < 1e-6);
        // Off the map: the cap, 2 m.
        let cap = 0.5 * (-4.0f64 / 0.08).exp() + 0.05;
        assert!((f64::from(f.at([-5.0, 0.0])) - cap.powi(3)).abs() < 1e-9);
        assert_eq!(f.free_cells().len(), 9);
        let ll = f.log_likelihood(&Se2::IDENTITY, &[[0.05, 0.05], [0.35, 0.05]]);
        assert!((ll - (1.0 + 0.55f64.powi(3) + pz.powi(3)).ln()).abs() < 1e-6);
        // The product model stores ln pz.
        let mut prob = params.clone();
        prob.laser_model_type = LaserModel::LikelihoodFieldProb;
        let f = LikelihoodField::new(&g, &prob, 10.0);
        let ll = f.log_likelihood(&Se2::IDENTITY, &[[0.05, 0.05], [0.35, 0.05]]);
        assert!((ll - (0.55f64.ln() + pz.ln())).abs() < 1e-6);
    }
}
