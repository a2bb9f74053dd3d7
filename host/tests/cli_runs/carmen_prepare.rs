//! `amr tools carmen-prepare` end to end: a synthetic "corrected" CARMEN log written by the test
//! (the structure of the Radish corrected logs: corrected poses in the FLASER lines, anchors after
//! them, raw odometry re-anchored on the corrected poses), prepared by the binary, the files checked
//! against the raw odometry and the truth the test drove, then read by `amr bench localize`.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code: a failed step fails the test")]

use std::io::Write as _;
use std::path::Path;
use std::process::{Command, Stdio};

use amr_core::carmen::{Record, parse_line};
use amr_core::geometry::{Polygon, cast_ray};
use amr_core::map::{MapYaml, load_map};
use amr_core::rng::Rng;
use amr_core::se2::Se2;

/// An L-shaped room with a pillar.
fn walls() -> Vec<Polygon> {
    let room =
        Polygon::new(vec![[0.0, 0.0], [8.0, 0.0], [8.0, 3.0], [5.0, 3.0], [5.0, 5.0], [0.0, 5.0]]).unwrap();
    let pillar = Polygon::new(vec![[2.0, 2.0], [2.5, 2.0], [2.5, 2.4], [2.0, 2.4]]).unwrap();
    vec![room, pillar]
}

fn distance_to_walls(p: [f64; 2], walls: &[Polygon]) -> f64 {
    let mut best = f64::INFINITY;
    for w in walls {
        let v = w.vertices();
        for i in 0..v.len() {
            let (a, b) = (v[i], v[(i + 1) % v.len()]);
            let e = [b[0] - a[0], b[1] - a[1]];
            let t =
                (((p[0] - a[0]) * e[0] + (p[1] - a[1]) * e[1]) / (e[0] * e[0] + e[1] * e[1])).clamp(0.0, 1.0);
            best = best.min((p[0] - a[0] - t * e[0]).hypot(p[1] - a[1] - t * e[1]));
        }
    }
    best
}

fn odom_line(p: &Se2, t: f64) -> String {
    format!("ODOM {:.6} {:.6} {:.6} 0 0 0 {t:.6} test {t:.6}\n", p.x, p.y, p.theta)
}

/// The corrected log's text, the raw odometry of each scan and the true (corrected) pose of each.
fn corrected_log() -> (String, Vec<Se2>, Vec<(f64, Se2)>) {
    let walls = walls();
    let scene: Vec<(Se2, &Polygon)> = walls.iter().map(|w| (Se2::IDENTITY, w)).collect();
    let mut rng = Rng::seed(7);
    let mut truth = Se2::new(1.0, 1.0, 0.0);
    // The raw odometry: its own frame, over-reading distance by 3 % and drifting to the left.
    let mut odom = Se2::new(3.0, -2.0, 0.7);
    let mut text = String::from(
        "# message formats defined: PARAM SYNC ODOM FLASER\nPARAM robot_frontlaser_offset 0.0 test 0\n",
    );
    let mut t = 100.0;
    // Before the first scan the ODOM lines are raw odometry.
    text += &odom_line(&odom, t);
    let (mut raw, mut scans) = (Vec::new(), Vec::new());
    let mut anchor: Option<(Se2, Se2)> = None; // (corrected, raw) at the last scan
    for k in 0..50 {
        if k > 0 {
            let step = if k < 25 {
                Se2::new(0.12, 0.0, 0.0)
            } else if k < 33 {
                Se2::new(0.05, 0.0, 0.19)
            } else {
                Se2::new(0.1, 0.0, 0.0)
            };
            // Three readings between scans, the last at the scan's stamp.
            for _ in 0..3 {
                let s = Se2::new(step.x / 3.0, 0.0, step.theta / 3.0);
                truth = truth * s;
                odom = odom * Se2::new(s.x * 1.03, 0.001, s.theta + 0.004);
                t += 0.1;
                let logged = match anchor {
                    Some((c, r)) => c * (r.inverse() * odom),
                    None => odom,
                };
                text += &odom_line(&logged, t);
            }
        }
        let ranges: Vec<String> = (0..180)
            .map(|i| {
                let a = truth.theta + (-90.0 + f64::from(i)).to_radians();
                cast_ray([truth.x, truth.y], a, 30.0, &scene)
                    .map_or("81.90".to_owned(), |r| format!("{:.3}", r + rng.gaussian(0.005)))
            })
            .collect();
        let c = format!("{:.6} {:.6} {:.6}", truth.x, truth.y, truth.theta);
        text += &format!("FLASER 180 {} {c} {c} {t:.6} test {t:.6}\n", ranges.join(" "));
        // The anchor: the corrected pose, stamped 0.
        text += &format!("ODOM {c} 0 0 0 0 test 0\nNEFF 30\n");
        let corrected = Se2::new(
            format!("{:.6}", truth.x).parse().unwrap(),
            format!("{:.6}", truth.y).parse().unwrap(),
            format!("{:.6}", truth.theta).parse().unwrap(),
        );
        anchor = Some((corrected, odom));
        raw.push(odom);
        scans.push((t, truth));
    }
    (text, raw, scans)
}

fn amr(args: &[&str], dir: &Path) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_amr"))
        .args(args)
        .env_remove("RUST_LOG")
        .current_dir(dir)
        .output()
        .unwrap()
}

#[test]
fn a_corrected_log_is_prepared_and_benchmarked() {
    let dir = tempfile::tempdir().unwrap();
    let (text, raw, truth) = corrected_log();
    std::fs::write(dir.path().join("room-corrected.log"), &text).unwrap();
    let run = amr(&["tools", "carmen-prepare", "room-corrected.log", "--out", "prepared"], dir.path());
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let out = dir.path().join("prepared");
    let mut files: Vec<String> =
        std::fs::read_dir(&out).unwrap().map(|e| e.unwrap().file_name().into_string().unwrap()).collect();
    files.sort();
    assert_eq!(files, ["room-gt.csv", "room-raw.log", "room_map.pgm", "room_map.yaml"]);

    // The raw log: every scan with its raw odometry (not the corrected pose), no anchors.
    let raw_log = std::fs::read_to_string(out.join("room-raw.log")).unwrap();
    let records: Vec<Record> = raw_log.lines().filter_map(|l| parse_line(l).unwrap()).collect();
    let odometry: Vec<Se2> = records
        .iter()
        .filter_map(|r| match r {
            Record::Laser(l) => l.odometry,
            Record::Odometry { .. } => None,
        })
        .collect();
    assert_eq!(odometry.len(), raw.len());
    for (k, (got, want)) in odometry.iter().zip(&raw).enumerate() {
        assert!(got.approx_eq(want, 1e-3, 1e-4), "scan {k}: {got:?}, raw odometry {want:?}");
    }
    let odom_lines = records.iter().filter(|r| matches!(r, Record::Odometry { .. })).count();
    assert_eq!(odom_lines, 1 + 3 * 49, "every ODOM line but the anchors");
    assert!(!raw_log.contains(" 0.000000 nohost 0.000000\n"), "an anchor (stamped 0) was kept");

    // The reference: the corrected pose of every scan.
    let gt = std::fs::read_to_string(out.join("room-gt.csv")).unwrap();
    let mut lines = gt.lines();
    assert_eq!(lines.next(), Some("scan,timestamp,x,y,theta"));
    let rows: Vec<Vec<f64>> = lines.map(|l| l.split(',').map(|v| v.parse().unwrap()).collect()).collect();
    assert_eq!(rows.len(), truth.len());
    for (k, (row, (t, p))) in rows.iter().zip(&truth).enumerate() {
        assert_eq!(row[0], k as f64);
        assert!((row[1] - t).abs() < 1e-6 && (row[2] - p.x).abs() < 1e-6 && (row[3] - p.y).abs() < 1e-6);
        assert!(amr_core::se2::angle_diff(row[4], p.theta).abs() < 1e-6);
    }

    // The map: walls occupied where the scans saw them, the path free, outside the room unknown.
    let yaml = MapYaml::parse(&std::fs::read_to_string(out.join("room_map.yaml")).unwrap()).unwrap();
    assert_eq!((yaml.image.as_str(), yaml.resolution), ("room_map.pgm", 0.05));
    let map = load_map(&yaml, &std::fs::read(out.join(&yaml.image)).unwrap()).unwrap();
    let walls = walls();
    let occupied: Vec<[f64; 2]> = (0..map.height)
        .flat_map(|j| (0..map.width).map(move |i| (i, j)))
        .filter(|&(i, j)| map.is_occupied(i, j))
        .map(|(i, j)| map.cell_center(i, j))
        .collect();
    assert!(occupied.len() > 300, "{} occupied cells", occupied.len());
    let near = occupied.iter().filter(|p| distance_to_walls(**p, &walls) < 0.06).count();
    assert!(near * 100 >= occupied.len() * 99, "{near} of {} occupied cells on a wall", occupied.len());
    for (_, p) in &truth {
        let (i, j) = map.cell_of([p.x, p.y]).unwrap();
        assert!(map.is_free(i, j), "the path at {p:?}");
    }
    let (i, j) = map.cell_of([7.0, 4.5]).unwrap();
    assert_eq!(map.get(i, j), Some(amr_core::map::UNKNOWN), "outside the room");

    // The bench reads exactly these files: AMCL tracks within centimetres where the raw odometry
    // alone drifts off.
    let bench =
        amr(&["bench", "localize", "--logs", out.to_str().unwrap(), "--seeds", "1", "--json"], dir.path());
    assert!(bench.status.success(), "{}", String::from_utf8_lossy(&bench.stderr));
    let report: serde_json::Value = serde_json::from_slice(&bench.stdout).unwrap();
    let log = &report["logs"][0];
    assert_eq!(log["name"], "room");
    assert_eq!(log["scans"], 50);
    let rmse = |v: &serde_json::Value| v["translation"]["rmse"].as_f64().unwrap();
    let (odometry, tracking) = (rmse(&log["odometry_only"]), rmse(&log["tracking"][0]["score"]));
    assert!(odometry > 0.3, "the raw odometry alone is {odometry:.3} m off");
    assert!(
        tracking < 0.15 && tracking * 3.0 < odometry,
        "tracking {tracking:.3} m off (odometry alone {odometry:.3} m)"
    );
}

/// A log whose stamps are not distinct (some public logs stamp every scan alike) is matched to its
/// reference by scan order, and so is another localiser's CSV given with `--nav2`.
#[test]
fn a_log_stamped_alike_is_matched_by_order_nav2_rows_too() {
    let dir = tempfile::tempdir().unwrap();
    let (text, _, _) = corrected_log();
    std::fs::write(dir.path().join("room-corrected.log"), &text).unwrap();
    let run = amr(&["tools", "carmen-prepare", "room-corrected.log", "--out", "p"], dir.path());
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let out = dir.path().join("p");
    // Every reference row stamped 0; a "nav2" estimate that is the reference itself, stamped 0.
    let gt = std::fs::read_to_string(out.join("room-gt.csv")).unwrap();
    let mut same = String::from("scan,timestamp,x,y,theta\n");
    let mut nav2 = String::from("timestamp,x,y,theta\n");
    for line in gt.lines().skip(1) {
        let f: Vec<&str> = line.split(',').collect();
        same += &format!("{},0,{},{},{}\n", f[0], f[2], f[3], f[4]);
        nav2 += &format!("0,{},{},{}\n", f[2], f[3], f[4]);
    }
    std::fs::write(out.join("room-gt.csv"), same).unwrap();
    let nav2_dir = dir.path().join("nav2");
    std::fs::create_dir(&nav2_dir).unwrap();
    std::fs::write(nav2_dir.join("room.csv"), &nav2).unwrap();
    let bench = amr(
        &["bench", "localize", "--logs", "p", "--seeds", "1", "--nav2", nav2_dir.to_str().unwrap(), "--json"],
        dir.path(),
    );
    assert!(bench.status.success(), "{}", String::from_utf8_lossy(&bench.stderr));
    let report: serde_json::Value = serde_json::from_slice(&bench.stdout).unwrap();
    let n = &report["logs"][0]["nav2"];
    assert_eq!(n["matched"], 50, "{n}");
    assert!(n["translation"]["rmse"].as_f64().is_some_and(|e| e < 1e-9), "{n}");
    // A CSV with a row missing cannot be matched by order: an error that names it.
    let short: String = nav2.lines().take(40).map(|l| format!("{l}\n")).collect();
    std::fs::write(nav2_dir.join("room.csv"), short).unwrap();
    let bench = amr(
        &["bench", "localize", "--logs", "p", "--seeds", "1", "--nav2", nav2_dir.to_str().unwrap()],
        dir.path(),
    );
    let stderr = String::from_utf8_lossy(&bench.stderr);
    assert_eq!(bench.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("room.csv") && stderr.contains("39 rows for 50 scans"), "{stderr}");
}

/// The public logs are published gzip-compressed: the `.log.gz` gives the same files as the log.
#[test]
fn a_gzip_compressed_log_gives_the_same_files() {
    use std::io::Write as _;
    let dir = tempfile::tempdir().unwrap();
    let (text, _, _) = corrected_log();
    std::fs::write(dir.path().join("room-corrected.log"), &text).unwrap();
    let mut z = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::best());
    z.write_all(text.as_bytes()).unwrap();
    std::fs::write(dir.path().join("room-corrected.log.gz"), z.finish().unwrap()).unwrap();
    for (log, out) in [("room-corrected.log", "plain"), ("room-corrected.log.gz", "gz")] {
        let run = amr(&["tools", "carmen-prepare", log, "--out", out], dir.path());
        assert!(run.status.success(), "{log}: {}", String::from_utf8_lossy(&run.stderr));
    }
    for file in ["room-gt.csv", "room-raw.log", "room_map.pgm", "room_map.yaml"] {
        let plain = std::fs::read(dir.path().join("plain").join(file)).unwrap();
        assert!(!plain.is_empty(), "{file}");
        assert_eq!(plain, std::fs::read(dir.path().join("gz").join(file)).unwrap(), "{file}");
    }
}

#[test]
fn standard_input_names_and_refusals() {
    let dir = tempfile::tempdir().unwrap();
    let (text, _, _) = corrected_log();
    let mut child = Command::new(env!("CARGO_BIN_EXE_amr"))
        .args(["tools", "carmen-prepare", "-", "--name", "piped", "--out", "."])
        .current_dir(dir.path())
        .stdin(Stdio::piped())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    child.stdin.take().unwrap().write_all(text.as_bytes()).unwrap();
    let piped = child.wait_with_output().unwrap();
    assert!(piped.status.success(), "{}", String::from_utf8_lossy(&piped.stderr));
    assert!(dir.path().join("piped-raw.log").exists() && dir.path().join("piped_map.pgm").exists());

    let refused = |args: &[&str], why: &str| {
        let out = amr(args, dir.path());
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{args:?}: {stderr}");
        assert!(stderr.contains(why), "{args:?}: {stderr}");
    };
    refused(&["tools", "carmen-prepare", "-", "--out", "x"], "give --name");
    std::fs::write(dir.path().join("z-corrected.log.gz"), [0x1f, 0x8b, 8, 0, 0, 0]).unwrap();
    refused(&["tools", "carmen-prepare", "z-corrected.log.gz", "--out", "x"], "not whole");
    // A raw log (the FLASER's odometry is not its laser pose) is not a corrected one.
    std::fs::write(
        dir.path().join("raw.log"),
        "ODOM 0 0 0 0 0 0 1 h 1\nFLASER 2 1.0 2.0 0.5 0 0 0 0 0 1 h 1\nODOM 0.5 0 0 0 0 0 2 h 2\n",
    )
    .unwrap();
    refused(&["tools", "carmen-prepare", "raw.log", "--out", "x"], "not a corrected log");
    refused(&["tools", "carmen-prepare", "raw.log", "--out", "x", "--name", "a/b"], "--name `a/b`");
    assert!(!dir.path().join("x").exists(), "nothing written on a refusal");
}

/// `amr tools carmen-kidnap` writes the log `--kidnap` kidnaps, for another localiser to run on;
/// the bench scores that localiser's CSV on the same kidnappings: one that is always right (the
/// reference) was never carried off, one that follows the kidnapped odometry alone was carried
/// off by every jump and never came back.
#[test]
fn a_kidnapped_log_is_written_and_another_localisers_run_on_it_scored() {
    let dir = tempfile::tempdir().unwrap();
    let (text, _, _) = corrected_log();
    std::fs::write(dir.path().join("room-corrected.log"), &text).unwrap();
    let run = amr(&["tools", "carmen-prepare", "room-corrected.log", "--out", "p"], dir.path());
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let run = amr(
        &["tools", "carmen-kidnap", "p/room-raw.log", "--every", "20", "--seed", "4", "--out", "k.log"],
        dir.path(),
    );
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(
        stderr.contains("scan=20") && stderr.contains("scan=40") && stderr.contains("kidnappings=2"),
        "{stderr}"
    );
    let written = std::fs::read_to_string(dir.path().join("k.log")).unwrap();
    let raw = std::fs::read_to_string(dir.path().join("p/room-raw.log")).unwrap();
    // Everything but the poses kept: same lines, same ranges and stamps.
    assert_eq!(written.lines().count(), raw.lines().count());
    let lasers = |t: &str| -> Vec<(Vec<String>, Se2)> {
        t.lines()
            .filter(|l| l.starts_with("FLASER"))
            .map(|l| {
                let f: Vec<&str> = l.split_ascii_whitespace().collect();
                let n: usize = f[1].parse().unwrap();
                let pose = |k: usize| {
                    Se2::new(f[k].parse().unwrap(), f[k + 1].parse().unwrap(), f[k + 2].parse().unwrap())
                };
                let kept = f[..2 + n].iter().chain(&f[8 + n..]).map(|s| (*s).to_owned()).collect();
                (kept, pose(5 + n))
            })
            .collect()
    };
    let (a, b) = (lasers(&raw), lasers(&written));
    assert_eq!(a.len(), 50);
    for (k, ((ka, oa), (kb, ob))) in a.iter().zip(&b).enumerate() {
        assert_eq!(ka, kb, "scan {k}");
        // Before the first kidnapping the odometry is the raw one; after it, moved.
        assert_eq!(oa.approx_eq(ob, 1e-5, 1e-5), k < 20, "scan {k}: {oa:?} {ob:?}");
    }

    // The other localiser's CSVs: the reference (always right) and the kidnapped odometry alone
    // aligned on the first reference pose (carried off by each jump, never back).
    let gt = std::fs::read_to_string(dir.path().join("p/room-gt.csv")).unwrap();
    let rows: Vec<Vec<f64>> =
        gt.lines().skip(1).map(|l| l.split(',').map(|v| v.parse().unwrap()).collect()).collect();
    let first = Se2::new(rows[0][2], rows[0][3], rows[0][4]);
    let align = first * b[0].1.inverse();
    let mut right = String::from("timestamp,x,y,theta\n");
    let mut carried = String::from("timestamp,x,y,theta\n");
    for (r, (_, o)) in rows.iter().zip(&b) {
        right += &format!("{},{},{},{}\n", r[1], r[2], r[3], r[4]);
        let p = align * *o;
        carried += &format!("{},{},{},{}\n", r[1], p.x, p.y, p.theta);
    }
    for (csv, carried_off) in [(right, false), (carried, true)] {
        let nav2_dir = dir.path().join(if carried_off { "carried" } else { "right" });
        std::fs::create_dir(&nav2_dir).unwrap();
        std::fs::write(nav2_dir.join("room-kidnap20-s4.csv"), csv).unwrap();
        let bench = amr(
            &["bench", "localize", "--logs", "p", "--seeds", "4", "--kidnap", "20", "--json", "--nav2"]
                .into_iter()
                .chain([nav2_dir.to_str().unwrap()])
                .collect::<Vec<_>>(),
            dir.path(),
        );
        assert!(bench.status.success(), "{}", String::from_utf8_lossy(&bench.stderr));
        let report: serde_json::Value = serde_json::from_slice(&bench.stdout).unwrap();
        let log = &report["logs"][0];
        let ours: Vec<u64> = log["kidnapped"][0]["kidnaps"]
            .as_array()
            .unwrap()
            .iter()
            .map(|k| k["scan"].as_u64().unwrap())
            .collect();
        assert_eq!(ours, [20, 40]);
        let (seed, theirs) = (&log["nav2_kidnapped"][0][0], log["nav2_kidnapped"][0][1].as_array().unwrap());
        assert_eq!(seed, 4);
        assert_eq!(theirs.iter().map(|k| k["scan"].as_u64().unwrap()).collect::<Vec<_>>(), ours);
        for k in theirs {
            assert_eq!(k["carried_off"], carried_off, "{k}");
            assert!(k["back_after"].is_null() && k["lost_after"].is_null(), "{k}");
        }
    }
}
