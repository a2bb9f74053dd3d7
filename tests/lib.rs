//! `hil-tests`: the integration tests across the crates, one test target each: configuration
//! fixtures, HIL runs against the mocks, supervision, degradation and fault-recovery drills,
//! determinism, recording, one server core on every path, the crate graph. This library holds what
//! they share: the shipped configuration and the bad-config fixtures.
//!
//! A fixture in `fixtures/bad-config/NAME.toml` breaks one rule. Its header says how:
//!
//! ```toml
//! # file: robot-a.toml                 the file of config/ it changes
//! # mode: overlay                      overlay (default) | replace | add | delete
//! # remove: kinematics.wheel_radius_m  (optional, repeatable) delete this key first
//! # expect: robot-a.toml: kinematics.wheel_radius_m: must be > 0 (got -0.05)
//! ```
//!
//! `overlay` merges the fixture's tables into the shipped file (its keys win); `replace` swaps the
//! file's text for the fixture's body; `add` puts the body in as a new file; `delete` removes the
//! file. `expect` is exactly what
//! `amr config check` prints after `error: `, without the line number.

use std::path::{Path, PathBuf};

use amr_actors::config::ConfigFile;
use amr_actors::config::{ConfigSource, read_files};

/// The repository's `config/` directory.
#[must_use]
pub fn config_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../config")
}

/// The fixtures directory for broken configurations.
#[must_use]
pub fn bad_config_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/bad-config")
}

/// One bad-config fixture, parsed.
#[derive(Debug, Clone)]
pub struct Fixture {
    pub name: String,
    pub file: String,
    pub mode: String,
    pub remove: Vec<String>,
    pub expect: String,
    pub body: String,
}

/// Every fixture, sorted by name.
pub fn fixtures() -> Result<Vec<Fixture>, String> {
    let mut paths: Vec<PathBuf> = std::fs::read_dir(bad_config_dir())
        .map_err(|e| e.to_string())?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "toml"))
        .collect();
    paths.sort();
    paths.iter().map(|p| parse_fixture(p)).collect()
}

fn parse_fixture(path: &Path) -> Result<Fixture, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let name = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
    let mut fx = Fixture {
        name: name.clone(),
        file: String::new(),
        mode: "overlay".into(),
        remove: Vec::new(),
        expect: String::new(),
        body: String::new(),
    };
    let mut body = Vec::new();
    for line in text.lines() {
        let header = line.strip_prefix("# ").and_then(|l| l.split_once(": "));
        match header {
            Some(("file", v)) => fx.file = v.trim().to_owned(),
            Some(("mode", v)) => fx.mode = v.trim().to_owned(),
            Some(("remove", v)) => fx.remove.push(v.trim().to_owned()),
            Some(("expect", v)) => fx.expect = v.trim().to_owned(),
            _ => body.push(line),
        }
    }
    fx.body = body.join("\n") + "\n";
    if fx.file.is_empty() || fx.expect.is_empty() {
        return Err(format!("fixture {name}: needs `# file:` and `# expect:` lines"));
    }
    Ok(fx)
}

fn merge(base: &mut toml::Table, overlay: toml::Table) {
    for (k, v) in overlay {
        match (base.get_mut(&k), v) {
            (Some(toml::Value::Table(b)), toml::Value::Table(o)) => merge(b, o),
            (_, v) => {
                base.insert(k, v);
            }
        }
    }
}

fn remove_key(table: &mut toml::Table, dotted: &str) -> Result<(), String> {
    let mut parts: Vec<&str> = dotted.split('.').collect();
    let leaf = parts.pop().ok_or("empty key")?;
    let mut t = table;
    for p in parts {
        t = t
            .get_mut(p)
            .and_then(toml::Value::as_table_mut)
            .ok_or_else(|| format!("no table {p} in {dotted}"))?;
    }
    t.remove(leaf).map(|_| ()).ok_or_else(|| format!("no key {dotted}"))
}

/// The shipped configuration with `fixture` applied.
pub fn apply(fixture: &Fixture) -> Result<Vec<ConfigFile>, String> {
    let mut files = read_files(&ConfigSource::Dir(config_dir())).map_err(|e| e.to_string())?;
    let existing = files.iter().position(|f| f.path == fixture.file);
    match (fixture.mode.as_str(), existing) {
        ("add", None) => {
            files.push(ConfigFile { path: fixture.file.clone(), bytes: fixture.body.clone().into_bytes() })
        }
        ("replace", Some(i)) => files[i].bytes = fixture.body.clone().into_bytes(),
        ("delete", Some(i)) => {
            files.remove(i);
        }
        ("overlay", Some(i)) => {
            let text = files[i].text().map_err(|e| e.to_string())?;
            let mut base: toml::Table = toml::from_str(text).map_err(|e| e.to_string())?;
            for key in &fixture.remove {
                remove_key(&mut base, key)?;
            }
            let overlay: toml::Table = toml::from_str(&fixture.body).map_err(|e| e.to_string())?;
            merge(&mut base, overlay);
            files[i].bytes = toml::to_string(&base).map_err(|e| e.to_string())?.into_bytes();
        }
        (mode, _) => {
            return Err(format!("fixture {}: mode {mode} does not fit file {}", fixture.name, fixture.file));
        }
    }
    Ok(files)
}

/// Write a configuration set into a directory (for running the binary on it).
pub fn write_dir(files: &[ConfigFile], dir: &Path) -> std::io::Result<()> {
    for f in files {
        let path = dir.join(&f.path);
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent)?;
        }
        std::fs::write(path, &f.bytes)?;
    }
    Ok(())
}

/// An error as `amr config check` prints it, less the line number.
#[must_use]
pub fn without_line(e: &amr_core::config::ConfigError) -> String {
    let mut s = e.file.clone();
    if !e.key.is_empty() {
        s += ": ";
        s += &e.key;
    }
    s + ": " + &e.rule
}

/// A short scenario on the paper's site: V starts at (−2 m, 0, 0°) with the pair 0.9 m apart and the
/// experiments' limits; `segments` is the TOML array, e.g. `[{ straight_m = 2.0 }]`.
///
/// # Panics
/// If `segments` is not a valid segment list (a test's own literal).
#[must_use]
#[allow(clippy::expect_used, reason = "the tests' own literal")]
pub fn short_scenario(segments: &str) -> amr_core::config::ScenarioConfig {
    toml::from_str(&short_scenario_text(segments)).expect("a valid scenario")
}

/// The text of [`short_scenario`] (one lap).
#[must_use]
pub fn short_scenario_text(segments: &str) -> String {
    format!(
        "map = \"paper-site\"\nspacing_m = 0.9\nlaps = 1\nsegments = {segments}\n\
         [start]\nx_m = -2.0\ny_m = 0.0\nyaw_deg = 0.0\n\
         [limits]\nmax_speed_mps = 0.22\nmax_accel_mps2 = 0.05\nmax_yaw_rate_radps = 0.2\n"
    )
}

/// Options of a simulation of `scenario` with typical noise, at most `max_s` seconds long.
#[must_use]
pub fn sim_options(
    scenario: amr_core::config::ScenarioConfig,
    seed: u64,
    can: amr_sim::SimCan,
    max_s: u64,
) -> amr_sim::SimOptions {
    amr_sim::SimOptions {
        scenario_name: "short".into(),
        scenario,
        seed,
        noise: hil_mocks::world::Noise::TYPICAL,
        can,
        configuration: None,
        max_duration: Some(std::time::Duration::from_secs(max_s)),
        map: None,
        surveyed_map: false,
    }
}
