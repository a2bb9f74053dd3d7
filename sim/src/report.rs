//! What a simulation run reports: the localisation error against the true pose, the per-stage
//! latency table in the layout of the paper's Table 4, and which devices reached Ok.

use std::collections::BTreeMap;
use std::fmt::Write as _;

use amr_core::metrics::ErrorStats;
use amr_msgs::StageTimes;
use amr_msgs::{Device, Health};
use serde::Serialize;

/// One row of the latency table.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct LatencyRow {
    pub stage: &'static str,
    pub count: usize,
    pub median_ms: f64,
    pub p95_ms: f64,
}

/// The paper's Table 4 stages, in its order, from the recorded updates.
#[must_use]
pub fn latency_table(times: &[StageTimes]) -> Vec<LatencyRow> {
    // AMCL counts only the updates in which the filter ran (it skips until V has moved
    // `update_min_d` or turned `update_min_a`).
    type Column = fn(&StageTimes) -> Option<f64>;
    let rows: [(&'static str, Column); 7] = [
        ("acquisition + sync", |t| Some(t.acquisition_sync_s)),
        ("preprocessing", |t| Some(t.preprocess_s)),
        ("tracking", |t| Some(t.tracking_s)),
        ("heading search", |t| Some(t.heading_s)),
        ("virtual scan", |t| Some(t.virtual_scan_s)),
        ("AMCL (filter updates)", |t| t.amcl_s),
        ("end to end", |t| Some(t.end_to_end_s)),
    ];
    rows.iter()
        .map(|(stage, f)| {
            let v: Vec<f64> = times.iter().filter_map(|t| f(t).map(|s| s * 1000.0)).collect();
            let s = ErrorStats::of(&v);
            LatencyRow {
                stage,
                count: s.map_or(0, |s| s.count),
                median_ms: s.map_or(f64::NAN, |s| s.median),
                p95_ms: s.map_or(f64::NAN, |s| s.p95),
            }
        })
        .collect()
}

/// Errors of one estimate of V against the truth at its stamp.
#[derive(Debug, Clone, Copy, Serialize, PartialEq)]
pub struct ErrorSample {
    pub t_s: f64,
    pub e_x_m: f64,
    pub e_y_m: f64,
    pub e_theta_rad: f64,
    /// The estimate was verified (V tracking, no robot disagreeing): the formation may drive on it.
    pub verified: bool,
}

/// The whole report.
#[derive(Debug, Clone, Serialize)]
pub struct SimReport {
    pub scenario: String,
    pub seed: u64,
    pub configuration: String,
    /// Time the run took, s, on its clock (`clock`).
    pub duration_s: f64,
    /// `wall` (real time) or `virtual` (tokio's paused clock, devices over in-memory pipes).
    pub clock: String,
    /// How far into the plan the formation got, s, and the plan's length.
    pub plan_s: f64,
    pub plan_len_s: f64,
    pub final_phase: String,
    /// V's position error (2D) against the truth, over every fused estimate.
    pub error_2d: Option<ErrorStats>,
    pub error_heading: Option<ErrorStats>,
    pub samples: Vec<ErrorSample>,
    pub latency: Vec<LatencyRow>,
    /// Per robot, per device: the best health reached and the last one.
    pub health: BTreeMap<String, BTreeMap<String, (String, String)>>,
    /// Per robot: its counters (scans, rejected frames, refusals…).
    pub counters: BTreeMap<String, BTreeMap<String, u64>>,
    /// Per robot: how far it ended from its slot in the true V, m.
    pub final_formation_error_m: Vec<f64>,
    /// Per robot: its true pose at the end, `[x, y, θ]`.
    pub final_truth: Vec<[f64; 3]>,
}

/// Best-first rank of a health.
#[must_use]
pub fn rank(h: Health) -> u8 {
    match h {
        Health::Ok => 0,
        Health::Degraded => 1,
        Health::Starting => 2,
        Health::Lost => 3,
        Health::Fault => 4,
    }
}

impl SimReport {
    /// Why the run failed, if it did: the plan did not finish (when `plan_must_finish`: not a run
    /// cut short on purpose), or a verified estimate of V (one the formation may drive on) was
    /// farther than `max_error_m` from the truth, or V was never verified.
    #[must_use]
    pub fn failures(&self, max_error_m: f64, plan_must_finish: bool) -> Vec<String> {
        let mut out = Vec::new();
        if plan_must_finish && self.final_phase != "Finished" {
            out.push(format!(
                "the plan did not finish: formation {} at {:.1} s of {:.1} s",
                self.final_phase, self.plan_s, self.plan_len_s
            ));
        }
        let worst = self
            .samples
            .iter()
            .filter(|s| s.verified)
            .map(|s| (s.e_x_m.hypot(s.e_y_m), s.t_s))
            .max_by(|a, b| a.0.total_cmp(&b.0));
        if let Some((e, t)) = worst.filter(|(e, _)| *e > max_error_m) {
            out.push(format!(
                "V's verified estimate was {:.1} cm from the truth at t = {t:.1} s (bound {:.1} cm)",
                e * 100.0,
                max_error_m * 100.0
            ));
        }
        if !self.samples.is_empty() && self.samples.iter().all(|s| !s.verified) {
            out.push("V was never verified: no estimate the formation could drive on".to_owned());
        }
        out
    }

    /// Whether every device of every robot reached Ok at some point.
    #[must_use]
    pub fn every_device_reached_ok(&self) -> bool {
        let wanted =
            [Device::Lidar, Device::Imu, Device::CanBus, Device::Drives, Device::Odometry, Device::Safety];
        self.health.values().all(|devices| {
            wanted.iter().all(|d| devices.get(&format!("{d:?}")).is_some_and(|(best, _)| best == "Ok"))
        })
    }

    /// The report as text: the error summary, the latency table and the device health.
    #[must_use]
    pub fn to_text(&self) -> String {
        let mut s = String::new();
        let _ = writeln!(
            s,
            "scenario {} ({}), seed {}: {:.1} s of {:.1} s planned, formation {}, {:.1} s of {} time",
            self.scenario,
            self.configuration,
            self.seed,
            self.plan_s,
            self.plan_len_s,
            self.final_phase,
            self.duration_s,
            self.clock
        );
        match self.error_2d {
            Some(e) => {
                let _ = writeln!(
                    s,
                    "localisation of V vs the true pose ({} estimates): RMSE {:.1} cm, median {:.1} cm, P95 {:.1} cm, max {:.1} cm",
                    e.count,
                    e.rmse * 100.0,
                    e.median * 100.0,
                    e.p95 * 100.0,
                    e.max * 100.0
                );
            }
            None => {
                let _ = writeln!(s, "localisation of V: no fused estimate");
            }
        }
        if let Some(h) = self.error_heading {
            let _ =
                writeln!(s, "heading of V: RMSE {:.2}°, max {:.2}°", h.rmse.to_degrees(), h.max.to_degrees());
        }
        if !self.final_formation_error_m.is_empty() {
            let cm: Vec<String> =
                self.final_formation_error_m.iter().map(|e| format!("{:.1} cm", e * 100.0)).collect();
            let poses: Vec<String> = self
                .final_truth
                .iter()
                .map(|p| format!("({:.3}, {:.3}, {:.1}°)", p[0], p[1], p[2].to_degrees()))
                .collect();
            let _ = writeln!(
                s,
                "formation at the end: robots {} from their slots in the true V; true poses {}",
                cm.join(", "),
                poses.join(", ")
            );
        }
        let _ = writeln!(s, "\nper-stage latency (layout of the paper's Table 4), ms:");
        let _ = writeln!(s, "| stage | n | median | P95 |");
        let _ = writeln!(s, "|---|---:|---:|---:|");
        for r in &self.latency {
            let _ = writeln!(s, "| {} | {} | {:.2} | {:.2} |", r.stage, r.count, r.median_ms, r.p95_ms);
        }
        let _ = writeln!(s, "\ndevices (best / last health):");
        for (robot, devices) in &self.health {
            let list: Vec<String> = devices.iter().map(|(d, (b, l))| format!("{d} {b}/{l}")).collect();
            let _ = writeln!(s, "  {robot}: {}", list.join(", "));
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn latency_rows_are_in_the_papers_order_with_median_and_p95() {
        let times: Vec<StageTimes> = (1..=100)
            .map(|k| StageTimes {
                end_to_end_s: f64::from(k) / 1000.0,
                amcl_s: (k % 2 == 0).then_some(0.002),
                ..StageTimes::default()
            })
            .collect();
        let t = latency_table(&times);
        let names: Vec<&str> = t.iter().map(|r| r.stage).collect();
        assert_eq!(
            names,
            [
                "acquisition + sync",
                "preprocessing",
                "tracking",
                "heading search",
                "virtual scan",
                "AMCL (filter updates)",
                "end to end"
            ]
        );
        let e2e = &t[6];
        assert_eq!(e2e.count, 100);
        assert!((e2e.median_ms - 50.5).abs() < 1e-9 && (e2e.p95_ms - 95.05).abs() < 1e-9, "{e2e:?}");
        assert!((t[5].median_ms - 2.0).abs() < 1e-12 && t[5].count == 50);
        assert!(latency_table(&[]).iter().all(|r| r.count == 0 && r.median_ms.is_nan()));
    }
}
