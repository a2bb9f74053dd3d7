//! The paper's test site as polygons (the map in `config/maps/paper-site.*` is rendered from these;
//! `config/maps/README.md` says what they are based on).

use amr_core::geometry::{Polygon, PolygonError};

/// The site's length along x, m (paper §5.1: "3.1 m × 10 m indoor open area").
pub const PAPER_SITE_LENGTH_M: f64 = 10.0;
/// The site's width along y, m.
pub const PAPER_SITE_WIDTH_M: f64 = 3.1;

/// The walls of the site, centred on the origin with x along its length, and its few lateral
/// features: a door recess (0.9 m wide, 0.2 m deep) in the +y wall at x = 1.0–1.9 m and a
/// 0.3 m × 0.3 m column against the −y wall at x = −2.15 to −1.85 m. The first polygon is the
/// room (its edges are the walls; its inside is the free area).
pub fn paper_site() -> Result<Vec<Polygon>, PolygonError> {
    let (hx, hy) = (PAPER_SITE_LENGTH_M / 2.0, PAPER_SITE_WIDTH_M / 2.0);
    let room = Polygon::new(vec![
        [-hx, -hy],
        [hx, -hy],
        [hx, hy],
        [1.9, hy],
        [1.9, hy + 0.2],
        [1.0, hy + 0.2],
        [1.0, hy],
        [-hx, hy],
    ])?;
    let column = Polygon::new(vec![[-2.15, -hy], [-1.85, -hy], [-1.85, -hy + 0.3], [-2.15, -hy + 0.3]])?;
    Ok(vec![room, column])
}
