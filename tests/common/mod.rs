//! Helpers shared by the integration tests: the real data beside the project, and
//! ground-truth homographies.
#![allow(dead_code)]

use std::path::{Path, PathBuf};

use clearview::geometry::Homography;
use clearview::imaging::RgbF32;
use clearview::imaging::convert::luminance;
use clearview::session::{FillOutcome, Session};

/// `../shared/data` relative to the project root, or `None` (with the reason printed) when
/// it is absent: tests on real images skip only then.
pub fn data_dir() -> Option<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data");
    if dir.is_dir() {
        Some(dir)
    } else {
        eprintln!("skipping: {} is absent (the shared data set lives beside the project)", dir.display());
        None
    }
}

/// A 3×3 matrix in any of the data set's text layouts (`%e`, Java doubles, blank lines).
pub fn read_homography(path: &Path) -> Homography {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let v: Vec<f64> = text
        .split_whitespace()
        .map(|t| t.parse().unwrap_or_else(|e| panic!("{}: {t:?}: {e}", path.display())))
        .collect();
    assert_eq!(v.len(), 9, "{}: expected 9 numbers", path.display());
    Homography::from_rows([[v[0], v[1], v[2]], [v[3], v[4], v[5]], [v[6], v[7], v[8]]]).expect("regular H")
}

/// The ground truth for `img1 → imgN` of a sequence, refined where a refined file exists.
pub fn ground_truth(seq: &Path, n: usize) -> Homography {
    let refined = seq.join(format!("H1to{n}p.refined"));
    if refined.exists() { read_homography(&refined) } else { read_homography(&seq.join(format!("H1to{n}p"))) }
}

/// The image `imgN` of a sequence, whatever its extension.
pub fn sequence_image(seq: &Path, n: usize) -> PathBuf {
    for ext in ["png", "jpg", "ppm"] {
        let p = seq.join(format!("img{n}.{ext}"));
        if p.exists() {
            return p;
        }
    }
    panic!("{}: no img{n}", seq.display());
}

/// Feeds `views` to session `s` (its keyframe and mask set), each aligned by the session
/// and admitted as `view<i>`, filling after each batch (`batches`: the batch sizes, in
/// order): the outcome of each fill.
pub fn fill_in_batches(s: &mut Session, views: &[RgbF32], batches: &[usize]) -> Vec<FillOutcome> {
    let mut next = views.iter().enumerate();
    let mut outcomes = Vec::new();
    for &n in batches {
        for (i, v) in next.by_ref().take(n) {
            let record = s.align(luminance(v)).unwrap();
            assert!(record.accepted, "view {i} refused: {:?}", record.reason);
            let pixels = v.map(|p| p.map(|c| (c.clamp(0.0, 1.0) * 255.0).round() as u8));
            s.admit(format!("view{i}"), record, Some(&pixels)).unwrap();
        }
        s.request_fill();
        outcomes.push(s.fill(&mut ()).expect("a fill"));
    }
    outcomes
}
