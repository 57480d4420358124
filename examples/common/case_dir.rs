//! The folder layout of a generated fill case, shared by the examples that write them
//! (`fill_cases`, `service_cases`) for the scripts in `bench/` that read them.

use std::path::Path;

use clearview::imaging::convert::{mask_to_luma8, to_rgb8};
use clearview::imaging::{Mask, RgbF32};

/// Writes `key.png`, `mask.png`, `truth.png` and `view-1.png`… into `dir`.
pub fn save_case(dir: &Path, key: &RgbF32, mask: &Mask, truth: &RgbF32, views: &[RgbF32]) {
    std::fs::create_dir_all(dir).unwrap();
    to_rgb8(key).save(dir.join("key.png")).unwrap();
    mask_to_luma8(mask).save(dir.join("mask.png")).unwrap();
    to_rgb8(truth).save(dir.join("truth.png")).unwrap();
    for (i, v) in views.iter().enumerate() {
        to_rgb8(v).save(dir.join(format!("view-{}.png", i + 1))).unwrap();
    }
    println!("{}: {} masked pixels, {} views", dir.display(), mask.hole_count(), views.len());
}
