//! `amr sim --ros2-live dds --ros2-cmd-vel` against Eclipse Cyclone DDS (its Python binding, with
//! the C library it bundles; `peers/ros2_dds_peer.py`), the DDS of many ROS 2 installations: the
//! peer reads our scans, /tf and V's estimate with its covariance, gets /map as a late joiner
//! (transient local), gives V's pose on /initialpose and turns the formation on /cmd_vel. DDS
//! discovers by multicast: both run in a network namespace of their own (`unshare -n`, loopback
//! only), nothing leaves it.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code: a failed step fails the test")]

use std::process::Command;

use amr_actors::config::{ConfigSource, load};
use hil_tests::config_dir;

/// Run the shell script `body` in a network namespace of its own (`unshare -n`) with loopback up
/// and multicast routed on it (DDS discovers by multicast): nothing leaves the namespace. At most
/// 120 s. The script stops at the first failing command until it says `set +e`.
pub(crate) fn in_own_netns(body: &str) -> std::process::Output {
    let script = format!(
        "set -e\nip link set lo up\nip link set lo multicast on\nip route add 224.0.0.0/4 dev lo\n{body}"
    );
    Command::new("timeout")
        .args(["120", "unshare", "-n", "sh", "-c", &script])
        .env_remove("RUST_LOG")
        .output()
        .expect("unshare and ip (util-linux, iproute2)")
}

#[test]
fn cyclone_dds_sees_the_fleet_and_drives_it_in_a_namespace_of_its_own() {
    let dir = tempfile::tempdir().unwrap();
    let (err, out) = (dir.path().join("sim.err"), dir.path().join("peer.json"));
    let config = config_dir();
    let script = format!(
        r#""{amr}" sim --quiet --duration 40 --config "{config}" --ros2-live dds --ros2-domain 5 --ros2-cmd-vel >/dev/null 2>"{err}" &
SIM=$!
sleep 3
set +e
python3 "{peer}" 5 5 0.3 >"{out}"
STATUS=$?
kill -INT $SIM
wait $SIM
exit $STATUS
"#,
        amr = env!("CARGO_BIN_EXE_amr"),
        config = config.display(),
        err = err.display(),
        peer = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/cli_runs/peers/ros2_dds_peer.py"),
        out = out.display(),
    );
    let run = in_own_netns(&script);
    let sim_err = std::fs::read_to_string(&err).unwrap_or_default();
    assert!(
        run.status.success(),
        "the namespace run failed: {}\n{}\namr sim: {sim_err}",
        String::from_utf8_lossy(&run.stdout),
        String::from_utf8_lossy(&run.stderr)
    );
    let v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    assert!(
        sim_err.contains("the filters start again there"),
        "the server did not take Cyclone's /initialpose:\n{sim_err}"
    );

    let scans = v["scans"].as_array().unwrap();
    assert!(scans.len() >= 10, "{} scans\n{sim_err}", scans.len());
    assert!(
        scans.iter().all(|s| s["frame_id"] == "robot-a/laser" && s["ranges"] == 271),
        "{:?}",
        &scans[..3]
    );
    // /map, published before the peer existed, came to it once (transient local).
    let maps = v["maps"].as_array().unwrap();
    assert_eq!(maps.len(), 1, "{maps:?}");
    let grid = load(&ConfigSource::Dir(config)).unwrap().scenario("straight").unwrap().map;
    assert_eq!(maps[0]["width"].as_u64(), Some(grid.width as u64));
    assert_eq!(maps[0]["height"].as_u64(), Some(grid.height as u64));
    assert_eq!(maps[0]["cells"].as_u64(), Some((grid.width * grid.height) as u64));
    let pairs: Vec<(String, String)> = serde_json::from_value(v["tf_pairs"].clone()).unwrap();
    for (p, c) in [("V/odom", "V"), ("map", "V/odom"), ("robot-a/odom", "robot-a"), ("map", "robot-b/odom")] {
        assert!(pairs.contains(&(p.into(), c.into())), "{p} → {c} not in {pairs:?}");
    }
    // V's estimates in `map` with their covariance, and V turning under the twists (its plan
    // goes straight).
    let est: Vec<serde_json::Value> = v["estimates"].as_array().unwrap().clone();
    assert!(est.len() > 10);
    assert!(est.iter().all(|e| e[5] == "map" && e[4].as_f64().unwrap() > 0.0), "{:?}", &est[..2]);
    let (drive, silent) = (v["phases"]["drive"].as_f64().unwrap(), v["phases"]["silent"].as_f64().unwrap());
    let heading_at = |t: f64| {
        let e = est
            .iter()
            .min_by(|a, b| (a[0].as_f64().unwrap() - t).abs().total_cmp(&(b[0].as_f64().unwrap() - t).abs()));
        e.unwrap()[3].as_f64().unwrap()
    };
    let turned = amr_core::se2::angle_diff(heading_at(silent), heading_at(drive));
    assert!(turned > 0.3, "V turned {turned} rad under 0.3 rad/s for 5 s\n{sim_err}");
}
