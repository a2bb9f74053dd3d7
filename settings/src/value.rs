//! Validated scalar types for configuration fields.
//!
//! Each type checks its rule while the file is deserialised, so a bad value is reported with the
//! key path and line where it stands (`kinematics.wheel_radius_m: must be > 0 (got -0.05)`).
//! TOML accepts `nan` and `inf` as floats; none of these types does.

use std::time::Duration;

use serde::Deserialize;

macro_rules! bounded_f64 {
    ($(#[$meta:meta])* $name:ident, $rule:literal, $ok:expr) => {
        $(#[$meta])*
        #[derive(Debug, Clone, Copy, PartialEq, PartialOrd, Deserialize)]
        #[serde(try_from = "f64")]
        pub struct $name(f64);

        impl $name {
            /// Check `value` against the rule of this type.
            pub fn new(value: f64) -> Result<Self, String> {
                let ok: fn(f64) -> bool = $ok;
                if value.is_finite() && ok(value) {
                    Ok(Self(value))
                } else {
                    Err(format!(concat!("must be ", $rule, " (got {})"), value))
                }
            }

            #[must_use]
            pub fn get(self) -> f64 {
                self.0
            }
        }

        impl TryFrom<f64> for $name {
            type Error = String;
            fn try_from(value: f64) -> Result<Self, String> {
                Self::new(value)
            }
        }
    };
}

bounded_f64!(
    /// A finite number > 0.
    Positive, "> 0", |v| v > 0.0
);
bounded_f64!(
    /// A finite number ≥ 0.
    NonNegative, ">= 0", |v| v >= 0.0
);
bounded_f64!(
    /// A finite number in [0, 1].
    Fraction, "in [0, 1]", |v| (0.0..=1.0).contains(&v)
);
bounded_f64!(
    /// A finite number in (0, 1), e.g. a probability that must not be certain.
    OpenFraction, "in (0, 1)", |v| v > 0.0 && v < 1.0
);
bounded_f64!(
    /// Any finite number.
    Finite, "a finite number", |_| true
);

/// Reads a TOML integer, naming what it should be when it is something else (a float, a string).
struct WholeNumber(&'static str);

impl serde::de::Visitor<'_> for WholeNumber {
    type Value = i64;

    fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.0)
    }

    fn visit_i64<E: serde::de::Error>(self, v: i64) -> Result<i64, E> {
        Ok(v)
    }

    fn visit_u64<E: serde::de::Error>(self, v: u64) -> Result<i64, E> {
        i64::try_from(v).map_err(|_| E::invalid_value(serde::de::Unexpected::Unsigned(v), &self))
    }
}

fn whole_number<'de, D: serde::Deserializer<'de>, T>(
    deserializer: D,
    what: &'static str,
    check: fn(i64) -> Result<T, String>,
) -> Result<T, D::Error> {
    let v = deserializer.deserialize_i64(WholeNumber(what))?;
    check(v).map_err(serde::de::Error::custom)
}

/// A duration given in whole milliseconds, > 0.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub struct Millis(u32);

impl<'de> Deserialize<'de> for Millis {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        whole_number(deserializer, "a whole number of milliseconds", Millis::new)
    }
}

impl Millis {
    pub fn new(ms: i64) -> Result<Self, String> {
        match u32::try_from(ms) {
            Ok(v) if v > 0 => Ok(Millis(v)),
            _ => Err(format!("must be a whole number of milliseconds in 1..={} (got {ms})", u32::MAX)),
        }
    }

    #[must_use]
    pub fn ms(self) -> u32 {
        self.0
    }

    #[must_use]
    pub fn duration(self) -> Duration {
        Duration::from_millis(u64::from(self.0))
    }
}

/// A whole count ≥ 1 (window lengths, particle counts, beams).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub struct Count(u32);

impl<'de> Deserialize<'de> for Count {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        whole_number(deserializer, "a whole number", Count::new)
    }
}

impl Count {
    pub fn new(n: i64) -> Result<Self, String> {
        match u32::try_from(n) {
            Ok(v) if v > 0 => Ok(Count(v)),
            _ => Err(format!("must be a whole number in 1..={} (got {n})", u32::MAX)),
        }
    }

    #[must_use]
    pub fn get(self) -> u32 {
        self.0
    }

    /// As an index-sized count.
    #[must_use]
    pub fn usize(self) -> usize {
        self.0 as usize
    }
}

// Deserialisers for fields that keep a plain type (a driver's sans-IO settings are plain
// numbers and durations) but take the same checks and words as the types above:
// `#[serde(deserialize_with = "amr_settings::value::ms")] pub sync_period_ms: u32`.

/// Whole milliseconds > 0, as a [`Duration`] (`reply_timeout_ms = 300`; rename the field).
pub fn millis<'de, D: serde::Deserializer<'de>>(deserializer: D) -> Result<Duration, D::Error> {
    Millis::deserialize(deserializer).map(Millis::duration)
}

/// Whole milliseconds > 0, as a number of milliseconds.
pub fn ms<'de, D: serde::Deserializer<'de>>(deserializer: D) -> Result<u32, D::Error> {
    Millis::deserialize(deserializer).map(Millis::ms)
}

/// A whole count >= 1.
pub fn count<'de, D: serde::Deserializer<'de>>(deserializer: D) -> Result<u32, D::Error> {
    Count::deserialize(deserializer).map(Count::get)
}

/// A finite number > 0.
pub fn positive<'de, D: serde::Deserializer<'de>>(deserializer: D) -> Result<f64, D::Error> {
    Positive::deserialize(deserializer).map(Positive::get)
}

/// Capped exponential backoff between reconnection attempts: `{ initial_ms = 100, max_ms = 5000 }`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(from = "BackoffMs")]
pub struct Backoff {
    /// Wait before the first retry.
    pub initial: Duration,
    /// The cap: the wait doubles after each failure up to this.
    pub max: Duration,
}

/// The file's spelling of a [`Backoff`].
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct BackoffMs {
    initial_ms: Millis,
    max_ms: Millis,
}

impl From<BackoffMs> for Backoff {
    fn from(b: BackoffMs) -> Self {
        Backoff { initial: b.initial_ms.duration(), max: b.max_ms.duration() }
    }
}

impl Backoff {
    /// The wait may not start above its cap. `key` is the backoff's own key path.
    pub fn check(&self, key: &str) -> Result<(), super::Violation> {
        super::rule(
            self.initial <= self.max,
            format!("{key}.initial_ms"),
            format!(
                "must not exceed {key}.max_ms ({} ms > {} ms)",
                self.initial.as_millis(),
                self.max.as_millis()
            ),
        )
    }
}
