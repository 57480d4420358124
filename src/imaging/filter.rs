//! Separable Gaussian smoothing and image gradients (pure layer).

use rayon::prelude::*;

use super::GrayF32;

/// A normalised 1-D Gaussian kernel of standard deviation `sigma`, radius ⌈3σ⌉.
pub fn gaussian_kernel(sigma: f32) -> Vec<f32> {
    let radius = (3.0 * sigma).ceil().max(1.0) as usize;
    let mut k: Vec<f32> = (0..=2 * radius)
        .map(|i| {
            let d = i as f32 - radius as f32;
            (-d * d / (2.0 * sigma * sigma)).exp()
        })
        .collect();
    let sum: f32 = k.iter().sum();
    k.iter_mut().for_each(|v| *v /= sum);
    k
}

/// Gaussian blur with standard deviation `sigma` (borders replicate the edge pixel).
pub fn gaussian_blur(src: &GrayF32, sigma: f32) -> GrayF32 {
    let mut out = GrayF32::new(0, 0, 0.0);
    let mut scratch = GrayF32::new(0, 0, 0.0);
    gaussian_blur_into(src, sigma, &mut scratch, &mut out);
    out
}

/// [`gaussian_blur`] into reused buffers.
pub fn gaussian_blur_into(src: &GrayF32, sigma: f32, scratch: &mut GrayF32, out: &mut GrayF32) {
    separable_into(src, &gaussian_kernel(sigma), scratch, out);
}

/// Convolves with `kernel` along rows, then along columns (odd-length, centred kernel).
pub fn separable_into(src: &GrayF32, kernel: &[f32], scratch: &mut GrayF32, out: &mut GrayF32) {
    let (w, h) = (src.width(), src.height());
    let r = kernel.len() / 2;
    scratch.reset(w, h, 0.0);
    out.reset(w, h, 0.0);
    if w == 0 || h == 0 {
        return;
    }
    // Rows: pad each row by replication so the inner loop has no branches.
    scratch.as_mut_slice().par_chunks_mut(w).enumerate().for_each_init(
        || vec![0.0f32; w + 2 * r],
        |padded, (y, dst)| {
            let row = src.row(y);
            padded[r..r + w].copy_from_slice(row);
            let (first, last) = (row[0], row[w - 1]);
            padded[..r].iter_mut().for_each(|v| *v = first);
            padded[r + w..].iter_mut().for_each(|v| *v = last);
            // Tap by tap over the whole row: contiguous, so it vectorises.
            dst.iter_mut().for_each(|d| *d = 0.0);
            for (i, &k) in kernel.iter().enumerate() {
                for (d, s) in dst.iter_mut().zip(&padded[i..i + w]) {
                    *d += k * s;
                }
            }
        },
    );
    // Columns: accumulate whole rows, which is cache-friendly and vectorises.
    let tmp = &*scratch;
    out.as_mut_slice().par_chunks_mut(w).enumerate().for_each(|(y, dst)| {
        for (i, &k) in kernel.iter().enumerate() {
            let yy = (y as isize + i as isize - r as isize).clamp(0, h as isize - 1) as usize;
            for (d, s) in dst.iter_mut().zip(tmp.row(yy)) {
                *d += k * s;
            }
        }
    });
}

/// Central-difference gradients `(∂x, ∂y)`, replicated at the borders.
pub fn gradients(src: &GrayF32) -> (GrayF32, GrayF32) {
    let (w, h) = (src.width(), src.height());
    let mut gx = GrayF32::new(w, h, 0.0);
    let mut gy = GrayF32::new(w, h, 0.0);
    if w == 0 || h == 0 {
        return (gx, gy);
    }
    gx.as_mut_slice().par_chunks_mut(w).zip(gy.as_mut_slice().par_chunks_mut(w)).enumerate().for_each(
        |(y, (rx, ry))| {
            let row = src.row(y);
            let up = src.row(y.saturating_sub(1));
            let down = src.row((y + 1).min(h - 1));
            for x in 0..w {
                let l = row[x.saturating_sub(1)];
                let r = row[(x + 1).min(w - 1)];
                rx[x] = 0.5 * (r - l);
                ry[x] = 0.5 * (down[x] - up[x]);
            }
        },
    );
    (gx, gy)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kernel_is_normalised_and_symmetric() {
        let k = gaussian_kernel(1.5);
        assert!((k.iter().sum::<f32>() - 1.0).abs() < 1e-5);
        for i in 0..k.len() / 2 {
            assert!((k[i] - k[k.len() - 1 - i]).abs() < 1e-7);
        }
    }

    #[test]
    fn blur_keeps_constant_and_mean() {
        let flat = GrayF32::new(9, 7, 0.25);
        assert!(gaussian_blur(&flat, 2.0).as_slice().iter().all(|v| (v - 0.25).abs() < 1e-6));
        let spike = GrayF32::from_fn(21, 21, |x, y| if x == 10 && y == 10 { 1.0 } else { 0.0 });
        let b = gaussian_blur(&spike, 1.0);
        assert!((b.as_slice().iter().sum::<f32>() - 1.0).abs() < 1e-4);
        assert!(b.get(10, 10) > b.get(11, 10) && b.get(11, 10) > b.get(12, 10));
    }

    #[test]
    fn gradient_of_a_ramp() {
        let ramp = GrayF32::from_fn(6, 5, |x, y| 2.0 * x as f32 - 3.0 * y as f32);
        let (gx, gy) = gradients(&ramp);
        assert!((gx.get(2, 2) - 2.0).abs() < 1e-6);
        assert!((gy.get(2, 2) + 3.0).abs() < 1e-6);
    }
}
