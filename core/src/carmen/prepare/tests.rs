//! Tests of preparing a corrected CARMEN log: odometry, map cells, raw log and reference, refusals.

use super::*;
use crate::carmen::{Record, parse_line};

fn odom(pose: Se2, anchor: bool) -> Event {
    Event::Odometry(OdometryLine {
        pose,
        velocity: [0.0; 3],
        timestamp_s: 1.0,
        logger_timestamp_s: 1.0,
        anchor,
    })
}

fn laser(pose: Se2, ranges_m: Vec<f64>) -> LaserLine {
    LaserLine { ranges_m, pose, odometry: pose, timestamp_s: 1.0, logger_timestamp_s: 1.0, line: 1 }
}

/// Raw readings r0..r5; scans at corrected poses c1 (after r1) and c2 (after r4), far from the
/// raw frame. Each ODOM line after a scan is c ∘ r(scan)⁻¹ ∘ r(t), as in a corrected log.
#[test]
fn odometry_is_rebuilt_by_chaining_increments_across_a_segment_break() {
    let r: Vec<Se2> = [(0.0, 0.0, 0.0), (0.5, 0.1, 0.2), (0.9, 0.3, 0.5), (1.2, 0.7, 0.9), (1.3, 1.2, 1.4)]
        .iter()
        .chain(&[(1.1, 1.6, 1.9)])
        .map(|&(x, y, t)| Se2::new(x, y, t))
        .collect();
    let (c1, c2) = (Se2::new(10.0, -4.0, -2.5), Se2::new(10.3, -3.1, -1.7));
    let seen_from = |c: Se2, at: Se2, t: Se2| c * (at.inverse() * t);
    let events = vec![
        odom(r[0], false),
        odom(r[1], false),
        Event::Laser(laser(c1, vec![1.0])),
        odom(c1, true),
        odom(seen_from(c1, r[1], r[2]), false),
        odom(seen_from(c1, r[1], r[3]), false),
        odom(seen_from(c1, r[1], r[4]), false),
        Event::Laser(laser(c2, vec![1.0])),
        odom(c2, true),
        odom(seen_from(c2, r[4], r[5]), false),
    ];
    let raw = raw_odometry(&events).unwrap();
    let expected = [
        Some(r[0]),
        Some(r[1]),
        Some(r[1]),
        None,
        Some(r[2]),
        Some(r[3]),
        Some(r[4]),
        Some(r[4]),
        None,
        Some(r[5]),
    ];
    assert_eq!(raw.len(), expected.len());
    for (k, (got, want)) in raw.iter().zip(&expected).enumerate() {
        match (got, want) {
            (Some(g), Some(w)) => assert!(g.approx_eq(w, 1e-12, 1e-12), "event {k}: {g:?} != {w:?}"),
            (None, None) => {}
            _ => panic!("event {k}: {got:?} != {want:?}"),
        }
    }
    assert_eq!(
        raw_odometry(&[Event::Laser(laser(c1, vec![1.0])), odom(r[0], false)]),
        Err(PrepareError::ScanBeforeOdometry { line: 1 })
    );
}

#[test]
fn cells_by_their_hits_and_passes() {
    assert_eq!(cell_state(0, 0), UNKNOWN);
    assert_eq!(cell_state(0, 1), FREE);
    assert_eq!(cell_state(1, 0), OCCUPIED);
    assert_eq!(cell_state(1, 3), OCCUPIED, "a quarter of the observations");
    assert_eq!(cell_state(1, 4), FREE);
    assert_eq!(cell_state(u32::MAX, u32::MAX), OCCUPIED);
}

/// Two beams from (0.5, 2.5) heading 0 on 1 m cells: -90° for 2 m ends in cell (0, 0), 0° for 3 m
/// in (3, 2). The second scan's beams are unused: one at the log's largest reading (no return),
/// one beyond the range limit.
#[test]
fn a_tiny_log_gives_the_expected_cells() {
    let p = Se2::new(0.5, 2.5, 0.0);
    let (a, b) = (laser(p, vec![2.0, 3.0]), laser(p, vec![45.0, 81.9]));
    let options = MapOptions { resolution_m: 1.0, margin_m: 0.0, ..MapOptions::default() };
    let g = build_map(&[&a, &b], &options).unwrap();
    assert_eq!((g.width, g.height, g.origin), (4, 3, Se2::IDENTITY));
    let (o, f, u) = (OCCUPIED, FREE, UNKNOWN);
    #[rustfmt::skip]
    let expected = vec![
        o, u, u, u, // row 0 (bottom)
        f, u, u, u,
        f, f, f, o,
    ];
    assert_eq!(g.cells, expected);
    // At 5 cm with the default margin the endpoints are still the only occupied cells.
    let g = build_map(&[&a, &b], &MapOptions::default()).unwrap();
    let occupied = occupied_centres(&g);
    assert_eq!(occupied.len(), 2, "{occupied:?}");
    for (c, want) in occupied.iter().zip([[0.5, 0.5], [3.5, 2.5]]) {
        assert!((c[0] - want[0]).abs() <= 0.05 && (c[1] - want[1]).abs() <= 0.05, "{c:?} vs {want:?}");
    }
    assert_eq!(build_map(&[], &options), Err(PrepareError::NoScans));
}

fn occupied_centres(g: &crate::map::OccupancyGrid) -> Vec<[f64; 2]> {
    (0..g.height)
        .flat_map(|j| (0..g.width).map(move |i| (i, j)))
        .filter(|&(i, j)| g.is_occupied(i, j))
        .map(|(i, j)| g.cell_center(i, j))
        .collect()
}

/// A corrected log by hand: raw odometry (0,0,0) → (1,0,0) → scan → (2,0,0), corrected to
/// (5,5,π/2) at the scan, the laser 0.25 m ahead.
const CORRECTED: &str = "\
# a corrected log
PARAM robot_frontlaser_offset 0.25 nohost 0
ODOM 0 0 0 0 0 0 1.0 h 1.0
ODOM 1 0 0 0.3 0 0 2.0 h 2.0
FLASER 3 1.5 2.5 81.9 5 5 1.5707963267948966 5 5 1.5707963267948966 2.0 h 2.5
ODOM 5 5 1.5707963267948966 0 0 0 0 h 0
NEFF 30
ODOM 5 6 1.5707963267948966 0.3 0 0 3.0 h 3.0
";

#[test]
fn a_corrected_log_becomes_raw_log_and_reference() {
    let p = prepare(CORRECTED, &MapOptions::default()).unwrap();
    assert_eq!((p.scans, p.odometry_lines, p.anchors), (1, 3, 1));
    let records: Vec<Record> = p.raw_log.lines().filter_map(|l| parse_line(l).unwrap()).collect();
    let poses: Vec<(Se2, Option<Se2>)> = records
        .iter()
        .map(|r| match r {
            Record::Odometry { pose, .. } => (*pose, None),
            Record::Laser(l) => (l.logged_pose.unwrap(), l.odometry),
        })
        .collect();
    let want = [
        (Se2::new(0.0, 0.0, 0.0), None),
        (Se2::new(1.0, 0.0, 0.0), None),
        (Se2::new(1.25, 0.0, 0.0), Some(Se2::new(1.0, 0.0, 0.0))),
        (Se2::new(2.0, 0.0, 0.0), None),
    ];
    assert_eq!(poses.len(), want.len(), "{}", p.raw_log);
    for ((g, go), (w, wo)) in poses.iter().zip(&want) {
        assert!(g.approx_eq(w, 1e-6, 1e-6), "{g:?} != {w:?}\n{}", p.raw_log);
        assert_eq!(go.is_some(), wo.is_some());
        if let (Some(g), Some(w)) = (go, wo) {
            assert!(g.approx_eq(w, 1e-6, 1e-6), "{g:?} != {w:?}");
        }
    }
    assert!(p.raw_log.contains("FLASER 3 1.5 2.5 81.9 "), "{}", p.raw_log);
    assert!(p.raw_log.contains("PARAM robot_frontlaser_offset 0.25 nohost 0\n"));
    assert!(p.raw_log.contains(" 0.300000 0.000000 0.000000 3.000000 nohost 3.000000\n"));
    assert_eq!(p.reference_csv, "scan,timestamp,x,y,theta\n0,2.000000,5.000000,5.000000,1.570796\n");
    // Both beams used (81.9 is the log's largest reading: no return), at the corrected pose.
    // Heading 90°, beams at -90° and -30°: east 1.5 m, and 2.5 m at 60°.
    let g = &p.map;
    let occupied = occupied_centres(g);
    assert_eq!(occupied.len(), 2, "{occupied:?}");
    let want = [[6.5, 5.0], [5.0 + 2.5 * 0.5, 5.0 + 2.5 * 0.75f64.sqrt()]];
    for (c, w) in occupied.iter().zip(want) {
        assert!((c[0] - w[0]).abs() <= 0.05 && (c[1] - w[1]).abs() <= 0.05, "{c:?} vs {w:?}");
    }
}

#[test]
fn logs_that_are_not_corrected_are_refused() {
    // A raw log: the FLASER's odometry differs from its laser pose.
    let raw = CORRECTED.replace("5 5 1.5707963267948966 2.0 h", "1 0 0 2.0 h");
    assert!(matches!(prepare(&raw, &MapOptions::default()), Err(PrepareError::NotCorrected(_))));
    // No anchor after the scan.
    let unanchored = CORRECTED.replace("ODOM 5 5 1.5707963267948966 0 0 0 0 h 0\n", "");
    assert!(matches!(prepare(&unanchored, &MapOptions::default()), Err(PrepareError::NotCorrected(_))));
    let no_scan = "ODOM 0 0 0 0 0 0 1 h 1\n";
    assert_eq!(prepare(no_scan, &MapOptions::default()), Err(PrepareError::NoScans));
    let broken = CORRECTED.replace("ODOM 1 0 0 0.3", "ODOM 1 zero 0 0.3");
    assert!(matches!(prepare(&broken, &MapOptions::default()), Err(PrepareError::Line { line: 4, .. })));
    let offset = CORRECTED.replace("offset 0.25", "offset far");
    assert_eq!(prepare(&offset, &MapOptions::default()), Err(PrepareError::LaserOffset("far".into())));
}
