//! Maps built the way SLAM builds them (and the way the tool that turns the public Radish CARMEN logs,
//! stored in the GitHub repository `acschaefer/ple`, into raw-odometry logs and references builds the
//! real-data maps): every beam is traced from the sensor; the cells it passes through collect a
//! *miss*, the cell its endpoint falls in collects a *hit*. A cell is occupied when
//! `hits / (hits + misses) ≥ occ_ratio` (and it has at least `min_hits`), free when observed
//! otherwise, unknown when never observed. Beams without a return mark nothing.
//!
//! Such a map is what a robot is given, unlike one rasterised from the world's own polygons: walls
//! are as thick as the endpoints' scatter, their surface sits at the centre of the endpoint cells,
//! unseen faces and rooms are unknown, and clutter seen while surveying is in it.

use super::{FREE, OCCUPIED, OccupancyGrid, UNKNOWN};
use crate::scan::Scan;
use crate::se2::Se2;

/// Hit and miss counts over an unrotated grid.
#[derive(Debug, Clone)]
pub struct Survey {
    width: usize,
    height: usize,
    resolution_m: f64,
    /// World position of the lower-left corner of cell (0, 0).
    origin: [f64; 2],
    hits: Vec<u32>,
    misses: Vec<u32>,
    /// Scratch: the cells of one ray, in order, without repeats (a straight ray meets each cell in one
    /// stretch, so dropping consecutive repeats is enough).
    ray: Vec<usize>,
}

impl Survey {
    /// An empty survey of `width × height` cells whose lower-left corner is at `origin`.
    #[must_use]
    pub fn new(origin: [f64; 2], width: usize, height: usize, resolution_m: f64) -> Self {
        Survey {
            width,
            height,
            resolution_m,
            origin,
            hits: vec![0; width * height],
            misses: vec![0; width * height],
            ray: Vec::new(),
        }
    }

    fn cell(&self, p: [f64; 2]) -> Option<usize> {
        let (u, v) =
            ((p[0] - self.origin[0]) / self.resolution_m, (p[1] - self.origin[1]) / self.resolution_m);
        if u >= 0.0 && v >= 0.0 && (u as usize) < self.width && (v as usize) < self.height {
            Some(v as usize * self.width + u as usize)
        } else {
            None
        }
    }

    /// Add one scan taken by a sensor at `sensor` (world pose). Beams without a return (NaN) and
    /// beams at or beyond the scan's maximum range are skipped.
    pub fn add_scan(&mut self, sensor: &Se2, scan: &Scan) {
        // Samples every quarter cell along the ray, as make_map.py does.
        let step = self.resolution_m / 4.0;
        let o = [sensor.x, sensor.y];
        for i in 0..scan.len() {
            let r = scan.ranges_m()[i];
            if !(r.is_finite() && r < scan.range_max_m) {
                continue;
            }
            let a = sensor.theta + scan.angle(i);
            let (s, c) = a.sin_cos();
            let end = [o[0] + r * c, o[1] + r * s];
            let end_cell = self.cell(end);
            let mut ray = std::mem::take(&mut self.ray);
            ray.clear();
            let n = (r / step).ceil() as usize;
            for k in 0..n {
                let d = k as f64 * step;
                if let Some(cell) = self.cell([o[0] + d * c, o[1] + d * s])
                    && Some(cell) != end_cell
                    && ray.last() != Some(&cell)
                {
                    ray.push(cell);
                }
            }
            for &cell in &ray {
                self.misses[cell] += 1;
            }
            self.ray = ray;
            if let Some(cell) = end_cell {
                self.hits[cell] += 1;
            }
        }
    }

    /// The map: occupied where `hits / (hits + misses) ≥ occ_ratio` and `hits ≥ min_hits`, free where
    /// observed otherwise, unknown elsewhere.
    #[must_use]
    pub fn grid(&self, occ_ratio: f64, min_hits: u32) -> OccupancyGrid {
        let mut g = OccupancyGrid::filled(
            self.width,
            self.height,
            self.resolution_m,
            Se2::new(self.origin[0], self.origin[1], 0.0),
            UNKNOWN,
        );
        for (k, cell) in g.cells.iter_mut().enumerate() {
            let (h, m) = (self.hits[k], self.misses[k]);
            if h + m == 0 {
                continue;
            }
            *cell =
                if h >= min_hits && f64::from(h) >= occ_ratio * f64::from(h + m) { OCCUPIED } else { FREE };
        }
        g
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_beam_by_hand() {
        // A sensor at (0.05, 0.05) looking along +x, a return at 0.5 m: cells 0..4 of row 0 are
        // passed (misses), cell 5 holds the endpoint (hit), cells beyond are unseen.
        let mut s = Survey::new([0.0, 0.0], 10, 2, 0.1);
        let scan = Scan::new(0.0, 0.1, 0.05, 10.0, vec![0.5]);
        s.add_scan(&Se2::new(0.05, 0.05, 0.0), &scan);
        let g = s.grid(0.5, 1);
        let row: Vec<i8> = (0..10).map(|i| g.get(i, 0).unwrap()).collect();
        assert_eq!(row, [FREE, FREE, FREE, FREE, FREE, OCCUPIED, UNKNOWN, UNKNOWN, UNKNOWN, UNKNOWN]);
        assert_eq!(g.get(0, 1), Some(UNKNOWN));
        // A later beam through the endpoint cell turns it free (1 hit, 2 misses).
        let through = Scan::new(0.0, 0.1, 0.05, 10.0, vec![0.8]);
        s.add_scan(&Se2::new(0.05, 0.05, 0.0), &through);
        s.add_scan(&Se2::new(0.05, 0.05, 0.0), &through);
        let g = s.grid(0.5, 1);
        assert_eq!(g.get(5, 0), Some(FREE));
        assert_eq!(g.get(8, 0), Some(OCCUPIED));
        // No return, or at the maximum range: nothing marked.
        let mut s = Survey::new([0.0, 0.0], 10, 2, 0.1);
        s.add_scan(&Se2::new(0.05, 0.05, 0.0), &Scan::new(0.0, 0.1, 0.05, 0.5, vec![f64::NAN]));
        s.add_scan(&Se2::new(0.05, 0.05, 0.0), &Scan::new(0.0, 0.1, 0.05, 0.5, vec![0.5]));
        assert!(s.grid(0.5, 1).cells.iter().all(|c| *c == UNKNOWN));
    }
}
