//! `clearview align` as a user runs it: the real binary on files made in the test, its
//! JSON, its words and its exit codes (0 accepted, 3 rejected, 1 unreadable, 64 usage).

use std::path::Path;
use std::process::{Command, Output};

use clearview::geometry::Homography;
use clearview::imaging::convert::to_rgb8;
use clearview::synth;

const BIN: &str = env!("CARGO_BIN_EXE_clearview");

fn run(args: &[&std::ffi::OsStr]) -> Output {
    Command::new(BIN).args(args).output().expect("the binary runs")
}

/// Writes a keyframe, a view of the same facade through `truth`, and an unrelated facade.
fn scene(dir: &Path, truth: &Homography) {
    let (w, h) = (480, 360);
    let facade = synth::facade(w * 2, h * 2, 4);
    let centre = Homography::translation(w as f64 / 2.0, h as f64 / 2.0);
    let key = synth::render_view(&facade, &centre, w, h, [0.5; 3]);
    let view = synth::render_view(&facade, &centre.after(&truth.inverse().unwrap()), w, h, [0.5; 3]);
    to_rgb8(&key).save(dir.join("key.png")).unwrap();
    to_rgb8(&view).save(dir.join("view.jpg")).unwrap();
    to_rgb8(&synth::facade(w, h, 999)).save(dir.join("other.png")).unwrap();
}

#[test]
fn aligned_pair_prints_json_with_the_homography_and_exits_0() {
    let dir = tempfile::tempdir().unwrap();
    let truth = Homography::from_rows([[0.97, 0.1, 14.0], [-0.08, 1.02, -9.0], [5e-5, -8e-5, 1.0]]).unwrap();
    scene(dir.path(), &truth);
    let out = run(&[
        "align".as_ref(),
        "--json".as_ref(),
        dir.path().join("key.png").as_os_str(),
        dir.path().join("view.jpg").as_os_str(),
    ]);
    assert_eq!(out.status.code(), Some(0), "stderr: {}", String::from_utf8_lossy(&out.stderr));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).expect("one JSON object");
    for key in ["homography", "inliers", "matches", "median_residual_px", "accepted", "time_ms"] {
        assert!(v.get(key).is_some(), "missing {key} in {v}");
    }
    assert_eq!(v["accepted"], true);
    let rows: Vec<Vec<f64>> = serde_json::from_value(v["homography"].clone()).unwrap();
    let h = Homography::from_rows([0, 1, 2].map(|r| [rows[r][0], rows[r][1], rows[r][2]])).unwrap();
    let err = h.mean_corner_error(&truth, 480, 360);
    assert!(err < 0.5, "corner error {err} px");
    assert!(v["inliers"].as_u64().unwrap() >= 20);
}

#[test]
fn text_output_names_the_files_and_the_verdict() {
    let dir = tempfile::tempdir().unwrap();
    scene(dir.path(), &Homography::translation(6.0, -4.0));
    let out = run(&[
        "align".as_ref(),
        dir.path().join("key.png").as_os_str(),
        dir.path().join("view.jpg").as_os_str(),
    ]);
    assert_eq!(out.status.code(), Some(0));
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("key.png") && text.contains("view.jpg"), "{text}");
    assert!(text.contains("verdict  accepted"), "{text}");
}

#[test]
fn another_scene_is_rejected_with_a_reason_and_exit_3() {
    let dir = tempfile::tempdir().unwrap();
    scene(dir.path(), &Homography::identity());
    let out = run(&[
        "align".as_ref(),
        "--json".as_ref(),
        dir.path().join("key.png").as_os_str(),
        dir.path().join("other.png").as_os_str(),
    ]);
    assert_eq!(out.status.code(), Some(3), "stdout: {}", String::from_utf8_lossy(&out.stdout));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("other.png") && err.contains("rejected"), "{err}");
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["accepted"], false);
}

#[test]
fn unreadable_files_exit_1_naming_the_file_and_the_reason() {
    let dir = tempfile::tempdir().unwrap();
    scene(dir.path(), &Homography::identity());
    let key = dir.path().join("key.png");
    // Missing, empty, garbage, truncated.
    let missing = dir.path().join("missing.png");
    let empty = dir.path().join("empty.jpg");
    std::fs::write(&empty, b"").unwrap();
    let garbage = dir.path().join("garbage.png");
    std::fs::write(&garbage, b"this is not an image at all").unwrap();
    let truncated = dir.path().join("truncated.png");
    let bytes = std::fs::read(&key).unwrap();
    std::fs::write(&truncated, &bytes[..bytes.len() / 2]).unwrap();
    for (path, words) in [
        (&missing, "cannot read"),
        (&empty, "empty file"),
        (&garbage, "not an image"),
        (&truncated, "cannot decode"),
    ] {
        let out = run(&["align".as_ref(), key.as_os_str(), path.as_os_str()]);
        assert_eq!(out.status.code(), Some(1), "{}", path.display());
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(&*path.to_string_lossy()) && err.contains(words), "{}: {err}", path.display());
    }
}

#[test]
fn a_decompression_bomb_is_refused_by_the_pixel_limit() {
    let dir = tempfile::tempdir().unwrap();
    scene(dir.path(), &Homography::identity());
    let key = dir.path().join("key.png");
    let out =
        run(&["align".as_ref(), "--max-pixels".as_ref(), "1000".as_ref(), key.as_os_str(), key.as_os_str()]);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("more than the limit of 1000"), "{err}");
}

#[test]
fn bad_usage_exits_64() {
    assert_eq!(run(&["align".as_ref()]).status.code(), Some(64));
    assert_eq!(
        run(&["align".as_ref(), "--estimator".as_ref(), "magic".as_ref(), "a".as_ref(), "b".as_ref()])
            .status
            .code(),
        Some(64)
    );
    assert_eq!(run(&["no-such-command".as_ref()]).status.code(), Some(64));
    assert_eq!(run(&["--help".as_ref()]).status.code(), Some(0));
}

#[test]
fn the_keyframes_mask_is_taken_and_a_wrong_sized_one_is_usage() {
    let dir = tempfile::tempdir().unwrap();
    let truth = Homography::from_rows([[0.98, 0.04, 10.0], [-0.03, 1.0, -6.0], [3e-5, 0.0, 1.0]]).unwrap();
    scene(dir.path(), &truth);
    // A tree-sized hole over the keyframe's left part, as a user paints it.
    let mask =
        image::GrayImage::from_fn(480, 360, |x, y| image::Luma([if x < 190 && y > 40 { 255 } else { 0 }]));
    mask.save(dir.path().join("mask.png")).unwrap();
    let align = |extra: &[&std::ffi::OsStr]| {
        let mut args: Vec<&std::ffi::OsStr> = vec!["align".as_ref(), "--json".as_ref()];
        args.extend_from_slice(extra);
        let (key, view) = (dir.path().join("key.png"), dir.path().join("view.jpg"));
        args.extend_from_slice(&[key.as_os_str(), view.as_os_str()]);
        let out = run(&args);
        (out.status.code(), serde_json::from_slice::<serde_json::Value>(&out.stdout).ok(), out.stderr)
    };
    // Which corners the mask keeps out is the library's test (align.rs); here, that the
    // flag reaches it, and the alignment from the rest is as good.
    let (code, plain, _) = align(&[]);
    assert_eq!(code, Some(0));
    let mask_path = dir.path().join("mask.png");
    let (code, masked, err) = align(&["--mask".as_ref(), mask_path.as_os_str()]);
    assert_eq!(code, Some(0), "{}", String::from_utf8_lossy(&err));
    let (plain, masked) = (plain.unwrap(), masked.unwrap());
    let corners = |v: &serde_json::Value| v["key_corners"].as_u64().unwrap();
    assert!(corners(&masked) < corners(&plain) * 8 / 10, "{} of {}", corners(&masked), corners(&plain));
    let rows: Vec<Vec<f64>> = serde_json::from_value(masked["homography"].clone()).unwrap();
    let h = Homography::from_rows([0, 1, 2].map(|r| [rows[r][0], rows[r][1], rows[r][2]])).unwrap();
    assert!(h.mean_corner_error(&truth, 480, 360) < 0.5);

    image::GrayImage::new(100, 80).save(dir.path().join("small.png")).unwrap();
    let small = dir.path().join("small.png");
    let (code, _, err) = align(&["--mask".as_ref(), small.as_os_str()]);
    let err = String::from_utf8_lossy(&err);
    assert_eq!(code, Some(64), "{err}");
    assert!(err.contains("100x80") && err.contains("480x360"), "{err}");
}
