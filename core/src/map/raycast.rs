//! Ray casting through an occupancy grid whose occupied cells are solid squares: the simulated
//! LiDAR on any map. The ray walks the cells it crosses in order (Amanatides & Woo,
//! "A fast voxel traversal algorithm for ray tracing", Eurographics 1987) and stops at the first
//! occupied one; the range is where the ray enters that cell, so a wall's face is its cells' edge.
//! Free and unknown cells let the ray through.

use super::{OCCUPIED, OccupancyGrid};

impl OccupancyGrid {
    /// Distance along the ray from `from` (world frame) at `angle_rad` to the first occupied cell,
    /// or `None` within `max_range_m` (or if the ray never meets the grid). A ray that starts in
    /// an occupied cell returns 0.
    #[must_use]
    pub fn cast_ray(&self, from: [f64; 2], angle_rad: f64, max_range_m: f64) -> Option<f64> {
        let res = self.resolution_m;
        if self.width == 0 || self.height == 0 || res.is_nan() || res <= 0.0 || !max_range_m.is_finite() {
            return None;
        }
        // In the grid's frame, in cell units.
        let p = self.origin.inverse().transform_point(from);
        let (x, y) = (p[0] / res, p[1] / res);
        let (dy, dx) = (angle_rad - self.origin.theta).sin_cos();
        let (w, h) = (self.width as f64, self.height as f64);
        let t_max = max_range_m / res;
        // Where the ray is inside [0, w] × [0, h] (slabs).
        let (mut t0, mut t1) = (0.0_f64, t_max);
        for (o, d, hi) in [(x, dx, w), (y, dy, h)] {
            if d.abs() < 1e-15 {
                if o < 0.0 || o > hi {
                    return None;
                }
            } else {
                let (a, b) = ((0.0 - o) / d, (hi - o) / d);
                t0 = t0.max(a.min(b));
                t1 = t1.min(a.max(b));
            }
        }
        if t0 > t1 {
            return None;
        }
        // The first cell, from a point just inside the grid.
        let cell = |v: f64, n: usize| (v.floor().max(0.0) as usize).min(n - 1);
        let (mut i, mut j) = (cell(x + t0 * dx, self.width), cell(y + t0 * dy, self.height));
        let step = |d: f64| if d > 0.0 { 1_i64 } else { -1 };
        let next = |o: f64, d: f64, c: usize| {
            if d.abs() < 1e-15 {
                f64::INFINITY
            } else {
                let edge = if d > 0.0 { c as f64 + 1.0 } else { c as f64 };
                (edge - o) / d
            }
        };
        let (mut tx, mut ty) = (next(x, dx, i), next(y, dy, j));
        let (ddx, ddy) = (
            if dx.abs() < 1e-15 { f64::INFINITY } else { 1.0 / dx.abs() },
            if dy.abs() < 1e-15 { f64::INFINITY } else { 1.0 / dy.abs() },
        );
        let mut t = t0;
        // Bounded: each pass moves to a neighbouring cell, at most width + height of them.
        for _ in 0..=(self.width + self.height) {
            if self.cells[j * self.width + i] == OCCUPIED {
                return (t <= t_max).then_some(t * res);
            }
            if tx < ty {
                t = tx;
                tx += ddx;
                let n = i as i64 + step(dx);
                if n < 0 || n >= self.width as i64 {
                    return None;
                }
                i = n as usize;
            } else {
                t = ty;
                ty += ddy;
                let n = j as i64 + step(dy);
                if n < 0 || n >= self.height as i64 {
                    return None;
                }
                j = n as usize;
            }
            if t > t1 {
                return None;
            }
        }
        None
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "tests")]

    use proptest::prelude::*;

    use super::super::{FREE, UNKNOWN};
    use super::*;
    use crate::geometry::{Polygon, cast_ray};
    use crate::se2::Se2;

    /// The occupied cells as square polygons, for the polygon ray caster.
    fn boxes(g: &OccupancyGrid) -> Vec<Polygon> {
        let r = g.resolution_m;
        let mut out = Vec::new();
        for j in 0..g.height {
            for i in 0..g.width {
                if g.is_occupied(i, j) {
                    let c = [[0.0, 0.0], [r, 0.0], [r, r], [0.0, r]]
                        .map(|[a, b]| g.origin.transform_point([i as f64 * r + a, j as f64 * r + b]));
                    out.push(Polygon::new(c.to_vec()).unwrap());
                }
            }
        }
        out
    }

    #[test]
    fn a_wall_of_cells_is_hit_at_its_face() {
        // 10 × 10 cells of 0.1 m from (-0.5, -0.5); column i = 8 occupied: its face at x = 0.3.
        let mut g = OccupancyGrid::filled(10, 10, 0.1, Se2::new(-0.5, -0.5, 0.0), FREE);
        for j in 0..10 {
            g.set(8, j, OCCUPIED);
        }
        g.set(2, 5, UNKNOWN);
        let d = g.cast_ray([0.0, 0.0], 0.0, 5.0).unwrap();
        assert!((d - 0.3).abs() < 1e-12, "{d}");
        let d = g.cast_ray([0.0, 0.0], 0.5, 5.0).unwrap();
        assert!((d - 0.3 / 0.5f64.cos()).abs() < 1e-12, "{d}");
        assert_eq!(
            g.cast_ray([0.0, 0.0], std::f64::consts::PI, 5.0),
            None,
            "unknown and free let it through"
        );
        assert_eq!(g.cast_ray([0.0, 0.0], 0.0, 0.25), None, "beyond the range");
        assert_eq!(g.cast_ray([0.35, 0.0], 0.0, 5.0), Some(0.0), "from inside a wall");
        // From outside the grid, towards it and away from it.
        let d = g.cast_ray([-2.0, 0.01], 0.0, 5.0).unwrap();
        assert!((d - 2.3).abs() < 1e-12, "{d}");
        assert_eq!(g.cast_ray([-2.0, 0.0], std::f64::consts::PI, 5.0), None);
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(300))]

        /// Random grids, poses and rays: the same range as the polygon ray caster on the occupied
        /// cells' squares.
        #[test]
        fn agrees_with_the_polygon_caster_on_the_cells_squares(
            cells in proptest::collection::vec(0u8..10, 64),
            ox in -1.0f64..1.0, oy in -1.0f64..1.0, yaw in -3.2f64..3.2,
            fx in -1.5f64..2.5, fy in -1.5f64..2.5, angle in -3.2f64..3.2,
        ) {
            let mut g = OccupancyGrid::filled(8, 8, 0.25, Se2::new(ox, oy, yaw), FREE);
            for (k, c) in cells.iter().enumerate() {
                if *c == 0 {
                    g.cells[k] = OCCUPIED;
                }
            }
            let from = Se2::new(ox, oy, yaw).transform_point([fx, fy]);
            let squares = boxes(&g);
            let scene: Vec<(Se2, &Polygon)> = squares.iter().map(|p| (Se2::IDENTITY, p)).collect();
            let inside = g.cell_of(from).is_some_and(|(i, j)| g.is_occupied(i, j));
            let want = if inside { Some(0.0) } else { cast_ray(from, angle, 10.0, &scene) };
            let got = g.cast_ray(from, angle, 10.0);
            match (got, want) {
                (Some(a), Some(b)) => prop_assert!((a - b).abs() < 1e-9, "grid {a} polygons {b}"),
                (a, b) => prop_assert_eq!(a, b),
            }
        }
    }
}
