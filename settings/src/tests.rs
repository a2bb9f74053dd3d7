#![allow(clippy::unwrap_used, reason = "tests")]

use super::*;
use crate::value::{Backoff, Count, Millis, Positive};

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
    let e =
        ConfigError { file: "a.toml".into(), line: Some(3), key: "x.y".into(), rule: "must be > 0".into() };
    assert_eq!(e.to_string(), "a.toml:3: x.y: must be > 0");
    assert_eq!(ConfigError::file_level("b.toml", "missing").to_string(), "b.toml: missing");
}

/// A small file type with a nested section, as a driver's would be.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct Outer {
    period_ms: Millis,
    inner: Inner,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct Inner {
    gain: Positive,
    attempts: Count,
    reconnect: Backoff,
}

impl Section for Inner {
    fn validate(&self, path: &str) -> Result<(), Violation> {
        rule(
            self.attempts.get() <= 10,
            join(path, "attempts"),
            format!("must be at most 10 (got {})", self.attempts.get()),
        )?;
        self.reconnect.check(&join(path, "reconnect"))
    }
}

impl ConfigFileType for Outer {
    fn validate(&self) -> Result<(), Violation> {
        self.inner.validate("inner")
    }
}

const GOOD: &str =
    "period_ms = 20\n[inner]\ngain = 1.5\nattempts = 3\nreconnect = { initial_ms = 100, max_ms = 500 }\n";

#[test]
fn a_file_parses_into_its_types() {
    let o: Outer = parse_file("o.toml", GOOD).unwrap();
    assert_eq!(o.period_ms.ms(), 20);
    assert_eq!(o.inner.gain.get(), 1.5);
    assert_eq!(o.inner.reconnect.max, std::time::Duration::from_millis(500));
}

#[test]
fn each_kind_of_error_names_file_line_key_and_rule() {
    let err = |text: &str| parse_file::<Outer>("o.toml", text).unwrap_err().to_string();
    assert_eq!(err("period_ms = [\n"), "o.toml:1: not valid TOML: unclosed array, expected `]`");
    assert_eq!(
        err(&GOOD.replace("gain = 1.5", "gain = -1.5")),
        "o.toml:3: inner.gain: must be > 0 (got -1.5)"
    );
    assert_eq!(
        err(&GOOD.replace("period_ms = 20", "period_ms = 2.5")),
        "o.toml:1: period_ms: invalid type: floating point `2.5`, expected a whole number of milliseconds"
    );
    assert_eq!(
        err(&GOOD.replace("attempts = 3", "attempts = 30")),
        "o.toml:4: inner.attempts: must be at most 10 (got 30)"
    );
    assert_eq!(
        err(&GOOD.replace("initial_ms = 100", "initial_ms = 1000")),
        "o.toml:5: inner.reconnect.initial_ms: must not exceed inner.reconnect.max_ms (1000 ms > 500 ms)"
    );
    assert_eq!(
        err(&GOOD.replace("gain", "gian")),
        "o.toml:3: inner.gian: unknown field `gian`, expected one of `gain`, `attempts`, `reconnect`"
    );
}
