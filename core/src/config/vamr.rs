//! `vamr.toml`: the Virtual-AMR pipeline parameters (paper Table 2, docs/method.md §2–6).

use serde::Deserialize;

use super::value::{Count, Fraction, OpenFraction, Positive};
use super::{ConfigFileType, Violation, rule};

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VamrParams {
    pub preprocess: PreprocessParams,
    pub contour: ContourParams,
    pub tracker: TrackerParams,
    pub heading: HeadingParams,
    pub fusion: FusionParams,
}

/// Scan preprocessing (docs/method.md §2). Windows are in beams; the beam count and step come from
/// each scan.
#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PreprocessParams {
    /// Median filter window (Table 2: 11), odd.
    pub median_window_beams: Count,
    /// Smoothing window of Eq. 3 (Table 2: 11 inclusive samples).
    pub smoothing_window_beams: Count,
    /// Neighbouring beams whose ranges differ by more than this belong to different objects: the
    /// smoothing never averages across such a jump (the paper does not say; blending a robot's edge
    /// with the wall behind it would invent points in free space).
    pub segment_jump_m: Positive,
}

/// Neighbour contour recognition (docs/method.md §3).
#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ContourParams {
    /// Points fitted on each side of a candidate corner (Table 2: N = 10).
    pub line_fit_points: Count,
    /// How far a fitted corner angle may be from the outline's corner angle.
    pub corner_angle_tolerance_deg: Positive,
    /// Largest RMS distance of the fitted points from their lines.
    pub max_fit_rms_m: Positive,
}

/// The constant-velocity Kalman tracker (Eq. 8–10; docs/method.md §4).
#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrackerParams {
    /// σ_a of the white-noise-acceleration Q (0.05 m/s²; Q is built from the true Δt).
    pub accel_sigma_mps2: Positive,
    /// R = diag(r, r) (Table 2: 4.0e-4 m²).
    pub measurement_var_m2: Positive,
    /// P0 position terms (Table 2: 2.5e-3 m²).
    pub initial_position_var_m2: Positive,
    /// P0 velocity terms (Table 2: 1.0e-2 m²/s²).
    pub initial_velocity_var_m2ps2: Positive,
    /// ROI half-widths (h_x0, h_y0) of Eq. 10 (Table 2: 0.25 m, 0.25 m).
    pub roi_half_width_m: [Positive; 2],
    /// γ of Eq. 10 (Table 2: 2.0), applied to the position standard deviation.
    pub roi_gamma: Positive,
    /// N_miss,max: consecutive invalid synchronised packets before the track is lost (Table 2: 3).
    pub max_missed_packets: Count,
    /// Mahalanobis gate as a chi-square probability with 2 degrees of freedom.
    pub gate_probability: OpenFraction,
}

/// The relative-heading search (Eq. 11–12; docs/method.md §5).
#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HeadingParams {
    /// ε_d of Eq. 11 (Table 2: 3 mm).
    pub distance_gate_m: Positive,
    /// Δθ, the angular increment (Table 2: 0.1°).
    pub step_deg: Positive,
    /// Nearest-neighbour search half-width in beam indices (Table 2: ±10).
    pub neighbour_window_beams: Count,
    /// Half-width of the refined search around the previous estimate (the paper does not give it).
    pub refine_window_deg: Positive,
    /// A best score below this is a failed estimate.
    pub min_score: Fraction,
    /// A best score less than this many times the runner-up (the best more than 1° away) is a
    /// failed estimate: the peak is not distinct.
    pub min_peak_ratio: Positive,
    /// Ours: a best angle matched by fewer source points than this is a failed estimate, whatever
    /// its score: a score is a share of the source points, and where the scans barely overlap a
    /// peak of one or two chance matches still stands out. Absent: any count (the paper).
    #[serde(default)]
    pub min_matches: Option<Count>,
    /// A refined estimate further than this from the prediction (the last heading carried
    /// forward by both robots' odometry) is refused as an outlier; absent: none is (the paper).
    #[serde(default)]
    pub prior_gate_deg: Option<Positive>,
    /// Ours: a refined estimate that passes the gate is blended with the prediction (a scalar
    /// Kalman filter) instead of replacing it. The prediction's uncertainty grows by this much per
    /// √s (the two robots' odometry headings drifting apart). Absent, or `search_sigma_deg`
    /// absent: each estimate replaces the heading (the paper).
    #[serde(default)]
    pub drift_deg_per_sqrt_s: Option<Positive>,
    /// Ours: the uncertainty (1σ) of one refined estimate, for the blend above.
    #[serde(default)]
    pub search_sigma_deg: Option<Positive>,
    /// Ours: the blend also learns the rate at which the two robots' odometry headings drift
    /// apart (the residuals of their gyro biases), whose prior 1σ this is, and carries the
    /// heading forward with it. Absent: a random walk only.
    #[serde(default)]
    pub drift_rate_sigma_deg_per_s: Option<Positive>,
    /// Ours: Eq. 11 counts a source point that lands within ε_d of the target scan's surface (the
    /// segments between neighbouring beams whose ranges differ by at most this), not only of its
    /// points. Absent: points only (the paper).
    #[serde(default)]
    pub surface_max_jump_m: Option<Positive>,
}

impl HeadingParams {
    /// The blend's (drift per √s, search σ), radians, when both are set.
    #[must_use]
    pub fn blend_rad(&self) -> Option<(f64, f64)> {
        Some((self.drift_deg_per_sqrt_s?.get().to_radians(), self.search_sigma_deg?.get().to_radians()))
    }

    /// The surface's range jump, m, when matching against the surface.
    #[must_use]
    pub fn surface_jump_m(&self) -> Option<f64> {
        self.surface_max_jump_m.map(Positive::get)
    }
}

/// Body masks and the virtual scan (docs/method.md §6).
#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FusionParams {
    /// The chassis polygon is grown by this much before masking body returns.
    pub mask_inflation_m: Positive,
    /// Angular bin of the virtual scan; absent → the finest step among the source scans.
    #[serde(default)]
    pub virtual_bin_deg: Option<Positive>,
    /// Whose motion the motion model of AMCL on the virtual scan samples; absent → V's (the paper).
    #[serde(default)]
    pub amcl_motion: AmclMotion,
}

/// Whose motion the motion model of AMCL on the virtual scan samples. Either way the filter
/// tracks V, on V's odometry, with the same points and map; what differs is the noise.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum AmclMotion {
    /// V's own (the paper, §3.2). When the formation turns on the spot V only rotates, and the
    /// differential-drive model moves its samples along their heading only: a cloud that has
    /// drifted sideways keeps no sideways spread and cannot follow the scan's pull back.
    #[default]
    Virtual,
    /// The reference robot's (ours): V's increment is sampled as the reference robot drove it (an
    /// arc in the formation's turns) and carried back to V ([`crate::amcl::Amcl::set_motion_body`]).
    Reference,
}

impl ConfigFileType for VamrParams {
    fn validate(&self) -> Result<(), Violation> {
        let median = self.preprocess.median_window_beams.get();
        rule(
            median % 2 == 1,
            "preprocess.median_window_beams",
            format!("must be odd so the window has a centre beam (got {median})"),
        )?;
        rule(
            self.contour.line_fit_points.get() >= 2,
            "contour.line_fit_points",
            format!("a line needs at least 2 points (got {})", self.contour.line_fit_points.get()),
        )?;
        let h = &self.heading;
        rule(
            h.step_deg.get() <= 10.0,
            "heading.step_deg",
            format!("must be at most 10° (got {}°)", h.step_deg.get()),
        )?;
        rule(
            h.refine_window_deg.get() >= h.step_deg.get() && h.refine_window_deg.get() <= 180.0,
            "heading.refine_window_deg",
            format!(
                "must lie between heading.step_deg and 180° (got {}° with a {}° step)",
                h.refine_window_deg.get(),
                h.step_deg.get()
            ),
        )?;
        rule(
            h.min_peak_ratio.get() >= 1.0,
            "heading.min_peak_ratio",
            format!("must be at least 1 (got {})", h.min_peak_ratio.get()),
        )?;
        if let Some(bin) = self.fusion.virtual_bin_deg {
            rule(
                bin.get() <= 10.0,
                "fusion.virtual_bin_deg",
                format!("must be at most 10° (got {}°)", bin.get()),
            )?;
        }
        Ok(())
    }
}
