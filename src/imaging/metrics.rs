//! How close a result is to the truth over the pixels that were filled: PSNR and SSIM
//! restricted to a mask (pure layer). Tests, benchmarks and the demo all judge the fill
//! with these.

use super::convert::luminance;
use super::{Mask, RgbF32};

/// Intersection over union of two masks (> 127 marked); 1 when both are empty.
pub fn mask_iou(a: &Mask, b: &Mask) -> f64 {
    let (mut inter, mut union) = (0usize, 0usize);
    for (&p, &q) in a.as_slice().iter().zip(b.as_slice()) {
        inter += usize::from(p > 127 && q > 127);
        union += usize::from(p > 127 || q > 127);
    }
    if union == 0 { 1.0 } else { inter as f64 / union as f64 }
}

/// PSNR in dB of `img` against `truth` over the pixels `mask` marks, all three channels,
/// for values in 0..=1; infinite where they agree exactly, `NaN` for an empty mask.
pub fn masked_psnr(img: &RgbF32, truth: &RgbF32, mask: &Mask) -> f64 {
    let (mut se, mut n) = (0.0f64, 0usize);
    for ((a, b), &m) in img.as_slice().iter().zip(truth.as_slice()).zip(mask.as_slice()) {
        if m > 127 {
            for c in 0..3 {
                se += f64::from(a[c] - b[c]).powi(2);
            }
            n += 3;
        }
    }
    if n == 0 {
        f64::NAN
    } else if se == 0.0 {
        f64::INFINITY
    } else {
        10.0 * (n as f64 / se).log10()
    }
}

/// A pixel is grossly wrong when some channel is off by more than this many 8-bit levels.
pub const GROSS_LEVELS: f32 = 30.0;

/// How honest a result's confidence map is about its errors, over the masked pixels.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Honesty {
    pub masked: usize,
    /// Masked pixels marked confident (confidence >= 128).
    pub confident: usize,
    /// Masked pixels with a gross error ([`GROSS_LEVELS`]).
    pub gross: usize,
    /// Confident pixels with a gross error.
    pub confident_gross: usize,
}

impl Honesty {
    /// Share of the mask marked confident.
    pub fn confident_share(&self) -> f64 {
        ratio(self.confident, self.masked)
    }
    /// Share of the confident pixels that are grossly wrong (the issue asks <= 8 %).
    pub fn confident_error_rate(&self) -> f64 {
        ratio(self.confident_gross, self.confident)
    }
    /// Share of the grossly wrong pixels marked not confident (the issue asks >= 60 %);
    /// 1 when nothing is grossly wrong.
    pub fn flagged_recall(&self) -> f64 {
        if self.gross == 0 { 1.0 } else { ratio(self.gross - self.confident_gross, self.gross) }
    }
    /// Sums the counts of several cases.
    pub fn add(&mut self, o: &Honesty) {
        self.masked += o.masked;
        self.confident += o.confident;
        self.gross += o.gross;
        self.confident_gross += o.confident_gross;
    }
}

fn ratio(a: usize, b: usize) -> f64 {
    if b == 0 { 0.0 } else { a as f64 / b as f64 }
}

/// The honesty figures of `img` against `truth` with its `confidence` map (>= 128 sure),
/// over the pixels `mask` marks. Values are 0..=1; an error counts on 8-bit levels.
pub fn honesty(img: &RgbF32, truth: &RgbF32, mask: &Mask, confidence: &Mask) -> Honesty {
    let mut h = Honesty::default();
    for (((a, b), &m), &c) in
        img.as_slice().iter().zip(truth.as_slice()).zip(mask.as_slice()).zip(confidence.as_slice())
    {
        if m <= 127 {
            continue;
        }
        h.masked += 1;
        let sure = c >= 128;
        let to8 = |v: f32| (v * 255.0).round().clamp(0.0, 255.0);
        let gross = (0..3).any(|k| (to8(a[k]) - to8(b[k])).abs() > GROSS_LEVELS);
        h.confident += usize::from(sure);
        h.gross += usize::from(gross);
        h.confident_gross += usize::from(sure && gross);
    }
    h
}

/// Mean SSIM of the luminance over 7×7 windows centred on the masked pixels (uniform
/// window, the usual constants for a 0..=1 range); windows that would leave the image
/// are skipped. `NaN` when no window counts.
pub fn masked_ssim(img: &RgbF32, truth: &RgbF32, mask: &Mask) -> f64 {
    let (a, b) = (luminance(img), luminance(truth));
    let (c1, c2) = (0.01f64.powi(2), 0.03f64.powi(2));
    let (w, h) = (a.width(), a.height());
    let (mut sum, mut n) = (0.0, 0usize);
    for y in 3..h.saturating_sub(3) {
        for x in 3..w.saturating_sub(3) {
            if !mask.is_hole(x, y) {
                continue;
            }
            let (mut sa, mut sb, mut saa, mut sbb, mut sab) = (0.0f64, 0.0, 0.0, 0.0, 0.0);
            for yy in y - 3..=y + 3 {
                for xx in x - 3..=x + 3 {
                    let (p, q) = (f64::from(a.get(xx, yy)), f64::from(b.get(xx, yy)));
                    sa += p;
                    sb += q;
                    saa += p * p;
                    sbb += q * q;
                    sab += p * q;
                }
            }
            let k = 49.0;
            let (ma, mb) = (sa / k, sb / k);
            let (va, vb, cov) = (saa / k - ma * ma, sbb / k - mb * mb, sab / k - ma * mb);
            sum += ((2.0 * ma * mb + c1) * (2.0 * cov + c2)) / ((ma * ma + mb * mb + c1) * (va + vb + c2));
            n += 1;
        }
    }
    if n == 0 { f64::NAN } else { sum / n as f64 }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn psnr_and_ssim_of_known_differences() {
        let truth = RgbF32::from_fn(20, 20, |x, y| [((x * 7 + y * 3) % 11) as f32 / 10.0; 3]);
        let mut mask = Mask::new(20, 20, 0);
        for y in 5..15 {
            for x in 5..15 {
                mask.set(x, y, 255);
            }
        }
        assert_eq!(masked_psnr(&truth, &truth, &mask), f64::INFINITY);
        assert!((masked_ssim(&truth, &truth, &mask) - 1.0).abs() < 1e-9);
        // An error of 0.1 everywhere: MSE 0.01, 20 dB, whatever lies outside the mask.
        let mut off = truth.map(|p| p.map(|v| v + 0.1));
        off.set(0, 0, [9.0; 3]);
        assert!((masked_psnr(&off, &truth, &mask) - 20.0).abs() < 1e-4);
        // A constant shift keeps structure but not luminance: SSIM just under 1.
        let s = masked_ssim(&off, &truth, &mask);
        assert!(s < 1.0 && s > 0.9, "{s}");
        assert!(masked_psnr(&truth, &truth, &Mask::new(20, 20, 0)).is_nan());
    }
}
