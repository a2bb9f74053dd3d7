//! `server.toml`: the formation, the fusion gates and the T1–T4 switch.

use serde::Deserialize;

use super::value::{Millis, Positive};
use super::{ConfigFileType, RobotId, Violation, rule};

/// The four configurations of the paper's ablation (Table 12, docs/method.md §9).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Deserialize, serde::Serialize)]
pub enum Configuration {
    /// Each robot's own AMCL; the centre is the midpoint of the two AMCL poses.
    T1,
    /// AMCL relative position + searched relative heading.
    T2,
    /// Tracked relative position + AMCL relative heading.
    T3,
    /// Tracked relative position + searched relative heading: the complete method.
    T4,
}

/// Where a configuration takes the relative position from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PositionFrom {
    /// The two robots' own AMCL poses.
    Amcl,
    /// The contour tracker, in the observer's scan.
    Tracker,
}

/// Where a configuration takes the relative heading from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HeadingFrom {
    /// The two robots' own AMCL poses.
    Amcl,
    /// The heading search against the observer's scan.
    Search,
}

impl Configuration {
    /// What the configuration means: the sources of the relative position and heading.
    #[must_use]
    pub fn sources(self) -> (PositionFrom, HeadingFrom) {
        match self {
            Configuration::T1 => (PositionFrom::Amcl, HeadingFrom::Amcl),
            Configuration::T2 => (PositionFrom::Amcl, HeadingFrom::Search),
            Configuration::T3 => (PositionFrom::Tracker, HeadingFrom::Amcl),
            Configuration::T4 => (PositionFrom::Tracker, HeadingFrom::Search),
        }
    }

    /// The configuration of these sources (T1–T4 are names for the four).
    #[must_use]
    pub fn of(position: PositionFrom, heading: HeadingFrom) -> Configuration {
        match (position, heading) {
            (PositionFrom::Amcl, HeadingFrom::Amcl) => Configuration::T1,
            (PositionFrom::Amcl, HeadingFrom::Search) => Configuration::T2,
            (PositionFrom::Tracker, HeadingFrom::Amcl) => Configuration::T3,
            (PositionFrom::Tracker, HeadingFrom::Search) => Configuration::T4,
        }
    }
}

/// One robot of the formation.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FormationMember {
    pub id: RobotId,
    /// Fusion weight `w_i` of Eq. 16 (1 for both robots in the paper).
    pub weight: Positive,
}

/// Packet gates of Eq. 15 and the end-to-end latency threshold of Table 2.
#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SyncGates {
    /// `Δt_sync,max`: largest spread of the scans' stamps in one fused packet.
    pub max_stamp_spread_ms: Millis,
    /// `τ_age,max`: largest age of a scan when it reaches the server.
    pub max_age_ms: Millis,
    /// `T_E2E,max`: an update slower than this end to end is counted as late.
    pub e2e_threshold_ms: Millis,
}

/// What the formation does while one robot's data is missing.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum OnRobotLost {
    /// Command zero velocity to every robot until the lost one returns.
    Stop,
    /// Keep the last formation reference but do not advance the plan.
    Hold,
}

/// How the server verifies V's estimate before the formation may drive on it (`[integrity]`).
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct IntegrityChecks {
    /// Where V places a robot and where the robot's own (tracking) AMCL places it may differ by
    /// at most this, m ...
    pub max_disagreement_m: f64,
    /// ... and this, degrees.
    pub max_disagreement_deg: f64,
    /// V's filter starts again from the robots' own estimates after no fused update for this
    /// long, ms.
    pub restart_after_ms: f64,
}

impl Default for IntegrityChecks {
    fn default() -> Self {
        IntegrityChecks { max_disagreement_m: 0.3, max_disagreement_deg: 10.0, restart_after_ms: 2000.0 }
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ServerConfig {
    pub configuration: Configuration,
    /// The robots of the formation, in order.
    pub robots: Vec<FormationMember>,
    pub sync: SyncGates,
    pub on_robot_lost: OnRobotLost,
    /// Absent: the defaults.
    #[serde(default)]
    pub integrity: IntegrityChecks,
}

impl ConfigFileType for ServerConfig {
    fn validate(&self) -> Result<(), Violation> {
        rule(
            self.robots.len() >= 2,
            "robots",
            format!("a formation needs at least 2 robots (got {})", self.robots.len()),
        )?;
        for (i, member) in self.robots.iter().enumerate() {
            if let Some(j) = self.robots[..i].iter().position(|m| m.id == member.id) {
                return Err(Violation {
                    key: format!("robots[{i}].id"),
                    rule: format!("robot `{}` is already listed as robots[{j}]", member.id),
                });
            }
        }
        let c = &self.integrity;
        rule(
            c.max_disagreement_m.is_finite() && c.max_disagreement_m > 0.0,
            "integrity.max_disagreement_m",
            format!("must be > 0 (got {})", c.max_disagreement_m),
        )?;
        rule(
            c.max_disagreement_deg.is_finite() && c.max_disagreement_deg > 0.0,
            "integrity.max_disagreement_deg",
            format!("must be > 0 (got {})", c.max_disagreement_deg),
        )?;
        rule(
            c.restart_after_ms.is_finite() && c.restart_after_ms > 0.0,
            "integrity.restart_after_ms",
            format!("must be > 0 (got {})", c.restart_after_ms),
        )?;
        let s = &self.sync;
        rule(
            s.max_stamp_spread_ms < s.max_age_ms,
            "sync.max_stamp_spread_ms",
            format!(
                "must be less than sync.max_age_ms ({} ms >= {} ms)",
                s.max_stamp_spread_ms.ms(),
                s.max_age_ms.ms()
            ),
        )?;
        rule(
            s.max_age_ms < s.e2e_threshold_ms,
            "sync.max_age_ms",
            format!(
                "must be less than sync.e2e_threshold_ms ({} ms >= {} ms)",
                s.max_age_ms.ms(),
                s.e2e_threshold_ms.ms()
            ),
        )?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn t1_to_t4_name_the_four_choices_of_sources() {
        for c in [Configuration::T1, Configuration::T2, Configuration::T3, Configuration::T4] {
            let (p, h) = c.sources();
            assert_eq!(Configuration::of(p, h), c);
        }
        assert_eq!(Configuration::T4.sources(), (PositionFrom::Tracker, HeadingFrom::Search));
        assert_eq!(Configuration::T2.sources(), (PositionFrom::Amcl, HeadingFrom::Search));
    }
}
