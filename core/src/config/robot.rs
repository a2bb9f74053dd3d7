//! The body of a robot (`robot-<id>.toml` less its `[devices.*]`): its name, chassis, kinematics,
//! LiDAR mount, motion limits and safety timeout. The devices' sections belong to their drivers
//! (amr-drivers); the whole file is put together where both are known (`amr_actors::config`).

use serde::Deserialize;

use super::value::{Finite, Millis, Positive};
use super::{Violation, rule};
use crate::geometry::Polygon;
use crate::se2::Se2;

/// A robot's name: 1–32 characters of `a-z`, `0-9` and `-`, starting with a letter. It appears in
/// file names, log fields and network keys (`fleet/<id>/scan`), hence the narrow alphabet.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Hash, Deserialize)]
#[serde(try_from = "String")]
pub struct RobotId(String);

impl RobotId {
    pub fn new(id: &str) -> Result<Self, String> {
        let ok_chars = id.chars().all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-');
        let starts = id.chars().next().is_some_and(|c| c.is_ascii_lowercase());
        if (1..=32).contains(&id.len()) && ok_chars && starts {
            Ok(RobotId(id.to_owned()))
        } else {
            Err(format!("must be 1-32 characters of a-z, 0-9 and '-', starting with a letter (got `{id}`)"))
        }
    }

    #[must_use]
    pub fn as_str(&self) -> &str {
        &self.0
    }
}

impl TryFrom<String> for RobotId {
    type Error = String;
    fn try_from(id: String) -> Result<Self, String> {
        RobotId::new(&id)
    }
}

impl std::fmt::Display for RobotId {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ChassisConfig {
    /// Outline at scan height, in the base frame, metres, counter-clockwise.
    pub outline_m: Polygon,
}

#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct KinematicsConfig {
    pub wheel_radius_m: Positive,
    /// Distance between the two wheels' contact points.
    pub track_width_m: Positive,
}

/// A sensor's mounting pose in the base frame.
#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MountConfig {
    pub x_m: Finite,
    pub y_m: Finite,
    pub yaw_deg: Finite,
}

impl MountConfig {
    /// The mounting pose as a transform (sensor frame → base frame).
    #[must_use]
    pub fn to_se2(&self) -> Se2 {
        Se2::from_degrees(self.x_m.get(), self.y_m.get(), self.yaw_deg.get())
    }
}

/// Motion limits every robot enforces on itself, whatever it is told (docs/method.md §8).
#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MotionLimits {
    pub max_speed_mps: Positive,
    pub max_accel_mps2: Positive,
    pub max_yaw_rate_radps: Positive,
}

#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SafetyConfig {
    /// No fresh velocity command for this long → stop (at `stop_decel_mps2`).
    pub command_timeout_ms: Millis,
    /// Wheel-surface deceleration of every stop the safety layer makes (watchdog, link loss,
    /// disarm, lost drives), m/s²: separate from the motion limit, which is a comfort limit for
    /// driving. Without it, the drives' quick-stop deceleration (`devices.drives.quick_stop_decel_mps2`).
    #[serde(default)]
    pub stop_decel_mps2: Option<Positive>,
}

impl SafetyConfig {
    /// The safety watchdog must notice a missing command before the robot has travelled far: a
    /// timeout beyond one second is a misconfiguration, not a tuning choice. `path` is where the
    /// section stands (`safety`).
    pub fn validate(&self, path: &str) -> Result<(), Violation> {
        rule(
            self.command_timeout_ms.ms() <= 1000,
            amr_settings::join(path, "command_timeout_ms"),
            format!("must be at most 1000 ms (got {} ms)", self.command_timeout_ms.ms()),
        )
    }
}
