//! The crate graph points one way (`docs/architecture.md`, rules between crates): the configuration plumbing
//! (settings) depends on nothing of ours, core and drivers only on it, the message vocabulary
//! (msgs) only on core, actors on core, msgs and drivers, hil-mocks
//! on core and drivers (never on the actors or their messages), the simulation on those, the
//! network link on core, msgs and actors, the ROS 2 layer (ros2) on nothing of ours, the recorder
//! on core, msgs, actors and ros2, the experiments (lab) on core, msgs, actors, hil-mocks, the
//! simulation and the recorder, the tests on everything but host, and nothing at all depends on
//! host.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code: a failed step fails the test")]

use std::collections::BTreeSet;
use std::path::Path;

const OURS: [&str; 13] = [
    "amr-settings",
    "amr-core",
    "amr-msgs",
    "amr-drivers",
    "amr-actors",
    "hil-mocks",
    "amr-sim",
    "amr-net",
    "amr-ros2",
    "amr-record",
    "amr-lab",
    "host",
    "hil-tests",
];

fn our_deps(member_dir: &str) -> (String, BTreeSet<String>) {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("..").join(member_dir).join("Cargo.toml");
    let manifest: toml::Table = toml::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    let name = manifest["package"]["name"].as_str().unwrap().to_owned();
    let mut deps = BTreeSet::new();
    for section in ["dependencies", "dev-dependencies", "build-dependencies"] {
        if let Some(table) = manifest.get(section).and_then(toml::Value::as_table) {
            deps.extend(table.keys().filter(|k| OURS.contains(&k.as_str())).cloned());
        }
    }
    (name, deps)
}

#[test]
fn dependencies_point_one_way() {
    let workspace: toml::Table = toml::from_str(
        &std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("../Cargo.toml")).unwrap(),
    )
    .unwrap();
    let members: Vec<&str> =
        workspace["workspace"]["members"].as_array().unwrap().iter().map(|m| m.as_str().unwrap()).collect();
    assert_eq!(members.len(), OURS.len(), "a new member needs a rule here");

    // host may use every other member; the tests every library (every member but host and them).
    let not_host: Vec<&str> = OURS.iter().copied().filter(|n| *n != "host").collect();
    let libraries: Vec<&str> = not_host.iter().copied().filter(|n| *n != "hil-tests").collect();
    let allowed = |name: &str| -> &[&str] {
        match name {
            "amr-settings" => &[],
            // Each owns its part of the configuration, written with settings' values and errors.
            "amr-core" | "amr-drivers" => &["amr-settings"],
            "amr-msgs" => &["amr-core"],
            "amr-actors" => &["amr-core", "amr-msgs", "amr-drivers"],
            "hil-mocks" => &["amr-core", "amr-drivers", "amr-settings"],
            // The simulation wires the actors to the mocks, and runs the evaluation on the server's
            // core; `amr sim`, `amr eval` and the HIL tests share it.
            "amr-sim" => &["amr-core", "amr-msgs", "amr-drivers", "amr-actors", "hil-mocks"],
            // The network link and the recorder carry the fleet's messages and the actors' ports.
            "amr-net" => &["amr-core", "amr-msgs", "amr-actors"],
            // ROS 2's encoding, message types and wire conventions know nothing of the fleet.
            "amr-ros2" => &[],
            "amr-record" => &["amr-core", "amr-msgs", "amr-actors", "amr-ros2"],
            // The experiments run the simulation's evaluation, record its trials and read
            // configurations: everything below them but the network link and ROS 2.
            "amr-lab" => &["amr-core", "amr-msgs", "amr-actors", "hil-mocks", "amr-sim", "amr-record"],
            "hil-tests" => &libraries,
            // host is the wiring: it may use every library, and its tests use the fixtures crate.
            "host" => &not_host,
            other => panic!("unknown member {other}"),
        }
    };
    for dir in members {
        let (name, deps) = our_deps(dir);
        let extra: Vec<&String> = deps.iter().filter(|d| !allowed(&name).contains(&d.as_str())).collect();
        assert!(extra.is_empty(), "{name} ({dir}/) must not depend on {extra:?}");
        assert!(!deps.contains("host"), "{name} depends on host");
    }
}
