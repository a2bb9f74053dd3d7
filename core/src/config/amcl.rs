//! `amcl.toml`: AMCL parameters, with nav2_amcl's names (docs/method.md §7) so that a
//! nav2 user can carry a parameter file over key by key. Keys we do not implement are rejected,
//! not silently ignored.

use serde::Deserialize;

use super::value::{Count, Finite, Fraction, NonNegative, OpenFraction, Positive};
use super::{ConfigFileType, Violation, rule};
use crate::se2::Se2;

/// The laser model (nav2 `laser_model_type`). The beam model is not offered: the virtual scan's
/// points do not share one origin, so only endpoint models apply (docs/method.md §6).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
pub enum LaserModel {
    /// nav2's default: weight `1 + Σ pz³`.
    #[serde(rename = "likelihood_field")]
    LikelihoodField,
    /// The product of the beams' `pz` (nav2 `likelihood_field_prob`, without beam skipping): far more
    /// discriminating.
    #[serde(rename = "likelihood_field_prob")]
    LikelihoodFieldProb,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AmclParams {
    pub laser_model_type: LaserModel,
    pub min_particles: Count,
    pub max_particles: Count,
    /// KLD-sampling error bound ε (nav2 `pf_err`).
    pub pf_err: OpenFraction,
    /// KLD-sampling normal quantile z (nav2 `pf_z`, used directly as the quantile).
    pub pf_z: OpenFraction,
    /// Differential motion model noise: rotation from rotation.
    pub alpha1: NonNegative,
    /// Rotation from translation.
    pub alpha2: NonNegative,
    /// Translation from translation.
    pub alpha3: NonNegative,
    /// Translation from rotation.
    pub alpha4: NonNegative,
    /// Not in nav2: the share of motion samples that do not trust the odometry's increment: their
    /// translation is drawn uniformly from [−1.5, 1.5] × the odometry's, and their heading gets
    /// 0.2 rad more noise (a heavy tail for wheel slip, bumps, a robot turned by hand, and odometers
    /// that lose the direction of travel: freiburg-079's never reports reversing while the robot
    /// reverses 83 times). Absent: 0, nav2's pure Gaussian model.
    #[serde(default = "zero_fraction")]
    pub odom_slip_share: Fraction,
    /// Not in nav2: how likely the odometry is to have lied over one update (the prior of the slip
    /// tail), when it differs from `odom_slip_share` (how many samples try it). Slipped samples weigh
    /// `probability / share`, the others `(1 − probability) / (1 − share)` (importance sampling),
    /// so the tail is explored by as many samples while it moves the cloud's mean only by the
    /// probability's share of each increment: where the scans do not hold the filter along its way,
    /// a tail believed at 0.1 puts the estimate 10 % of the distance behind the robot. Absent: the
    /// share (every trying sample believed). Needs `odom_slip_share > 0` if above 0.
    #[serde(default)]
    pub odom_slip_probability: Option<Fraction>,
    /// Distance-map cutoff of the likelihood field.
    pub laser_likelihood_max_dist: Positive,
    /// ≤ 0: use the scan's own maximum range (nav2 convention).
    pub laser_max_range: Finite,
    /// ≤ 0: use the scan's own minimum range (nav2 convention).
    pub laser_min_range: Finite,
    /// Beams used per update, evenly subsampled over the valid beams.
    pub max_beams: Count,
    pub z_hit: Fraction,
    pub z_rand: Fraction,
    pub sigma_hit: Positive,
    /// Translation that triggers a filter update.
    pub update_min_d: NonNegative,
    /// Rotation that triggers a filter update.
    pub update_min_a: NonNegative,
    /// Resample every n-th update.
    pub resample_interval: Count,
    /// Augmented MCL: slow average decay (0 disables random injection).
    pub recovery_alpha_slow: Fraction,
    /// Augmented MCL: fast average decay (0 disables random injection).
    pub recovery_alpha_fast: Fraction,
    /// Beam skipping (nav2 `do_beamskip`, likelihood_field_prob only): once the particles have
    /// converged (all within 0.5 m of their mean in x and y), a beam is used only if more than
    /// `beam_skip_threshold` of the particles place its endpoint within `beam_skip_distance` of the
    /// map; if at least `beam_skip_error_threshold` of the beams would be skipped, all are used (the
    /// filter is probably wrong, not the world). Unmapped obstacles (people, furniture) then stop
    /// pulling the pose. Absent: off, as in nav2.
    #[serde(default)]
    pub do_beamskip: bool,
    #[serde(default = "default_beam_skip_distance")]
    pub beam_skip_distance: Positive,
    #[serde(default = "default_beam_skip_threshold")]
    pub beam_skip_threshold: Fraction,
    #[serde(default = "default_beam_skip_error_threshold")]
    pub beam_skip_error_threshold: Fraction,
    /// Start from this pose instead of global localisation.
    #[serde(default)]
    pub initial_pose: Option<InitialPose>,
    /// Not in nav2: how the filter judges its own estimate against the map, and re-localises
    /// when it is lost (`amcl::integrity`). Absent: the defaults.
    #[serde(default)]
    pub integrity: crate::amcl::integrity::IntegrityParams,
}

fn zero_fraction() -> Fraction {
    Fraction::new(0.0).unwrap_or_else(|_| unreachable!("0 is a fraction"))
}

// nav2's defaults (amcl_node.cpp).
fn default_beam_skip_distance() -> Positive {
    Positive::new(0.5).unwrap_or_else(|_| unreachable!("0.5 > 0"))
}
fn default_beam_skip_threshold() -> Fraction {
    Fraction::new(0.3).unwrap_or_else(|_| unreachable!("0.3 is a fraction"))
}
fn default_beam_skip_error_threshold() -> Fraction {
    Fraction::new(0.9).unwrap_or_else(|_| unreachable!("0.9 is a fraction"))
}

/// An initial pose with its spread (nav2 `initial_pose` plus the covariance it takes from
/// `/initialpose`).
#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InitialPose {
    pub x: Finite,
    pub y: Finite,
    pub yaw: Finite,
    pub std_xy_m: NonNegative,
    pub std_yaw_rad: NonNegative,
}

impl InitialPose {
    #[must_use]
    pub fn pose(&self) -> Se2 {
        Se2::new(self.x.get(), self.y.get(), self.yaw.get())
    }
}

impl AmclParams {
    /// The configured maximum range, or `None` for "the scan's own" (nav2: a value ≤ 0).
    #[must_use]
    pub fn max_range_m(&self) -> Option<f64> {
        Some(self.laser_max_range.get()).filter(|r| *r > 0.0)
    }

    /// The configured minimum range, or `None` for "the scan's own" (nav2: a value ≤ 0).
    #[must_use]
    pub fn min_range_m(&self) -> Option<f64> {
        Some(self.laser_min_range.get()).filter(|r| *r > 0.0)
    }

    /// The prior probability of a slip per update (`odom_slip_probability`, else the share).
    #[must_use]
    pub fn slip_probability(&self) -> f64 {
        self.odom_slip_probability.unwrap_or(self.odom_slip_share).get()
    }
}

impl ConfigFileType for AmclParams {
    fn validate(&self) -> Result<(), Violation> {
        rule(
            self.min_particles <= self.max_particles,
            "min_particles",
            format!(
                "must not exceed max_particles ({} > {})",
                self.min_particles.get(),
                self.max_particles.get()
            ),
        )?;
        if let Err(e) = self.integrity.check() {
            rule(false, "integrity", e)?;
        }
        rule(
            self.max_beams.get() >= 2,
            "max_beams",
            format!("must be at least 2 (got {})", self.max_beams.get()),
        )?;
        rule(
            self.z_hit.get() + self.z_rand.get() > 0.0,
            "z_hit",
            "z_hit and z_rand must not both be 0: every particle would weigh nothing",
        )?;
        if let (Some(min), Some(max)) = (self.min_range_m(), self.max_range_m()) {
            rule(
                min < max,
                "laser_min_range",
                format!("must be less than laser_max_range ({min} m >= {max} m)"),
            )?;
        }
        rule(
            self.slip_probability() == 0.0 || self.odom_slip_share.get() > 0.0,
            "odom_slip_probability",
            "needs odom_slip_share > 0: without samples that try the slip tail, it cannot be believed",
        )?;
        rule(
            !self.do_beamskip || self.laser_model_type == LaserModel::LikelihoodFieldProb,
            "do_beamskip",
            "beam skipping needs laser_model_type = \"likelihood_field_prob\" (nav2 ignores it otherwise)",
        )?;
        let (slow, fast) = (self.recovery_alpha_slow.get(), self.recovery_alpha_fast.get());
        rule(
            (slow == 0.0) == (fast == 0.0),
            "recovery_alpha_slow",
            format!(
                "must be 0 together with recovery_alpha_fast (random injection off) or both > 0 \
                 (got {slow} and {fast})"
            ),
        )?;
        rule(
            slow == 0.0 || slow < fast,
            "recovery_alpha_slow",
            format!(
                "must be less than recovery_alpha_fast: the slow average must move slower ({slow} >= {fast})"
            ),
        )?;
        Ok(())
    }
}
