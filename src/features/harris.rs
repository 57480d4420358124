//! Harris corners (the paper's step 1): structure tensor under a Gaussian window,
//! non-maximum suppression, sub-pixel refinement, and grid bucketing so corners spread
//! over the whole image (pure layer).

use rayon::prelude::*;

use crate::imaging::{GrayF32, filter};

/// Parameters of [`harris`].
#[derive(Debug, Clone, PartialEq)]
pub struct HarrisParams {
    /// σ of the Gaussian window that integrates the structure tensor, pixels.
    pub sigma_i: f32,
    /// Harris' k in `det − k·trace²`.
    pub k: f32,
    /// Responses below this share of the image's strongest response are ignored.
    pub relative_threshold: f32,
    /// Responses below this absolute value are ignored (flat, noisy regions such as sky).
    pub absolute_threshold: f32,
    /// A corner must be the maximum of its `(2r+1)²` neighbourhood.
    pub nms_radius: usize,
    /// The image is cut into `grid × grid` cells; each keeps at most
    /// `max_corners / grid²` corners, its strongest, so a busy tree cannot take them all.
    pub grid: usize,
    /// At most this many corners in all.
    pub max_corners: usize,
    /// Corners closer than this to the border are dropped (their windows fall outside).
    pub border: usize,
}

impl Default for HarrisParams {
    fn default() -> Self {
        Self {
            sigma_i: 1.5,
            k: 0.04,
            relative_threshold: 1e-3,
            absolute_threshold: 1e-7,
            nms_radius: 2,
            grid: 8,
            max_corners: 1000,
            border: 8,
        }
    }
}

/// A corner at sub-pixel position `(x, y)` of the image it was found in.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Corner {
    pub x: f32,
    pub y: f32,
    pub response: f32,
}

/// Rows per band in [`response`]: small enough that a band's buffers stay in cache.
const BAND: usize = 32;

/// The Harris response `det(M) − k·trace(M)²` of the structure tensor `M`: Sobel
/// gradients (a derivative of a small Gaussian), their products integrated under a
/// Gaussian window of σ = `sigma_i`. Computed band by band, fused, so each band's
/// intermediates stay in cache and bands run in parallel.
pub fn response(img: &GrayF32, params: &HarrisParams) -> GrayF32 {
    let (w, h) = (img.width(), img.height());
    let mut out = GrayF32::new(w, h, 0.0);
    if w < 3 || h < 3 {
        return out;
    }
    let kernel = filter::gaussian_kernel(params.sigma_i);
    let r = kernel.len() / 2;
    let k = params.k;
    out.as_mut_slice().par_chunks_mut(BAND * w).enumerate().for_each_init(
        || Band::new(w, BAND + 2 * r, r),
        |band, (b, dst)| {
            let y0 = b * BAND;
            let rows = dst.len() / w;
            band.tensor(img, y0 as isize - r as isize, rows + 2 * r);
            band.window(&kernel, rows, k, dst);
        },
    );
    out
}

/// Scratch for one band of [`response`].
struct Band {
    w: usize,
    r: usize,
    /// Gradient products for the band plus the window's halo rows.
    xx: Vec<f32>,
    yy: Vec<f32>,
    xy: Vec<f32>,
    /// After the vertical pass (band rows only).
    vxx: Vec<f32>,
    vyy: Vec<f32>,
    vxy: Vec<f32>,
    /// One row of each product after both passes, and a padded row for the horizontal one.
    sxx: Vec<f32>,
    syy: Vec<f32>,
    sxy: Vec<f32>,
    padded: Vec<f32>,
}

impl Band {
    fn new(w: usize, rows: usize, r: usize) -> Self {
        let n = w * rows;
        Self {
            w,
            r,
            xx: vec![0.0; n],
            yy: vec![0.0; n],
            xy: vec![0.0; n],
            vxx: vec![0.0; n],
            vyy: vec![0.0; n],
            vxy: vec![0.0; n],
            sxx: vec![0.0; w],
            syy: vec![0.0; w],
            sxy: vec![0.0; w],
            padded: vec![0.0; w + 2 * r],
        }
    }

    /// Sobel gradient products for `rows` image rows starting at `first` (rows outside
    /// the image replicate the border).
    fn tensor(&mut self, img: &GrayF32, first: isize, rows: usize) {
        let (w, h) = (self.w, img.height() as isize);
        let row = |y: isize| img.row(y.clamp(0, h - 1) as usize);
        for j in 0..rows {
            let y = first + j as isize;
            let (up, mid, down) = (row(y - 1), row(y), row(y + 1));
            let o = j * w;
            let (xx, yy, xy) = (&mut self.xx[o..o + w], &mut self.yy[o..o + w], &mut self.xy[o..o + w]);
            // Interior: contiguous slices, so the loop vectorises.
            let inner = (1..w - 1)
                .zip(xx[1..w - 1].iter_mut().zip(yy[1..w - 1].iter_mut()).zip(xy[1..w - 1].iter_mut()));
            for (x, ((pxx, pyy), pxy)) in inner {
                let gx =
                    (up[x + 1] - up[x - 1]) + 2.0 * (mid[x + 1] - mid[x - 1]) + (down[x + 1] - down[x - 1]);
                let gy = (down[x - 1] - up[x - 1]) + 2.0 * (down[x] - up[x]) + (down[x + 1] - up[x + 1]);
                let (gx, gy) = (gx * 0.125, gy * 0.125);
                *pxx = gx * gx;
                *pyy = gy * gy;
                *pxy = gx * gy;
            }
            // Borders replicate their neighbour's value: corners are never taken there.
            xx[0] = xx[1];
            yy[0] = yy[1];
            xy[0] = xy[1];
            xx[w - 1] = xx[w - 2];
            yy[w - 1] = yy[w - 2];
            xy[w - 1] = xy[w - 2];
        }
    }

    /// The Gaussian window over the products (vertical, then horizontal) for the band's
    /// `rows` output rows, and the response `det − k·trace²` into `dst`. The kernel is
    /// symmetric, so mirrored taps are added before multiplying.
    fn window(&mut self, kernel: &[f32], rows: usize, k: f32, dst: &mut [f32]) {
        let (w, r) = (self.w, self.r);
        for (src, out) in [(&self.xx, &mut self.vxx), (&self.yy, &mut self.vyy), (&self.xy, &mut self.vxy)] {
            for j in 0..rows {
                let d = &mut out[j * w..(j + 1) * w];
                let centre = &src[(j + r) * w..(j + r + 1) * w];
                for (a, &b) in d.iter_mut().zip(centre) {
                    *a = kernel[r] * b;
                }
                for (i, &kv) in kernel[..r].iter().enumerate() {
                    let (above, below) =
                        (&src[(j + i) * w..(j + i + 1) * w], &src[(j + 2 * r - i) * w..][..w]);
                    add_symmetric_tap(d, above, below, kv);
                }
            }
        }
        let padded = &mut self.padded;
        for j in 0..rows {
            for (src, out) in
                [(&self.vxx, &mut self.sxx), (&self.vyy, &mut self.syy), (&self.vxy, &mut self.sxy)]
            {
                let row = &src[j * w..(j + 1) * w];
                padded[r..r + w].copy_from_slice(row);
                let (first, last) = (row[0], row[w - 1]);
                padded[..r].iter_mut().for_each(|v| *v = first);
                padded[r + w..].iter_mut().for_each(|v| *v = last);
                for (a, &b) in out.iter_mut().zip(&padded[r..r + w]) {
                    *a = kernel[r] * b;
                }
                for (i, &kv) in kernel[..r].iter().enumerate() {
                    let (left, right) = (&padded[i..i + w], &padded[2 * r - i..2 * r - i + w]);
                    add_symmetric_tap(out, left, right, kv);
                }
            }
            let d = &mut dst[j * w..(j + 1) * w];
            for (((d, &a), &bb), &c) in d.iter_mut().zip(&self.sxx).zip(&self.syy).zip(&self.sxy) {
                let tr = a + bb;
                *d = a * bb - c * c - k * tr * tr;
            }
        }
    }
}

/// `d += k·(a + b)` elementwise: a pair of mirrored taps of a symmetric kernel. Its own
/// function, so the three slices are known not to overlap and the loop vectorises.
#[inline(never)]
fn add_symmetric_tap(d: &mut [f32], a: &[f32], b: &[f32], k: f32) {
    let n = d.len();
    let (a, b) = (&a[..n], &b[..n]);
    for i in 0..n {
        d[i] += k * (a[i] + b[i]);
    }
}

/// Harris corners of `img`, strongest first within each grid cell, spread by the grid.
pub fn harris(img: &GrayF32, params: &HarrisParams) -> Vec<Corner> {
    let b = params.border.max(params.nms_radius).max(1);
    if img.width() <= 2 * b || img.height() <= 2 * b {
        return Vec::new();
    }
    corners_of(&response(img, params), params)
}

/// [`harris`] from the image's [`response`] (made with the same `params`), for a caller
/// that reads the response too.
pub fn corners_of(r: &GrayF32, params: &HarrisParams) -> Vec<Corner> {
    let (w, h) = (r.width(), r.height());
    let b = params.border.max(params.nms_radius).max(1);
    if w <= 2 * b || h <= 2 * b {
        return Vec::new();
    }
    let max = r.as_slice().iter().copied().fold(0.0f32, f32::max);
    let threshold = (params.relative_threshold * max).max(params.absolute_threshold);
    let nr = params.nms_radius as isize;
    // Neighbour offsets, nearest ring first: most pixels lose to a direct neighbour, so
    // they are rejected after a comparison or two.
    let mut offsets: Vec<(isize, isize)> =
        (-nr..=nr).flat_map(|dy| (-nr..=nr).map(move |dx| (dx, dy))).filter(|&o| o != (0, 0)).collect();
    offsets.sort_by_key(|&(dx, dy)| (dx.abs().max(dy.abs()), dy, dx));

    // Local maxima, row-parallel.
    let candidates: Vec<Corner> = (b..h - b)
        .into_par_iter()
        .flat_map_iter(|y| {
            let (r, offsets) = (&r, &offsets);
            let data = r.as_slice();
            (b..w - b).filter_map(move |x| {
                let i = y * w + x;
                let v = data[i];
                if v <= threshold {
                    return None;
                }
                for &(dx, dy) in offsets {
                    let u = data[(i as isize + dy * w as isize + dx) as usize];
                    // Ties are broken towards the earlier pixel, so plateaus yield one.
                    if u > v || (u == v && (dy < 0 || (dy == 0 && dx < 0))) {
                        return None;
                    }
                }
                let (ox, oy) = subpixel_offset(r, x, y);
                Some(Corner { x: x as f32 + ox, y: y as f32 + oy, response: v })
            })
        })
        .collect();

    // Grid bucketing: the strongest few of each cell.
    let grid = params.grid.max(1);
    let per_cell = params.max_corners.div_ceil(grid * grid).max(1);
    let mut cells: Vec<Vec<Corner>> = vec![Vec::new(); grid * grid];
    for c in candidates {
        let cx = ((c.x as usize * grid) / w).min(grid - 1);
        let cy = ((c.y as usize * grid) / h).min(grid - 1);
        cells[cy * grid + cx].push(c);
    }
    let mut out: Vec<Corner> = Vec::new();
    for cell in &mut cells {
        cell.sort_unstable_by(|a, b| b.response.total_cmp(&a.response));
        out.extend(cell.iter().take(per_cell));
    }
    out.sort_unstable_by(|a, b| b.response.total_cmp(&a.response));
    out.truncate(params.max_corners);
    out
}

/// Offset of the peak of a parabola through the 3×3 neighbourhood, each axis separately,
/// clamped to half a pixel.
fn subpixel_offset(r: &GrayF32, x: usize, y: usize) -> (f32, f32) {
    let c = r.get(x, y);
    let fit = |m: f32, p: f32| {
        let denom = m - 2.0 * c + p;
        if denom < 0.0 { (0.5 * (m - p) / denom).clamp(-0.5, 0.5) } else { 0.0 }
    };
    (fit(r.get(x - 1, y), r.get(x + 1, y)), fit(r.get(x, y - 1), r.get(x, y + 1)))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A bright square on dark ground, corners at (20, 20), (40, 20), (40, 40), (20, 40)
    /// in the sense of pixel edges.
    fn square() -> GrayF32 {
        GrayF32::from_fn(
            64,
            64,
            |x, y| if (20..40).contains(&x) && (20..40).contains(&y) { 1.0 } else { 0.0 },
        )
    }

    #[test]
    fn finds_the_four_corners_of_a_square() {
        let corners = harris(&square(), &HarrisParams::default());
        assert_eq!(corners.len(), 4, "{corners:?}");
        // Harris' maximum sits about σ inside a blurred right-angle corner; guided matching
        // later compares patches, so this bias does not reach the homography.
        for (ex, ey) in [(19.5, 19.5), (39.5, 19.5), (39.5, 39.5), (19.5, 39.5)] {
            let near = corners.iter().any(|c| (c.x - ex).abs() < 1.5 && (c.y - ey).abs() < 1.5);
            assert!(near, "no corner near ({ex}, {ey}) in {corners:?}");
        }
    }

    #[test]
    fn edges_and_flat_regions_give_nothing() {
        let edge = GrayF32::from_fn(64, 64, |x, _| if x < 32 { 0.0 } else { 1.0 });
        assert!(harris(&edge, &HarrisParams::default()).is_empty());
        assert!(harris(&GrayF32::new(64, 64, 0.5), &HarrisParams::default()).is_empty());
    }

    #[test]
    fn subpixel_position_follows_a_shift() {
        // A soft right-angle corner at a fractional position.
        let corner = |cx: f32| {
            let step = |t: f32| 1.0 / (1.0 + (-t / 0.7).exp());
            GrayF32::from_fn(48, 48, |x, y| step(x as f32 - cx) * step(y as f32 - 24.0))
        };
        let p = HarrisParams { relative_threshold: 0.5, ..HarrisParams::default() };
        let a = harris(&corner(24.0), &p)[0];
        let b = harris(&corner(24.3), &p)[0];
        assert!(((b.x - a.x) - 0.3).abs() < 0.12, "shift {}", b.x - a.x);
    }

    #[test]
    fn grid_spreads_corners() {
        // Many corners on the left half (a checkerboard), a few on the right.
        let img = GrayF32::from_fn(256, 128, |x, y| {
            if x < 128 {
                (((x / 6) + (y / 6)) % 2) as f32
            } else if (180..200).contains(&x) && (50..70).contains(&y) {
                1.0
            } else {
                0.0
            }
        });
        let p = HarrisParams { grid: 2, max_corners: 40, ..HarrisParams::default() };
        let corners = harris(&img, &p);
        let right = corners.iter().filter(|c| c.x >= 128.0).count();
        assert!(right >= 4, "the sparse half kept {right} corners");
        assert!(corners.len() <= 40);
    }

    /// The banded, fused, symmetric-tap response against a plain whole-image computation:
    /// Sobel products, a replicated-border Gaussian down the columns, then along the rows.
    #[test]
    fn response_matches_a_plain_reference() {
        let (w, h) = (97, 75); // several bands, the last one partial
        let img = GrayF32::from_fn(w, h, |x, y| {
            let (xf, yf) = (x as f32, y as f32);
            0.5 + 0.3 * (xf * 0.37).sin() * (yf * 0.23).cos() + 0.2 * (((x / 7) + (y / 5)) % 2) as f32
        });
        let params = HarrisParams::default();
        let got = response(&img, &params);
        let kernel = filter::gaussian_kernel(params.sigma_i);
        let r = (kernel.len() / 2) as isize;
        let at = |x: isize, y: isize| img.get_clamped(x, y);
        let products = |x: isize, y: isize| {
            let x = x.clamp(1, w as isize - 2);
            let gx = (at(x + 1, y - 1) - at(x - 1, y - 1))
                + 2.0 * (at(x + 1, y) - at(x - 1, y))
                + (at(x + 1, y + 1) - at(x - 1, y + 1));
            let gy = (at(x - 1, y + 1) - at(x - 1, y - 1))
                + 2.0 * (at(x, y + 1) - at(x, y - 1))
                + (at(x + 1, y + 1) - at(x + 1, y - 1));
            let (gx, gy) = (gx * 0.125, gy * 0.125);
            [gx * gx, gy * gy, gx * gy]
        };
        let mut worst = 0.0f32;
        for y in 0..h as isize {
            for x in 0..w as isize {
                let mut s = [0.0f32; 3];
                for (j, kj) in kernel.iter().enumerate() {
                    // Vertical first, on the products of clamped rows; then horizontal, with
                    // the vertical result replicated at the row ends.
                    let yy = y + j as isize - r;
                    for (i, ki) in kernel.iter().enumerate() {
                        let xx = (x + i as isize - r).clamp(0, w as isize - 1);
                        let p = products(xx, yy);
                        for c in 0..3 {
                            s[c] += kj * ki * p[c];
                        }
                    }
                }
                let tr = s[0] + s[1];
                let want = s[0] * s[1] - s[2] * s[2] - params.k * tr * tr;
                worst = worst.max((got.get(x as usize, y as usize) - want).abs());
            }
        }
        let scale = got.as_slice().iter().fold(0.0f32, |m, v| m.max(v.abs()));
        assert!(worst <= 1e-4 * scale, "largest difference {worst} (response scale {scale})");
    }
}
