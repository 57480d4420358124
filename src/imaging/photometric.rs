//! Photometric compensation: a per-channel gain and offset that maps a view's colours
//! onto the keyframe's, fitted robustly on pixels both see (pure layer).
//!
//! The pixels a fit sees are never all of the same surface: a ring around a hole holds
//! bits of the occluder's halo, the view may have its own tree there. So the fit starts
//! from quantiles (robust to a quarter of outliers) and refines by iteratively reweighted
//! moment matching with Tukey's biweight, whose weight is zero for gross outliers.

/// `key ≈ gain · view + offset`, per channel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Gain {
    pub gain: [f32; 3],
    pub offset: [f32; 3],
}

impl Default for Gain {
    fn default() -> Self {
        Self::IDENTITY
    }
}

impl Gain {
    /// No change.
    pub const IDENTITY: Self = Self { gain: [1.0; 3], offset: [0.0; 3] };

    /// The view's colour `p` as the keyframe would have seen it.
    #[inline]
    pub fn apply(&self, p: [f32; 3]) -> [f32; 3] {
        [
            self.gain[0] * p[0] + self.offset[0],
            self.gain[1] * p[1] + self.offset[1],
            self.gain[2] * p[2] + self.offset[2],
        ]
    }
}

/// Parameters of [`fit_gain`].
#[derive(Debug, Clone, PartialEq)]
pub struct GainParams {
    /// Fewer sample pairs than this and the fit returns [`Gain::IDENTITY`].
    pub min_samples: usize,
    /// Gains are clamped to `1/max_gain ..= max_gain` (a wilder value is a bad fit).
    pub max_gain: f32,
    /// IRLS iterations.
    pub iterations: usize,
    /// Tukey's constant in robust standard deviations (4.685 is the usual 95 % efficiency).
    pub tukey_c: f32,
}

impl Default for GainParams {
    fn default() -> Self {
        Self { min_samples: 30, max_gain: 4.0, iterations: 10, tukey_c: 4.685 }
    }
}

/// Fits `key ≈ gain · view + offset` per channel on `(view, key)` colour pairs, robustly.
pub fn fit_gain(pairs: &[([f32; 3], [f32; 3])], params: &GainParams) -> Gain {
    if pairs.len() < params.min_samples.max(3) {
        return Gain::IDENTITY;
    }
    let mut out = Gain::IDENTITY;
    let mut xs = Vec::with_capacity(pairs.len());
    let mut ys = Vec::with_capacity(pairs.len());
    for c in 0..3 {
        xs.clear();
        ys.clear();
        xs.extend(pairs.iter().map(|p| p.0[c]));
        ys.extend(pairs.iter().map(|p| p.1[c]));
        let (g, b) = fit_line(&xs, &ys, params);
        out.gain[c] = g;
        out.offset[c] = b;
    }
    out
}

/// `q`-quantile (0..=1) of `v` (reorders a copy).
fn quantile(v: &[f32], q: f32) -> f32 {
    let mut s = v.to_vec();
    let k = ((s.len() - 1) as f32 * q).round() as usize;
    let (_, m, _) = s.select_nth_unstable_by(k, f32::total_cmp);
    *m
}

/// Robust `y ≈ g·x + b`: quantile start, then Tukey-weighted moment matching.
fn fit_line(x: &[f32], y: &[f32], params: &GainParams) -> (f32, f32) {
    let (lo, hi) = (1.0 / params.max_gain, params.max_gain);
    let spread_x = quantile(x, 0.75) - quantile(x, 0.25);
    let spread_y = quantile(y, 0.75) - quantile(y, 0.25);
    let mut g = if spread_x > 1e-4 { (spread_y / spread_x).clamp(lo, hi) } else { 1.0 };
    let mut b = quantile(y, 0.5) - g * quantile(x, 0.5);
    let mut r = vec![0.0f32; x.len()];
    for _ in 0..params.iterations {
        for i in 0..x.len() {
            r[i] = (y[i] - g * x[i] - b).abs();
        }
        let mad = quantile(&r, 0.5);
        let scale = (1.4826 * mad).max(1e-3) * params.tukey_c;
        let (mut sw, mut sx, mut sy, mut sxx, mut syy) = (0.0f64, 0.0f64, 0.0f64, 0.0f64, 0.0f64);
        for i in 0..x.len() {
            let u = r[i] / scale;
            if u >= 1.0 {
                continue;
            }
            let w = ((1.0 - u * u) * (1.0 - u * u)) as f64;
            let (xi, yi) = (x[i] as f64, y[i] as f64);
            sw += w;
            sx += w * xi;
            sy += w * yi;
            sxx += w * xi * xi;
            syy += w * yi * yi;
        }
        if sw < 3.0 {
            break;
        }
        let var_x = sxx - sx * sx / sw;
        let var_y = syy - sy * sy / sw;
        // Moments, not a regression: pairs that are slightly misregistered correlate
        // weakly, and a regression slope would shrink towards zero (attenuation), while the
        // spread of a texture is the same in both images.
        let (ng, nb) = if var_x > 1e-9 * sw {
            let ng = ((var_y / var_x).sqrt() as f32).clamp(lo, hi);
            (ng, ((sy - ng as f64 * sx) / sw) as f32)
        } else {
            // No spread in the view's values: only an offset can be known.
            (1.0, ((sy - sx) / sw) as f32)
        };
        let done = (ng - g).abs() < 1e-5 && (nb - b).abs() < 1e-5;
        g = ng;
        b = nb;
        if done {
            break;
        }
    }
    (g, b)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn recovers_a_known_gain_and_offset_despite_outliers() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let truth = Gain { gain: [0.8, 1.25, 1.0], offset: [0.05, -0.1, 0.02] };
        let pairs: Vec<_> = (0..2000)
            .map(|i| {
                let v: [f32; 3] = std::array::from_fn(|_| rng.random_range(0.1..0.7));
                let mut k = truth.apply(v).map(|c| c + rng.random_range(-0.01..0.01));
                if i % 10 < 3 {
                    // 30 % of the pairs see a tree in the view: dark green, unrelated.
                    k = [rng.random_range(0.0..1.0), rng.random_range(0.0..1.0), rng.random_range(0.0..1.0)];
                }
                (v, k)
            })
            .collect();
        let fit = fit_gain(&pairs, &GainParams::default());
        for c in 0..3 {
            assert!((fit.gain[c] - truth.gain[c]).abs() < 0.02, "gain {c}: {fit:?}");
            assert!((fit.offset[c] - truth.offset[c]).abs() < 0.01, "offset {c}: {fit:?}");
        }
        // A plain least-squares fit would not: the outliers drag it off.
        let n = pairs.len() as f64;
        let (sx, sy) = pairs.iter().fold((0.0, 0.0), |a, p| (a.0 + p.0[0] as f64, a.1 + p.1[0] as f64));
        let (mx, my) = (sx / n, sy / n);
        let (sxy, sxx) = pairs.iter().fold((0.0, 0.0), |a, p| {
            let (dx, dy) = (p.0[0] as f64 - mx, p.1[0] as f64 - my);
            (a.0 + dx * dy, a.1 + dx * dx)
        });
        assert!((sxy / sxx - 0.8).abs() > 0.1, "the test's outliers should matter to least squares");
    }

    #[test]
    fn too_few_samples_or_flat_views_are_safe() {
        assert_eq!(fit_gain(&[([0.5; 3], [0.6; 3]); 5], &GainParams::default()), Gain::IDENTITY);
        let flat = vec![([0.5; 3], [0.6; 3]); 100];
        let g = fit_gain(&flat, &GainParams::default());
        assert!((g.apply([0.5; 3])[1] - 0.6).abs() < 1e-4, "{g:?}");
    }
}
