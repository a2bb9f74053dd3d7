//! Simple counter-clockwise polygons: chassis outlines and map obstacles.

use std::fmt;

/// Why a vertex list is not a usable polygon.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PolygonError {
    #[error("a polygon needs at least 3 vertices (got {0})")]
    TooFewVertices(usize),
    #[error("vertex {0} is not finite")]
    NonFinite(usize),
    #[error("vertices {0} and {1} coincide")]
    RepeatedVertex(usize, usize),
    #[error("edges {0} and {1} cross: the polygon must be simple")]
    SelfIntersecting(usize, usize),
    #[error("vertices must run counter-clockwise (signed area {0:.6} m² is not positive)")]
    NotCounterClockwise(f64),
}

/// A simple (non-self-intersecting) polygon with counter-clockwise vertices and positive area.
/// The only way to build one is through validation, so every `Polygon` has these properties.
#[derive(Clone, PartialEq, serde::Deserialize)]
#[serde(try_from = "Vec<[f64; 2]>")]
pub struct Polygon {
    vertices: Vec<[f64; 2]>,
}

impl fmt::Debug for Polygon {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_tuple("Polygon").field(&self.vertices).finish()
    }
}

impl Polygon {
    /// Validate a vertex list: at least three finite, distinct vertices, no two edges crossing,
    /// counter-clockwise. Edge `i` runs from vertex `i` to vertex `i + 1` (wrapping).
    pub fn new(vertices: Vec<[f64; 2]>) -> Result<Self, PolygonError> {
        let n = vertices.len();
        if n < 3 {
            return Err(PolygonError::TooFewVertices(n));
        }
        if let Some(i) = vertices.iter().position(|v| !v[0].is_finite() || !v[1].is_finite()) {
            return Err(PolygonError::NonFinite(i));
        }
        for i in 0..n {
            for j in i + 1..n {
                if vertices[i] == vertices[j] {
                    return Err(PolygonError::RepeatedVertex(i, j));
                }
            }
        }
        let edge = |i: usize| (vertices[i], vertices[(i + 1) % n]);
        for i in 0..n {
            for j in i + 1..n {
                let adjacent = j == i + 1 || (i == 0 && j == n - 1);
                let (a, b) = edge(i);
                let (c, d) = edge(j);
                let crosses = if adjacent {
                    // Adjacent edges share one vertex; they are bad only if they fold back onto each other.
                    collinear_overlap(a, b, c, d)
                } else {
                    segments_intersect(a, b, c, d)
                };
                if crosses {
                    return Err(PolygonError::SelfIntersecting(i, j));
                }
            }
        }
        let area = signed_area(&vertices);
        if area <= 0.0 {
            return Err(PolygonError::NotCounterClockwise(area));
        }
        Ok(Polygon { vertices })
    }

    /// An axis-aligned rectangle centred on the origin (`length` along x, `width` along y).
    pub fn centered_rectangle(length_m: f64, width_m: f64) -> Result<Self, PolygonError> {
        let (hx, hy) = (length_m / 2.0, width_m / 2.0);
        Polygon::new(vec![[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
    }

    #[must_use]
    pub fn vertices(&self) -> &[[f64; 2]] {
        &self.vertices
    }

    /// Area in m² (positive: the vertices run counter-clockwise).
    #[must_use]
    pub fn area(&self) -> f64 {
        signed_area(&self.vertices)
    }

    /// `(min_x, min_y, max_x, max_y)`.
    #[must_use]
    pub fn bounds(&self) -> (f64, f64, f64, f64) {
        self.vertices.iter().fold(
            (f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY),
            |(x0, y0, x1, y1), v| (x0.min(v[0]), y0.min(v[1]), x1.max(v[0]), y1.max(v[1])),
        )
    }

    /// Shortest distance from `p` to the outline (0 on an edge), inside or outside.
    #[must_use]
    pub fn distance_to_boundary(&self, p: [f64; 2]) -> f64 {
        let n = self.vertices.len();
        (0..n)
            .map(|i| point_segment_distance(p, self.vertices[i], self.vertices[(i + 1) % n]))
            .fold(f64::INFINITY, f64::min)
    }

    /// Inside, or within `margin_m` of the outline: the polygon grown by a disc of that radius.
    #[must_use]
    pub fn contains_inflated(&self, p: [f64; 2], margin_m: f64) -> bool {
        self.contains(p) || self.distance_to_boundary(p) <= margin_m
    }

    /// Interior angle at vertex `k` (radians, in (0, 2π)).
    #[must_use]
    pub fn interior_angle(&self, k: usize) -> f64 {
        let n = self.vertices.len();
        let (prev, v, next) = (self.vertices[(k + n - 1) % n], self.vertices[k], self.vertices[(k + 1) % n]);
        let a = (next[1] - v[1]).atan2(next[0] - v[0]);
        let b = (prev[1] - v[1]).atan2(prev[0] - v[0]);
        (b - a).rem_euclid(std::f64::consts::TAU)
    }

    /// Whether a point lies inside (even-odd rule; points exactly on an edge may go either way).
    #[must_use]
    pub fn contains(&self, p: [f64; 2]) -> bool {
        let n = self.vertices.len();
        let mut inside = false;
        let mut j = n - 1;
        for i in 0..n {
            let (a, b) = (self.vertices[i], self.vertices[j]);
            if (a[1] > p[1]) != (b[1] > p[1]) {
                let x_cross = a[0] + (p[1] - a[1]) / (b[1] - a[1]) * (b[0] - a[0]);
                if p[0] < x_cross {
                    inside = !inside;
                }
            }
            j = i;
        }
        inside
    }
}

impl TryFrom<Vec<[f64; 2]>> for Polygon {
    type Error = PolygonError;
    fn try_from(vertices: Vec<[f64; 2]>) -> Result<Self, PolygonError> {
        Polygon::new(vertices)
    }
}

/// Distance from `p` to the segment `a`–`b`.
#[must_use]
pub(crate) fn point_segment_distance(p: [f64; 2], a: [f64; 2], b: [f64; 2]) -> f64 {
    let (ex, ey) = (b[0] - a[0], b[1] - a[1]);
    let len2 = ex * ex + ey * ey;
    let t = if len2 > 0.0 { (((p[0] - a[0]) * ex + (p[1] - a[1]) * ey) / len2).clamp(0.0, 1.0) } else { 0.0 };
    (p[0] - a[0] - t * ex).hypot(p[1] - a[1] - t * ey)
}

fn signed_area(v: &[[f64; 2]]) -> f64 {
    let n = v.len();
    (0..n)
        .map(|i| {
            let (a, b) = (v[i], v[(i + 1) % n]);
            a[0] * b[1] - b[0] * a[1]
        })
        .sum::<f64>()
        / 2.0
}

fn orient(a: [f64; 2], b: [f64; 2], c: [f64; 2]) -> f64 {
    (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
}

fn on_segment(a: [f64; 2], b: [f64; 2], p: [f64; 2]) -> bool {
    p[0] >= a[0].min(b[0]) && p[0] <= a[0].max(b[0]) && p[1] >= a[1].min(b[1]) && p[1] <= a[1].max(b[1])
}

/// Closed-segment intersection test (touching counts).
fn segments_intersect(a: [f64; 2], b: [f64; 2], c: [f64; 2], d: [f64; 2]) -> bool {
    let (d1, d2) = (orient(c, d, a), orient(c, d, b));
    let (d3, d4) = (orient(a, b, c), orient(a, b, d));
    if ((d1 > 0.0 && d2 < 0.0) || (d1 < 0.0 && d2 > 0.0))
        && ((d3 > 0.0 && d4 < 0.0) || (d3 < 0.0 && d4 > 0.0))
    {
        return true;
    }
    (d1 == 0.0 && on_segment(c, d, a))
        || (d2 == 0.0 && on_segment(c, d, b))
        || (d3 == 0.0 && on_segment(a, b, c))
        || (d4 == 0.0 && on_segment(a, b, d))
}

/// Two edges sharing a vertex overlap when they are collinear and point the same way from it.
fn collinear_overlap(a: [f64; 2], b: [f64; 2], c: [f64; 2], d: [f64; 2]) -> bool {
    // Find the shared vertex and the two far ends.
    let (shared, p, q) = if b == c {
        (b, a, d)
    } else if d == a {
        (a, b, c)
    } else {
        return segments_intersect(a, b, c, d);
    };
    let u = [p[0] - shared[0], p[1] - shared[1]];
    let v = [q[0] - shared[0], q[1] - shared[1]];
    let cross = u[0] * v[1] - u[1] * v[0];
    let dot = u[0] * v[0] + u[1] * v[1];
    cross == 0.0 && dot > 0.0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_paper_chassis_is_valid() {
        let p = Polygon::centered_rectangle(0.40, 0.40).unwrap();
        assert!((p.area() - 0.16).abs() < 1e-12);
        assert!(p.contains([0.0, 0.0]));
        assert!(p.contains([0.19, -0.19]));
        assert!(!p.contains([0.21, 0.0]));
        assert_eq!(p.bounds(), (-0.2, -0.2, 0.2, 0.2));
        assert!((p.distance_to_boundary([0.0, 0.0]) - 0.2).abs() < 1e-12);
        assert!((p.distance_to_boundary([0.5, 0.6]) - 0.3f64.hypot(0.4)).abs() < 1e-12);
        assert!(p.contains_inflated([0.24, 0.0], 0.05) && !p.contains_inflated([0.26, 0.0], 0.05));
        for k in 0..4 {
            assert!((p.interior_angle(k) - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
        }
    }

    #[test]
    fn each_rule_rejects() {
        assert_eq!(Polygon::new(vec![[0.0, 0.0], [1.0, 0.0]]), Err(PolygonError::TooFewVertices(2)));
        assert_eq!(
            Polygon::new(vec![[0.0, 0.0], [1.0, f64::NAN], [0.0, 1.0]]),
            Err(PolygonError::NonFinite(1))
        );
        assert_eq!(
            Polygon::new(vec![[0.0, 0.0], [1.0, 0.0], [0.0, 0.0], [0.0, 1.0]]),
            Err(PolygonError::RepeatedVertex(0, 2))
        );
        // A bow tie: edges 0 (0,0)-(1,1) and 2 (1,0)-(0,1) cross.
        assert_eq!(
            Polygon::new(vec![[0.0, 0.0], [1.0, 1.0], [1.0, 0.0], [0.0, 1.0]]),
            Err(PolygonError::SelfIntersecting(0, 2))
        );
        // Clockwise square.
        assert_eq!(
            Polygon::new(vec![[0.0, 0.0], [0.0, 1.0], [1.0, 1.0], [1.0, 0.0]]),
            Err(PolygonError::NotCounterClockwise(-1.0))
        );
        // A spike that folds back along itself.
        assert!(matches!(
            Polygon::new(vec![[0.0, 0.0], [2.0, 0.0], [1.0, 0.0], [1.0, 1.0]]),
            Err(PolygonError::SelfIntersecting(..))
        ));
    }

    #[test]
    fn concave_polygons_are_fine() {
        // An L shape.
        let l = Polygon::new(vec![[0.0, 0.0], [2.0, 0.0], [2.0, 1.0], [1.0, 1.0], [1.0, 2.0], [0.0, 2.0]])
            .unwrap();
        assert!((l.area() - 3.0).abs() < 1e-12);
        assert!(l.contains([0.5, 1.5]));
        assert!(!l.contains([1.5, 1.5]));
        // The reflex corner at (1, 1) is 270°.
        assert!((l.interior_angle(3) - 1.5 * std::f64::consts::PI).abs() < 1e-12);
    }
}
