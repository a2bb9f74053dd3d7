//! Occupancy grid maps: the ROS map_server format, the cell convention, distance transforms.
//!
//! Cell convention (deliberate; nav2_amcl's `MAP_GXWX` rounds instead, a half-cell shift): the map
//! frame is the `origin` pose (x, y, yaw) of the lower-left corner of the lower-left cell. Cell
//! `(i, j)` — column `i` from the left, row `j` from the bottom — covers
//! `[i·res, (i+1)·res) × [j·res, (j+1)·res)` in the map frame, and its centre is at
//! `((i + ½)·res, (j + ½)·res)`. A world point is mapped with `floor`. Row 0 of the grid is the
//! bottom row of the image (images are stored top row first, so loading flips them).

mod distance;
mod raycast;
mod ros;
mod survey;

pub use distance::{capped_distance_q, distance_transform_sq, euclidean_distance_m};
pub use ros::{MapError, MapMode, MapYaml, load_map, save_map};
pub use survey::Survey;

use crate::se2::Se2;

/// ROS OccupancyGrid values: 0 free, 100 occupied, −1 unknown, 1–99 graded (scale mode).
pub const FREE: i8 = 0;
pub const OCCUPIED: i8 = 100;
pub const UNKNOWN: i8 = -1;

/// A 2D occupancy grid.
#[derive(Debug, Clone, PartialEq)]
pub struct OccupancyGrid {
    pub width: usize,
    pub height: usize,
    pub resolution_m: f64,
    /// Pose of the lower-left corner of cell (0, 0) in the world.
    pub origin: Se2,
    /// Row-major from the bottom row: `cells[j * width + i]`.
    pub cells: Vec<i8>,
}

impl OccupancyGrid {
    /// A grid of `width × height` cells all set to `value`.
    #[must_use]
    pub fn filled(width: usize, height: usize, resolution_m: f64, origin: Se2, value: i8) -> Self {
        OccupancyGrid { width, height, resolution_m, origin, cells: vec![value; width * height] }
    }

    #[must_use]
    pub fn get(&self, i: usize, j: usize) -> Option<i8> {
        (i < self.width && j < self.height).then(|| self.cells[j * self.width + i])
    }

    pub fn set(&mut self, i: usize, j: usize, value: i8) {
        if i < self.width && j < self.height {
            self.cells[j * self.width + i] = value;
        }
    }

    /// The cell containing world point `p`, if inside the grid.
    #[must_use]
    pub fn cell_of(&self, p: [f64; 2]) -> Option<(usize, usize)> {
        let q = self.origin.inverse().transform_point(p);
        let (fi, fj) = ((q[0] / self.resolution_m).floor(), (q[1] / self.resolution_m).floor());
        (fi >= 0.0 && fj >= 0.0 && (fi as usize) < self.width && (fj as usize) < self.height)
            .then_some((fi as usize, fj as usize))
    }

    /// The world position of the centre of cell `(i, j)`.
    #[must_use]
    pub fn cell_center(&self, i: usize, j: usize) -> [f64; 2] {
        self.origin
            .transform_point([(i as f64 + 0.5) * self.resolution_m, (j as f64 + 0.5) * self.resolution_m])
    }

    /// AMCL's reading of a cell (nav2 `convertMap`): only exactly 0 is free and exactly 100 occupied.
    #[must_use]
    pub fn is_free(&self, i: usize, j: usize) -> bool {
        self.get(i, j) == Some(FREE)
    }

    #[must_use]
    pub fn is_occupied(&self, i: usize, j: usize) -> bool {
        self.get(i, j) == Some(OCCUPIED)
    }

    /// World-frame extent `(min_x, min_y, max_x, max_y)` of an unrotated grid.
    #[must_use]
    pub fn extent(&self) -> (f64, f64, f64, f64) {
        let (w, h) = (self.width as f64 * self.resolution_m, self.height as f64 * self.resolution_m);
        let corners = [[0.0, 0.0], [w, 0.0], [0.0, h], [w, h]].map(|c| self.origin.transform_point(c));
        corners
            .iter()
            .fold((f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY), |(a, b, c, d), p| {
                (a.min(p[0]), b.min(p[1]), c.max(p[0]), d.max(p[1]))
            })
    }
}

/// A map of polygon outlines (walls are polygon edges, as the ray caster sees them): cells an edge
/// passes through or touches are occupied, cells inside `free_region` are free, the rest unknown —
/// the inside of every other outline too (a rack or a column within the room is solid, and no
/// LiDAR sees into it: a map built from scans leaves it unknown, and AMCL must not draw particles
/// there).
#[must_use]
pub fn rasterize_outlines(
    outlines: &[crate::geometry::Polygon],
    free_region: &crate::geometry::Polygon,
    resolution_m: f64,
    origin: Se2,
    width: usize,
    height: usize,
) -> OccupancyGrid {
    let mut g = OccupancyGrid::filled(width, height, resolution_m, origin, UNKNOWN);
    // A cell is taken when an edge comes within half a side of its centre: that gives an unbroken
    // wall. An edge on a cell border is exactly half a side from both neighbours, so allow for
    // rounding, or such a wall can vanish from the map altogether.
    let half = resolution_m / 2.0 * (1.0 + 1e-9);
    let obstacles: Vec<&crate::geometry::Polygon> = outlines.iter().filter(|p| *p != free_region).collect();
    for j in 0..height {
        for i in 0..width {
            let c = g.cell_center(i, j);
            if outlines.iter().any(|p| p.distance_to_boundary(c) <= half) {
                g.set(i, j, OCCUPIED);
            } else if free_region.contains(c) && !obstacles.iter().any(|p| p.contains(c)) {
                g.set(i, j, FREE);
            }
        }
    }
    g
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rasterised_room() {
        let room = crate::geometry::Polygon::centered_rectangle(1.0, 0.5).unwrap();
        let g =
            rasterize_outlines(std::slice::from_ref(&room), &room, 0.1, Se2::new(-0.7, -0.45, 0.0), 14, 9);
        // The wall x = 0.5 lies on the border of columns 11 (0.4–0.5) and 12 (0.5–0.6): both touch it.
        assert!(g.is_occupied(11, 4) && g.is_occupied(12, 4));
        assert!(!g.is_occupied(10, 4) && !g.is_occupied(13, 4));
        assert!(g.is_free(7, 4), "the room's middle is free");
        assert_eq!(g.get(0, 0), Some(UNKNOWN), "outside is unknown");
        // An obstacle within a room, both with their edges on cell centres: the obstacle is solid
        // and never seen inside.
        let hall = crate::geometry::Polygon::centered_rectangle(2.0, 1.0).unwrap();
        let rack = crate::geometry::Polygon::centered_rectangle(0.6, 0.4).unwrap();
        let g3 = rasterize_outlines(&[hall.clone(), rack], &hall, 0.1, Se2::new(-1.15, -0.65, 0.0), 23, 13);
        assert!(g3.cell_center(11, 6)[0].abs() < 1e-9 && g3.cell_center(14, 6)[0] > 0.29);
        assert_eq!(g3.get(11, 6), Some(UNKNOWN), "the inside of a rack is unknown");
        assert_eq!(g3.get(12, 6), Some(UNKNOWN), "within a cell of its face too");
        assert!(g3.is_occupied(14, 6) && g3.is_occupied(11, 8), "its faces are walls");
        assert!(g3.is_free(16, 6) && g3.is_free(11, 10), "the room beside it is free");
        // A wall on cell borders, at an origin where the cell centres do not come out exact in
        // binary: x = 8.0 with 0.05 m cells from −0.5 (this wall once vanished from the map).
        let big = crate::geometry::Polygon::centered_rectangle(16.0, 2.0).unwrap();
        let g2 =
            rasterize_outlines(std::slice::from_ref(&big), &big, 0.05, Se2::new(-8.5, -1.5, 0.0), 340, 60);
        let (i, j) = g2.cell_of([7.99, 0.0]).unwrap();
        assert!(g2.is_occupied(i, j) && g2.is_occupied(i + 1, j), "both cells touching x = 8 are walls");
        // Every wall cell is within half a cell of the outline.
        for j in 0..g.height {
            for i in 0..g.width {
                if g.is_occupied(i, j) {
                    assert!(room.distance_to_boundary(g.cell_center(i, j)) <= 0.05 + 1e-9);
                }
            }
        }
    }

    #[test]
    fn cell_convention() {
        let g = OccupancyGrid::filled(4, 3, 0.5, Se2::new(-1.0, 2.0, 0.0), FREE);
        assert_eq!(
            g.cell_of([-1.0, 2.0]),
            Some((0, 0)),
            "the origin is the lower-left corner of cell (0, 0)"
        );
        assert_eq!(g.cell_of([-0.51, 2.49]), Some((0, 0)));
        assert_eq!(g.cell_of([-0.5, 2.5]), Some((1, 1)), "floor, not rounding");
        assert_eq!(g.cell_of([0.99, 3.49]), Some((3, 2)));
        assert_eq!(g.cell_of([1.0, 3.0]), None, "x = origin + width·res is outside");
        assert_eq!(g.cell_of([-1.01, 2.0]), None);
        assert_eq!(g.cell_center(0, 0), [-0.75, 2.25]);
        assert_eq!(g.cell_of(g.cell_center(3, 2)), Some((3, 2)));
        assert_eq!(g.extent(), (-1.0, 2.0, 1.0, 3.5));
    }

    #[test]
    fn rotated_origin() {
        // The map frame turned 90°: its +x is the world's +y.
        let g = OccupancyGrid::filled(4, 2, 1.0, Se2::from_degrees(0.0, 0.0, 90.0), FREE);
        assert_eq!(g.cell_of([-0.5, 3.5]), Some((3, 0)));
        let c = g.cell_center(3, 0);
        assert!((c[0] + 0.5).abs() < 1e-12 && (c[1] - 3.5).abs() < 1e-12);
    }
}
