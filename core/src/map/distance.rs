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

/// The distance (m) from every cell centre to the nearest `seed` cell centre, capped at `cap_m` and
/// quantised to a byte: `round(min(d, cap_m) / (cap_m / 255))`. Exact like
/// [`euclidean_distance_m`] up to the cap, but it works through the grid in bands of rows (with a
/// halo of `cap_m` above and below), so that beside its output it holds only one band: about 10 MB
/// for a 4 000-cell-wide map, where the full transform holds 8 bytes per cell (384 MB for a
/// 200 m × 600 m map at 0.05 m).
#[must_use]
pub fn capped_distance_q(
    seed: &[bool],
    width: usize,
    height: usize,
    resolution_m: f64,
    cap_m: f64,
) -> Vec<u8> {
    const BAND: usize = 512;
    let mut out = vec![u8::MAX; width * height];
    if width == 0 || height == 0 || seed.len() < width * height || cap_m.is_nan() || cap_m <= 0.0 {
        return out;
    }
    let halo = (cap_m / resolution_m).ceil() as usize + 1;
    let far = (halo + 1) as u32;
    let step = cap_m / f64::from(u8::MAX);
    let mut g: Vec<u32> = Vec::new();
    let (mut f, mut d) = (vec![0.0; width], vec![0.0; width]);
    let (mut v, mut z) = (vec![0usize; width], vec![0.0; width + 1]);
    let mut b0 = 0;
    while b0 < height {
        let b1 = (b0 + BAND).min(height);
        let (r0, r1) = (b0.saturating_sub(halo), (b1 + halo).min(height));
        let rows = r1 - r0;
        // Column pass: the distance in cells to the nearest seed in the same column (capped).
        g.clear();
        g.resize(rows * width, far);
        for i in 0..width {
            let mut last: Option<usize> = None;
            for r in 0..rows {
                if seed[(r0 + r) * width + i] {
                    last = Some(r);
                }
                if let Some(l) = last {
                    g[r * width + i] = ((r - l) as u32).min(far);
                }
            }
            let mut next: Option<usize> = None;
            for r in (0..rows).rev() {
                if seed[(r0 + r) * width + i] {
                    next = Some(r);
                }
                if let Some(n) = next {
                    let k = r * width + i;
                    g[k] = g[k].min(((n - r) as u32).min(far));
                }
            }
        }
        // Row pass over the band's own rows: the lower envelope of the column distances squared.
        for row in b0..b1 {
            let r = row - r0;
            for (fi, gi) in f.iter_mut().zip(&g[r * width..(r + 1) * width]) {
                *fi = if *gi >= far { f64::INFINITY } else { f64::from(*gi).powi(2) };
            }
            lower_envelope(&f, &mut d, &mut v, &mut z);
            for (o, d2) in out[row * width..(row + 1) * width].iter_mut().zip(&d) {
                let m = (d2.sqrt() * resolution_m).min(cap_m);
                *o = if m.is_finite() { (m / step).round() as u8 } else { u8::MAX };
            }
        }
        b0 = b1;
    }
    out
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

    proptest! {
        /// The banded, capped transform agrees with the full one (to within a quantisation step),
        /// also across band borders (bands of 512 rows; these grids are up to 1 100 rows).
        #[test]
        fn capped_equals_full(w in 1usize..40, h in 1usize..1100, cap_cells in 1usize..30, seeds in proptest::collection::vec((0usize..40, 0usize..1100), 0..60)) {
            let mut seed = vec![false; w * h];
            for (i, j) in seeds {
                if i < w && j < h {
                    seed[j * w + i] = true;
                }
            }
            let res = 0.05;
            let cap = cap_cells as f64 * res;
            let full = euclidean_distance_m(&seed, w, h, res);
            let q = capped_distance_q(&seed, w, h, res, cap);
            let step = cap / 255.0;
            for k in 0..w * h {
                let expect = full[k].min(cap);
                let got = f64::from(q[k]) * step;
                prop_assert!((got - expect).abs() <= step / 2.0 + 1e-9, "cell {k}: {got} vs {expect}");
            }
        }
    }

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
