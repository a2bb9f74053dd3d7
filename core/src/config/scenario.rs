//! `scenarios/<name>.toml`: an experiment of the paper (§5.1, §5.4; docs/method.md §11) — where the
//! pair starts, how far apart, and the path of the virtual robot V as straight and turning
//! segments.

use serde::Deserialize;

use super::value::{Count, Finite, Positive};
use super::{ConfigFileType, Violation, rule};
use crate::se2::Se2;

/// One piece of V's path.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Segment {
    /// Drive this far along V's heading (negative: backwards), m.
    #[serde(default)]
    pub straight_m: Option<Finite>,
    /// Then turn V on the spot by this much (left positive), degrees.
    #[serde(default)]
    pub turn_deg: Option<Finite>,
}

#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StartPose {
    pub x_m: Finite,
    pub y_m: Finite,
    pub yaw_deg: Finite,
}

#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScenarioLimits {
    pub max_speed_mps: Positive,
    pub max_accel_mps2: Positive,
    pub max_yaw_rate_radps: Positive,
}

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScenarioConfig {
    /// The map (a name under `maps/`).
    pub map: String,
    /// V's start pose in the map.
    pub start: StartPose,
    /// Distance between the two robots' centres, side by side across V's heading, m.
    pub spacing_m: Positive,
    /// The path, repeated `laps` times.
    pub segments: Vec<Segment>,
    pub laps: Count,
    pub limits: ScenarioLimits,
}

impl ScenarioConfig {
    #[must_use]
    pub fn start_pose(&self) -> Se2 {
        Se2::from_degrees(self.start.x_m.get(), self.start.y_m.get(), self.start.yaw_deg.get())
    }
}

impl ConfigFileType for ScenarioConfig {
    fn validate(&self) -> Result<(), Violation> {
        rule(!self.segments.is_empty(), "segments", "a scenario needs at least one segment")?;
        for (i, s) in self.segments.iter().enumerate() {
            rule(
                s.straight_m.is_some() || s.turn_deg.is_some(),
                format!("segments[{i}]"),
                "a segment needs straight_m, turn_deg or both",
            )?;
        }
        Ok(())
    }
}
