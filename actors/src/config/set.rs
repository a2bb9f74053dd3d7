//! A configuration set: the files of a `config/` directory, each parsed into the type of the crate
//! that owns it, and checked against each other (a server naming a robot with no file, a scenario
//! on a map that is not there).
//!
//! | file | type | owner |
//! |---|---|---|
//! | `robot-<id>.toml` | [`RobotConfig`] | body: amr-core; `[devices.*]`: amr-drivers |
//! | `server.toml`, `vamr.toml`, `amcl.toml`, `scenarios/<name>.toml` | [`ServerConfig`], [`VamrParams`], [`AmclParams`], [`ScenarioConfig`] | amr-core |
//! | `maps/<name>.yaml` + its image | [`OccupancyGrid`] | amr-core, checked by loading it |
//! | `network.toml` | kept as text here | amr-net (`NetSettings`) |
//! | `*.md` | documentation, ignored | |

use std::collections::BTreeMap;

use amr_core::config::{
    AmclParams, ConfigError, ScenarioConfig, ServerConfig, VamrParams, key_line, parse_file,
};
use amr_core::map::{MapYaml, OccupancyGrid, load_map};

use super::robot::RobotConfig;

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
        amr_core::map::MapError::Invalid { key, rule } => error(&yaml_file.path, key, rule),
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

/// The name of the set's map at `map` (a path relative to the file at `from`), if it is one:
/// `../maps/hall.yaml` from `scenarios/x.toml` is `hall`.
fn set_map_name(from: &str, map: &str) -> Option<String> {
    let mut parts: Vec<&str> = from.split('/').collect();
    parts.pop();
    for p in map.split('/') {
        match p {
            "" | "." => {}
            ".." => {
                parts.pop()?;
            }
            p => parts.push(p),
        }
    }
    match parts.as_slice() {
        ["maps", file] => file.strip_suffix(".yaml").map(str::to_owned),
        _ => None,
    }
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
    /// `network.toml`, if the set has one: the network link's own file, parsed and checked by
    /// the link (`amr_net::NetSettings`), which owns its type.
    pub network: Option<ConfigFile>,
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
                FileKind::Network => network = Some(f.clone()),
                FileKind::Map => {
                    let (name, grid) = load_map_file(f, &files)?;
                    maps.insert(name, grid);
                }
                FileKind::Scenario => {
                    let mut scenario = parse_file::<ScenarioConfig>(&f.path, f.text()?)?;
                    // `map = "../maps/NAME.yaml"`: a path relative to the scenario file, which in a
                    // set must be one of its maps.
                    if super::is_map_path(&scenario.map) {
                        scenario.map = set_map_name(&f.path, &scenario.map).ok_or_else(|| ConfigError {
                            file: f.path.clone(),
                            line: key_line(f.text().unwrap_or_default(), "map"),
                            key: "map".to_owned(),
                            rule: format!(
                                "names `{}`, which is not a map of this configuration (maps/<name>.yaml)",
                                scenario.map
                            ),
                        })?;
                    }
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
    #![allow(clippy::unwrap_used, reason = "tests")]

    use super::*;

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

    #[test]
    fn a_set_scenario_may_name_its_map_by_path() {
        assert_eq!(set_map_name("scenarios/x.toml", "../maps/hall.yaml").as_deref(), Some("hall"));
        assert_eq!(set_map_name("scenarios/x.toml", "./../maps/./hall.yaml").as_deref(), Some("hall"));
        assert_eq!(set_map_name("scenarios/x.toml", "hall.yaml"), None);
        assert_eq!(set_map_name("scenarios/x.toml", "../../maps/hall.yaml"), None);
        assert_eq!(set_map_name("scenarios/x.toml", "../maps/old/hall.yaml"), None);
        // Through the loader: the shipped set with `straight` naming its map by path.
        let mut files = crate::config::read_files(&crate::config::ConfigSource::Embedded).unwrap();
        let f = files.iter_mut().find(|f| f.path == "scenarios/straight.toml").unwrap();
        let text = f.text().unwrap().replace("map = \"paper-site\"", "map = \"../maps/paper-site.yaml\"");
        f.bytes = text.clone().into_bytes();
        let config = Config::from_files(files.clone()).unwrap();
        assert_eq!(config.scenarios["straight"].map, "paper-site");
        let f = files.iter_mut().find(|f| f.path == "scenarios/straight.toml").unwrap();
        f.bytes = text.replace("paper-site.yaml", "hall.yaml").into_bytes();
        let e = Config::from_files(files).unwrap_err();
        assert_eq!(
            (e.file.as_str(), e.key.as_str(), e.line),
            ("scenarios/straight.toml", "map", Some(4)),
            "{e}"
        );
    }
}
