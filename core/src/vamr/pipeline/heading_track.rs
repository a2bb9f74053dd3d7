//! One robot's relative heading across updates: carried forward by both robots' odometry
//! (predict), searched around that prediction or over the full circle, each estimate gated against
//! the prediction, blended with it, or, when the search finds nothing usable, the prediction kept
//! (fallback) (docs/method.md §5).

use crate::config::HeadingParams;
use crate::se2::{angle_diff, normalize_angle};
use crate::vamr::heading::{AngleGrid, HeadingEstimate};

use super::{Source, UpdateError};

/// Refined heading estimates refused in a row (they disagree with the odometry's prediction)
/// before the prediction is questioned by a full search: 1 s of scans at 15 Hz.
pub const MAX_REFUSED: u32 = 15;

/// Memory of the drift rate's estimate, s: its variance grows by its prior's over this long (the
/// robots' gyro biases wander with temperature, and a robot standing still learns its bias again).
pub const DRIFT_RATE_MEMORY_S: f64 = 60.0;

/// The blend of a kept relative heading and the searches' estimates: a Kalman filter whose state
/// is the error of the heading carried by both robots' odometry and, with
/// `heading.drift_rate_sigma_deg_per_s`, the rate at which their odometry headings drift apart (the
/// residuals of their gyro biases). Without that key the rate stays 0 and this is the scalar blend.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct HeadingBlend {
    /// Covariance of (heading, drift rate): rad², rad²/s, rad²/s².
    p: [[f64; 2]; 2],
    /// The drift rate learnt, rad/s, added to the odometry's prediction.
    rate: f64,
    /// The rate's prior variance, rad²/s² (0: no rate).
    rate_var: f64,
}

impl HeadingBlend {
    pub(super) fn new(heading_var: f64, params: &HeadingParams) -> Self {
        let rate_var = params.drift_rate_sigma_deg_per_s.map_or(0.0, |s| s.get().to_radians().powi(2));
        HeadingBlend { p: [[heading_var, 0.0], [0.0, rate_var]], rate: 0.0, rate_var }
    }

    /// `dt` seconds of odometry: the heading's variance grows by `white_var` per second (the
    /// gyros' white noise) and by what the rate's uncertainty makes of `dt`.
    fn predict(&mut self, dt: f64, white_var: f64) {
        let [[a, b], [_, d]] = self.p;
        let p01 = b + d * dt;
        self.p = [
            [a + 2.0 * b * dt + d * dt * dt + white_var * dt, p01],
            [p01, d + self.rate_var * dt / DRIFT_RATE_MEMORY_S],
        ];
    }

    /// A search's estimate, `innovation` from the prediction, with variance `r`: returns the
    /// heading's correction (and corrects the rate).
    fn update(&mut self, innovation: f64, r: f64) -> f64 {
        let [[a, b], [_, d]] = self.p;
        let s = a + r;
        if s <= 0.0 {
            return 0.0;
        }
        let (k0, k1) = (a / s, b / s);
        self.rate += k1 * innovation;
        let p01 = (1.0 - k0) * b;
        self.p = [[(1.0 - k0) * a, p01], [p01, d - k1 * b]];
        k0 * innovation
    }

    /// The heading is replaced (a full search, or the formation's guess) with variance `var`;
    /// what is known of the rate stays.
    fn restart(&mut self, var: f64) {
        self.p[0] = [var, 0.0];
        self.p[1][0] = 0.0;
    }
}

/// One non-reference robot's heading relative to its observer.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct HeadingTrack {
    /// The heading kept, rad.
    pub(super) heading: Option<f64>,
    /// Its and its observer's odometry yaw when the heading was last carried forward.
    yaws: Option<(f64, f64)>,
    /// When the heading was last carried forward, s.
    t: Option<f64>,
    /// Search results refused in a row (after [`MAX_REFUSED`] the prediction is questioned).
    refused: u32,
    /// The track was lost or the prediction questioned: the next search sweeps the full circle;
    /// the heading carried by odometry stays as the fallback should that search find nothing.
    pub(super) reacquire: bool,
    blend: HeadingBlend,
    /// The formation's heading for the robot: the fallback when nothing is known.
    pub(super) expected: Option<f64>,
}

impl HeadingTrack {
    pub(super) fn new(params: &HeadingParams) -> Self {
        HeadingTrack {
            heading: None,
            yaws: None,
            t: None,
            refused: 0,
            reacquire: false,
            blend: HeadingBlend::new(0.0, params),
            expected: None,
        }
    }

    /// Forget the heading (the robot's data stopped); when it was last carried and the
    /// formation's heading stay.
    pub(super) fn forget(&mut self, params: &HeadingParams) {
        self.heading = None;
        self.blend = HeadingBlend::new(0.0, params);
        self.refused = 0;
        self.reacquire = false;
    }

    /// Predict: carry the kept heading to `t_s` by both robots' odometry turns since
    /// (`yaws`: the robot's and its observer's odometry yaw now) and by the drift rate learnt.
    pub(super) fn predict(&mut self, t_s: f64, yaws: Option<(f64, f64)>, h: &HeadingParams) {
        let dt = self.t.map_or(0.0, |t0| (t_s - t0).max(0.0));
        if let (Some(prev), Some((ti, to)), Some((pi, po))) = (self.heading, yaws, self.yaws) {
            self.heading =
                Some(normalize_angle(prev + angle_diff(ti, pi) - angle_diff(to, po) + self.blend.rate * dt));
        }
        self.yaws = yaws;
        if let Some((drift, _)) = h.blend_rad() {
            self.blend.predict(dt, drift * drift);
        }
        self.t = Some(t_s);
    }

    /// Where to search: around the prediction, or the full circle when there is none or the
    /// track is being reacquired.
    pub(super) fn search_grid(&mut self, h: &HeadingParams) -> (AngleGrid, Source) {
        let full = std::mem::take(&mut self.reacquire);
        match self.heading.filter(|_| !full) {
            Some(prev) => {
                (AngleGrid::around(prev, h.refine_window_deg.get(), h.step_deg.get()), Source::RefinedSearch)
            }
            None => (AngleGrid::full(h.step_deg.get()), Source::FullSearch),
        }
    }

    /// Gate, blend or fall back: the heading this update uses, and where it came from, given the
    /// search's `estimate` made in `mode`. `robot` names the robot in an error.
    pub(super) fn settle(
        &mut self,
        estimate: Option<HeadingEstimate>,
        mode: Source,
        h: &HeadingParams,
        robot: usize,
    ) -> (Result<f64, UpdateError>, Source) {
        let predicted = self.heading;
        let distinct = estimate.filter(|e| distinct(e, h));
        let agrees = |e: &HeadingEstimate| agrees(e, predicted, mode, h);
        if distinct.as_ref().is_some_and(|e| !agrees(e)) {
            self.refused += 1;
        }
        let failed = UpdateError::NoHeading { robot, why: "search failed" };
        match distinct.filter(agrees) {
            Some(e) => {
                let theta = self.blend_in(e.theta_rad, predicted, mode, h);
                self.heading = Some(theta);
                self.refused = 0;
                (Ok(theta), mode)
            }
            None if self.refused > MAX_REFUSED => {
                // The prediction is questioned, not dropped: the next search sweeps the full
                // circle and whatever distinct peak it finds replaces the prediction, but if it
                // finds none the prediction is still the best there is. (Dropped, the fallback was
                // the formation's expected heading: 47° off in the middle of a turn of `turning`,
                // 2 robots 1 m apart, seed 11, where the prediction was 1.1° off and the refused
                // estimates 4°.)
                self.reacquire = true;
                self.refused = 0;
                (predicted.ok_or(failed), Source::PreviousHeading)
            }
            None => {
                if self.heading.is_none() {
                    // The formation's heading is a guess: the next estimates replace it.
                    self.heading = self.expected;
                    self.blend.restart(h.refine_window_deg.get().to_radians().powi(2));
                }
                (self.heading.ok_or(failed), Source::PreviousHeading)
            }
        }
    }

    /// Blend an accepted estimate with the prediction (a refined search with the blend on), or
    /// take it as it is and restart the blend there.
    fn blend_in(&mut self, theta_rad: f64, predicted: Option<f64>, mode: Source, h: &HeadingParams) -> f64 {
        match (h.blend_rad(), predicted) {
            (Some((_, sigma)), Some(prior)) if mode == Source::RefinedSearch => {
                let innovation = angle_diff(theta_rad, prior);
                let step = self.blend.update(innovation, sigma * sigma);
                normalize_angle(prior + step)
            }
            (blend, _) => {
                self.blend.restart(blend.map_or(0.0, |(_, sigma)| sigma * sigma));
                theta_rad
            }
        }
    }
}

/// A peak the search may be trusted with: score, distinctness from the runner-up, matches.
fn distinct(e: &HeadingEstimate, h: &HeadingParams) -> bool {
    e.score >= h.min_score.get()
        && e.score >= h.min_peak_ratio.get() * e.runner_up
        && h.min_matches.is_none_or(|m| e.matches() >= m.get())
}

/// A refined estimate within `prior_gate_deg` of the prediction (a full search is not gated).
fn agrees(e: &HeadingEstimate, predicted: Option<f64>, mode: Source, h: &HeadingParams) -> bool {
    match (h.prior_gate_deg, predicted) {
        (Some(gate), Some(p)) if mode == Source::RefinedSearch => {
            angle_diff(e.theta_rad, p).abs() <= gate.get().to_radians()
        }
        _ => true,
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "tests")]
    use super::*;

    /// The shipped heading parameters, the blend off (the scalar steps are checked on their own).
    fn params() -> HeadingParams {
        let mut h = crate::vamr::shipped_params().heading;
        h.drift_deg_per_sqrt_s = None;
        h.search_sigma_deg = None;
        h.drift_rate_sigma_deg_per_s = None;
        h
    }

    /// An estimate at `theta` with a clear peak (score 0.9, runner-up 0.1, 100 matches).
    fn peak(theta: f64) -> HeadingEstimate {
        HeadingEstimate { theta_rad: theta, score: 0.9, runner_up: 0.1, counts: vec![100] }
    }

    #[test]
    fn predict_carries_the_heading_by_both_robots_odometry_turns() {
        let h = params();
        let mut t = HeadingTrack::new(&h);
        t.predict(0.0, Some((0.0, 0.0)), &h);
        assert_eq!(t.heading, None, "nothing to carry yet");
        t.heading = Some(0.1);
        // The robot turned 0.3 rad, its observer 0.1: the relative heading grew by 0.2.
        t.predict(1.0, Some((0.3, 0.1)), &h);
        assert!((t.heading.unwrap() - 0.3).abs() < 1e-12, "{:?}", t.heading);
        // Without odometry the heading stays.
        t.predict(2.0, None, &h);
        assert!((t.heading.unwrap() - 0.3).abs() < 1e-12);
    }

    #[test]
    fn the_search_is_refined_around_the_prediction_unless_reacquiring() {
        let h = params();
        let mut t = HeadingTrack::new(&h);
        assert_eq!(t.search_grid(&h).1, Source::FullSearch, "no heading yet");
        t.heading = Some(0.5);
        assert_eq!(t.search_grid(&h).1, Source::RefinedSearch);
        t.reacquire = true;
        assert_eq!(t.search_grid(&h).1, Source::FullSearch);
        assert!(!t.reacquire, "a full search is one search");
        assert_eq!(t.search_grid(&h).1, Source::RefinedSearch);
    }

    #[test]
    fn estimates_are_gated_against_the_prediction_and_refusals_question_it() {
        let mut h = params();
        h.prior_gate_deg = Some(crate::config::value::Positive::new(5.0).unwrap());
        let mut t = HeadingTrack::new(&h);
        t.heading = Some(0.0);
        let (theta, source) = t.settle(Some(peak(0.05)), Source::RefinedSearch, &h, 1);
        assert_eq!((theta.unwrap(), source), (0.05, Source::RefinedSearch), "within the gate: taken");
        // 0.5 rad from the prediction: refused, the prediction kept; the one after MAX_REFUSED in a
        // row questions the prediction.
        for k in 0..MAX_REFUSED {
            let (theta, source) = t.settle(Some(peak(0.55)), Source::RefinedSearch, &h, 1);
            assert_eq!((theta.unwrap(), source), (0.05, Source::PreviousHeading), "refusal {k}");
            assert!(!t.reacquire);
        }
        let (theta, _) = t.settle(Some(peak(0.55)), Source::RefinedSearch, &h, 1);
        assert_eq!(theta.unwrap(), 0.05);
        assert!(t.reacquire, "the prediction is questioned: a full search next");
        // A full search is not gated: its peak replaces the prediction.
        let (theta, source) = t.settle(Some(peak(0.55)), Source::FullSearch, &h, 1);
        assert_eq!((theta.unwrap(), source), (0.55, Source::FullSearch));
    }

    #[test]
    fn without_a_distinct_peak_the_formations_heading_is_the_fallback() {
        let h = params();
        let mut t = HeadingTrack::new(&h);
        let flat = HeadingEstimate { theta_rad: 1.0, score: 0.9, runner_up: 0.89, counts: vec![100] };
        let (theta, source) = t.settle(Some(flat.clone()), Source::FullSearch, &h, 2);
        assert!(matches!(theta, Err(UpdateError::NoHeading { robot: 2, .. })), "{theta:?}");
        assert_eq!(source, Source::PreviousHeading);
        t.expected = Some(0.0);
        let (theta, _) = t.settle(Some(flat), Source::FullSearch, &h, 2);
        assert_eq!(theta.unwrap(), 0.0);
        t.forget(&h);
        assert_eq!((t.heading, t.expected), (None, Some(0.0)), "forgetting keeps the formation's heading");
    }

    #[test]
    fn the_blend_weighs_a_refined_estimate_against_the_prediction() {
        let mut h = params();
        h.drift_deg_per_sqrt_s = Some(crate::config::value::Positive::new(1.0).unwrap());
        h.search_sigma_deg = Some(crate::config::value::Positive::new(1.0).unwrap());
        let mut t = HeadingTrack::new(&h);
        t.predict(0.0, None, &h);
        // A full search's estimate restarts the blend with the search's variance, (1°)².
        assert_eq!(t.settle(Some(peak(0.02)), Source::FullSearch, &h, 1).0.unwrap(), 0.02);
        // A second of drift at 1°/√s doubles it: the next estimate gets two thirds of the way.
        t.predict(1.0, None, &h);
        let theta = t.settle(Some(peak(0.04)), Source::RefinedSearch, &h, 1).0.unwrap();
        assert!((theta - (0.02 + 0.02 * 2.0 / 3.0)).abs() < 1e-9, "{theta}");
    }
}
