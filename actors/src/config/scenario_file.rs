//! A scenario chosen by name (one of the configuration's `scenarios/`) or by path (a `.toml` file
//! anywhere, whose `map` may be a path relative to it: `map = "../maps/hall.yaml"`), with its map,
//! so that a site of one's own can be run without changing the shipped configuration. Errors
//! name the file and the key.

use std::path::{Path, PathBuf};

use amr_core::config::{ConfigError, ScenarioConfig, key_line, parse_file};
use amr_core::map::{MapError, MapYaml, OccupancyGrid, load_map};

use super::{Config, LoadError};

/// A scenario and the map it runs on.
#[derive(Debug, Clone)]
pub struct ChosenScenario {
    /// The scenario's name, or its file's path.
    pub name: String,
    /// A short name for output directories: the name, or the file's stem.
    pub stem: String,
    pub scenario: ScenarioConfig,
    /// The map's name in the configuration, or its YAML's path.
    pub map_name: String,
    pub map: OccupancyGrid,
}

/// Whether `which` names a scenario file rather than a scenario of the configuration.
#[must_use]
pub fn is_path(which: &str) -> bool {
    which.ends_with(".toml") || which.contains('/')
}

/// Whether a scenario's `map` is a path (to a map_server YAML) rather than a map's name.
#[must_use]
pub fn is_map_path(map: &str) -> bool {
    map.ends_with(".yaml") || map.ends_with(".yml") || map.contains('/')
}

fn invalid(file: &Path, key: &str, line: Option<usize>, rule: String) -> LoadError {
    LoadError::Invalid(ConfigError { file: file.display().to_string(), line, key: key.to_owned(), rule })
}

/// A map_server YAML and its image, from disk.
pub fn load_map_path(yaml_path: &Path) -> Result<OccupancyGrid, LoadError> {
    let text = std::fs::read_to_string(yaml_path)
        .map_err(|error| LoadError::Io { path: yaml_path.to_path_buf(), error })?;
    let yaml = MapYaml::parse(&text).map_err(|e| match e {
        MapError::Invalid { key, rule } => invalid(yaml_path, key, key_line(&text, key), rule),
        other => invalid(yaml_path, "", None, other.to_string()),
    })?;
    let image_path = yaml_path.parent().unwrap_or(Path::new(".")).join(&yaml.image);
    let image =
        std::fs::read(&image_path).map_err(|error| LoadError::Io { path: image_path.clone(), error })?;
    load_map(&yaml, &image).map_err(|e| invalid(&image_path, "", None, e.to_string()))
}

impl Config {
    /// The scenario `which`: a name of this configuration, or a path to a scenario file.
    pub fn scenario(&self, which: &str) -> Result<ChosenScenario, LoadError> {
        if !is_path(which) {
            let scenario = self.scenarios.get(which).cloned().ok_or_else(|| {
                let have: Vec<&String> = self.scenarios.keys().collect();
                invalid(Path::new("scenarios"), "", None, format!("no scenario `{which}` (have: {have:?})"))
            })?;
            // The set's loader checked that its scenarios name its maps.
            let map = self.maps.get(&scenario.map).cloned().ok_or_else(|| {
                invalid(Path::new("scenarios"), "map", None, format!("no map `{}`", scenario.map))
            })?;
            return Ok(ChosenScenario {
                name: which.to_owned(),
                stem: which.to_owned(),
                map_name: scenario.map.clone(),
                scenario,
                map,
            });
        }
        let path = PathBuf::from(which);
        let text =
            std::fs::read_to_string(&path).map_err(|error| LoadError::Io { path: path.clone(), error })?;
        let scenario = parse_file::<ScenarioConfig>(&path.display().to_string(), &text)?;
        let (map_name, map) = if is_map_path(&scenario.map) {
            let yaml = path.parent().unwrap_or(Path::new(".")).join(&scenario.map);
            if !yaml.is_file() {
                return Err(invalid(
                    &path,
                    "map",
                    key_line(&text, "map"),
                    format!(
                        "names {}, which is not a file (a path is relative to the scenario file)",
                        yaml.display()
                    ),
                ));
            }
            (yaml.display().to_string(), load_map_path(&yaml)?)
        } else {
            let map = self.maps.get(&scenario.map).cloned().ok_or_else(|| {
                let have: Vec<&String> = self.maps.keys().collect();
                invalid(
                    &path,
                    "map",
                    key_line(&text, "map"),
                    format!("names map `{}`, which the configuration has not (have: {have:?}; or give a path to a map YAML)", scenario.map),
                )
            })?;
            (scenario.map.clone(), map)
        };
        let stem = path.file_stem().map_or_else(|| which.to_owned(), |s| s.to_string_lossy().into_owned());
        Ok(ChosenScenario { name: which.to_owned(), stem, scenario, map_name, map })
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "tests")]

    use super::*;
    use crate::config::{ConfigSource, load};

    #[test]
    fn a_scenario_file_names_its_map_by_path_and_errors_name_file_and_key() {
        let config = load(&ConfigSource::Embedded).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let maps = dir.path().join("maps");
        std::fs::create_dir_all(&maps).unwrap();
        let shipped = crate::config::read_files(&ConfigSource::Embedded).unwrap();
        for f in shipped.iter().filter(|f| f.path.starts_with("maps/paper-site.")) {
            std::fs::write(dir.path().join(&f.path), &f.bytes).unwrap();
        }
        let scenarios = dir.path().join("scenarios");
        std::fs::create_dir_all(&scenarios).unwrap();
        let straight = shipped.iter().find(|f| f.path == "scenarios/straight.toml").unwrap().text().unwrap();
        let file = scenarios.join("mine.toml");
        std::fs::write(&file, straight.replace("map = \"paper-site\"", "map = \"../maps/paper-site.yaml\""))
            .unwrap();
        let chosen = config.scenario(file.to_str().unwrap()).unwrap();
        assert_eq!(chosen.stem, "mine");
        assert_eq!(chosen.map, config.maps["paper-site"]);
        assert!(chosen.map_name.ends_with("paper-site.yaml"));
        // By name, as before.
        assert_eq!(config.scenario("straight").unwrap().map_name, "paper-site");
        // A map path that is not there: the scenario file, its key and line.
        std::fs::write(&file, straight.replace("map = \"paper-site\"", "map = \"../maps/hall.yaml\""))
            .unwrap();
        let LoadError::Invalid(e) = config.scenario(file.to_str().unwrap()).unwrap_err() else { panic!() };
        assert_eq!((e.key.as_str(), e.line), ("map", Some(4)), "{e}");
        assert!(e.file.ends_with("mine.toml") && e.rule.contains("hall.yaml"), "{e}");
        // A broken map YAML: that file and its key.
        std::fs::write(maps.join("hall.yaml"), "image: hall.pgm\nresolution: -1\norigin: [0, 0, 0]\nnegate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n").unwrap();
        let LoadError::Invalid(e) = config.scenario(file.to_str().unwrap()).unwrap_err() else { panic!() };
        assert!(e.file.ends_with("hall.yaml") && e.key == "resolution", "{e}");
        // An unknown map name and a bad value in the scenario.
        std::fs::write(&file, straight.replace("map = \"paper-site\"", "map = \"hall\"")).unwrap();
        let e = config.scenario(file.to_str().unwrap()).unwrap_err().to_string();
        assert!(e.contains("mine.toml") && e.contains("`hall`"), "{e}");
        std::fs::write(&file, straight.replace("spacing_m = 0.9", "spacing_m = -0.9")).unwrap();
        let LoadError::Invalid(e) = config.scenario(file.to_str().unwrap()).unwrap_err() else { panic!() };
        assert_eq!(e.key, "spacing_m", "{e}");
        assert!(config.scenario("nowhere").unwrap_err().to_string().contains("no scenario `nowhere`"));
    }
}
