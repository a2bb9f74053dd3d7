use super::*;
use amr_core::map::{MapMode, MapYaml, load_map, rasterize_outlines, save_map};

fn square_robot() -> RobotSpec {
    RobotSpec {
        chassis: Polygon::centered_rectangle(0.4, 0.4).unwrap(),
        wheel_radius_m: 0.065,
        track_width_m: 0.33,
        lidar_mount: Se2::new(0.175, 0.0, 0.0),
        max_accel_mps2: 0.05,
    }
}

#[test]
fn acceleration_is_limited_and_the_pose_follows_the_arc() {
    let mut w = World::new(paper_site().unwrap(), Noise::NONE, 1);
    let r = w.add_robot(square_robot(), Se2::new(-3.0, 0.0, 0.0));
    w.command(r, 0.2, 0.0);
    // 0.05 m/s² from rest: after 1 s, 0.05 m/s and 2.5 cm travelled (v²/2a). The twist is the mean
    // over the last 10 ms step: (0.0495 + 0.05)/2.
    for _ in 0..100 {
        w.step(0.01);
    }
    assert!((w.twist(r).unwrap().0 - 0.04975).abs() < 1e-12, "{:?}", w.twist(r));
    assert!((w.pose(r).unwrap().x - (-3.0 + 0.025)).abs() < 1e-9, "{:?}", w.pose(r));
    // Turning on the spot at 0.2 rad/s once the wheels are up to speed: the exact arc keeps x, y.
    let mut w = World::new(vec![], Noise::NONE, 1);
    let r = w.add_robot(RobotSpec { max_accel_mps2: 1e9, ..square_robot() }, Se2::IDENTITY);
    w.command(r, 0.0, 0.2);
    for _ in 0..500 {
        w.step(0.01);
    }
    // 5 s at 0.2 rad/s less half of the first step: 0.999 rad.
    let p = w.pose(r).unwrap();
    assert!(p.x.abs() < 1e-12 && p.y.abs() < 1e-12 && (p.theta - 0.999).abs() < 1e-9, "{p:?}");
    // A circle: v = 0.1, ω = 0.2 → radius 0.5 m; after π/0.2 s the robot is 1 m to the left.
    let mut w = World::new(vec![], Noise::NONE, 1);
    let r = w.add_robot(RobotSpec { max_accel_mps2: 1e9, ..square_robot() }, Se2::IDENTITY);
    w.command(r, 0.1, 0.2);
    let steps = (std::f64::consts::PI / 0.2 / 0.001).round() as usize;
    for _ in 0..steps {
        w.step(0.001);
    }
    let p = w.pose(r).unwrap();
    assert!(p.x.abs() < 1e-3 && (p.y - 1.0).abs() < 1e-3, "{p:?}");
}

#[test]
fn encoders_measure_the_wheels_not_the_ground() {
    let noise = Noise { wheel_slip_sigma: 0.05, ..Noise::NONE };
    let mut w = World::new(vec![], noise, 7);
    let r = w.add_robot(RobotSpec { max_accel_mps2: 1e9, ..square_robot() }, Se2::IDENTITY);
    w.command(r, 0.2, 0.0);
    for _ in 0..1000 {
        w.step(0.01);
    }
    // The wheels turned exactly 10 s at 0.2 m/s, less half of the first step (spun up within it):
    // 1.999 m worth. The ground saw that ± slip.
    let enc = w.encoders_rad(r).unwrap();
    assert!((enc[0] * 0.065 - 1.999).abs() < 1e-9 && (enc[1] * 0.065 - 1.999).abs() < 1e-9, "{enc:?}");
    let p = w.pose(r).unwrap();
    assert!((p.x - 2.0).abs() > 1e-6, "slip moves the true pose away from the wheel odometry");
    // Quantised encoders report whole counts.
    let mut q = World { noise: Noise { encoder_counts_per_wheel_rev: 1000.0, ..Noise::NONE }, ..w.clone() };
    let counts = q.encoders_rad(r).unwrap()[0] / std::f64::consts::TAU * 1000.0;
    assert!((counts - counts.round()).abs() < 1e-6);
    // Reading noise of σ = 2 counts scatters single readings but does not accumulate.
    let mut noisy = World {
        noise: Noise { encoder_counts_per_wheel_rev: 1000.0, encoder_sigma_counts: 2.0, ..Noise::NONE },
        ..w.clone()
    };
    let exact = w.encoders_rad(r).unwrap()[0] / std::f64::consts::TAU * 1000.0;
    let readings: Vec<f64> = (0..400)
        .map(|_| noisy.encoders_rad(r).unwrap()[0] / std::f64::consts::TAU * 1000.0 - exact)
        .collect();
    let mean = readings.iter().sum::<f64>() / 400.0;
    let sd = (readings.iter().map(|d| (d - mean).powi(2)).sum::<f64>() / 400.0).sqrt();
    assert!(mean.abs() < 0.6 && (1.5..2.6).contains(&sd), "mean {mean}, sd {sd}");
}

#[test]
fn unequal_wheels_and_an_uncertain_track_bend_the_path_the_encoders_call_straight() {
    // Wheel odometry with the nominal radius and track, over the encoders.
    fn drive(noise: Noise, seed: u64, v: f64, w_cmd: f64, steps: usize) -> (Se2, Se2) {
        let mut w = World::new(vec![], noise, seed);
        let spec = RobotSpec { max_accel_mps2: 1e9, ..square_robot() };
        let r = w.add_robot(spec, Se2::IDENTITY);
        w.command(r, v, w_cmd);
        let mut odom = Se2::IDENTITY;
        let mut last = w.encoders_rad(r).unwrap();
        for _ in 0..steps {
            w.step(0.01);
            let enc = w.encoders_rad(r).unwrap();
            let (dl, dr) = ((enc[0] - last[0]) * 0.065, (enc[1] - last[1]) * 0.065);
            odom = odom * arc((dl + dr) / 2.0, (dr - dl) / 0.33);
            last = enc;
        }
        (w.pose(r).unwrap(), odom)
    }
    let systematic = Noise { wheel_radius_sigma: 0.002, track_width_sigma: 0.005, ..Noise::NONE };
    // 20 s at 0.2 m/s: the odometry says 4 m straight; the robot turned and drifted by what its
    // wheels differ. Over seeds the heading error spreads as (ε_r − ε_l)/b · s: 1σ ≈ 0.0028 ·
    // 4 / 0.33 ≈ 0.034 rad.
    let mut headings = Vec::new();
    for seed in 0..40 {
        let (truth, odom) = drive(systematic, seed, 0.2, 0.0, 2000);
        assert!(odom.y.abs() < 1e-9 && odom.theta.abs() < 1e-9, "the encoders see a straight line: {odom:?}");
        // The same seed bends the same way: drawn once per robot, deterministic.
        assert_eq!(drive(systematic, seed, 0.2, 0.0, 2000).0, truth);
        headings.push(truth.theta);
    }
    let sd = (headings.iter().map(|t| t * t).sum::<f64>() / headings.len() as f64).sqrt();
    assert!((0.018..0.06).contains(&sd), "heading error sd over seeds {sd} rad");
    assert!(headings.iter().all(|t| t.abs() < 0.15), "{headings:?}");
    // Turning on the spot, the track's error scales the turn the odometry reports: 2 rad by the
    // encoders is 2/(1 + ε_b) rad on the ground.
    let (truth, odom) = drive(Noise { track_width_sigma: 0.005, ..Noise::NONE }, 3, 0.0, 0.2, 1000);
    let ratio = odom.theta / truth.theta;
    assert!((ratio - 1.0).abs() > 1e-5 && (ratio - 1.0).abs() < 0.03, "odometry/true turn {ratio}");
    // Without them, the odometry of an exact robot is exact.
    let (truth, odom) = drive(Noise::NONE, 3, 0.2, 0.1, 1000);
    assert!((truth.x - odom.x).abs() < 1e-9 && (truth.theta - odom.theta).abs() < 1e-9);
}

#[test]
fn the_lidar_sees_walls_and_the_other_robot_but_not_itself() {
    let mut w = World::new(paper_site().unwrap(), Noise::NONE, 3);
    let a = w.add_robot(square_robot(), Se2::new(0.0, 0.45, 0.0));
    let b = w.add_robot(square_robot(), Se2::new(0.0, -0.45, 0.0));
    let beams = tim551_beams();
    let scan_a = w.scan(a, &beams).unwrap();
    // Straight right of A's LiDAR (−90°): B's left face, at y = −0.25, i.e. 0.70 m away.
    let right = scan_a.ranges_m()[45];
    assert!((right - 0.70).abs() < 1e-9, "{right}");
    // Straight ahead: the end wall at x = 5, 4.825 m from the LiDAR.
    assert!((scan_a.ranges_m()[135] - 4.825).abs() < 1e-9);
    // Without B, the same beam reaches the −y wall at 2.0 m.
    let mut alone = World::new(paper_site().unwrap(), Noise::NONE, 3);
    let a2 = alone.add_robot(square_robot(), Se2::new(0.0, 0.45, 0.0));
    assert!((alone.scan(a2, &beams).unwrap().ranges_m()[45] - 2.0).abs() < 1e-9);
    let _ = b;
}

#[test]
fn noise_and_dropouts_have_their_configured_size() {
    let noise = Noise { range_sigma_m: 0.01, dropout_probability: 0.1, ..Noise::NONE };
    let mut w = World::new(paper_site().unwrap(), noise, 5);
    let a = w.add_robot(square_robot(), Se2::new(0.0, 0.0, 0.0));
    let beams = tim551_beams();
    let (mut n, mut dropped, mut sum2) = (0usize, 0usize, 0.0);
    for _ in 0..40 {
        let s = w.scan(a, &beams).unwrap();
        let r = s.ranges_m()[135];
        n += 1;
        if r.is_nan() {
            dropped += 1;
        } else {
            sum2 += (r - 4.825).powi(2);
        }
    }
    let sigma = (sum2 / (n - dropped) as f64).sqrt();
    assert!((0.005..0.02).contains(&sigma), "{sigma}");
    assert!((1..=12).contains(&dropped), "{dropped} of 40 dropped at p = 0.1");
}

#[test]
fn same_seed_same_world() {
    let run = |seed| {
        let mut w = World::new(paper_site().unwrap(), Noise::TYPICAL, seed);
        let a = w.add_robot(square_robot(), Se2::new(-2.0, 0.45, 0.0));
        let b = w.add_robot(square_robot(), Se2::new(-2.0, -0.45, 0.0));
        let beams = tim551_beams();
        let mut out = Vec::new();
        for k in 0..200 {
            w.command(a, 0.2, 0.05 * f64::from(k % 7));
            w.command(b, 0.2, -0.02);
            w.step(0.02);
            if k % 10 == 0 {
                out.extend(w.scan(a, &beams).unwrap().ranges_m().iter().map(|r| r.to_bits()));
                out.push(w.gyro_radps(b).unwrap().to_bits());
                out.extend(w.encoders_rad(a).unwrap().map(f64::to_bits));
            }
        }
        out
    };
    assert_eq!(run(9), run(9));
    assert_ne!(run(9), run(10));
}

#[test]
fn the_gyro_reads_the_true_yaw_rate_plus_its_bias() {
    let noise = Noise { gyro_bias_max_radps: 0.01, gyro_sigma_radps: 0.001, ..Noise::NONE };
    let mut w = World::new(vec![], noise, 2);
    let r = w.add_robot(RobotSpec { max_accel_mps2: 1e9, ..square_robot() }, Se2::IDENTITY);
    w.command(r, 0.0, 0.1);
    // The first step spins up (mean rate 0.05); from the second on the rate is 0.1.
    w.step(0.01);
    w.step(0.01);
    let mean = (0..2000).map(|_| w.gyro_radps(r).unwrap()).sum::<f64>() / 2000.0;
    let bias = mean - 0.1;
    assert!(bias.abs() <= 0.01 + 1e-4 && bias.abs() > 1e-5, "bias {bias}");
}

/// The occlusion study's maps are the renderings of [`one_sided_hall`], [`corridor`] and
/// [`short_racks`]. Set `AMR_WRITE_MAPS=1` to re-render them.
#[test]
fn shipped_study_maps_match_their_sites() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../config/maps");
    let sites = [
        ("one-sided-hall", one_sided_hall().unwrap(), Se2::new(-20.275, -12.275, 0.0), 810, 410, [2.0, 7.2]),
        ("corridor", corridor().unwrap(), Se2::new(-20.275, -2.075, 0.0), 810, 82, [3.5, 1.8]),
        ("short-racks", short_racks().unwrap(), Se2::new(-20.275, -12.275, 0.0), 810, 570, [-5.0, 7.2]),
    ];
    for (name, site, origin, w, h, feature) in sites {
        let grid = rasterize_outlines(&site, &site[0], 0.05, origin, w, h);
        let (yaml, image) = save_map(&grid, MapMode::Trinary, 0.65, 0.196, &format!("{name}.pgm")).unwrap();
        if std::env::var_os("AMR_WRITE_MAPS").is_some() {
            std::fs::write(dir.join(format!("{name}.yaml")), &yaml).unwrap();
            std::fs::write(dir.join(format!("{name}.pgm")), &image).unwrap();
        }
        assert_eq!(std::fs::read_to_string(dir.join(format!("{name}.yaml"))).unwrap(), yaml, "{name}");
        assert_eq!(std::fs::read(dir.join(format!("{name}.pgm"))).unwrap(), image, "{name}");
        // A feature's face is occupied; the middle of the drive is free.
        let (i, j) = grid.cell_of(feature).unwrap();
        assert!(grid.is_occupied(i, j), "{name}: {feature:?}");
        let (i, j) = grid.cell_of([0.0, 0.0]).unwrap();
        assert!(grid.is_free(i, j), "{name}");
    }
}

/// The shipped map is the rendering of [`paper_site`]. Set `AMR_WRITE_MAPS=1` to re-render it after
/// changing the site (and say why in the map's README).
#[test]
fn shipped_paper_site_map_matches_the_site() {
    let site = paper_site().unwrap();
    let grid = rasterize_outlines(&site, &site[0], 0.05, Se2::new(-5.275, -1.825, 0.0), 210, 76);
    let (yaml, image) = save_map(&grid, MapMode::Trinary, 0.65, 0.196, "paper-site.pgm").unwrap();
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../config/maps");
    if std::env::var_os("AMR_WRITE_MAPS").is_some() {
        std::fs::write(dir.join("paper-site.yaml"), &yaml).unwrap();
        std::fs::write(dir.join("paper-site.pgm"), &image).unwrap();
    }
    let shipped_yaml = std::fs::read_to_string(dir.join("paper-site.yaml")).unwrap();
    let shipped_image = std::fs::read(dir.join("paper-site.pgm")).unwrap();
    assert_eq!(shipped_yaml, yaml);
    assert_eq!(shipped_image, image);
    let loaded = load_map(&MapYaml::parse(&shipped_yaml).unwrap(), &shipped_image).unwrap();
    assert_eq!(loaded, grid);
}

/// The world on a grid (any ROS map) sees what it sees on polygons: on the shipped map of the
/// paper's site, every beam returns in both, a wall's face is half a cell nearer (its cells are
/// those centred on the polygon edges), and another robot is still seen as its polygon.
#[test]
fn a_world_on_a_grid_sees_the_site_as_on_its_polygons() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../config/maps");
    let yaml = std::fs::read_to_string(dir.join("paper-site.yaml")).unwrap();
    let grid = load_map(&MapYaml::parse(&yaml).unwrap(), &std::fs::read(dir.join("paper-site.pgm")).unwrap())
        .unwrap();
    let mut on_grid = World::new(grid, Noise::NONE, 1);
    let mut on_polygons = World::new(paper_site().unwrap(), Noise::NONE, 1);
    for w in [&mut on_grid, &mut on_polygons] {
        w.add_robot(square_robot(), Se2::new(-2.0, 0.45, 0.2));
        w.add_robot(square_robot(), Se2::new(-1.0, -0.45, 0.0));
    }
    let beams = tim551_beams();
    let (g, p) = (on_grid.scan(0, &beams).unwrap(), on_polygons.scan(0, &beams).unwrap());
    let mut diffs = Vec::new();
    for (a, b) in g.ranges_m().iter().zip(p.ranges_m()) {
        assert_eq!(a.is_finite(), b.is_finite(), "a beam returns in one world only: {a} vs {b}");
        if a.is_finite() {
            assert!(*a <= b + 1e-9, "the grid's wall is behind the polygon's: {a} vs {b}");
            diffs.push(b - a);
        }
    }
    // The other robot is a polygon in both worlds: the same ranges.
    let same = diffs.iter().filter(|d| d.abs() < 1e-9).count();
    assert!(same >= 5, "{same} beams on the other robot");
    // The map's cells are centred on the site's walls (its origin is half a cell off the round
    // coordinates), so a wall's cells reach half a 5 cm cell in front of the polygon's edge: 2.5 cm
    // more along the normal, 2.5 cm / cos(incidence) along a beam (more for a beam grazing a wall).
    let mut walls: Vec<f64> = diffs.into_iter().filter(|d| d.abs() >= 1e-9).collect();
    walls.sort_by(f64::total_cmp);
    let (median, p90) = (walls[walls.len() / 2], walls[walls.len() * 9 / 10]);
    assert!(
        (0.022..0.04).contains(&median) && p90 < 0.1,
        "walls nearer by: median {median}, 90th percentile {p90}"
    );
}

/// Visibility counts what a neighbour hides: alone, a robot sees the whole site; beside another at
/// 0.9 m, the beams the other's body spans go to it (its near face 0.7 m from the LiDAR, which is
/// 0.175 m ahead of the centre: from atan(0.025/0.7) to atan(0.375/0.7), about 30° of 1° beams),
/// and as many fewer site returns are left.
#[test]
fn visibility_counts_the_beams_a_neighbour_takes() {
    let beams = tim551_beams();
    let mut w = World::new(paper_site().unwrap(), Noise::NONE, 1);
    let a = w.add_robot(square_robot(), Se2::new(-2.0, 0.45, 0.0));
    let alone = w.visibility(a, &beams).unwrap();
    assert_eq!((alone.beams, alone.on_robots), (271, 0));
    assert_eq!(alone.site_left, alone.site_alone);
    assert!(alone.site_alone > 250, "{alone:?}");
    let b = w.add_robot(square_robot(), Se2::new(-2.0, -0.45, 0.0));
    let v = w.visibility(a, &beams).unwrap();
    assert!((28..=33).contains(&v.on_robots), "{v:?}");
    assert_eq!(v.site_alone, alone.site_alone);
    assert_eq!(v.site_left, v.site_alone - v.on_robots);
    assert_eq!(w.visibility(b, &beams).unwrap().on_robots, v.on_robots);
    assert!(w.visibility(5, &beams).is_none());
}

/// `short-racks` is the blind-robot site: once the formation (along y = 2, up to 2 m either side)
/// has passed the partition's end at x = −4, nothing but the racks and the partition behind it
/// stands within the TiM551's 10 m. A wall running on 6 m away would give the far robot its side
/// and heading back.
#[test]
fn past_the_short_racks_nothing_else_is_in_range() {
    let site = short_racks().unwrap();
    let grid = rasterize_outlines(&site, &site[0], 0.05, Se2::new(-20.275, -12.275, 0.0), 810, 570);
    let mut behind = 0;
    for j in 0..grid.height {
        for i in 0..grid.width {
            if !grid.is_occupied(i, j) {
                continue;
            }
            let c = grid.cell_center(i, j);
            let near = [[-4.0, 0.0], [-4.0, 4.0], [0.5, 0.0], [0.5, 4.0]]
                .iter()
                .any(|p| (c[0] - p[0]).hypot(c[1] - p[1]) <= 10.0);
            if near {
                assert!(c[0] <= -3.95 && c[1] >= 7.15, "a feature at {c:?} in range of the blind stretch");
                behind += 1;
            }
        }
    }
    assert!(behind > 200, "the racks and the partition are in range ({behind} cells)");
}
