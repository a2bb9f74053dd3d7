//! Particle-set steps: KLD-sampling limit, systematic resampling with random injection, and the
//! cluster estimate (nav2_amcl `pf.c`, `pf_kdtree.c`).

use std::collections::{BTreeMap, BTreeSet};

use crate::rng::Rng;
use crate::se2::{Se2, normalize_angle};

/// A weighted pose hypothesis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Particle {
    pub pose: Se2,
    pub weight: f64,
}

/// Histogram bins of the KLD limit and the clusters: 0.5 m × 0.5 m × 10° (nav2 `pf_kdtree.c`).
pub const BIN_XY_M: f64 = 0.5;
pub const BIN_THETA_RAD: f64 = 10.0 * std::f64::consts::PI / 180.0;

type Bin = (i64, i64, i64);

fn bin(p: &Se2) -> Bin {
    (floor(p.x / BIN_XY_M), floor(p.y / BIN_XY_M), wrap_theta_bin(floor(p.theta / BIN_THETA_RAD)))
}

/// `x.floor() as i64` for |x| < 2⁴⁰ without the library call `floor` is on x86-64 without SSE4.1
/// (this runs for every particle at every resampling): biased, truncation is a floor.
fn floor(x: f64) -> i64 {
    const BIAS: i64 = 1 << 40;
    ((x + BIAS as f64) as i64).wrapping_sub(BIAS)
}

/// θ bin indices wrapped into `[−n/2, n/2)`, so +π and −π share a bin.
fn wrap_theta_bin(t: i64) -> i64 {
    let nt = theta_bins();
    let t = t.rem_euclid(nt);
    if t >= nt / 2 { t - nt } else { t }
}

/// Number of θ bins around the circle (for wrapping neighbours).
fn theta_bins() -> i64 {
    (std::f64::consts::TAU / BIN_THETA_RAD).round() as i64
}

/// KLD-sampling (Fox 2003) as nav2 computes it: with `k` occupied bins,
/// `n = ⌈(k−1)/(2ε) · (1 − 2/(9(k−1)) + √(2/(9(k−1)))·z)³⌉`, clamped to [min, max]; `k ≤ 1` gives max.
/// nav2 uses `pf_z` directly as the normal quantile `z`.
#[must_use]
pub fn kld_limit(k: usize, err: f64, z: f64, min: usize, max: usize) -> usize {
    if k <= 1 {
        return max;
    }
    let km1 = (k - 1) as f64;
    let b = 2.0 / (9.0 * km1);
    let x = 1.0 - b + b.sqrt() * z;
    let n = (km1 / (2.0 * err) * x * x * x).ceil();
    (n.max(0.0) as usize).clamp(min, max)
}

/// Number of distinct bins the poses occupy.
#[must_use]
pub fn occupied_bins(poses: impl Iterator<Item = Se2>) -> usize {
    poses.map(|p| bin(&p)).collect::<BTreeSet<_>>().len()
}

/// Resampling parameters for one step.
#[derive(Debug, Clone, Copy)]
pub struct ResampleLimits {
    pub min: usize,
    pub max: usize,
    pub err: f64,
    pub z: f64,
    /// Probability of replacing a draw by a random pose (augmented MCL's `max(0, 1 − w_fast/w_slow)`).
    pub inject_probability: f64,
}

fn gcd(a: usize, b: usize) -> usize {
    if b == 0 { a } else { gcd(b, a % b) }
}

/// Systematic (low-variance) resampling in O(N + M), combined with the KLD limit and random
/// injection. `particles` must have normalised weights.
///
/// nav2 resamples with one random number and a linear CDF scan per draw (O(N·M)) because, as its
/// code says, low-variance sampling does not combine easily with KLD's stop-when-enough rule: the
/// systematic draws come out in particle order, so the bin count would grow in a biased way. Here the
/// M = `max` systematic draws are made first, in O(N + M), and then visited in a pseudo-random
/// order (a stride coprime to M from a random start), stopping once the KLD limit for the bins seen
/// so far is met.
pub fn resample(
    particles: &[Particle],
    limits: &ResampleLimits,
    rng: &mut Rng,
    random_pose: &mut dyn FnMut(&mut Rng) -> Se2,
) -> Vec<Particle> {
    let m = limits.max.max(1);
    if particles.is_empty() {
        return Vec::new();
    }
    // Systematic draws.
    let step = 1.0 / m as f64;
    let mut u = rng.uniform() * step;
    let mut draws = Vec::with_capacity(m);
    let (mut i, mut cum) = (0usize, particles[0].weight);
    for _ in 0..m {
        while u > cum && i + 1 < particles.len() {
            i += 1;
            cum += particles[i].weight;
        }
        draws.push(i);
        u += step;
    }
    // Visit in a strided order and stop at the KLD limit.
    let mut stride = (m as f64 * 0.618_033_988_75) as usize | 1;
    while gcd(stride, m) != 1 {
        stride += 2;
    }
    let start = rng.below(m);
    let mut bins = BTreeSet::new();
    let mut out = Vec::with_capacity(m);
    for t in 0..m {
        let idx = draws[(start + t * stride) % m];
        let pose = if limits.inject_probability > 0.0 && rng.uniform() < limits.inject_probability {
            random_pose(rng)
        } else {
            particles[idx].pose
        };
        bins.insert(bin(&pose));
        out.push(Particle { pose, weight: 0.0 });
        if out.len() >= limits.min
            && out.len() >= kld_limit(bins.len(), limits.err, limits.z, limits.min, limits.max)
        {
            break;
        }
    }
    let w = 1.0 / out.len() as f64;
    for p in &mut out {
        p.weight = w;
    }
    out
}

/// A pose estimate: the weighted mean of a cluster and its covariance `[x, y, θ]` (θ variance is
/// circular, `−2 ln R`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Estimate {
    pub pose: Se2,
    pub covariance: [[f64; 3]; 3],
    /// The cluster's share of the total weight.
    pub weight: f64,
}

/// Clusters are connected groups of occupied bins (26-neighbourhood, θ wrapped), as nav2's
/// `pf_kdtree_cluster`; the estimate is the heaviest cluster's mean and covariance.
#[must_use]
pub fn cluster_estimate(particles: &[Particle]) -> Option<Estimate> {
    if particles.is_empty() {
        return None;
    }
    let mut by_bin: BTreeMap<Bin, Vec<usize>> = BTreeMap::new();
    for (k, p) in particles.iter().enumerate() {
        by_bin.entry(bin(&p.pose)).or_default().push(k);
    }
    let keys: Vec<Bin> = by_bin.keys().copied().collect();
    let index: BTreeMap<Bin, usize> = keys.iter().enumerate().map(|(i, k)| (*k, i)).collect();
    // Union-find over bins.
    let mut parent: Vec<usize> = (0..keys.len()).collect();
    fn find(parent: &mut [usize], mut x: usize) -> usize {
        while parent[x] != x {
            parent[x] = parent[parent[x]];
            x = parent[x];
        }
        x
    }
    for (i, &(bx, by, bt)) in keys.iter().enumerate() {
        for dx in -1..=1 {
            for dy in -1..=1 {
                for dt in -1..=1 {
                    if let Some(&j) = index.get(&(bx + dx, by + dy, wrap_theta_bin(bt + dt))) {
                        let (a, b) = (find(&mut parent, i), find(&mut parent, j));
                        if a != b {
                            parent[a.max(b)] = a.min(b);
                        }
                    }
                }
            }
        }
    }
    let total: f64 = particles.iter().map(|p| p.weight).sum();
    let mut clusters: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
    for (i, key) in keys.iter().enumerate() {
        let root = find(&mut parent, i);
        clusters.entry(root).or_default().extend(&by_bin[key]);
    }
    let best = clusters
        .values()
        .map(|members| (members.iter().map(|&k| particles[k].weight).sum::<f64>(), members))
        .fold(None::<(f64, &Vec<usize>)>, |acc, c| match acc {
            Some(a) if a.0 >= c.0 => Some(a),
            _ => Some(c),
        })?;
    let (w, members) = best;
    if w <= 0.0 {
        return None;
    }
    let (mut mx, mut my, mut ms, mut mc) = (0.0, 0.0, 0.0, 0.0);
    let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
    for &k in members {
        let p = &particles[k];
        let wk = p.weight / w;
        mx += wk * p.pose.x;
        my += wk * p.pose.y;
        let (sin, cos) = p.pose.theta.sin_cos();
        ms += wk * sin;
        mc += wk * cos;
        sxx += wk * p.pose.x * p.pose.x;
        sxy += wk * p.pose.x * p.pose.y;
        syy += wk * p.pose.y * p.pose.y;
    }
    let r = ms.hypot(mc).min(1.0);
    let var_theta = if r > 0.0 { -2.0 * r.ln() } else { f64::INFINITY };
    let cov =
        [[sxx - mx * mx, sxy - mx * my, 0.0], [sxy - mx * my, syy - my * my, 0.0], [0.0, 0.0, var_theta]];
    Some(Estimate {
        pose: Se2::new(mx, my, normalize_angle(ms.atan2(mc))),
        covariance: cov,
        weight: if total > 0.0 { w / total } else { 0.0 },
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kld_by_hand() {
        // k = 2, ε = 0.05, z = 0.99: (1/0.1)·(1 − 2/9 + √(2/9)·0.99)³ = 19.3 → 20, clamped to min.
        let b = 2.0f64 / 9.0;
        let expect = (10.0 * (1.0 - b + b.sqrt() * 0.99).powi(3)).ceil() as usize;
        assert_eq!(expect, 20);
        assert_eq!(kld_limit(2, 0.05, 0.99, 1, 5000), 20);
        assert_eq!(kld_limit(2, 0.05, 0.99, 500, 2000), 500);
        assert_eq!(kld_limit(1, 0.05, 0.99, 500, 2000), 2000, "nav2: one bin gives max");
        assert_eq!(kld_limit(1000, 0.05, 0.99, 500, 2000), 2000);
        assert!(kld_limit(100, 0.05, 0.99, 1, 100_000) > kld_limit(50, 0.05, 0.99, 1, 100_000));
    }

    #[test]
    fn systematic_resampling_follows_the_weights() {
        let mut rng = Rng::seed(1);
        // Two far-apart particles, weights 0.25 and 0.75.
        let ps = [
            Particle { pose: Se2::new(0.0, 0.0, 0.0), weight: 0.25 },
            Particle { pose: Se2::new(10.0, 0.0, 0.0), weight: 0.75 },
        ];
        let limits = ResampleLimits { min: 400, max: 400, err: 0.05, z: 0.99, inject_probability: 0.0 };
        let out = resample(&ps, &limits, &mut rng, &mut |_| Se2::IDENTITY);
        assert_eq!(out.len(), 400);
        let far = out.iter().filter(|p| p.pose.x > 5.0).count();
        // Systematic: exactly 300 ± 1.
        assert!((299..=301).contains(&far), "{far}");
        assert!(out.iter().all(|p| (p.weight - 1.0 / 400.0).abs() < 1e-15));
    }

    #[test]
    fn kld_stops_early_for_a_concentrated_set_and_injection_happens() {
        let mut rng = Rng::seed(2);
        // Spread over two bins: the limit for k = 2 is 20, so we stop at min.
        let ps: Vec<Particle> = (0..1000)
            .map(|k| Particle { pose: Se2::new(if k % 2 == 0 { 0.1 } else { 0.6 }, 0.1, 0.0), weight: 1e-3 })
            .collect();
        let limits = ResampleLimits { min: 50, max: 1000, err: 0.05, z: 0.99, inject_probability: 0.0 };
        assert_eq!(resample(&ps, &limits, &mut rng, &mut |_| Se2::IDENTITY).len(), 50);
        // With injection probability 1 every particle is a random pose.
        let all = ResampleLimits { inject_probability: 1.0, ..limits };
        let out = resample(&ps, &all, &mut rng, &mut |r| Se2::new(100.0 + r.uniform(), 0.0, 0.0));
        assert!(out.iter().all(|p| p.pose.x >= 100.0));
    }

    #[test]
    fn heaviest_cluster_wins_and_its_covariance_is_computed() {
        let mut ps = Vec::new();
        // Cluster A: 4 particles around (0, 0) heading ±1°; cluster B: 2 heavier particles far away.
        for (x, t) in [(0.0, 1.0), (0.1, -1.0), (0.0, -1.0), (0.1, 1.0)] {
            ps.push(Particle { pose: Se2::from_degrees(x, 0.0, t), weight: 0.1 });
        }
        ps.push(Particle { pose: Se2::new(5.0, 5.0, 3.1), weight: 0.3 });
        ps.push(Particle { pose: Se2::new(5.1, 5.0, -3.1), weight: 0.3 });
        let e = cluster_estimate(&ps).unwrap();
        // B (0.6) beats A (0.4); its headings 3.1 and −3.1 average to π across the wrap.
        assert!((e.weight - 0.6).abs() < 1e-12);
        assert!((e.pose.x - 5.05).abs() < 1e-12 && (e.pose.y - 5.0).abs() < 1e-12);
        assert!((e.pose.theta.abs() - std::f64::consts::PI).abs() < 1e-9, "{}", e.pose.theta);
        assert!((e.covariance[0][0] - 0.0025).abs() < 1e-12, "{:?}", e.covariance);
        assert!(e.covariance[1][1].abs() < 1e-12);
        let r = 3.1f64.cos().abs();
        assert!((e.covariance[2][2] - (-2.0 * r.ln())).abs() < 1e-9);
    }
}
