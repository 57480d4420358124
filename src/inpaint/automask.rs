//! The automatic mask: pixels where the keyframe disagrees with the consensus of the
//! aligned views are transient occluders (pure layer).
//!
//! A person or a car is where it is in one photograph only; the facade is the same in all
//! of them. So each view is warped into the keyframe, compensated photometrically, and
//! where at least `min_views` views agree with each other but not with the keyframe, the
//! keyframe shows something that was not there in the others. Small blobs (misregistration
//! along sharp edges, noise) are opened away, gaps closed, and the result grown a little so
//! that the fill also replaces the object's soft edge.

use super::Source;
use crate::geometry::Homography;
use crate::imaging::photometric::{Gain, GainParams, fit_gain};
use crate::imaging::warp::{Interpolation, Rect, warp};
use crate::imaging::{Mask, Plane, RgbF32, RgbPixel};

/// Parameters of [`auto_mask`].
#[derive(Debug, Clone, PartialEq)]
pub struct AutoMaskParams {
    /// At least this many views must see a pixel (and agree) to judge it.
    pub min_views: usize,
    /// RGB distance (Euclidean, 0..=√3) between the keyframe and the views' consensus
    /// above which a pixel is transient.
    pub threshold: f32,
    /// Views within this RGB distance of their median agree.
    pub agreement: f32,
    /// Both sides are box-averaged over `(2·r + 1)²` before comparing (tolerates the
    /// alignment's fraction of a pixel along sharp edges).
    pub blur_radius: usize,
    /// Opening radius: removes specks and thin lines narrower than about twice this.
    pub open_radius: usize,
    /// Closing radius: joins a figure's parts.
    pub close_radius: usize,
    /// The mask is finally grown by this many pixels (full resolution).
    pub dilate_radius: usize,
    /// The comparison runs on an image box-reduced to at most this many pixels.
    pub work_pixels: usize,
}

impl Default for AutoMaskParams {
    fn default() -> Self {
        Self {
            min_views: 2,
            threshold: 0.15,
            agreement: 0.12,
            blur_radius: 1,
            open_radius: 2,
            close_radius: 3,
            dilate_radius: 3,
            work_pixels: 1_500_000,
        }
    }
}

/// The mask of transient objects in `key` (255 = fill), judged against `sources`.
pub fn auto_mask<P: RgbPixel>(key: &RgbF32, sources: &[Source<'_, P>], params: &AutoMaskParams) -> Mask {
    let (w, h) = (key.width(), key.height());
    if sources.len() < params.min_views.max(1) || w == 0 || h == 0 {
        return Mask::new(w, h, 0);
    }
    let f = ((w * h) as f64 / params.work_pixels.max(1) as f64).sqrt().ceil().max(1.0) as usize;
    let key_r = reduce(key, f);
    let (rw, rh) = (key_r.width(), key_r.height());
    // x_full = f·x_reduced + (f − 1)/2 on both sides.
    let to_full = Homography::from_rows([
        [f as f64, 0.0, (f as f64 - 1.0) / 2.0],
        [0.0, f as f64, (f as f64 - 1.0) / 2.0],
        [0.0, 0.0, 1.0],
    ])
    .expect("scaling is regular");
    let from_full = to_full.inverse().expect("scaling is regular");
    let warped: Vec<(RgbF32, Plane<bool>)> = sources
        .iter()
        .map(|s| {
            let view_r = reduce(s.image, f);
            let hr = from_full.after(&s.homography).after(&to_full);
            let wv = warp(&view_r, &hr, Rect::full(rw, rh), None, Interpolation::Bilinear);
            let gain = fit_whole(&key_r, &wv.image, &wv.valid);
            let img = wv.image.map(|&p| gain.apply(p));
            (box_blur(&img, &wv.valid, params.blur_radius), wv.valid)
        })
        .collect();
    let all = Plane::new(rw, rh, true);
    let key_b = box_blur(&key_r, &all, params.blur_radius);

    let mut changed = Plane::new(rw, rh, false);
    let mut vals: Vec<[f32; 3]> = Vec::with_capacity(sources.len());
    let mut chan: Vec<f32> = Vec::with_capacity(sources.len());
    for y in 0..rh {
        for x in 0..rw {
            vals.clear();
            vals.extend(warped.iter().filter(|(_, v)| v.get(x, y)).map(|(img, _)| img.get(x, y)));
            if vals.len() < params.min_views {
                continue;
            }
            let med: [f32; 3] = std::array::from_fn(|c| {
                chan.clear();
                chan.extend(vals.iter().map(|v| v[c]));
                chan.sort_unstable_by(f32::total_cmp);
                let n = chan.len();
                0.5 * (chan[(n - 1) / 2] + chan[n / 2])
            });
            let dist = |a: [f32; 3], b: [f32; 3]| ((0..3).map(|c| (a[c] - b[c]).powi(2)).sum::<f32>()).sqrt();
            let agreeing: Vec<[f32; 3]> =
                vals.iter().copied().filter(|&v| dist(v, med) < params.agreement).collect();
            if agreeing.len() < params.min_views {
                continue;
            }
            let mean: [f32; 3] =
                std::array::from_fn(|c| agreeing.iter().map(|v| v[c]).sum::<f32>() / agreeing.len() as f32);
            if dist(key_b.get(x, y), mean) > params.threshold {
                changed.set(x, y, true);
            }
        }
    }
    let opened = dilate(&erode(&changed, params.open_radius), params.open_radius);
    let closed = erode(&dilate(&opened, params.close_radius), params.close_radius);
    let full = Plane::from_fn(w, h, |x, y| closed.get((x / f).min(rw - 1), (y / f).min(rh - 1)));
    dilate(&full, params.dilate_radius).map(|&b| if b { 255 } else { 0 })
}

/// Gain and offset of a whole warped view against the keyframe, on a grid of samples.
fn fit_whole(key: &RgbF32, view: &RgbF32, valid: &Plane<bool>) -> Gain {
    let n = valid.as_slice().iter().filter(|&&v| v).count();
    let step = (n / 40_000).max(1);
    let pairs: Vec<([f32; 3], [f32; 3])> = valid
        .as_slice()
        .iter()
        .enumerate()
        .filter(|(_, v)| **v)
        .step_by(step)
        .map(|(i, _)| (view.as_slice()[i], key.as_slice()[i]))
        .collect();
    fit_gain(&pairs, &GainParams::default())
}

/// Box average of `f × f` blocks (the last ones partial).
fn reduce<P: RgbPixel>(img: &Plane<P>, f: usize) -> RgbF32 {
    if f <= 1 {
        return img.map(|p| p.to_f32());
    }
    let (w, h) = (img.width(), img.height());
    let (rw, rh) = (w.div_ceil(f), h.div_ceil(f));
    RgbF32::from_fn(rw, rh, |x, y| {
        let mut s = [0.0f32; 3];
        let mut n = 0.0;
        for yy in y * f..((y + 1) * f).min(h) {
            for xx in x * f..((x + 1) * f).min(w) {
                let p = img.get(xx, yy).to_f32();
                for c in 0..3 {
                    s[c] += p[c];
                }
                n += 1.0;
            }
        }
        s.map(|v| v / n)
    })
}

/// Box average over `(2r + 1)²` of the valid pixels only.
fn box_blur(img: &RgbF32, valid: &Plane<bool>, r: usize) -> RgbF32 {
    if r == 0 {
        return img.clone();
    }
    let (w, h) = (img.width(), img.height());
    let r = r as isize;
    RgbF32::from_fn(w, h, |x, y| {
        let mut s = [0.0f32; 3];
        let mut n = 0.0;
        for dy in -r..=r {
            for dx in -r..=r {
                let (xx, yy) = (x as isize + dx, y as isize + dy);
                if valid.get_checked(xx, yy) == Some(true) {
                    let p = img.get(xx as usize, yy as usize);
                    for c in 0..3 {
                        s[c] += p[c];
                    }
                    n += 1.0;
                }
            }
        }
        if n > 0.0 { s.map(|v| v / n) } else { img.get(x, y) }
    })
}

/// 1-D max (`grow`) or min filter of radius `r` along rows (`vertical` false) or columns.
fn filter_1d(m: &Plane<bool>, r: usize, grow: bool, vertical: bool) -> Plane<bool> {
    let (w, h) = (m.width(), m.height());
    let (len, lines) = if vertical { (h, w) } else { (w, h) };
    let idx = |line: usize, k: usize| if vertical { k * w + line } else { line * w + k };
    let src = m.as_slice();
    let mut out = vec![false; w * h];
    for line in 0..lines {
        // Running count of `true` in the window [k − r, k + r] ∩ [0, len).
        let mut count = 0usize;
        for k in 0..r.min(len) {
            count += src[idx(line, k)] as usize;
        }
        for k in 0..len {
            if k + r < len {
                count += src[idx(line, k + r)] as usize;
            }
            if k > r {
                count -= src[idx(line, k - r - 1)] as usize;
            }
            let window = (k + r).min(len - 1) + 1 - k.saturating_sub(r);
            out[idx(line, k)] = if grow { count > 0 } else { count == window };
        }
    }
    Plane::from_vec(w, h, out)
}

/// Dilation by a `(2r + 1)²` square.
pub fn dilate(m: &Plane<bool>, r: usize) -> Plane<bool> {
    if r == 0 {
        return m.clone();
    }
    filter_1d(&filter_1d(m, r, true, false), r, true, true)
}

/// Erosion by a `(2r + 1)²` square (pixels beyond the border do not count against).
pub fn erode(m: &Plane<bool>, r: usize) -> Plane<bool> {
    if r == 0 {
        return m.clone();
    }
    filter_1d(&filter_1d(m, r, false, false), r, false, true)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::{Occluder, facade, paint_occluder, render_view};

    #[test]
    fn morphology_grows_and_shrinks_squares() {
        let m = Plane::from_fn(20, 20, |x, y| x == 10 && y == 10);
        let d = dilate(&m, 2);
        assert_eq!(d.as_slice().iter().filter(|&&v| v).count(), 25);
        assert!(d.get(8, 12) && !d.get(7, 10));
        assert_eq!(erode(&d, 2).as_slice().iter().filter(|&&v| v).count(), 1);
        assert!(erode(&d, 3).as_slice().iter().all(|&v| !v));
    }

    #[test]
    fn finds_a_pasted_person_and_not_the_facade() {
        let (w, h) = (240, 180);
        let scene = facade(w, h, 11);
        let mut key = scene.clone();
        let mut truth = Mask::new(w, h, 0);
        paint_occluder(&mut key, Some(&mut truth), Occluder::Person, 120.0, 95.0, 90.0, 3);
        let hs = [
            Homography::translation(6.5, -3.0),
            Homography::from_rows([[1.02, 0.01, -5.0], [-0.01, 0.99, 4.0], [1e-5, 0.0, 1.0]]).unwrap(),
            Homography::translation(-7.0, 2.5),
        ];
        // Views of the same facade, one of them darker and each with a tree elsewhere.
        let views: Vec<RgbF32> = hs
            .iter()
            .enumerate()
            .map(|(i, hm)| {
                let mut v = render_view(&scene, &hm.inverse().unwrap(), w, h, [0.5; 3]);
                if i == 1 {
                    crate::synth::expose(&mut v, 0.8, 0.02);
                }
                paint_occluder(&mut v, None, Occluder::Tree, 30.0 + 80.0 * i as f32, 40.0, 40.0, i as u64);
                v
            })
            .collect();
        let sources: Vec<Source<'_>> =
            views.iter().zip(&hs).map(|(v, &homography)| Source { image: v, homography }).collect();
        let m = auto_mask(&key, &sources, &AutoMaskParams::default());
        let (mut hit, mut false_pos) = (0, 0);
        for i in 0..w * h {
            let (t, p) = (truth.as_slice()[i] > 127, m.as_slice()[i] > 127);
            hit += (t && p) as usize;
            false_pos += (!t && p) as usize;
        }
        let person = truth.hole_count();
        assert!(hit as f32 > 0.9 * person as f32, "found {hit} of {person}");
        // Allowed: the dilation ring around the person (≈ perimeter × 3), nothing else.
        assert!(false_pos < person, "{false_pos} false positives for a {person}-pixel person");
        // A keyframe equal to the scene: nothing is transient.
        let none = auto_mask(&scene, &sources, &AutoMaskParams::default());
        assert!(none.hole_count() < w * h / 200, "{} pixels flagged on a clean keyframe", none.hole_count());
    }
}
