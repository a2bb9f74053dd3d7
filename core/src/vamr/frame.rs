//! Synchronisation and the virtual frame (paper §4.4, Eq. 14–18; docs/method.md §6).

use crate::se2::Se2;

/// One robot's scan packet times: the scan's stamp and when the server received it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PacketTimes {
    pub stamp_s: f64,
    pub received_s: f64,
}

/// Why a set of packets is not fused.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum SyncFailure {
    /// `max t_i − min t_i` exceeds `Δt_sync,max`.
    Spread { spread_s: f64 },
    /// Robot `robot`'s packet is older than `τ_age,max` on arrival (or arrived before it was stamped).
    Age { robot: usize, age_s: f64 },
    /// Fewer than two packets.
    TooFew,
}

/// Eq. 15: `max t_i − min t_i ≤ Δt_sync,max` and `max (t_rx,i − t_i) ≤ τ_age,max`. A packet stamped
/// after its reception (clocks disagree) fails the age test too: its age cannot be trusted.
pub fn sync_gate(packets: &[PacketTimes], max_spread_s: f64, max_age_s: f64) -> Result<(), SyncFailure> {
    if packets.len() < 2 {
        return Err(SyncFailure::TooFew);
    }
    let (lo, hi) = packets
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| (lo.min(p.stamp_s), hi.max(p.stamp_s)));
    // Written so that a NaN stamp fails the gate.
    let within = (hi - lo).partial_cmp(&max_spread_s).is_some_and(|o| o.is_le());
    if !within {
        return Err(SyncFailure::Spread { spread_s: hi - lo });
    }
    for (robot, p) in packets.iter().enumerate() {
        let age_s = p.received_s - p.stamp_s;
        if !(0.0..=max_age_s).contains(&age_s) {
            return Err(SyncFailure::Age { robot, age_s });
        }
    }
    Ok(())
}

/// Eq. 16, for N robots: V in the reference robot's base frame, as the weighted centroid of the
/// robot centres and the weighted circular mean of their headings. `relative[i]` is
/// `T_{B_i}^{B_ref}` (the reference itself is the identity) with weight `w_i > 0`.
/// With two robots this is exactly Eq. 16: `x_V = w_B·x_AB/(w_A+w_B)`,
/// `ψ_V = atan2(w_B sin θ_AB, w_A + w_B cos θ_AB)`.
#[must_use]
pub fn virtual_frame(relative: &[(Se2, f64)]) -> Se2 {
    let w: f64 = relative.iter().map(|(_, w)| w).sum();
    if relative.is_empty() || w <= 0.0 {
        return Se2::IDENTITY;
    }
    let x = relative.iter().map(|(t, wi)| wi * t.x).sum::<f64>() / w;
    let y = relative.iter().map(|(t, wi)| wi * t.y).sum::<f64>() / w;
    let s = relative.iter().map(|(t, wi)| wi * t.theta.sin()).sum::<f64>();
    let c = relative.iter().map(|(t, wi)| wi * t.theta.cos()).sum::<f64>();
    Se2::new(x, y, s.atan2(c))
}

/// `T_{B_i}^V = (T_V^{B_ref})⁻¹ · T_{B_i}^{B_ref}` for every robot; Eq. 17–18 follow by composing with
/// each robot's `T_{L_i}^{B_i}`.
#[must_use]
pub fn robots_in_virtual(v_in_ref: &Se2, relative: &[(Se2, f64)]) -> Vec<Se2> {
    let inv = v_in_ref.inverse();
    relative.iter().map(|(t, _)| inv * *t).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn eq_15_by_hand() {
        let p = |stamp_s, received_s| PacketTimes { stamp_s, received_s };
        assert_eq!(sync_gate(&[p(1.00, 1.05), p(1.04, 1.06)], 0.05, 0.1), Ok(()));
        assert_eq!(
            sync_gate(&[p(1.00, 1.05), p(1.06, 1.07)], 0.05, 0.1)
                .map_err(|e| matches!(e, SyncFailure::Spread { .. })),
            Err(true)
        );
        assert_eq!(
            sync_gate(&[p(1.00, 1.15), p(1.01, 1.02)], 0.05, 0.1)
                .map_err(|e| matches!(e, SyncFailure::Age { robot: 0, .. })),
            Err(true)
        );
        assert_eq!(
            sync_gate(&[p(1.00, 0.99), p(1.00, 1.01)], 0.05, 0.1)
                .map_err(|e| matches!(e, SyncFailure::Age { robot: 0, .. })),
            Err(true)
        );
        assert_eq!(sync_gate(&[p(1.0, 1.0)], 0.05, 0.1), Err(SyncFailure::TooFew));
        assert!(sync_gate(&[p(f64::NAN, 1.0), p(1.0, 1.0)], 0.05, 0.1).is_err(), "NaN stamps never pass");
    }

    #[test]
    fn eq_16_two_robots_by_hand() {
        // B is 0.9 m to A's right, turned 10°; equal weights → V at the midpoint, 5°.
        let ab = Se2::from_degrees(0.0, -0.9, 10.0);
        let v = virtual_frame(&[(Se2::IDENTITY, 1.0), (ab, 1.0)]);
        assert!(v.approx_eq(&Se2::from_degrees(0.0, -0.45, 5.0), 1e-12, 1e-12), "{v:?}");
        // Weights 1 and 3: x_V = 3/4 of the way; ψ_V = atan2(3 sin 10°, 1 + 3 cos 10°).
        let v = virtual_frame(&[(Se2::IDENTITY, 1.0), (ab, 3.0)]);
        let psi = (3.0 * 10f64.to_radians().sin()).atan2(1.0 + 3.0 * 10f64.to_radians().cos());
        assert!(v.approx_eq(&Se2::new(0.0, -0.675, psi), 1e-12, 1e-12));
        // T_{B_i}^V: A sits at +0.45 m lateral in V, B at -0.45 m, both turned ∓5°.
        let in_v = robots_in_virtual(
            &virtual_frame(&[(Se2::IDENTITY, 1.0), (ab, 1.0)]),
            &[(Se2::IDENTITY, 1.0), (ab, 1.0)],
        );
        assert!(
            (in_v[0].theta.to_degrees() + 5.0).abs() < 1e-9
                && (in_v[1].theta.to_degrees() - 5.0).abs() < 1e-9
        );
        let d = (in_v[0].x - in_v[1].x).hypot(in_v[0].y - in_v[1].y);
        assert!((d - 0.9).abs() < 1e-12);
        assert!(
            (in_v[0].x + in_v[1].x).abs() < 1e-12 && (in_v[0].y + in_v[1].y).abs() < 1e-12,
            "V is the midpoint"
        );
    }

    #[test]
    fn three_robots_centroid_and_circular_mean() {
        let rel = [
            (Se2::IDENTITY, 1.0),
            (Se2::from_degrees(0.0, -0.9, 179.0), 1.0),
            (Se2::from_degrees(0.0, 0.9, -179.0), 1.0),
        ];
        let v = virtual_frame(&rel);
        assert!(v.x.abs() < 1e-12 && v.y.abs() < 1e-12);
        // The circular mean of 0°, 179°, -179° is 180° (the arithmetic mean would say 0°).
        assert!((v.theta.abs() - std::f64::consts::PI).abs() < 1e-12, "{}", v.theta);
    }
}
