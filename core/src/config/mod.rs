//! The configuration schema: TOML text in, validated domain types out.
//!
//! A configuration is a set of files (normally the `config/` directory):
//!
//! | file | type | what |
//! |---|---|---|
//! | `robot-<id>.toml` | [`RobotConfig`] | one robot: chassis, kinematics, LiDAR mount, limits, devices |
//! | `server.toml` | [`ServerConfig`] | the formation, fusion weights and gates, the T1–T4 switch |
//! | `vamr.toml` | [`VamrParams`] | the Virtual-AMR pipeline parameters (paper Table 2) |
//! | `amcl.toml` | [`AmclParams`] | AMCL parameters (nav2_amcl names; `odom_slip_share` is ours) |
//! | `maps/<name>.yaml` + its image | [`OccupancyGrid`] | a ROS map_server map, checked by loading it |
//! | `scenarios/<name>.toml` | [`ScenarioConfig`] | an experiment: start, spacing, V's path, on a map |
//! | `*.md` | — | documentation, ignored |
//!
//! Every struct rejects unknown keys. Rules on a single value are checked while the file is
//! deserialised (see [`value`]); rules that relate several values are checked afterwards. Either
//! way the first broken rule comes back as a [`ConfigError`] naming the file, the key and the rule.
//! This module does no IO: callers read the files and hand over their text.

mod amcl;
mod network;
mod robot;
mod scenario;
mod server;
pub mod value;
mod vamr;

use std::collections::BTreeMap;
use std::fmt;

use serde::de::DeserializeOwned;

use crate::map::{MapYaml, OccupancyGrid, load_map};

pub use amcl::{AmclParams, InitialPose, LaserModel};
pub use network::{MAX_LEASE_MS, NetworkConfig, NetworkServer};
pub use robot::{
    CanConfig, CanTransport, ChassisConfig, CommLossReaction, DeviceSource, DriveConfig, DrivesConfig,
    IMU_BAUD_RATES, IMU_STREAM_RATES_HZ, ImuConfig, ImuDataMode, KinematicsConfig, LidarConfig, LidarDialect,
    LidarStartup, MotionLimits, MountConfig, NodeId, RobotConfig, RobotId, SafetyConfig,
};
pub use scenario::{ScenarioConfig, ScenarioLimits, Segment, StartPose};
pub use server::{Configuration, FormationMember, OnRobotLost, ServerConfig, SyncGates};
pub use vamr::{ContourParams, FusionParams, HeadingParams, PreprocessParams, TrackerParams, VamrParams};

/// The first broken rule of a configuration: which file, which key, which rule.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ConfigError {
    /// The file, as given by the caller (normally relative to the configuration directory).
    pub file: String,
    /// 1-based line of the offending key, when known.
    pub line: Option<usize>,
    /// Dotted key path (`devices.drives.left.node_id`); empty for a file-level problem.
    pub key: String,
    /// The rule, in words, with the offending value.
    pub rule: String,
}

impl fmt::Display for ConfigError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.file)?;
        if let Some(line) = self.line {
            write!(f, ":{line}")?;
        }
        if !self.key.is_empty() {
            write!(f, ": {}", self.key)?;
        }
        write!(f, ": {}", self.rule)
    }
}

impl std::error::Error for ConfigError {}

/// A broken cross-field rule inside one file, before the file name is attached.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Violation {
    pub key: String,
    pub rule: String,
}

/// `Ok(())` when `holds`, else a [`Violation`] of `key`.
pub(crate) fn rule(holds: bool, key: impl Into<String>, rule: impl Into<String>) -> Result<(), Violation> {
    if holds { Ok(()) } else { Err(Violation { key: key.into(), rule: rule.into() }) }
}

/// A configuration file type: deserialised, then checked for rules across its fields.
pub trait ConfigFileType: DeserializeOwned {
    /// Rules that relate several fields of this file.
    fn validate(&self) -> Result<(), Violation>;
}

/// Parse and validate one file of type `T`. `file` names it in errors.
pub fn parse_file<T: ConfigFileType>(file: &str, text: &str) -> Result<T, ConfigError> {
    let error = |line, key: String, rule: String| ConfigError { file: file.to_owned(), line, key, rule };
    let de = toml::Deserializer::parse(text)
        .map_err(|e| error(span_line(text, e.span()), String::new(), syntax_rule(&e)))?;
    let value: T = serde_path_to_error::deserialize(de).map_err(|e| {
        let key = e.path().to_string();
        let key = if key == "." { String::new() } else { key };
        let inner = e.into_inner();
        error(span_line(text, inner.span()), key, inner.message().to_owned())
    })?;
    value.validate().map_err(|v| error(key_line(text, &v.key), v.key, v.rule))?;
    Ok(value)
}

fn syntax_rule(e: &toml::de::Error) -> String {
    format!("not valid TOML: {}", e.message().trim_end())
}

fn span_line(text: &str, span: Option<std::ops::Range<usize>>) -> Option<usize> {
    let start = span?.start.min(text.len());
    Some(text.as_bytes()[..start].iter().filter(|&&b| b == b'\n').count() + 1)
}

/// Line of a key path such as `devices.drives.right.node_id` or `robots[1].id`, found through
/// toml's span-keeping parse so it works for dotted keys, inline tables and arrays of tables alike.
fn key_line(text: &str, key: &str) -> Option<usize> {
    use toml::de::{DeTable, DeValue};
    let root = DeTable::parse(text).ok()?;
    let mut table = root.get_ref();
    let mut span = None;
    let segments: Vec<&str> = key.split('.').collect();
    for (i, segment) in segments.iter().enumerate() {
        let mut parts = segment.split('[');
        let name = parts.next()?;
        let (k, mut value) = table.iter().find(|(k, _)| k.get_ref().as_ref() == name)?;
        span = Some(k.span());
        for index in parts {
            let index: usize = index.trim_end_matches(']').parse().ok()?;
            match value.get_ref() {
                DeValue::Array(items) => value = items.get(index)?,
                _ => return None,
            }
            span = Some(value.span());
        }
        if i + 1 < segments.len() {
            match value.get_ref() {
                DeValue::Table(t) => table = t,
                _ => return None,
            }
        }
    }
    span_line(text, span)
}

/// A map's YAML and its image (in `maps/`, named by the YAML): the grid, by the map's name.
fn load_map_file(
    yaml_file: &ConfigFile,
    files: &[ConfigFile],
) -> Result<(String, OccupancyGrid), ConfigError> {
    let error = |file: &str, key: &str, rule: String| ConfigError {
        file: file.to_owned(),
        line: None,
        key: key.to_owned(),
        rule,
    };
    let yaml = MapYaml::parse(yaml_file.text()?).map_err(|e| match e {
        crate::map::MapError::Invalid { key, rule } => error(&yaml_file.path, key, rule),
        other => error(&yaml_file.path, "", other.to_string()),
    })?;
    let image_path = format!("maps/{}", yaml.image);
    let image = files.iter().find(|f| f.path == image_path).ok_or_else(|| {
        error(&yaml_file.path, "image", format!("names {image_path}, which is not in the configuration"))
    })?;
    let grid = load_map(&yaml, &image.bytes).map_err(|e| error(&image_path, "", e.to_string()))?;
    let name = yaml_file.path.trim_start_matches("maps/").trim_end_matches(".yaml").to_owned();
    Ok((name, grid))
}

/// What a file in a configuration directory is, judged by its path.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FileKind {
    Robot,
    Server,
    Vamr,
    Amcl,
    /// `network.toml`: the fleet's network link (optional).
    Network,
    /// `maps/<name>.yaml`: a map's metadata.
    Map,
    /// `maps/<name>.pgm` or `.png`: a map's image, read through its YAML.
    MapImage,
    /// `scenarios/<name>.toml`.
    Scenario,
    /// Documentation (`*.md`): skipped.
    Documentation,
}

impl FileKind {
    /// Classify a path relative to the configuration directory (`/`-separated).
    pub fn of(path: &str) -> Result<FileKind, String> {
        if path.ends_with(".md") {
            return Ok(FileKind::Documentation);
        }
        match path {
            "server.toml" => Ok(FileKind::Server),
            "vamr.toml" => Ok(FileKind::Vamr),
            "amcl.toml" => Ok(FileKind::Amcl),
            "network.toml" => Ok(FileKind::Network),
            p if p.starts_with("robot-") && p.ends_with(".toml") && !p.contains('/') => Ok(FileKind::Robot),
            p if p.strip_prefix("scenarios/").is_some_and(|n| !n.contains('/') && n.ends_with(".toml")) => {
                Ok(FileKind::Scenario)
            }
            p if p.strip_prefix("maps/").is_some_and(|name| !name.contains('/')) => {
                if p.ends_with(".yaml") {
                    Ok(FileKind::Map)
                } else if p.ends_with(".pgm") || p.ends_with(".png") {
                    Ok(FileKind::MapImage)
                } else {
                    Err("unknown file in maps/: expected <name>.yaml with a .pgm or .png image".to_owned())
                }
            }
            _ => Err(
                "unknown configuration file: expected robot-<id>.toml, server.toml, vamr.toml, amcl.toml, network.toml, \
                      maps/<name>.yaml, scenarios/<name>.toml or *.md documentation"
                    .to_owned(),
            ),
        }
    }
}

/// One file of a configuration set: its path relative to the set's root (`/`-separated) and its
/// contents.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ConfigFile {
    pub path: String,
    pub bytes: Vec<u8>,
}

impl ConfigFile {
    /// The contents as text, or the error naming the file.
    pub fn text(&self) -> Result<&str, ConfigError> {
        std::str::from_utf8(&self.bytes).map_err(|_| ConfigError {
            file: self.path.clone(),
            line: None,
            key: String::new(),
            rule: "not UTF-8 text".to_owned(),
        })
    }
}

/// A complete, validated configuration: every robot, the server, and the algorithm parameters.
#[derive(Debug, Clone)]
pub struct Config {
    /// Robots sorted by id.
    pub robots: Vec<RobotConfig>,
    pub server: ServerConfig,
    pub vamr: VamrParams,
    pub amcl: AmclParams,
    /// Maps by name (`maps/<name>.yaml`).
    pub maps: BTreeMap<String, OccupancyGrid>,
    /// Scenarios by name (`scenarios/<name>.toml`).
    pub scenarios: BTreeMap<String, ScenarioConfig>,
    /// The network link (`network.toml`), if the set has one.
    pub network: Option<NetworkConfig>,
}

impl Config {
    /// Parse and validate a whole set. Files are taken in path order and the first broken rule is
    /// returned, so the same set always gives the same error.
    pub fn from_files(mut files: Vec<ConfigFile>) -> Result<Config, ConfigError> {
        files.sort_by(|a, b| a.path.cmp(&b.path));
        let mut robots: Vec<(String, RobotConfig)> = Vec::new();
        let (mut server, mut vamr, mut amcl, mut network) = (None, None, None, None);
        let mut maps = BTreeMap::new();
        let mut scenarios = BTreeMap::new();
        for f in &files {
            let kind = FileKind::of(&f.path).map_err(|rule| ConfigError {
                file: f.path.clone(),
                line: None,
                key: String::new(),
                rule,
            })?;
            match kind {
                FileKind::Documentation | FileKind::MapImage => {}
                FileKind::Server => server = Some(parse_file::<ServerConfig>(&f.path, f.text()?)?),
                FileKind::Vamr => vamr = Some(parse_file::<VamrParams>(&f.path, f.text()?)?),
                FileKind::Amcl => amcl = Some(parse_file::<AmclParams>(&f.path, f.text()?)?),
                FileKind::Network => network = Some(parse_file::<NetworkConfig>(&f.path, f.text()?)?),
                FileKind::Map => {
                    let (name, grid) = load_map_file(f, &files)?;
                    maps.insert(name, grid);
                }
                FileKind::Scenario => {
                    let scenario = parse_file::<ScenarioConfig>(&f.path, f.text()?)?;
                    let name = f.path.trim_start_matches("scenarios/").trim_end_matches(".toml").to_owned();
                    scenarios.insert(name, (f.path.clone(), scenario));
                }
                FileKind::Robot => {
                    let text = f.text()?;
                    let robot = parse_file::<RobotConfig>(&f.path, text)?;
                    let stem = f.path.trim_end_matches(".toml");
                    if robot.id.as_str() != stem {
                        return Err(ConfigError {
                            file: f.path.clone(),
                            line: key_line(text, "id"),
                            key: "id".to_owned(),
                            rule: format!("must equal the file name `{stem}` (got `{}`)", robot.id.as_str()),
                        });
                    }
                    robots.push((f.path.clone(), robot));
                }
            }
        }
        let missing = |file: &str| ConfigError {
            file: file.to_owned(),
            line: None,
            key: String::new(),
            rule: "missing: a configuration needs this file".to_owned(),
        };
        let server = server.ok_or_else(|| missing("server.toml"))?;
        let vamr = vamr.ok_or_else(|| missing("vamr.toml"))?;
        let amcl = amcl.ok_or_else(|| missing("amcl.toml"))?;
        let robots: Vec<RobotConfig> = robots.into_iter().map(|(_, r)| r).collect();
        let server_text =
            files.iter().find(|f| f.path == "server.toml").and_then(|f| f.text().ok()).unwrap_or_default();
        for (i, member) in server.robots.iter().enumerate() {
            if !robots.iter().any(|r| r.id == member.id) {
                let key = format!("robots[{i}].id");
                return Err(ConfigError {
                    file: "server.toml".to_owned(),
                    line: key_line(server_text, &key),
                    key,
                    rule: format!(
                        "names robot `{}`, but there is no robot file with that id (expected {}.toml)",
                        member.id.as_str(),
                        member.id.as_str()
                    ),
                });
            }
        }
        let mut checked = BTreeMap::new();
        for (name, (path, scenario)) in scenarios {
            if !maps.contains_key(&scenario.map) {
                let text =
                    files.iter().find(|f| f.path == path).and_then(|f| f.text().ok()).unwrap_or_default();
                return Err(ConfigError {
                    file: path,
                    line: key_line(text, "map"),
                    key: "map".to_owned(),
                    rule: format!("names map `{}`, but there is no maps/{}.yaml", scenario.map, scenario.map),
                });
            }
            checked.insert(name, scenario);
        }
        Ok(Config { robots, server, vamr, amcl, maps, scenarios: checked, network })
    }

    /// The robot with this id.
    #[must_use]
    pub fn robot(&self, id: &str) -> Option<&RobotConfig> {
        self.robots.iter().find(|r| r.id.as_str() == id)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const DOC: &str = "id = 1\n[devices.drives]\nleft = { node_id = 1 }\n\n[[robots]]\nid = \"a\"\n[[robots]]\nid = \"b\"\n[tracker]\nroi = [0.25,\n  -0.25]\n";

    #[test]
    fn key_lines_through_tables_inline_tables_and_arrays() {
        assert_eq!(key_line(DOC, "id"), Some(1));
        assert_eq!(key_line(DOC, "devices.drives.left.node_id"), Some(3));
        assert_eq!(key_line(DOC, "robots[0].id"), Some(6));
        assert_eq!(key_line(DOC, "robots[1].id"), Some(8));
        assert_eq!(key_line(DOC, "tracker.roi[1]"), Some(11));
        assert_eq!(key_line(DOC, "tracker.nothing"), None);
        assert_eq!(key_line("not = [toml", "not"), None);
    }

    #[test]
    fn error_display_names_file_line_key_and_rule() {
        let e = ConfigError {
            file: "a.toml".into(),
            line: Some(3),
            key: "x.y".into(),
            rule: "must be > 0".into(),
        };
        assert_eq!(e.to_string(), "a.toml:3: x.y: must be > 0");
        let file_level =
            ConfigError { file: "b.toml".into(), line: None, key: String::new(), rule: "missing".into() };
        assert_eq!(file_level.to_string(), "b.toml: missing");
    }

    #[test]
    fn classification() {
        assert_eq!(FileKind::of("robot-a.toml"), Ok(FileKind::Robot));
        assert_eq!(FileKind::of("server.toml"), Ok(FileKind::Server));
        assert_eq!(FileKind::of("maps/README.md"), Ok(FileKind::Documentation));
        assert_eq!(FileKind::of("maps/site.yaml"), Ok(FileKind::Map));
        assert_eq!(FileKind::of("maps/site.pgm"), Ok(FileKind::MapImage));
        assert!(FileKind::of("maps/site.jpg").is_err());
        assert!(FileKind::of("maps/old/site.yaml").is_err());
        assert!(FileKind::of("robots/robot-a.toml").is_err());
        assert!(FileKind::of("robot-a.yaml").is_err());
    }
}
