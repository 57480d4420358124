//! Image containers and pixel operations shared by the whole core (pure layer).
//!
//! The core works on its own small, dense, row-major buffers rather than on the `image`
//! crate's generic types: the geometry wants `f32` luminance, the fill wants `f32` RGB,
//! and both want cheap row slices and bilinear sampling without per-pixel trait calls.
//! Conversion from and to `image` lives in [`convert`].

pub mod colour;
pub mod convert;
pub mod decode;
pub mod encode;
pub mod filter;
pub mod meta;
pub mod metrics;
pub mod photometric;
pub mod pyramid;
pub mod sharpness;
pub mod warp;
pub mod webp;

use std::fmt;

/// An axis-aligned rectangle of pixels, `x..x + width` × `y..y + height`: the regions the
/// fill works in and the parts of views it keeps.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Rect {
    pub x: usize,
    pub y: usize,
    pub width: usize,
    pub height: usize,
}

impl Rect {
    /// The whole of a `width × height` image.
    pub fn full(width: usize, height: usize) -> Self {
        Self { x: 0, y: 0, width, height }
    }

    /// The rectangle `[x0, x1) × [y0, y1)`.
    pub fn from_corners(x0: usize, y0: usize, x1: usize, y1: usize) -> Self {
        Self { x: x0, y: y0, width: x1.saturating_sub(x0), height: y1.saturating_sub(y0) }
    }

    /// The smallest rectangle holding every pixel of `px` (empty when `px` is).
    pub fn around(px: &[(usize, usize)]) -> Self {
        if px.is_empty() {
            return Self::default();
        }
        let [x0, y0, x1, y1] = px.iter().fold([usize::MAX, usize::MAX, 0, 0], |[x0, y0, x1, y1], &(x, y)| {
            [x0.min(x), y0.min(y), x1.max(x), y1.max(y)]
        });
        Self::from_corners(x0, y0, x1 + 1, y1 + 1)
    }

    /// One past the last column.
    pub fn x1(&self) -> usize {
        self.x + self.width
    }

    /// One past the last row.
    pub fn y1(&self) -> usize {
        self.y + self.height
    }

    /// `self` grown by `margin` on every side and clipped to a `width × height` image.
    pub fn grown(&self, margin: usize, width: usize, height: usize) -> Self {
        Self::from_corners(
            self.x.saturating_sub(margin),
            self.y.saturating_sub(margin),
            (self.x1() + margin).min(width),
            (self.y1() + margin).min(height),
        )
    }

    pub fn area(&self) -> usize {
        self.width * self.height
    }

    /// The pixels in both `self` and `other` (empty when they do not overlap).
    pub fn intersection(&self, other: &Rect) -> Self {
        Self::from_corners(
            self.x.max(other.x),
            self.y.max(other.y),
            self.x1().min(other.x1()),
            self.y1().min(other.y1()),
        )
    }

    /// `true` when the image pixel `(x, y)` is inside.
    pub fn contains(&self, x: usize, y: usize) -> bool {
        x >= self.x && y >= self.y && x < self.x1() && y < self.y1()
    }
}

/// A dense, row-major image of `T` pixels: `data[y * width + x]`.
#[derive(PartialEq)]
pub struct Plane<T> {
    width: usize,
    height: usize,
    data: Vec<T>,
}

/// Planes of at least this many pixels are copied on every core ([`Plane::clone`]).
const PARALLEL_CLONE_FROM: usize = 1 << 20;

impl<T: Clone + Send + Sync> Clone for Plane<T> {
    /// A copy; from [`PARALLEL_CLONE_FROM`] pixels up, made on every core. A 12 MP RGB
    /// result is 144 MB: its copy (the page faults of the new memory with it) took one core
    /// 140 ms of every landing in the service (BENCHMARKS.md, "Capture service").
    fn clone(&self) -> Self {
        let data = if self.data.len() >= PARALLEL_CLONE_FROM {
            use rayon::prelude::*;
            self.data.par_iter().cloned().collect()
        } else {
            self.data.clone()
        };
        Self { width: self.width, height: self.height, data }
    }
}

/// Luminance (or one channel) in `f32`, nominally 0..=1.
pub type GrayF32 = Plane<f32>;
/// Linear-ish RGB in `f32`, nominally 0..=1 per channel.
pub type RgbF32 = Plane<[f32; 3]>;
/// An 8-bit mask; a value > 127 means "fill this pixel" (ARCHITECTURE.md).
pub type Mask = Plane<u8>;
/// RGB in 8 bits per channel, as photographs are decoded: views are kept this way (a
/// quarter of [`RgbF32`]'s memory) and read as `f32` only where they are sampled.
pub type Rgb8 = Plane<[u8; 3]>;

/// An RGB pixel the core can read as `f32` in 0..=1: an [`RgbF32`] pixel as it is, an
/// [`Rgb8`] one divided by 255 (exactly as `image`'s `to_rgb32f` does, so sampling an 8-bit
/// image gives the same numbers as converting it first and sampling the copy).
pub trait RgbPixel: Copy + Send + Sync {
    fn to_f32(self) -> [f32; 3];
}

impl RgbPixel for [f32; 3] {
    #[inline]
    fn to_f32(self) -> [f32; 3] {
        self
    }
}

/// `v / 255` for every 8-bit value.
const FROM_U8: [f32; 256] = {
    let mut t = [0.0; 256];
    let mut v = 0;
    while v < 256 {
        t[v] = v as f32 / 255.0;
        v += 1;
    }
    t
};

impl RgbPixel for [u8; 3] {
    #[inline]
    fn to_f32(self) -> [f32; 3] {
        self.map(|v| FROM_U8[v as usize])
    }
}

impl<T> fmt::Debug for Plane<T> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Plane({}x{})", self.width, self.height)
    }
}

impl<T: Copy> Plane<T> {
    /// An image of `width × height` pixels, all equal to `value`.
    pub fn new(width: usize, height: usize, value: T) -> Self {
        Self { width, height, data: vec![value; width * height] }
    }

    /// An image whose pixel at `(x, y)` is `f(x, y)`.
    pub fn from_fn(width: usize, height: usize, mut f: impl FnMut(usize, usize) -> T) -> Self {
        let mut data = Vec::with_capacity(width * height);
        for y in 0..height {
            for x in 0..width {
                data.push(f(x, y));
            }
        }
        Self { width, height, data }
    }

    /// As [`Plane::from_fn`], the rows computed in parallel.
    pub fn par_from_fn(width: usize, height: usize, f: impl Fn(usize, usize) -> T + Sync) -> Self
    where
        T: Send,
    {
        use rayon::prelude::*;
        let data: Vec<T> = {
            let f = &f;
            (0..height).into_par_iter().flat_map_iter(|y| (0..width).map(move |x| f(x, y))).collect()
        };
        Self { width, height, data }
    }

    /// Wraps `data` (row-major, `width * height` long).
    ///
    /// # Panics
    /// If the length does not match the dimensions: that is a bug in the caller.
    pub fn from_vec(width: usize, height: usize, data: Vec<T>) -> Self {
        assert_eq!(data.len(), width * height, "plane data does not match {width}x{height}");
        Self { width, height, data }
    }

    /// Resizes to `width × height` and fills with `value`, reusing the allocation.
    pub fn reset(&mut self, width: usize, height: usize, value: T) {
        self.width = width;
        self.height = height;
        self.data.clear();
        self.data.resize(width * height, value);
    }

    #[inline]
    pub fn width(&self) -> usize {
        self.width
    }

    #[inline]
    pub fn height(&self) -> usize {
        self.height
    }

    #[inline]
    pub fn len(&self) -> usize {
        self.data.len()
    }

    #[inline]
    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }

    #[inline]
    pub fn get(&self, x: usize, y: usize) -> T {
        self.data[y * self.width + x]
    }

    #[inline]
    pub fn set(&mut self, x: usize, y: usize, value: T) {
        self.data[y * self.width + x] = value;
    }

    /// The pixel at `(x, y)`, or `None` outside the image.
    #[inline]
    pub fn get_checked(&self, x: isize, y: isize) -> Option<T> {
        if x < 0 || y < 0 || x as usize >= self.width || y as usize >= self.height {
            None
        } else {
            Some(self.data[y as usize * self.width + x as usize])
        }
    }

    /// The pixel at `(x, y)` with coordinates clamped to the border.
    #[inline]
    pub fn get_clamped(&self, x: isize, y: isize) -> T {
        let x = x.clamp(0, self.width as isize - 1) as usize;
        let y = y.clamp(0, self.height as isize - 1) as usize;
        self.data[y * self.width + x]
    }

    #[inline]
    pub fn row(&self, y: usize) -> &[T] {
        &self.data[y * self.width..(y + 1) * self.width]
    }

    #[inline]
    pub fn row_mut(&mut self, y: usize) -> &mut [T] {
        &mut self.data[y * self.width..(y + 1) * self.width]
    }

    #[inline]
    pub fn as_slice(&self) -> &[T] {
        &self.data
    }

    #[inline]
    pub fn as_mut_slice(&mut self) -> &mut [T] {
        &mut self.data
    }

    pub fn into_vec(self) -> Vec<T> {
        self.data
    }

    /// `true` when `(x, y)` (real-valued) lies inside the pixel-centre rectangle.
    #[inline]
    pub fn contains(&self, x: f64, y: f64) -> bool {
        x >= 0.0 && y >= 0.0 && x <= (self.width - 1) as f64 && y <= (self.height - 1) as f64
    }

    /// A copy of the pixels inside `r` (which must lie inside the image).
    pub fn crop(&self, r: Rect) -> Self {
        let mut data = Vec::with_capacity(r.area());
        for y in r.y..r.y1() {
            data.extend_from_slice(&self.row(y)[r.x..r.x1()]);
        }
        Self { width: r.width, height: r.height, data }
    }

    /// Writes `src` over the pixels inside `r` (`src` is `r`-sized).
    pub fn paste(&mut self, src: &Self, r: Rect) {
        assert_eq!(
            (src.width, src.height),
            (r.width, r.height),
            "paste needs a plane the size of the rectangle"
        );
        for y in 0..r.height {
            self.row_mut(r.y + y)[r.x..r.x1()].copy_from_slice(src.row(y));
        }
    }

    /// Applies `f` to every pixel, producing a new image.
    pub fn map<U: Copy>(&self, f: impl FnMut(&T) -> U) -> Plane<U> {
        Plane { width: self.width, height: self.height, data: self.data.iter().map(f).collect() }
    }
}

impl Mask {
    /// `true` where the mask asks for the pixel to be filled.
    #[inline]
    pub fn is_hole(&self, x: usize, y: usize) -> bool {
        self.get(x, y) > 127
    }

    /// The bounding box of the holes, or `None` when there are none.
    pub fn hole_bounds(&self) -> Option<Rect> {
        self.hole_bounds_within(Rect::full(self.width, self.height))
    }

    /// The bounding box of the hole pixels inside `rect` (which must lie in the mask),
    /// `None` when there is none.
    pub fn hole_bounds_within(&self, rect: Rect) -> Option<Rect> {
        let (mut x0, mut y0, mut x1, mut y1) = (usize::MAX, usize::MAX, 0, 0);
        for y in rect.y..rect.y + rect.height {
            let row = &self.row(y)[rect.x..rect.x + rect.width];
            let (Some(first), Some(last)) =
                (row.iter().position(|&v| v > 127), row.iter().rposition(|&v| v > 127))
            else {
                continue;
            };
            x0 = x0.min(rect.x + first);
            x1 = x1.max(rect.x + last + 1);
            y0 = y0.min(y);
            y1 = y + 1;
        }
        (x0 != usize::MAX).then(|| Rect::from_corners(x0, y0, x1, y1))
    }

    /// How many pixels the mask asks to fill.
    pub fn hole_count(&self) -> usize {
        self.data.iter().filter(|&&v| v > 127).count()
    }

    /// What a mask that is probably a mistake comes to, in a user's words: one that marks
    /// no pixel (all black) or every pixel (all white); `None` for any other.
    pub fn mistake(&self) -> Option<&'static str> {
        let masked = self.hole_count();
        if masked == 0 {
            Some("the mask marks no pixel (all black): nothing to fill, the keyframe itself is the result")
        } else if masked as f64 >= 0.999 * self.data.len() as f64 {
            Some(
                "the mask covers the whole keyframe (all white): the result is made of the views alone, and what no view sees is invented",
            )
        } else {
            None
        }
    }

    /// What a mask file that covers most of the keyframe but not all of it probably is, in
    /// a user's words (black strokes on white, the convention of some editors, mark all but
    /// the strokes); `None` for any other. [`Mask::mistake`] says the rest.
    pub fn inverted(&self) -> Option<&'static str> {
        let masked = self.hole_count() as f64;
        let all = self.data.len() as f64;
        (masked >= MOSTLY_MASKED * all && masked < 0.999 * all).then_some(
            "the mask covers most of the keyframe: white is what is removed and black what is kept; is it inverted?",
        )
    }
}

/// A mask file that asks to remove more than this share of the keyframe is probably
/// inverted ([`Mask::inverted`]): people, cars and trees in front of a facade leave most of
/// it to be seen.
const MOSTLY_MASKED: f64 = 0.75;

/// The four samples around a real-valued position of a `w × h` image and the weights
/// between them: indices of the top-left, top-right, bottom-left and bottom-right
/// neighbours, and the fractions `fx`, `fy`. `None` when the 2×2 neighbourhood is not
/// inside the image (a position on the last row or column counts when it is exactly on it).
#[inline]
fn bilinear_taps(w: usize, h: usize, x: f32, y: f32) -> Option<([usize; 4], f32, f32)> {
    if !(x >= 0.0 && y >= 0.0) {
        return None;
    }
    let x0 = x as usize;
    let y0 = y as usize;
    if x0 >= w || y0 >= h {
        return None;
    }
    let fx = x - x0 as f32;
    let fy = y - y0 as f32;
    let x1 = if x0 + 1 < w {
        x0 + 1
    } else if fx == 0.0 {
        x0
    } else {
        return None;
    };
    let y1 = if y0 + 1 < h {
        y0 + 1
    } else if fy == 0.0 {
        y0
    } else {
        return None;
    };
    Some(([y0 * w + x0, y0 * w + x1, y1 * w + x0, y1 * w + x1], fx, fy))
}

/// Samples a grey image at a real-valued position with bilinear interpolation.
///
/// Returns `None` when the 2×2 neighbourhood is not inside the image (so callers can tell
/// "not seen" from "black").
#[inline]
pub fn bilinear(img: &GrayF32, x: f32, y: f32) -> Option<f32> {
    let ([i00, i01, i10, i11], fx, fy) = bilinear_taps(img.width, img.height, x, y)?;
    let d = &img.data;
    let (a, b, c, e) = (d[i00], d[i01], d[i10], d[i11]);
    let top = a + (b - a) * fx;
    let bottom = c + (e - c) * fx;
    Some(top + (bottom - top) * fy)
}

/// Bilinear sample with the coordinates clamped to the image (never fails).
#[inline]
pub fn bilinear_clamped(img: &GrayF32, x: f32, y: f32) -> f32 {
    let x = x.clamp(0.0, (img.width - 1) as f32);
    let y = y.clamp(0.0, (img.height - 1) as f32);
    bilinear(img, x, y).unwrap_or(0.0)
}

/// Samples an RGB image at a real-valued position with bilinear interpolation; `None`
/// outside the image.
#[inline]
pub fn bilinear_rgb<P: RgbPixel>(img: &Plane<P>, x: f32, y: f32) -> Option<[f32; 3]> {
    let ([i00, i01, i10, i11], fx, fy) = bilinear_taps(img.width, img.height, x, y)?;
    let d = &img.data;
    let (a, b, c, e) = (d[i00].to_f32(), d[i01].to_f32(), d[i10].to_f32(), d[i11].to_f32());
    let mut out = [0.0; 3];
    for k in 0..3 {
        let top = a[k] + (b[k] - a[k]) * fx;
        let bottom = c[k] + (e[k] - c[k]) * fx;
        out[k] = top + (bottom - top) * fy;
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bilinear_interpolates_and_refuses_outside() {
        let img = GrayF32::from_fn(3, 2, |x, y| (x + 10 * y) as f32);
        assert_eq!(bilinear(&img, 0.0, 0.0), Some(0.0));
        assert_eq!(bilinear(&img, 2.0, 1.0), Some(12.0));
        assert!((bilinear(&img, 0.5, 0.5).unwrap() - 5.5).abs() < 1e-6);
        assert_eq!(bilinear(&img, -0.1, 0.0), None);
        assert_eq!(bilinear(&img, 2.1, 0.0), None);
        assert_eq!(bilinear(&img, 0.0, 1.5), None);
    }

    #[test]
    fn rgb_bilinear_matches_grey_per_channel() {
        let g = GrayF32::from_fn(4, 4, |x, y| (x * y) as f32);
        let c = g.map(|&v| [v, 2.0 * v, -v]);
        let s = bilinear_rgb(&c, 1.3, 2.7).unwrap();
        let v = bilinear(&g, 1.3, 2.7).unwrap();
        assert!((s[0] - v).abs() < 1e-5 && (s[1] - 2.0 * v).abs() < 1e-5 && (s[2] + v).abs() < 1e-5);
    }

    #[test]
    fn eight_bit_pixels_sample_as_their_f32_copy() {
        let img8 = Rgb8::from_fn(5, 4, |x, y| [(x * 60) as u8, (y * 80) as u8, (x * y * 17) as u8]);
        let img = img8.map(|p| p.map(|v| v as f32 / 255.0));
        assert_eq!([0u8, 128, 255].to_f32(), [0.0, 128.0 / 255.0, 1.0]);
        for (x, y) in [(0.0, 0.0), (1.3, 2.7), (3.99, 0.5), (4.0, 3.0)] {
            assert_eq!(bilinear_rgb(&img8, x, y), bilinear_rgb(&img, x, y), "at {x},{y}");
        }
        assert_eq!(bilinear_rgb(&img8, 4.5, 0.0), None);
    }

    #[test]
    fn hole_bounds_crop_and_paste() {
        let mut m = Mask::new(20, 10, 0);
        assert_eq!(m.hole_bounds(), None);
        m.set(3, 4, 255);
        m.set(11, 7, 200);
        m.set(15, 2, 100); // not a hole
        let r = m.hole_bounds().unwrap();
        assert_eq!(r, Rect::from_corners(3, 4, 12, 8));
        let img = GrayF32::from_fn(20, 10, |x, y| (x + 100 * y) as f32);
        let part = img.crop(r);
        assert_eq!((part.width(), part.height(), part.get(0, 0), part.get(8, 3)), (9, 4, 403.0, 711.0));
        let mut blank = GrayF32::new(20, 10, 0.0);
        blank.paste(&part, r);
        assert_eq!(blank.get(11, 7), 711.0);
        assert_eq!(blank.get(2, 4), 0.0);
    }

    #[test]
    fn a_mask_over_most_of_the_keyframe_is_probably_inverted() {
        let mask = |holes: usize| Mask::from_fn(100, 10, |x, y| if y * 100 + x < holes { 255 } else { 0 });
        assert_eq!(mask(740).inverted(), None);
        assert!(mask(760).inverted().is_some_and(|w| w.contains("inverted")));
        assert_eq!(mask(1000).inverted(), None, "all white: `mistake` says so");
        assert!(mask(1000).mistake().is_some() && mask(760).mistake().is_none());
    }

    #[test]
    fn mask_counts_holes_above_127() {
        let m = Mask::from_vec(4, 1, vec![0, 127, 128, 255]);
        assert_eq!(m.hole_count(), 2);
        assert!(!m.is_hole(1, 0) && m.is_hole(2, 0));
    }
}
