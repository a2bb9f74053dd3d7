//! Body masks and the virtual scan (paper §4.4, Eq. 19; docs/method.md §6).

use crate::geometry::Polygon;
use crate::scan::Scan;
use crate::se2::Se2;
use std::f64::consts::{PI, TAU};

/// One robot's contribution: its raw scan, mount, outline and pose in V.
#[derive(Debug, Clone, Copy)]
pub struct FusionInput<'a> {
    pub scan: &'a Scan,
    pub lidar_to_base: Se2,
    pub chassis: &'a Polygon,
    /// `T_{B_i}^V`.
    pub base_in_v: Se2,
}

/// The fused measurement: points in V and the virtual scan built from them.
#[derive(Debug, Clone)]
pub struct VirtualScan {
    /// Eq. 19: `S_V`, with the robot each point came from.
    pub points: Vec<([f64; 2], usize)>,
    /// Polar bins around V's origin, the nearest point per bin; empty bins are invalid (no return).
    pub scan: Scan,
    /// Points removed by the body masks, per robot.
    pub masked: Vec<usize>,
}

/// `M_i`: whether a point of robot `i` (in V) lies inside any robot's outline grown by `inflation_m`
/// (the other robots at their estimated poses, and robot `i` itself).
fn masked(p_v: [f64; 2], inputs: &[FusionInput<'_>], inflation_m: f64) -> bool {
    inputs
        .iter()
        .any(|o| o.chassis.contains_inflated(o.base_in_v.inverse().transform_point(p_v), inflation_m))
}

/// Eq. 19 and the virtual scan. `bin_rad` is the angular bin (default: the finest source step).
#[must_use]
pub fn fuse(inputs: &[FusionInput<'_>], inflation_m: f64, bin_rad: Option<f64>) -> VirtualScan {
    let bin = bin_rad
        .or_else(|| inputs.iter().map(|i| i.scan.angle_increment_rad.abs()).reduce(f64::min))
        .filter(|b| *b > 0.0)
        .unwrap_or(1f64.to_radians());
    let count = (TAU / bin).round().max(1.0) as usize;
    let bin = TAU / count as f64;
    let mut points = Vec::new();
    let mut masked_count = vec![0; inputs.len()];
    let mut range_max: f64 = 0.0;
    for (i, inp) in inputs.iter().enumerate() {
        let to_v = inp.base_in_v * inp.lidar_to_base;
        range_max = range_max.max(inp.scan.range_max_m + to_v.translation_norm());
        for b in inp.scan.points_in(&to_v) {
            if masked(b.p, inputs, inflation_m) {
                masked_count[i] += 1;
            } else {
                points.push((b.p, i));
            }
        }
    }
    let mut ranges = vec![f64::NAN; count];
    for (p, _) in &points {
        let k = (((p[1].atan2(p[0]) + PI) / bin).floor() as usize).min(count - 1);
        let r = p[0].hypot(p[1]);
        if ranges[k].is_nan() || r < ranges[k] {
            ranges[k] = r;
        }
    }
    let scan = Scan::new(-PI + bin / 2.0, bin, 0.0, range_max, ranges);
    VirtualScan { points, scan, masked: masked_count }
}
