//! The robot's configuration: a set of files from a directory or from the copy embedded at build
//! time ([`load`]), each parsed into the types of the crate that owns it ([`Config`],
//! [`ConfigFile`]); the robot file ([`RobotConfig`]) puts a body from amr-core and devices from
//! amr-drivers together.

use std::fmt;
use std::path::{Path, PathBuf};

pub use amr_core::config::ConfigError;

mod robot;
mod scenario_file;
mod set;

pub use robot::{Devices, RobotConfig};
pub use scenario_file::{ChosenScenario, is_map_path, is_path, load_map_path};
pub use set::{Config, ConfigFile, FileKind};

mod embedded {
    include!(concat!(env!("OUT_DIR"), "/embedded_config.rs"));
}

/// Where a configuration comes from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ConfigSource {
    /// A directory laid out like `config/`.
    Dir(PathBuf),
    /// The `config/` directory as it was when this binary was built.
    Embedded,
}

impl fmt::Display for ConfigSource {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ConfigSource::Dir(p) => write!(f, "{}", p.display()),
            ConfigSource::Embedded => f.write_str("embedded defaults (config/ at build time)"),
        }
    }
}

/// Why a configuration could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    #[error("cannot read {path}: {error}")]
    Io { path: PathBuf, error: std::io::Error },
    #[error(transparent)]
    Invalid(#[from] ConfigError),
}

/// Read every file of a source, in path order, with paths relative to its root (`/`-separated).
/// Hidden files and directories (`.name`) are skipped.
pub fn read_files(source: &ConfigSource) -> Result<Vec<ConfigFile>, LoadError> {
    let raw: Vec<(String, Vec<u8>)> = match source {
        ConfigSource::Embedded => {
            embedded::FILES.iter().map(|(p, b)| ((*p).to_owned(), b.to_vec())).collect()
        }
        ConfigSource::Dir(dir) => {
            let mut out = Vec::new();
            walk(dir, dir, &mut out)?;
            out
        }
    };
    Ok(raw.into_iter().map(|(path, bytes)| ConfigFile { path, bytes }).collect())
}

/// Read and validate a whole configuration.
pub fn load(source: &ConfigSource) -> Result<Config, LoadError> {
    Ok(Config::from_files(read_files(source)?)?)
}

fn walk(root: &Path, dir: &Path, out: &mut Vec<(String, Vec<u8>)>) -> Result<(), LoadError> {
    let io = |path: &Path| {
        let path = path.to_path_buf();
        move |error| LoadError::Io { path, error }
    };
    let mut entries =
        std::fs::read_dir(dir).map_err(io(dir))?.collect::<Result<Vec<_>, _>>().map_err(io(dir))?;
    entries.sort_by_key(std::fs::DirEntry::file_name);
    for entry in entries {
        if entry.file_name().to_string_lossy().starts_with('.') {
            continue;
        }
        let path = entry.path();
        if entry.file_type().map_err(io(&path))?.is_dir() {
            walk(root, &path, out)?;
        } else {
            let bytes = std::fs::read(&path).map_err(io(&path))?;
            let rel = path
                .strip_prefix(root)
                .unwrap_or(&path)
                .components()
                .map(|c| c.as_os_str().to_string_lossy())
                .collect::<Vec<_>>()
                .join("/");
            out.push((rel, bytes));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn embedded_and_directory_copies_are_the_same_files() {
        let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../config");
        let from_dir = read_files(&ConfigSource::Dir(dir)).unwrap();
        let embedded = read_files(&ConfigSource::Embedded).unwrap();
        assert_eq!(from_dir, embedded);
        assert!(from_dir.iter().any(|f| f.path == "server.toml"));
    }

    #[test]
    fn unreadable_directory_is_an_io_error_naming_it() {
        let err = load(&ConfigSource::Dir(PathBuf::from("/nonexistent/amr-config"))).unwrap_err();
        assert!(matches!(err, LoadError::Io { .. }));
        assert!(err.to_string().contains("/nonexistent/amr-config"), "{err}");
        // The cause is said once: in the message, not again as the error's source (which a
        // report of the whole chain, `{:#}`, would print a second time).
        assert!(err.to_string().contains("os error"), "{err}");
        assert!(std::error::Error::source(&err).is_none(), "{err}");
    }

    #[test]
    fn binary_file_is_reported_not_text() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("server.toml"), [0xff, 0xfe, 0x00]).unwrap();
        let err = load(&ConfigSource::Dir(dir.path().to_path_buf())).unwrap_err();
        assert_eq!(err.to_string(), "server.toml: not UTF-8 text");
    }
}
