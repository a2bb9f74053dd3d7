//! Tests of the AMCL filter's odometry, motion body, skipped beams and subsampling; the shipped params.

use super::*;

pub(crate) fn shipped_params() -> AmclParams {
    crate::config::parse_file("amcl.toml", include_str!("../../../config/amcl.toml"))
        .expect("shipped amcl.toml")
}

#[test]
fn pose_between_updates_follows_the_odometry() {
    let mut g = crate::map::OccupancyGrid::filled(40, 40, 0.1, Se2::IDENTITY, crate::map::FREE);
    g.set(20, 20, crate::map::OCCUPIED);
    let params = shipped_params();
    let field = Arc::new(LikelihoodField::new(&g, &params, 10.0));
    let mut amcl = Amcl::new(params, field, 1);
    assert_eq!(amcl.pose_at(&Se2::IDENTITY), None);
    amcl.init_pose(Se2::new(1.0, 1.0, std::f64::consts::FRAC_PI_2), 0.0, 0.0);
    // The first update sets the odometry reference at (5, 5, 0).
    assert!(matches!(amcl.update(Se2::new(5.0, 5.0, 0.0), &[], false), UpdateOutcome::Updated { .. }));
    // 0.03 m forward in odometry is below update_min_d: skipped, but the pose moves with it.
    let d = amcl.params.update_min_d.get();
    assert!(d > 0.03, "update_min_d {d}");
    assert_eq!(amcl.update(Se2::new(5.03, 5.0, 0.0), &[], false), UpdateOutcome::Skipped);
    let p = amcl.pose_at(&Se2::new(5.03, 5.0, 0.0)).unwrap();
    let e = amcl.estimate().unwrap().pose;
    assert!(
        (p.x - e.x).abs() < 1e-9 && (p.y - (e.y + 0.03)).abs() < 1e-9,
        "forward is +y for this heading: {p:?} vs {e:?}"
    );
}

/// Where the scans say nothing (none here), the cloud moves as its samples' weighted mean does.
/// Slipped samples move 0 on average (uniform in ±1.5 × the increment), so a tail believed at
/// 0.1 leaves the estimate 10 % of the way behind, plus what the spread headings cost (a
/// sample that drives at an angle gets less far along): 4.2 m driven, the shipped tail tried by
/// 10 % of the samples and believed at its prior, against believed at 10 %, and not at all.
#[test]
fn a_blind_filter_keeps_up_with_its_odometry_by_the_slip_prior() {
    use crate::config::value::Fraction;
    let g = crate::map::OccupancyGrid::filled(40, 40, 0.1, Se2::IDENTITY, crate::map::FREE);
    let shipped = shipped_params();
    let lag = |probability: Option<f64>| {
        let mut params = shipped.clone();
        params.odom_slip_share = Fraction::new(0.1).unwrap();
        params.odom_slip_probability = probability.map(|p| Fraction::new(p).unwrap());
        let field = Arc::new(LikelihoodField::new(&g, &params, 10.0));
        let mut amcl = Amcl::new(params, field, 3);
        amcl.init_pose(Se2::IDENTITY, 0.0, 0.0);
        for k in 0..=70 {
            assert!(matches!(
                amcl.update(Se2::new(0.06 * f64::from(k), 0.0, 0.0), &[], false),
                UpdateOutcome::Updated { .. }
            ));
        }
        4.2 - amcl.estimate().unwrap().pose.x
    };
    let (believed, shipped_lag, never) =
        (lag(None), lag(shipped.odom_slip_probability.map(|p| p.get())), lag(Some(0.0)));
    eprintln!(
        "lag: believed at the share {believed:.3} m, at the shipped prior {shipped_lag:.3} m, never {never:.3} m"
    );
    assert!(believed > 0.4, "{believed}");
    assert!(never.abs() < 0.03, "{never}");
    assert!(shipped_lag < believed / 3.0, "{shipped_lag} vs {believed}");
}

/// A pure rotation of the tracked frame moves its samples along their heading only; with the
/// wheeled body 0.45 m to its side ([`Amcl::set_motion_body`]) the body drives an arc, and its
/// noise spreads the samples sideways too, around the same mean.
#[test]
fn a_motion_body_beside_the_frame_spreads_a_turn_sideways() {
    let g = crate::map::OccupancyGrid::filled(40, 40, 0.1, Se2::IDENTITY, crate::map::FREE);
    let mut params = shipped_params();
    // Without the slip tail (its samples do not follow the increment, which moves the mean).
    params.odom_slip_share = crate::config::value::Fraction::new(0.0).unwrap();
    let field = Arc::new(LikelihoodField::new(&g, &params, 10.0));
    let spread = |body: Option<Se2>| {
        let mut amcl = Amcl::new(params.clone(), Arc::clone(&field), 1);
        if let Some(b) = body {
            amcl.set_motion_body(b);
        }
        amcl.init_pose(Se2::new(2.0, 2.0, 0.0), 0.0, 0.0);
        assert!(matches!(amcl.update(Se2::IDENTITY, &[], true), UpdateOutcome::Updated { .. }));
        // The frame turns 0.3 rad on the spot.
        amcl.predict(&Se2::IDENTITY, &Se2::new(0.0, 0.0, 0.3));
        let n = amcl.particles.len() as f64;
        let (mx, my) =
            amcl.particles.iter().fold((0.0, 0.0), |(x, y), p| (x + p.pose.x / n, y + p.pose.y / n));
        // Across the starting heading (x): y.
        let sd_y = (amcl.particles.iter().map(|p| (p.pose.y - my).powi(2)).sum::<f64>() / n).sqrt();
        (mx, my, sd_y)
    };
    let (_, my, sd_alone) = spread(None);
    assert!(sd_alone < 1e-9 && (my - 2.0).abs() < 1e-9, "V alone: sideways spread {sd_alone}");
    let (mx, my, sd_body) = spread(Some(Se2::new(0.0, -0.45, 0.0)));
    assert!(sd_body > 0.003, "with the body beside it: sideways spread {sd_body}");
    assert!((mx - 2.0).abs() < 0.01 && (my - 2.0).abs() < 0.01, "mean ({mx}, {my})");
}

/// With beam skipping the recovery averages are per-beam means over every beam, skipped or not:
/// half the beams skipped must neither make the fit look better than a perfect one (a product
/// over the beams used divided by all of them did: the square root of the best per-beam
/// likelihood) nor hide them (a mean over the beams used only: a kidnapped filter skips what
/// contradicts it).
#[test]
fn skipped_beams_do_not_count_as_perfect_fits() {
    let mut g = crate::map::OccupancyGrid::filled(100, 100, 0.05, Se2::IDENTITY, crate::map::FREE);
    for j in 0..100 {
        g.set(80, j, crate::map::OCCUPIED);
    }
    let mut params = shipped_params();
    assert!(params.do_beamskip && params.laser_model_type == crate::config::LaserModel::LikelihoodFieldProb);
    params.recovery_alpha_slow = crate::config::value::Fraction::new(0.001).unwrap();
    params.recovery_alpha_fast = crate::config::value::Fraction::new(0.1).unwrap();
    let field = Arc::new(LikelihoodField::new(&g, &params, 10.0));
    let mut amcl = Amcl::new(params.clone(), field, 1);
    // Every particle at one pose: converged, so beams are skipped.
    amcl.init_pose(Se2::new(1.0, 2.5, 0.0), 0.0, 0.0);
    // 30 beams on the wall's cell centres (x = 4.025), 30 on nothing 1.5 m short of it.
    let points: Vec<[f64; 2]> = (0..60)
        .map(|k| {
            let y = -1.0 + f64::from(k / 2) * 0.07;
            if k % 2 == 0 { [3.025, y] } else { [1.5, y] }
        })
        .collect();
    assert!(matches!(amcl.update(Se2::IDENTITY, &points, false), UpdateOutcome::Updated { .. }));
    // Half the beams at the best pz, half 1.525 m from the wall (at the floor).
    let best = 0.5 + 0.5 / 10.0;
    let worst = 0.5 * (-(1.525f64 * 1.525) / (2.0 * 0.2 * 0.2)).exp() + 0.5 / 10.0;
    let expect = (best * worst).sqrt();
    assert!(
        (amcl.w_slow - expect).abs() < 0.02 * expect,
        "w_slow {} vs the per-beam mean over every beam {expect}",
        amcl.w_slow
    );
}

#[test]
fn subsampling_spreads_over_valid_points() {
    let pts: Vec<[f64; 2]> = (0..271).map(|i| [f64::from(i), 0.0]).collect();
    let s = subsample(&pts, 60);
    assert_eq!(s.len(), 60);
    assert_eq!(s[0], [0.0, 0.0]);
    assert_eq!(s[59], [270.0, 0.0]);
    assert!(s.windows(2).all(|w| w[1][0] > w[0][0]));
    assert_eq!(subsample(&pts[..10], 60).len(), 10);
}
