//! Exact Euclidean distance transform in linear time (Felzenszwalb & Huttenlocher, "Distance
//! Transforms of Sampled Functions", 2012): a 1D lower envelope of parabolas per column, then per row.

/// Squared distance, in cells², from every cell to the nearest `seed` cell (`INFINITY` if none).
/// `seed` is row-major with `width` columns.
#[must_use]
pub fn distance_transform_sq(seed: &[bool], width: usize, height: usize) -> Vec<f64> {
    let mut f: Vec<f64> = seed.iter().map(|&s| if s { 0.0 } else { f64::INFINITY }).collect();
    let n = width.max(height);
    let (mut v, mut z, mut buf, mut out) = (vec![0usize; n], vec![0.0; n + 1], vec![0.0; n], vec![0.0; n]);
    // Columns.
    for i in 0..width {
        for j in 0..height {
            buf[j] = f[j * width + i];
        }
        lower_envelope(&buf[..height], &mut out[..height], &mut v, &mut z);
        for j in 0..height {
            f[j * width + i] = out[j];
        }
    }
    // Rows.
    for j in 0..height {
        let row = &mut f[j * width..(j + 1) * width];
        buf[..width].copy_from_slice(row);
        lower_envelope(&buf[..width], &mut out[..width], &mut v, &mut z);
        row.copy_from_slice(&out[..width]);
    }
    f
}

/// `d(q) = min_p ((q − p)² + f(p))` over one line.
fn lower_envelope(f: &[f64], d: &mut [f64], v: &mut [usize], z: &mut [f64]) {
    let n = f.len();
    // Start at the first finite sample; an all-infinite line stays infinite.
    let Some(first) = f.iter().position(|x| x.is_finite()) else {
        d.fill(f64::INFINITY);
        return;
    };
    let mut k = 0;
    v[0] = first;
    z[0] = f64::NEG_INFINITY;
    z[1] = f64::INFINITY;
    let sq = |x: usize| (x * x) as f64;
    for q in first + 1..n {
        if !f[q].is_finite() {
            continue;
        }
        loop {
            let p = v[k];
            let s = ((f[q] + sq(q)) - (f[p] + sq(p))) / (2.0 * (q as f64 - p as f64));
            if s <= z[k] && k > 0 {
                k -= 1;
            } else {
                k += 1;
                v[k] = q;
                z[k] = s;
                z[k + 1] = f64::INFINITY;
                break;
            }
        }
    }
    let mut k = 0;
    for (q, dq) in d.iter_mut().enumerate() {
        while z[k + 1] < q as f64 {
            k += 1;
        }
        let p = v[k];
        let dx = q as f64 - p as f64;
        *dq = dx * dx + f[p];
    }
}

/// Distance in metres from every cell centre to the nearest occupied cell centre.
#[must_use]
pub fn euclidean_distance_m(seed: &[bool], width: usize, height: usize, resolution_m: f64) -> Vec<f64> {
    distance_transform_sq(seed, width, height).into_iter().map(|d2| d2.sqrt() * resolution_m).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn brute(seed: &[bool], w: usize, h: usize) -> Vec<f64> {
        (0..w * h)
            .map(|c| {
                let (ci, cj) = ((c % w) as f64, (c / w) as f64);
                seed.iter()
                    .enumerate()
                    .filter(|(_, s)| **s)
                    .map(|(k, _)| {
                        let (ki, kj) = ((k % w) as f64, (k / w) as f64);
                        (ci - ki).powi(2) + (cj - kj).powi(2)
                    })
                    .fold(f64::INFINITY, f64::min)
            })
            .collect()
    }

    #[test]
    fn by_hand() {
        // One seed in the middle of a 5×3 grid.
        let mut seed = vec![false; 15];
        seed[7] = true;
        let d = distance_transform_sq(&seed, 5, 3);
        assert_eq!(d, vec![5.0, 2.0, 1.0, 2.0, 5.0, 4.0, 1.0, 0.0, 1.0, 4.0, 5.0, 2.0, 1.0, 2.0, 5.0]);
        assert!(distance_transform_sq(&[false; 6], 3, 2).iter().all(|x| x.is_infinite()));
    }

    proptest! {
        #[test]
        fn equals_brute_force(w in 1usize..24, h in 1usize..24, density in 0.0..0.3f64, seed_bits in prop::collection::vec(any::<u16>(), 576)) {
            let seed: Vec<bool> = (0..w * h).map(|k| f64::from(seed_bits[k]) / 65536.0 < density).collect();
            prop_assert_eq!(distance_transform_sq(&seed, w, h), brute(&seed, w, h));
        }
    }
}
