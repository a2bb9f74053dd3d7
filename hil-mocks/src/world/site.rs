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

fn rect(x0: f64, y0: f64, x1: f64, y1: f64) -> Vec<[f64; 2]> {
    vec![[x0, y0], [x1, y0], [x1, y1], [x0, y1]]
}

/// The occlusion study's hall (`amr eval --study occlusion`), `config/maps/one-sided-hall.*`:
/// 40 m × 20 m (x from −20 to 20, y from −12 to 8), its features on one side only — ten racks
/// 2 m × 0.8 m against the +y wall, at irregular gaps so that no two stretches look alike — and
/// nothing else within the TiM551's 10 m from where the formations drive (y from −4 to 6, x from −6
/// to 4): the −y and end walls stand 12 m and more away. A robot localises on the racks alone, and
/// a neighbour on their side hides part of them.
pub fn one_sided_hall() -> Result<Vec<Polygon>, PolygonError> {
    let mut out = vec![Polygon::new(rect(-20.0, -12.0, 20.0, 8.0))?];
    for x0 in [-18.5, -14.0, -10.5, -6.0, -2.5, 1.5, 5.0, 9.5, 13.0, 17.0] {
        out.push(Polygon::new(rect(x0, 7.2, x0 + 2.0, 8.0))?);
    }
    Ok(out)
}

/// The occlusion study's corridor (`amr eval --study occlusion`), `config/maps/corridor.*`: 40 m
/// long and 3 m wide (x from −20 to 20, y from −1.5 to 1.5), plain walls but for door recesses 1 m
/// wide and 0.3 m deep, four in each wall at irregular places: the only features along it. The end
/// walls stand 14 m and more from where the formations drive.
pub fn corridor() -> Result<Vec<Polygon>, PolygonError> {
    let mut room = vec![[-20.0, -1.5]];
    for x in [-12.0, -2.0, 8.0, 16.0] {
        room.extend([[x, -1.5], [x, -1.8], [x + 1.0, -1.8], [x + 1.0, -1.5]]);
    }
    room.extend([[20.0, -1.5], [20.0, 1.5]]);
    for x in [12.0, 3.0, -7.0, -16.0] {
        room.extend([[x + 1.0, 1.5], [x + 1.0, 1.8], [x, 1.8], [x, 1.5]]);
    }
    room.push([-20.0, 1.5]);
    Ok(vec![Polygon::new(room)?])
}

/// The occlusion study's blind-robot site (`amr eval --study occlusion`),
/// `config/maps/short-racks.*`: three of [`one_sided_hall`]'s racks (x from −14 to −4 m) against a
/// partition wall 0.2 m thick that runs from the hall's −x end wall to the racks' end, in a hall
/// 40 m × 28 m (x from −20 to 20, y from −12 to 16). A formation driving on past the partition's
/// end (`short-racks`, along y = 2) sees the racks only behind its shoulder: the robot nearest them
/// sees them still, while its neighbour's lines of sight to them pass through that robot's body (a
/// TiM551 mounted at the front sees nothing beyond 135° from ahead). The hall's walls stand 10 m
/// and more from every robot of the study's formations (13.75 m from two robots 0.5 m apart), at
/// and beyond the LiDARs' reach, so the far robot, alone, loses every constraint. The racks stand
/// against a partition, not against the hall's +y wall: a wall running on past them 6 m from the
/// formation would give the far robot its side and heading back.
pub fn short_racks() -> Result<Vec<Polygon>, PolygonError> {
    let mut out =
        vec![Polygon::new(rect(-20.0, -12.0, 20.0, 16.0))?, Polygon::new(rect(-20.0, 8.0, -4.0, 8.2))?];
    for x0 in [-14.0, -10.5, -6.0] {
        out.push(Polygon::new(rect(x0, 7.2, x0 + 2.0, 8.0))?);
    }
    Ok(out)
}

/// The polygons of the shipped map `name` (`config/maps/<name>.*` is their rendering), or `None`
/// for a map that is not one of ours.
#[must_use]
pub fn shipped_site(name: &str) -> Option<Result<Vec<Polygon>, PolygonError>> {
    match name {
        "paper-site" => Some(paper_site()),
        "one-sided-hall" => Some(one_sided_hall()),
        "corridor" => Some(corridor()),
        "short-racks" => Some(short_racks()),
        _ => None,
    }
}
