//! `clearview fill` as a user runs it: the real binary on a scene made in the test.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use clearview::imaging::convert::{mask_to_luma8, to_rgb, to_rgb8};
use clearview::imaging::metrics::masked_psnr;
use clearview::imaging::{Mask, RgbF32};
use clearview::synth;

mod common;

const BIN: &str = env!("CARGO_BIN_EXE_clearview");
const W: usize = 480;
const H: usize = 360;

struct Scene {
    dir: tempfile::TempDir,
    /// The keyframe as it would be without the occluder.
    truth: RgbF32,
    mask: Mask,
    views: Vec<PathBuf>,
}

impl Scene {
    fn path(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }
}

/// A keyframe with a tree in front of the facade, its mask, and three views from elsewhere,
/// each with a person in a different place and its own exposure.
fn scene() -> Scene {
    let synth::TreeScene { truth, key, mask, views } = synth::tree_scene(W, H, 21, 8);
    write_scene(&key, &mask, truth, &views)
}

fn fill<S: AsRef<std::ffi::OsStr>>(args: impl IntoIterator<Item = S>) -> Output {
    Command::new(BIN).arg("fill").args(args).output().expect("the binary runs")
}

/// `fill` with `args`, which must succeed.
fn fill_ok<S: AsRef<std::ffi::OsStr>>(args: impl IntoIterator<Item = S>) -> Output {
    let o = fill(args);
    assert_eq!(o.status.code(), Some(0), "stderr: {}", String::from_utf8_lossy(&o.stderr));
    o
}

/// The usual arguments: keyframe, its mask, `out`, `report`, then the scene's views.
fn args(s: &Scene, out: &Path, report: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = vec![
        "--keyframe".into(),
        s.path("key.png"),
        "--mask".into(),
        s.path("key.mask.png"),
        "--out".into(),
        out.into(),
        "--report".into(),
        report.into(),
    ];
    v.extend(s.views.iter().cloned());
    v
}

#[test]
fn fills_the_mask_writes_a_report_and_leaves_the_rest_alone() {
    let s = scene();
    let (out, report) = (s.path("clear.png"), s.path("report.json"));
    fill_ok(args(&s, &out, &report));
    let result = to_rgb(&image::open(&out).unwrap());
    let key = to_rgb(&image::open(s.path("key.png")).unwrap());
    assert_eq!((result.width(), result.height()), (W, H));
    // Outside the mask the keyframe's own pixels, exactly.
    for ((r, k), &m) in result.as_slice().iter().zip(key.as_slice()).zip(s.mask.as_slice()) {
        if m <= 127 {
            assert_eq!(r, k);
        }
    }
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    assert_eq!(v["masked_pixels"].as_u64().unwrap() as usize, s.mask.hole_count());
    assert_eq!(v["views"].as_array().unwrap().len(), 3);
    let stages: Vec<&str> =
        v["timings_ms"].as_array().unwrap().iter().map(|t| t[0].as_str().unwrap()).collect();
    assert!(
        stages.contains(&"decode") && stages.contains(&"align") && stages.contains(&"write"),
        "{stages:?}"
    );
    let psnr = masked_psnr(&result, &s.truth, &s.mask);
    println!("masked PSNR {psnr:.2} dB");
    // Measured 26.8 dB; the fallback alone (nothing from the views) gives about 14.
    assert!(psnr > 23.0, "masked PSNR {psnr:.2} dB");
    let from_views = v["share_from_views"].as_f64().unwrap();
    assert!(from_views > 0.95, "only {from_views:.3} of the mask from the views");
}

#[test]
fn a_bad_view_is_reported_and_skipped_and_the_rest_still_fill() {
    let mut s = scene();
    let bad = s.path("broken.jpg");
    std::fs::write(&bad, b"\xff\xd8\xff\xe0 truncated").unwrap();
    let other = s.path("other.png");
    to_rgb8(&synth::facade(W, H, 777)).save(&other).unwrap();
    s.views.push(bad.clone());
    s.views.push(other.clone());
    let (out, report) = (s.path("clear.jpg"), s.path("report.json"));
    let o = fill_ok(args(&s, &out, &report));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("broken.jpg") && err.contains("other.png"), "{err}");
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    let views = v["views"].as_array().unwrap();
    assert_eq!(views.iter().filter(|v| v["accepted"] == true).count(), 3);
    // A JPEG header with nothing after it: refused as cut short, naming the file.
    let reason = views[3]["reason"].as_str().unwrap();
    assert!(reason.contains("broken.jpg") && reason.contains("cut short"), "{}", views[3]);
    assert_eq!(views[4]["accepted"], false);
    assert!(image::open(&out).is_ok());
}

#[test]
fn every_view_rejected_still_writes_a_result_and_exits_3() {
    let s = scene();
    let other = s.path("other.png");
    to_rgb8(&synth::facade(W, H, 778)).save(&other).unwrap();
    let out = s.path("clear.png");
    let o = fill([
        "--keyframe".into(),
        s.path("key.png"),
        "--mask".into(),
        s.path("key.mask.png"),
        "--out".into(),
        out.clone(),
        other.clone(),
    ]);
    assert_eq!(o.status.code(), Some(3), "stderr: {}", String::from_utf8_lossy(&o.stderr));
    assert!(image::open(&out).is_ok());
}

#[test]
fn a_mask_of_the_wrong_size_is_a_clear_error() {
    let s = scene();
    let small = s.path("small.png");
    mask_to_luma8(&Mask::new(100, 80, 255)).save(&small).unwrap();
    let out = s.path("clear.png");
    let o = fill([
        "--keyframe".into(),
        s.path("key.png"),
        "--mask".into(),
        small.clone(),
        "--out".into(),
        out.clone(),
        s.views[0].clone(),
    ]);
    assert_eq!(o.status.code(), Some(1));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("small.png") && err.contains("100x80") && err.contains("480x360"), "{err}");
    assert!(!out.exists());
}

#[test]
fn never_overwrites_an_input_and_refuses_unknown_formats() {
    let s = scene();
    let key = s.path("key.png");
    let before = std::fs::read(&key).unwrap();
    let o = fill([
        "--keyframe".into(),
        key.clone(),
        "--mask".into(),
        s.path("key.mask.png"),
        "--out".into(),
        key.clone(),
        s.views[0].clone(),
    ]);
    assert_eq!(o.status.code(), Some(64));
    assert!(String::from_utf8_lossy(&o.stderr).contains("refusing to overwrite"));
    assert_eq!(std::fs::read(&key).unwrap(), before);
    let o = fill([
        "--keyframe".into(),
        key.clone(),
        "--mask".into(),
        s.path("key.mask.png"),
        "--out".into(),
        s.path("clear.xyz"),
        s.views[0].clone(),
    ]);
    assert_eq!(o.status.code(), Some(64));
}

/// An output named in a folder that does not exist is refused before any work, with the
/// path and the reason, and nothing is written (it failed after the fill, the result
/// already written beside it). `--save-mask` with a mask file is bad usage: there is no
/// found mask to save.
#[test]
fn an_output_in_a_missing_folder_is_refused_before_the_fill() {
    let s = scene();
    let (out, report) = (s.path("clear.png"), s.path("report.json"));
    let missing = s.path("no-such-folder").join("confidence.png");
    let mut a = args(&s, &out, &report);
    a.splice(0..0, ["--confidence".into(), missing.clone()]);
    let o = fill(a);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "stderr: {err}");
    assert!(err.contains(&missing.display().to_string()) && err.contains("does not exist"), "{err}");
    assert!(!out.exists() && !report.exists(), "written before the refusal");
    let mut a = args(&s, &out, &report);
    a.splice(0..0, ["--save-mask".into(), s.path("found.png")]);
    let o = fill(a);
    assert_eq!(o.status.code(), Some(64), "stderr: {}", String::from_utf8_lossy(&o.stderr));
    assert!(!out.exists() && !s.path("found.png").exists());
}

/// `--mask auto` with one view judges by that view alone: it says so, and the mask it
/// finds covers the keyframe's tree, not the rest of the picture.
#[test]
fn an_automatic_mask_from_one_view_is_found_and_said_to_be_less_sure() {
    let s = scene();
    let (out, found) = (s.path("clear.png"), s.path("found.png"));
    let key = s.path("key.png");
    let o = fill([
        "--keyframe".into(),
        key.clone(),
        "--mask".into(),
        "auto".into(),
        "--save-mask".into(),
        found.clone(),
        "--out".into(),
        out.clone(),
        s.views[0].clone(),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(0), "stderr: {err}");
    assert!(err.contains("--mask auto") && err.contains("1 view aligned") && err.contains("surer"), "{err}");
    let (truth, mask) = (mask_of(&s.path("key.mask.png")), mask_of(&found));
    let both = truth.iter().zip(&mask).filter(|&(&t, &m)| t && m).count();
    let either = truth.iter().zip(&mask).filter(|&(&t, &m)| t || m).count();
    let iou = both as f64 / either.max(1) as f64;
    assert!(iou > 0.5, "IoU of the mask found with one view and the tree's: {iou:.3}");
}

/// The pixels of a mask file that mark a fill (> 127).
fn mask_of(path: &Path) -> Vec<bool> {
    image::open(path).unwrap().to_luma8().pixels().map(|p| p.0[0] > 127).collect()
}

/// An all-black mask (a mask exported without its strokes) fills nothing. The command says
/// so, on stderr with the mask's name and on stdout, and claims no share of the mask: "100 %
/// confident, 100 % taken from views" of an empty mask described a fill that never was. The
/// result is the keyframe, pixel for pixel.
#[test]
fn an_empty_mask_is_told_and_no_share_of_it_is_claimed() {
    let s = scene();
    let (out, report) = (s.path("clear.png"), s.path("report.json"));
    let black = s.path("black.mask.png");
    mask_to_luma8(&Mask::new(W, H, 0)).save(&black).unwrap();
    let mut a = args(&s, &out, &report);
    a[3] = black.clone();
    let o = fill_ok(a);
    let (err, text) = (String::from_utf8_lossy(&o.stderr), String::from_utf8_lossy(&o.stdout));
    assert!(err.contains(&black.display().to_string()) && err.contains("marks no pixel"), "{err}");
    assert!(text.contains("nothing filled") && !text.contains("% confident"), "{text}");
    assert!(!text.contains("filled every pixel"), "{text}");
    let (k, r) = (image::open(s.path("key.png")).unwrap().to_rgb8(), image::open(&out).unwrap().to_rgb8());
    assert!(k == r, "the result is not the keyframe");
}

/// A photograph given as the mask (the wrong file picked: it has the keyframe's size) is
/// refused with the reason: taken as a mask, every pixel over 127 would have been removed.
#[test]
fn a_photograph_given_as_the_mask_is_refused() {
    let s = scene();
    let (out, report) = (s.path("clear.png"), s.path("report.json"));
    let mut a = args(&s, &out, &report);
    a[3] = s.views[0].clone();
    let o = fill(a);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "stderr: {err}");
    assert!(err.contains(&s.views[0].display().to_string()) && err.contains("not a mask"), "{err}");
    assert!(!out.exists());
}

/// A mask painted in an editor on a transparent layer, in red, exported with the
/// transparency stored as white: read by luminance alone, every transparent pixel was
/// white ("the mask covers the whole keyframe") and the red stroke was kept. It is read as
/// the editor shows it, and the result is the one made with the black-and-white mask.
#[test]
fn a_mask_painted_on_a_transparent_layer_removes_what_was_painted() {
    let s = scene();
    let (plain, report) = (s.path("plain.png"), s.path("plain.json"));
    fill_ok(args(&s, &plain, &report));
    let layer = image::RgbaImage::from_fn(W as u32, H as u32, |x, y| {
        if s.mask.is_hole(x as usize, y as usize) {
            image::Rgba([220, 30, 30, 255])
        } else {
            image::Rgba([255, 255, 255, 0])
        }
    });
    layer.save(s.path("key.mask.png")).unwrap();
    let (out, report) = (s.path("clear.png"), s.path("report.json"));
    let o = fill_ok(args(&s, &out, &report));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!err.contains("covers the whole keyframe") && !err.contains("marks no pixel"), "{err}");
    let (a, b) = (image::open(&plain).unwrap().to_rgb8(), image::open(&out).unwrap().to_rgb8());
    assert!(a == b, "the painted layer was not read as the mask it shows");
}

/// A mask painted the other way round (black strokes on white) asks to remove all but the
/// occluder: the fill goes on, as asked (here every view is refused: the keyframe's few
/// corners left outside the mask match nothing), and says what the mask probably is.
#[test]
fn a_mask_over_most_of_the_keyframe_is_called_probably_inverted() {
    let s = scene();
    let inverted = s.mask.map(|&v| 255 - v);
    mask_to_luma8(&inverted).save(s.path("key.mask.png")).unwrap();
    let (out, report) = (s.path("clear.png"), s.path("report.json"));
    let o = fill(args(&s, &out, &report));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("key.mask.png") && err.contains("is it inverted?"), "{err}");
}

/// A glob that takes in the keyframe (`*.jpg`), or a view given twice, is what a user
/// types. The keyframe as a view shows the occluder where the mask is and painted it back
/// (on a facade with slabs, 25.3 dB fell to 16.6 dB and most of the mask went doubtful); a
/// second copy of a view witnessed its own errors twice. Both are skipped, with the reason,
/// and the result is the one made without them, pixel for pixel.
#[test]
fn the_keyframe_among_the_views_and_a_view_given_twice_are_skipped() {
    let s = scene();
    let (plain, report) = (s.path("plain.png"), s.path("plain.json"));
    fill_ok(args(&s, &plain, &report));
    let copy = s.path("copy-of-view-1.png");
    std::fs::copy(&s.views[0], &copy).unwrap();
    let (out, report) = (s.path("clear.png"), s.path("report.json"));
    let mut a = args(&s, &out, &report);
    a.extend([s.path("key.png"), copy.clone()]);
    fill_ok(a);
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    let views = v["views"].as_array().unwrap();
    assert_eq!(views.len(), 5);
    let reason = |i: usize| views[i]["reason"].as_str().unwrap_or("").to_owned();
    assert!(views[..3].iter().all(|v| v["accepted"] == true), "{views:#?}");
    assert!(views[3]["accepted"] == false && reason(3).contains("the same picture"), "{:#?}", views[3]);
    let first = s.views[0].display().to_string();
    assert!(views[4]["accepted"] == false && reason(4).contains(&first), "{:#?}", views[4]);
    let (a, b) = (image::open(&plain).unwrap().to_rgb8(), image::open(&out).unwrap().to_rgb8());
    assert!(a == b, "the result changed with the keyframe and a copy among the views");
}

/// The same shot saved again (a JPEG made from a view's file, as a phone's HEIC and its
/// JPEG, or an export, are) is not a second witness: it is skipped, naming the view, and the
/// result is the one made without it. Compared byte for byte, the copy was taken, and the
/// 16 rendered facades lost 0.9 dB with a view's JPEG added (BENCHMARKS.md, "The same shot
/// twice").
#[test]
fn the_same_shot_saved_again_is_skipped() {
    let s = scene();
    let (plain, report) = (s.path("plain.png"), s.path("plain.json"));
    fill_ok(args(&s, &plain, &report));
    let again = s.path("view-2-again.jpg");
    let view = image::open(&s.views[1]).unwrap().to_rgb8();
    let mut jpeg = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 85).encode_image(&view).unwrap();
    std::fs::write(&again, &jpeg).unwrap();
    let (out, report) = (s.path("clear.png"), s.path("report.json"));
    let mut a = args(&s, &out, &report);
    a.push(again.clone());
    fill_ok(a);
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    let views = v["views"].as_array().unwrap();
    assert_eq!(views.len(), 4);
    assert!(views[..3].iter().all(|v| v["accepted"] == true), "{views:#?}");
    let reason = views[3]["reason"].as_str().unwrap_or("");
    let first = s.views[1].display().to_string();
    assert!(
        views[3]["accepted"] == false && reason.contains("the same picture") && reason.contains(&first),
        "{:#?}",
        views[3]
    );
    let (a, b) = (image::open(&plain).unwrap().to_rgb8(), image::open(&out).unwrap().to_rgb8());
    assert!(a == b, "the result changed with a view's JPEG among the views");
}

/// A black-and-white picture among a colour keyframe's views has no colour to give: a grey
/// copy of the keyframe painted its occluder back in grey, and one of a view filled a dark
/// doorway green (the ring's gain, one tint for the whole hole), called sure. Both are
/// skipped with the reason, and the result is the one made without them. A black-and-white
/// keyframe takes colour views, and its result stays black and white (the views' colour
/// came through before); there a grey copy of a view is that view again.
#[test]
fn black_and_white_pictures_give_no_colour_and_a_black_and_white_keyframe_keeps_none() {
    let s = scene();
    let grey_copy = |from: &Path, to: &str| {
        let to = s.path(to);
        image::open(from).unwrap().to_luma8().save(&to).unwrap();
        to
    };
    let (plain, report) = (s.path("plain.png"), s.path("plain.json"));
    fill_ok(args(&s, &plain, &report));
    let (grey_key, grey_view) =
        (grey_copy(&s.path("key.png"), "key-bw.png"), grey_copy(&s.views[1], "view-2-bw.png"));
    let (out, report) = (s.path("clear.png"), s.path("report.json"));
    let mut a = args(&s, &out, &report);
    a.extend([grey_key.clone(), grey_view]);
    fill_ok(a);
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    let views = v["views"].as_array().unwrap();
    assert!(views[..3].iter().all(|v| v["accepted"] == true), "{views:#?}");
    for v in &views[3..] {
        let reason = v["reason"].as_str().unwrap_or("");
        assert!(v["accepted"] == false && reason.contains("black-and-white"), "{v:#?}");
    }
    let (a, b) = (image::open(&plain).unwrap().to_rgb8(), image::open(&out).unwrap().to_rgb8());
    assert!(a == b, "the result changed with black-and-white copies among the views");

    // The keyframe in black and white, the views in colour, and a grey copy of view 1.
    let (out, report) = (s.path("bw-clear.png"), s.path("bw-report.json"));
    let mut a = args(&s, &out, &report);
    a[1] = grey_key.clone();
    a.push(grey_copy(&s.views[0], "view-1-bw.png"));
    fill_ok(a);
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    let views = v["views"].as_array().unwrap();
    assert!(views[..3].iter().all(|v| v["accepted"] == true), "{views:#?}");
    let reason = views[3]["reason"].as_str().unwrap_or("");
    let first = s.views[0].display().to_string();
    assert!(reason.contains("the same picture") && reason.contains(&first), "{:#?}", views[3]);
    let (result, key) = (image::open(&out).unwrap().to_rgb8(), image::open(&grey_key).unwrap().to_rgb8());
    let coloured = result.pixels().filter(|p| p.0.iter().max() != p.0.iter().min()).count();
    assert_eq!(coloured, 0, "pixels with colour in a black-and-white keyframe's result");
    let changed = result.pixels().zip(key.pixels()).filter(|(r, k)| r != k).count();
    assert!(changed > s.mask.hole_count() / 2, "the mask was filled: {changed} pixels changed");
}

/// `--confidence` writes the fill's confidence as it is: 0 outside the mask, and inside every
/// grade the model gave, so that the map's mean over the mask is the report's expected
/// quality and its pixels at 128 or more are the report's confident ones. (It was written as
/// a mask, 0 or 255, and the grades were lost.)
#[test]
fn the_confidence_map_keeps_the_grades_the_report_counts() {
    let s = scene();
    let (out, report, conf) = (s.path("clear.png"), s.path("report.json"), s.path("confidence.png"));
    let mut a = args(&s, &out, &report);
    a.splice(0..0, ["--confidence".into(), conf.clone()]);
    fill_ok(a);
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    let map = image::open(&conf).unwrap().to_luma8();
    assert_eq!((map.width() as usize, map.height() as usize), (W, H));
    let (mut sum, mut sure, mut grades) = (0.0f64, 0u64, std::collections::BTreeSet::new());
    for (&c, &m) in map.as_raw().iter().zip(s.mask.as_slice()) {
        if m > 127 {
            sum += f64::from(c) / 255.0;
            sure += u64::from(c >= 128);
            grades.insert(c);
        } else {
            assert_eq!(c, 0, "confidence outside the mask");
        }
    }
    assert_eq!(sure, v["confident_pixels"].as_u64().unwrap());
    let mean = sum / s.mask.hole_count() as f64;
    let expected = v["expected_quality"].as_f64().unwrap();
    println!("mean confidence {mean:.4}, report {expected:.4}, {} grades", grades.len());
    assert!((mean - expected).abs() < 1e-6, "the map's mean {mean:.4}, the report's {expected:.4}");
    assert!(grades.len() > 2, "grades {grades:?}");
}

/// Writes a case as a user's files: keyframe, mask and views.
fn write_scene(key: &RgbF32, mask: &Mask, truth: RgbF32, rendered: &[RgbF32]) -> Scene {
    let dir = tempfile::tempdir().unwrap();
    to_rgb8(key).save(dir.path().join("key.png")).unwrap();
    mask_to_luma8(mask).save(dir.path().join("key.mask.png")).unwrap();
    let mut views = Vec::new();
    for (i, view) in rendered.iter().enumerate() {
        let p = dir.path().join(format!("view-{i}.png"));
        to_rgb8(view).save(&p).unwrap();
        views.push(p);
    }
    Scene { dir, truth, mask: mask.clone(), views }
}

/// A facade with slabs standing off the wall (`synth::facade`), three views.
fn slab_scene(flat: bool) -> Scene {
    let c = synth::facade::parallax_case(640, 480, 3, 13, flat);
    write_scene(&c.key, &c.mask, c.truth, &c.views)
}

/// `clearview fill` with `--no-planes` and as it runs by default: the result, the report,
/// stdout.
fn with_and_without_planes(s: &Scene) -> [(RgbF32, serde_json::Value, String); 2] {
    [false, true].map(|planes| {
        let name = if planes { "planes" } else { "wall" };
        let (out, report) = (s.path(&format!("{name}.png")), s.path(&format!("{name}.json")));
        let mut a = args(s, &out, &report);
        if !planes {
            a.insert(0, "--no-planes".into());
        }
        a.splice(0..0, ["--surfaces".into(), s.path(&format!("{name}.surfaces.png"))]);
        let o = fill_ok(a);
        let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
        (to_rgb(&image::open(&out).unwrap()), v, String::from_utf8_lossy(&o.stdout).into_owned())
    })
}

/// The sweep for surfaces off the wall is on by default and says what it did: the report
/// lists the surfaces the sweep found, whether the result was filled through them and the
/// masked pixels each filled, and the summary tells it. On a facade with slabs they fill
/// part of the mask and the result is closer to the truth than the wall's homography alone;
/// on the same facade without slabs nothing is found and no pixel changes. With
/// `--no-planes` the report has no `planes`.
#[test]
fn planes_reports_the_surfaces_it_filled_through() {
    let s = slab_scene(false);
    let [(wall, wall_report, _), (swept, report, stdout)] = with_and_without_planes(&s);
    assert!(wall_report.get("planes").is_none(), "{wall_report}");
    assert_eq!(report["planes"]["used"], true, "{report}");
    let surfaces = report["planes"]["surfaces"].as_array().expect("surfaces listed");
    assert!(!surfaces.is_empty(), "{report}");
    let filled: u64 = surfaces.iter().map(|p| p["filled_pixels"].as_u64().unwrap()).sum();
    let masked = report["masked_pixels"].as_u64().unwrap();
    assert!(filled > 0 && filled < masked, "{filled} of {masked} masked pixels through surfaces");
    for p in surfaces {
        assert!(p["views"].as_u64().unwrap() >= 2, "a surface seen by one view: {p}");
        assert!(p["kept"] == true || p["filled_pixels"] == 0, "filled through a surface not kept: {p}");
        assert_eq!(p["region"].as_array().unwrap().len(), 4);
    }
    assert!(stdout.contains(&format!("{filled} masked pixels filled through")), "{stdout}");
    // The surface map says the same pixel by pixel: 1 through the wall, 2 + s through
    // surface s, nothing outside the mask; without the sweep every masked pixel is the wall's.
    let counts = |name: &str| {
        let map = image::open(s.path(&format!("{name}.surfaces.png"))).unwrap().into_luma8();
        let mut n = vec![0u64; 256];
        for (&v, &m) in map.as_raw().iter().zip(s.mask.as_slice()) {
            assert!((m > 127) == (v > 0), "surface {v} where the mask is {m}");
            n[usize::from(v)] += 1;
        }
        n
    };
    let n = counts("planes");
    assert_eq!(n[1], masked - filled);
    for (k, p) in surfaces.iter().enumerate() {
        assert_eq!(n[2 + k], p["filled_pixels"].as_u64().unwrap(), "surface {k}");
    }
    assert_eq!(counts("wall")[1], masked);
    let (a, b) = (masked_psnr(&wall, &s.truth, &s.mask), masked_psnr(&swept, &s.truth, &s.mask));
    assert!(b > a + 1.5, "swept {b:.2} dB vs the wall alone {a:.2} dB");

    let [(plain, _, _), (same, report, stdout)] = with_and_without_planes(&slab_scene(true));
    assert_eq!(report["planes"]["surfaces"].as_array().map(Vec::len), Some(0), "{report}");
    assert_eq!(report["planes"]["used"], false, "{report}");
    assert!(stdout.contains("no surface off the wall found"), "{stdout}");
    assert!(plain == same, "the sweep changed pixels on a flat wall");
}

/// `service_cases`' nonplanar-5: a pier stands off the wall, and the sweep finds it in
/// three views of four. The fourth, which has no homography for it, shows its own occluder
/// in the window beside the pier; without it the views agree better through the pier's
/// plane than through the wall there, and that plane was carried over the window: its
/// frame came out doubled, 5.4 dB below the wall's fill. Judged both ways by the views,
/// the fill through the surface is worse, and the wall's fill is the result, pixel for
/// pixel, with the report saying so.
#[test]
fn surfaces_the_views_do_not_back_are_found_but_not_used() {
    let c = synth::occlusion_case(synth::CaseFamily::NonPlanar, 640, 480, 4, 5);
    let s = write_scene(&c.key, &c.mask, c.truth, &c.views);
    let [(plain, _, _), (result, report, stdout)] = with_and_without_planes(&s);
    let planes = &report["planes"];
    assert!(!planes["surfaces"].as_array().unwrap().is_empty(), "{report}");
    assert_eq!(planes["used"], false, "{report}");
    assert!(
        planes["surfaces"].as_array().unwrap().iter().all(|p| p["filled_pixels"] == 0 && p["kept"] == false),
        "{report}"
    );
    assert!(stdout.contains("the views back the wall's fill better"), "{stdout}");
    assert!(plain == result, "the result is not the wall's fill");
}

/// `--mask auto` on real photographs (`../shared/data/multiview/parapano_hunt`: keyframe
/// hunt3, a lawn and a path before a long building, walkers and a cyclist on the path far
/// off): the path's edges near the camera lie far off the building's plane, and through its
/// homography the views show them moved; they are the ground seen with parallax, and each
/// view shows them along its epipolar line. The walkers are not there in the views, and
/// are masked. (Before the epipolar lines were looked along, the left edge took 14 423
/// pixels of the box below; looked along without the rule that a patch must match at one
/// place only, the walkers matched dark things further along the lines and were lost.)
#[test]
fn an_automatic_mask_takes_the_walkers_and_leaves_the_paths_edges() {
    let Some(data) = common::data_dir() else { return };
    let dir = data.join("multiview/parapano_hunt");
    let tmp = tempfile::tempdir().unwrap();
    let found = tmp.path().join("found.png");
    let mut a: Vec<PathBuf> = vec![
        "--keyframe".into(),
        dir.join("hunt3.jpg"),
        "--mask".into(),
        "auto".into(),
        "--save-mask".into(),
        found.clone(),
        "--out".into(),
        tmp.path().join("clear.png"),
    ];
    a.extend(["hunt2.jpg", "hunt4.jpg", "hunt1.jpg", "hunt5.jpg"].map(|v| dir.join(v)));
    fill_ok(a);
    let mask = image::open(&found).unwrap().to_luma8();
    let masked = |x: std::ops::Range<u32>, y: std::ops::Range<u32>| {
        let n = x.len() * y.len();
        let on =
            y.flat_map(|y| x.clone().map(move |x| (x, y))).filter(|&(x, y)| mask.get_pixel(x, y)[0] > 127);
        (on.count(), n)
    };
    let (edge, _) = masked(0..290, 760..1080);
    println!("the path's left edge: {edge} pixels masked");
    assert!(edge < 1500, "{edge} pixels of the path's left edge masked");
    for (name, x, y) in [
        ("walker by the lamp", 299..349, 665..725),
        ("cyclist", 357..395, 655..741),
        ("two walkers", 479..533, 657..719),
        ("walker on the right", 649..677, 661..711),
    ] {
        let (on, n) = masked(x, y);
        // Each box is loose around its walker (the lamp's also holds a walker no mask
        // takes): the mask, ending a pixel or two past the outline, covers 46 to 57 % of
        // them (61 % when it was grown by 3 px).
        println!("{name}: {on} of {n} pixels masked");
        assert!(3 * on > n, "{name}: {on} of {n} pixels masked");
    }
}

/// Night shots from one tripod between which cars drove on
/// (`../shared/data/transient/night_street_cars`) are views of their own, each with the
/// street where another has a car: with in3 as the keyframe and `--mask auto`, in1 and in2
/// both fill. Over the whole frame (the mask still to be found) the cars are only 2.4 % of
/// the pixels grossly apart, and in2 was skipped as "the same picture" as in1, leaving one
/// view and no consensus.
#[test]
fn night_shots_from_one_tripod_with_cars_moved_are_two_views() {
    let Some(data) = common::data_dir() else { return };
    let dir = data.join("transient/night_street_cars");
    let tmp = tempfile::tempdir().unwrap();
    let report = tmp.path().join("report.json");
    let mut a: Vec<PathBuf> = vec![
        "--keyframe".into(),
        dir.join("in3.jpg"),
        "--mask".into(),
        "auto".into(),
        "--out".into(),
        tmp.path().join("clear.png"),
        "--report".into(),
        report.clone(),
    ];
    a.extend(["in1.jpg", "in2.jpg"].map(|v| dir.join(v)));
    fill_ok(a);
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    let views = v["views"].as_array().unwrap();
    assert!(views.iter().all(|v| v["accepted"] == true), "{views:#?}");
    assert!(views.iter().all(|v| v["filled_pixels"].as_u64().unwrap() > 0), "{views:#?}");
}
