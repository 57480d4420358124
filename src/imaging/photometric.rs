//! Photometric compensation: a per-channel gain and offset that maps a view's colours
//! onto the keyframe's, fitted robustly on pixels both see (pure layer).
//!
//! The pixels a fit sees are never all of the same surface: a ring around a hole holds
//! bits of the occluder's halo, the view may have its own tree there. So the fit starts
//! from quantiles (robust to a quarter of outliers) and refines by iteratively reweighted
//! moment matching with Tukey's biweight, whose weight is zero for gross outliers.
//!
//! A line cannot follow a camera that answers the light with a curve (a view much darker
//! than the keyframe, whose highlights the keyframe clips): [`fit_tone`] fits a monotone
//! tone curve on the whole overlap of view and keyframe, and keeps it only where it
//! explains clearly more of the pairs than the line.

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
    /// A channel whose weighted pairs correlate less than this keeps gain 1 and offset 0:
    /// the pairs are not one surface under two exposures but two different things (a
    /// view's own occluder over the ring, a flat car body against a textured wall), and
    /// the spread-matching gain of such pairs is arbitrary (it ran to the bound, 4, with an
    /// offset of −1.9, and amplified a frame's noise fourfold into the hole).
    pub min_correlation: f32,
}

impl Default for GainParams {
    fn default() -> Self {
        Self { min_samples: 30, max_gain: 4.0, iterations: 10, tukey_c: 4.685, min_correlation: 0.3 }
    }
}

/// Fits `key ≈ gain · view + offset` per channel on `(view, key)` colour pairs, robustly.
/// A channel whose pairs do not correlate ([`GainParams::min_correlation`]) is left as it
/// is: nothing in them tells the view's light.
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
    // Whether the pairs the last iteration weighed correlate at least `min_correlation`
    // (pairs with no spread on the view's side count as related: only their offset is fitted).
    let mut related = true;
    for _ in 0..params.iterations {
        for i in 0..x.len() {
            r[i] = (y[i] - g * x[i] - b).abs();
        }
        let mad = quantile(&r, 0.5);
        let scale = (1.4826 * mad).max(1e-3) * params.tukey_c;
        let (mut sw, mut sx, mut sy, mut sxx, mut syy, mut sxy) =
            (0.0f64, 0.0f64, 0.0f64, 0.0f64, 0.0f64, 0.0f64);
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
            sxy += w * xi * yi;
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
            let cov = sxy - sx * sy / sw;
            related = var_y <= 1e-9 * sw || cov >= f64::from(params.min_correlation) * (var_x * var_y).sqrt();
            let ng = ((var_y / var_x).sqrt() as f32).clamp(lo, hi);
            (ng, ((sy - ng as f64 * sx) / sw) as f32)
        } else {
            // No spread in the view's values: only an offset can be known.
            related = true;
            (1.0, ((sy - sx) / sw) as f32)
        };
        let done = (ng - g).abs() < 1e-5 && (nb - b).abs() < 1e-5;
        g = ng;
        b = nb;
        if done {
            break;
        }
    }
    if related { (g, b) } else { (1.0, 0.0) }
}

/// A monotone tone curve per channel: `key ≈ curve(view)`, piecewise linear between knots
/// (view value, key value), extended beyond the end knots along the end segments. It
/// follows a camera response that a line cannot (a view much darker than the keyframe,
/// whose highlights the keyframe clips).
#[derive(Debug, Clone, PartialEq)]
pub struct ToneCurve {
    /// Per channel, knots with strictly increasing view values and non-decreasing key values.
    pub knots: [Vec<(f32, f32)>; 3],
}

impl ToneCurve {
    /// The view's colour `p` as the keyframe would have seen it.
    #[inline]
    pub fn apply(&self, p: [f32; 3]) -> [f32; 3] {
        std::array::from_fn(|c| eval(&self.knots[c], p[c]))
    }
}

/// The piecewise-linear curve through `knots` (at least two) at `x`; beyond the end knots
/// along the end segment, its slope at most [`MAX_END_SLOPE`] (two end knots close together
/// must not send the view's darkest or brightest values far off).
fn eval(knots: &[(f32, f32)], x: f32) -> f32 {
    let k = knots.partition_point(|&(kx, _)| kx <= x).clamp(1, knots.len() - 1);
    let ((x0, y0), (x1, y1)) = (knots[k - 1], knots[k]);
    let slope = (y1 - y0) / (x1 - x0);
    if x > x1 {
        y1 + (x - x1) * slope.min(MAX_END_SLOPE)
    } else if x < x0 {
        y0 + (x - x0) * slope.min(MAX_END_SLOPE)
    } else {
        y0 + (x - x0) * slope
    }
}

/// The steepest a tone curve is extended beyond its end knots (the gain's own bound).
const MAX_END_SLOPE: f32 = 4.0;

/// Parameters of [`fit_tone`].
#[derive(Debug, Clone, PartialEq)]
pub struct ToneParams {
    /// Knots of the curve (equal-count bins of the view's values).
    pub bins: usize,
    /// Fewer pairs per bin than this and there is no curve.
    pub min_per_bin: usize,
    /// A pair is explained by a model when its residual is below this (0..=1 units), on
    /// every channel.
    pub tolerance: f32,
    /// The curve is taken only when it explains at least this share of all pairs more than
    /// the line does (an occluder's pairs scatter: bent towards them, a curve explains few
    /// of them and loses the building's pairs there)...
    pub min_gain: f32,
    /// ...and at least this many times the pairs the line leaves unexplained are explained
    /// by the curve (a share of those).
    pub min_recovered: f32,
    /// Rounds of matching again on the pairs the curve explains.
    pub trim_rounds: usize,
}

impl Default for ToneParams {
    fn default() -> Self {
        Self {
            bins: 32,
            min_per_bin: 40,
            tolerance: 8.0 / 255.0,
            min_gain: 0.1,
            min_recovered: 0.3,
            trim_rounds: 2,
        }
    }
}

/// What [`fit_tone`] found: the curve when it explains the pairs clearly better than the
/// robust line, the line, and the shares of pairs each explains.
#[derive(Debug, Clone, PartialEq)]
pub struct ToneFit {
    pub curve: Option<ToneCurve>,
    /// The robust line ([`fit_gain`], default parameters) the curve was weighed against:
    /// what to use where there is no curve.
    pub line: Gain,
    /// Share of the pairs the line explains (all channels within the tolerance).
    pub line_share: f32,
    /// The same for the curve.
    pub curve_share: f32,
}

/// Fits a monotone tone curve per channel on `(view, key)` colour pairs taken over the
/// whole overlap of a view and the keyframe (where the view's own occluders are a small
/// share), and keeps it only when it explains the pairs better than the robust line
/// ([`fit_gain`]) by a margin ([`ToneParams::min_gain`], [`ToneParams::min_recovered`]):
/// on an exposure that is linear the line stays.
///
/// The curve matches the view's quantiles to the keyframe's (the spread of a texture is
/// the same in both images, so unlike a regression of key on view it is not flattened by
/// misregistration), then again on the pairs it explains within three robust standard
/// deviations ([`ToneParams::trim_rounds`]), so that a view's occluder does not shift the
/// quantiles; equal view values are merged and the knots made non-decreasing.
pub fn fit_tone(pairs: &[([f32; 3], [f32; 3])], params: &ToneParams) -> ToneFit {
    let line = fit_gain(pairs, &GainParams::default());
    let none = ToneFit { curve: None, line, line_share: 0.0, curve_share: 0.0 };
    let bins = params.bins.min(pairs.len() / params.min_per_bin.max(1));
    if bins < 4 {
        return none;
    }
    let Some(mut curve) = quantile_curve(pairs, bins) else { return none };
    // Trimmed: matched again on the pairs the curve explains within a band (three robust
    // standard deviations of its residuals, at least twice the tolerance), so that pairs
    // of an occluder no longer shift the quantiles.
    for _ in 0..params.trim_rounds {
        let worst: Vec<f32> = pairs
            .iter()
            .map(|&(v, k)| {
                let t = curve.apply(v);
                (0..3).map(|c| (t[c] - k[c]).abs()).fold(0.0, f32::max)
            })
            .collect();
        let band = (3.0 * 1.4826 * quantile(&worst, 0.5)).max(2.0 * params.tolerance);
        let kept: Vec<_> = pairs.iter().zip(&worst).filter(|&(_, &r)| r < band).map(|(p, _)| *p).collect();
        if kept.len() * 2 < pairs.len() {
            break;
        }
        match quantile_curve(&kept, bins) {
            Some(c) => curve = c,
            None => break,
        }
    }
    let (mut line_ok, mut curve_ok) = (0usize, 0usize);
    for &(v, k) in pairs {
        let (l, t) = (line.apply(v), curve.apply(v));
        line_ok += usize::from((0..3).all(|c| (l[c] - k[c]).abs() < params.tolerance));
        curve_ok += usize::from((0..3).all(|c| (t[c] - k[c]).abs() < params.tolerance));
    }
    let n = pairs.len() as f32;
    let (line_share, curve_share) = (line_ok as f32 / n, curve_ok as f32 / n);
    let gain = curve_share - line_share;
    let better = gain >= params.min_gain && gain >= params.min_recovered * (1.0 - line_share);
    ToneFit { curve: better.then_some(curve), line, line_share, curve_share }
}

/// Per channel, the view's quantiles matched to the keyframe's (`bins + 1` knots from the
/// 1st to the 99th percentile; equal view values merged), made non-decreasing.
fn quantile_curve(pairs: &[([f32; 3], [f32; 3])], bins: usize) -> Option<ToneCurve> {
    let mut knots: [Vec<(f32, f32)>; 3] = Default::default();
    let n = pairs.len();
    if n == 0 {
        return None;
    }
    // The ranks of the quantiles: those of the values sorted.
    let ranks: Vec<usize> = (0..=bins)
        .map(|b| {
            let q = 0.01 + 0.98 * b as f32 / bins as f32;
            ((n - 1) as f32 * q).round() as usize
        })
        .collect();
    for (c, out) in knots.iter_mut().enumerate() {
        let mut xs: Vec<f32> = pairs.iter().map(|p| p.0[c]).collect();
        let mut ys: Vec<f32> = pairs.iter().map(|p| p.1[c]).collect();
        select_ranks(&mut xs, &ranks);
        select_ranks(&mut ys, &ranks);
        // (view value, key value, weight) per quantile.
        let mut pts: Vec<(f32, f32, f32)> = Vec::with_capacity(bins + 1);
        for &i in &ranks {
            let (x, y) = (xs[i], ys[i]);
            match pts.last_mut() {
                Some(last) if x - last.0 < 1e-4 => {
                    last.1 = (last.1 * last.2 + y) / (last.2 + 1.0);
                    last.2 += 1.0;
                }
                _ => pts.push((x, y, 1.0)),
            }
        }
        if pts.len() < 2 {
            return None;
        }
        *out = monotone(&pts);
    }
    Some(ToneCurve { knots })
}

/// Puts at each of `ranks` (non-decreasing, each below `v.len()`) the value a sort of `v`
/// (by [`f32::total_cmp`]) puts there: a selection splits `v` at the middle rank, and each
/// side takes the ranks that fall in it, so that `v` is never wholly sorted.
fn select_ranks(v: &mut [f32], ranks: &[usize]) {
    let Some(&mid) = ranks.get(ranks.len() / 2) else { return };
    let (below, _, above) = v.select_nth_unstable_by(mid, f32::total_cmp);
    let (lo, hi) = ranks.split_at(ranks.len() / 2);
    let lo: Vec<usize> = lo.iter().copied().filter(|&r| r < mid).collect();
    let hi: Vec<usize> = hi.iter().filter(|&&r| r > mid).map(|&r| r - mid - 1).collect();
    select_ranks(below, &lo);
    select_ranks(above, &hi);
}

/// Pool-adjacent-violators: the non-decreasing sequence closest (weighted least squares)
/// to the points' key values, as knots.
fn monotone(pts: &[(f32, f32, f32)]) -> Vec<(f32, f32)> {
    // Blocks of (sum of weight·y, sum of weight, number of points).
    let mut blocks: Vec<(f64, f64, usize)> = Vec::with_capacity(pts.len());
    for &(_, y, w) in pts {
        blocks.push((y as f64 * w as f64, w as f64, 1));
        while blocks.len() >= 2 {
            let (b, a) = (blocks[blocks.len() - 1], blocks[blocks.len() - 2]);
            if a.0 / a.1 <= b.0 / b.1 {
                break;
            }
            blocks.pop();
            *blocks.last_mut().expect("two blocks") = (a.0 + b.0, a.1 + b.1, a.2 + b.2);
        }
    }
    let mut out = Vec::with_capacity(pts.len());
    let mut i = 0;
    for (sy, sw, n) in blocks {
        for p in &pts[i..i + n] {
            out.push((p.0, (sy / sw) as f32));
        }
        i += n;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// The values a selection puts at the ranks are the sorted values there, with ties,
    /// repeated ranks and the ends.
    #[test]
    fn the_ranks_selected_hold_the_sorted_values() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for n in [1usize, 2, 7, 100, 5000] {
            let v: Vec<f32> = (0..n).map(|_| (rng.random::<f32>() * 50.0).round() / 50.0).collect();
            let mut sorted = v.clone();
            sorted.sort_unstable_by(f32::total_cmp);
            let mut ranks: Vec<usize> = (0..40).map(|_| rng.random_range(0..n)).chain([0, n - 1]).collect();
            ranks.sort_unstable();
            let mut got = v.clone();
            select_ranks(&mut got, &ranks);
            for &r in &ranks {
                assert_eq!(got[r].to_bits(), sorted[r].to_bits(), "rank {r} of {n}");
            }
        }
    }

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

    /// A dark view of a bright keyframe whose highlights clip (leuven's light): the curve
    /// is taken and follows the response where the robust line misses it by far.
    #[test]
    fn a_camera_response_gets_a_curve() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let response = |v: f32| (1.6 * v.powf(0.6)).min(1.0);
        let pairs: Vec<_> = (0..20_000)
            .map(|i| {
                let v: [f32; 3] = std::array::from_fn(|_| rng.random_range(0.02..0.6f32));
                let mut k = v.map(|c| response(c) + rng.random_range(-0.01..0.01));
                if i % 10 == 0 {
                    // A tenth of the pairs show the view's own occluder.
                    k = [rng.random_range(0.0..1.0), rng.random_range(0.0..1.0), rng.random_range(0.0..1.0)];
                }
                (v, k)
            })
            .collect();
        let fit = fit_tone(&pairs, &ToneParams::default());
        assert!(fit.curve_share > fit.line_share + 0.3, "{fit:?}");
        let curve = fit.curve.expect("a curve");
        let line = fit_gain(&pairs, &GainParams::default());
        let (mut worst_curve, mut worst_line) = (0.0f32, 0.0f32);
        for v in [0.05, 0.1, 0.2, 0.3, 0.4, 0.5] {
            worst_curve = worst_curve.max((curve.apply([v; 3])[0] - response(v)).abs());
            worst_line = worst_line.max((line.apply([v; 3])[0] - response(v)).abs());
        }
        assert!(worst_curve < 0.02 && worst_line > 0.06, "curve {worst_curve}, line {worst_line}");
        // Monotone.
        for c in 0..3 {
            assert!(curve.knots[c].windows(2).all(|w| w[0].0 < w[1].0 && w[0].1 <= w[1].1));
        }
    }

    /// A linear exposure with a quarter of the pairs on the view's occluder: one dark value
    /// of the view against the whole range of the keyframe's wall. A curve bends towards
    /// that cluster, but explains fewer pairs than the line: no curve.
    #[test]
    fn an_occluder_does_not_fake_a_curve() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let pairs: Vec<_> = (0..20_000)
            .map(|i| {
                if i % 4 == 0 {
                    let k: [f32; 3] = std::array::from_fn(|_| rng.random_range(0.3..0.9f32));
                    ([0.12 + rng.random_range(-0.01..0.01f32); 3], k)
                } else {
                    let v: [f32; 3] = std::array::from_fn(|_| rng.random_range(0.1..0.7f32));
                    (v, v.map(|c| 1.25 * c + 0.02 + rng.random_range(-0.01..0.01)))
                }
            })
            .collect();
        let fit = fit_tone(&pairs, &ToneParams::default());
        assert!(fit.curve.is_none(), "{fit:?}");
        assert!(fit.line_share > 0.7, "{fit:?}");
    }

    /// Two end knots close together make a steep end segment: beyond them the curve goes
    /// on no steeper than a gain may be, and it stays continuous at the knots.
    #[test]
    fn a_curve_is_extended_gently_beyond_its_ends() {
        let knots = vec![(0.1, 0.1), (0.1002, 0.3), (0.5, 0.6), (0.5002, 0.9)];
        let curve = ToneCurve { knots: [knots.clone(), knots.clone(), knots] };
        let low = curve.apply([0.0; 3])[0];
        let high = curve.apply([0.6; 3])[0];
        assert!((low - (0.1 - 0.1 * MAX_END_SLOPE)).abs() < 1e-5, "{low}");
        assert!((high - (0.9 + 0.0998 * MAX_END_SLOPE)).abs() < 1e-4, "{high}");
        for &(x, y) in &curve.knots[0] {
            assert!((curve.apply([x; 3])[0] - y).abs() < 1e-5);
        }
    }

    /// A view whose ring shows its own occluder (a nearly flat car body, lightly noisy)
    /// against the keyframe's textured wall: the pairs do not correlate, and matching their
    /// spreads ran the gain to its bound. Nothing is fitted to them; a view of the same
    /// wall, darker and noisy, is still fitted.
    #[test]
    fn pairs_that_do_not_correlate_fit_no_gain() {
        let mut rng = ChaCha8Rng::seed_from_u64(16);
        let wall: Vec<f32> = (0..400).map(|_| rng.random_range(0.3..0.7f32)).collect();
        let car: Vec<([f32; 3], [f32; 3])> =
            wall.iter().map(|&k| ([0.62 + rng.random_range(-0.02..0.02f32); 3], [k; 3])).collect();
        let spread = fit_gain(&car, &GainParams { min_correlation: -1.0, ..GainParams::default() });
        assert!(spread.gain[0] > 3.0, "the spreads' gain, unchecked: {spread:?}");
        assert_eq!(fit_gain(&car, &GainParams::default()), Gain::IDENTITY);
        let darker: Vec<([f32; 3], [f32; 3])> =
            wall.iter().map(|&k| ([0.6 * k + 0.05 + rng.random_range(-0.01..0.01f32); 3], [k; 3])).collect();
        let g = fit_gain(&darker, &GainParams::default());
        assert!((g.gain[0] - 1.0 / 0.6).abs() < 0.1 && (g.apply([0.35; 3])[0] - 0.5).abs() < 0.02, "{g:?}");
    }

    #[test]
    fn too_few_samples_or_flat_views_are_safe() {
        assert_eq!(fit_gain(&[([0.5; 3], [0.6; 3]); 5], &GainParams::default()), Gain::IDENTITY);
        let flat = vec![([0.5; 3], [0.6; 3]); 100];
        let g = fit_gain(&flat, &GainParams::default());
        assert!((g.apply([0.5; 3])[1] - 0.6).abs() < 1e-4, "{g:?}");
    }
}
