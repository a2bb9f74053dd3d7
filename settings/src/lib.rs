//! `amr-settings`: the configuration plumbing shared by every crate that owns a configuration type,
//! below all of them. Each crate deserialises its own part of the TOML configuration into its own
//! types, built from the validated scalars of [`value`] (a bad value is refused with its key path
//! and line) and read with [`parse_file`] ([`ConfigFileType`], [`Section`]), which then checks the
//! rules that relate several fields and reports the first broken one as a [`ConfigError`] naming
//! file, line, key and rule; [`DeviceSource`] is the one key every device section has. No IO:
//! callers read the files and hand over their text.

pub mod value;

use std::fmt;

use serde::Deserialize;
use serde::de::DeserializeOwned;

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

impl ConfigError {
    /// A problem with a whole file (missing, not UTF-8, unknown): no key, no line.
    #[must_use]
    pub fn file_level(file: &str, rule: impl Into<String>) -> Self {
        ConfigError { file: file.to_owned(), line: None, key: String::new(), rule: rule.into() }
    }

    /// A broken rule of `key` in the file whose text is `text` (the line is looked up).
    #[must_use]
    pub fn at_key(file: &str, text: &str, key: impl Into<String>, rule: impl Into<String>) -> Self {
        let key = key.into();
        ConfigError { file: file.to_owned(), line: key_line(text, &key), key, rule: rule.into() }
    }
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
    /// The full dotted key path from the top of the file.
    pub key: String,
    pub rule: String,
}

impl fmt::Display for Violation {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: {}", self.key, self.rule)
    }
}

impl std::error::Error for Violation {}

/// `key` inside the table at `path` (`join("devices.lidar", "port")` is `devices.lidar.port`; an
/// empty path is the top of the file).
#[must_use]
pub fn join(path: &str, key: &str) -> String {
    if path.is_empty() { key.to_owned() } else { format!("{path}.{key}") }
}

/// `Ok(())` when `holds`, else a [`Violation`] of `key`.
pub fn rule(holds: bool, key: impl Into<String>, rule: impl Into<String>) -> Result<(), Violation> {
    if holds { Ok(()) } else { Err(Violation { key: key.into(), rule: rule.into() }) }
}

/// A section of a file (a TOML table) with rules across its own fields. It is told where it
/// stands (`path`, e.g. `devices.lidar`) so that a violation, and a rule's words when they name
/// a sibling key, give full key paths.
pub trait Section {
    /// Rules that relate several fields of this section.
    fn validate(&self, path: &str) -> Result<(), Violation>;
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
#[must_use]
pub fn key_line(text: &str, key: &str) -> Option<usize> {
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

/// Whether a device is the real hardware or a mock device served from the simulated world. The
/// driver is the same either way; only the far end of its transport changes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum DeviceSource {
    Real,
    Mock,
}

impl DeviceSource {
    /// The configuration spelling.
    #[must_use]
    pub fn name(self) -> &'static str {
        match self {
            DeviceSource::Real => "real",
            DeviceSource::Mock => "mock",
        }
    }
}

#[cfg(test)]
mod tests;
