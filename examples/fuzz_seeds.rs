//! Writes the seed corpora of the fuzz targets (`fuzz/`): tiny valid images in every
//! format clearview reads, views of the fuzz keyframe, masks, the shipped configuration
//! and a saved session state. Generated, so nothing is copied from the data folder.
//!
//! `cargo run --release --example fuzz_seeds -- [OUT]` (OUT defaults to `fuzz/corpus`;
//! one folder per target).

use std::io::Cursor;
use std::path::Path;

use clearview::daemon::state::SessionState;
use clearview::geometry::Homography;
use clearview::imaging::convert::{mask_to_luma8, to_rgb8};
use clearview::imaging::{Mask, RgbF32};
use clearview::session::AlignRecord;
use clearview::synth::{self, Occluder};
use image::codecs::jpeg::JpegEncoder;
use image::codecs::png::PngEncoder;
use image::{DynamicImage, ExtendedColorType, ImageEncoder, ImageFormat};

/// The fuzz harness's keyframe (`fuzz/src/lib.rs`: `synth::facade(160, 120, 7)`).
const KEY_W: usize = 160;
const KEY_H: usize = 120;

fn encode(img: &DynamicImage, format: ImageFormat) -> Vec<u8> {
    let mut out = Cursor::new(Vec::new());
    img.write_to(&mut out, format).unwrap_or_else(|e| panic!("{format:?}: {e}"));
    out.into_inner()
}

/// A JPEG carrying an EXIF orientation tag.
fn jpeg_with_orientation(img: &image::RgbImage, orientation: u16) -> Vec<u8> {
    let mut bytes = Vec::new();
    let mut enc = JpegEncoder::new_with_quality(&mut bytes, 85);
    enc.set_exif_metadata(clearview::synth::exif_orientation(orientation)).unwrap();
    enc.write_image(img.as_raw(), img.width(), img.height(), ExtendedColorType::Rgb8).unwrap();
    bytes
}

/// Raw grey pixels as the alignment target reads them: width − 1, height − 1, values.
fn raw(img: &RgbF32) -> Vec<u8> {
    let gray = clearview::imaging::convert::luminance(img);
    let mut out = vec![(gray.width() - 1) as u8, (gray.height() - 1) as u8];
    out.extend(gray.as_slice().iter().map(|v| (v.clamp(0.0, 1.0) * 255.0) as u8));
    out
}

fn write(dir: &Path, name: &str, bytes: &[u8]) {
    std::fs::create_dir_all(dir).unwrap();
    std::fs::write(dir.join(name), bytes).unwrap_or_else(|e| panic!("{}: {e}", dir.join(name).display()));
}

fn main() {
    let out = std::env::args().nth(1).unwrap_or_else(|| "fuzz/corpus".into());
    let out = Path::new(&out);
    let key = synth::facade(KEY_W, KEY_H, 7);

    // decode: one small image per format and pixel layout.
    let small = DynamicImage::ImageRgb8(to_rgb8(&synth::facade(24, 16, 3)));
    let d = out.join("decode");
    write(&d, "rgb8.png", &encode(&small, ImageFormat::Png));
    write(&d, "gray8.png", &encode(&DynamicImage::ImageLuma8(small.to_luma8()), ImageFormat::Png));
    write(&d, "rgba16.png", &encode(&DynamicImage::ImageRgba16(small.to_rgba16()), ImageFormat::Png));
    write(&d, "one.png", &encode(&DynamicImage::ImageRgb8(image::RgbImage::new(1, 1)), ImageFormat::Png));
    write(&d, "rgb8.jpg", &encode(&small, ImageFormat::Jpeg));
    write(&d, "gray8.jpg", &encode(&DynamicImage::ImageLuma8(small.to_luma8()), ImageFormat::Jpeg));
    write(&d, "exif6.jpg", &jpeg_with_orientation(&small.to_rgb8(), 6));
    write(&d, "rgb8.tif", &encode(&small, ImageFormat::Tiff));
    write(&d, "gray16.tif", &encode(&DynamicImage::ImageLuma16(small.to_luma16()), ImageFormat::Tiff));
    write(&d, "rgba8.webp", &encode(&DynamicImage::ImageRgba8(small.to_rgba8()), ImageFormat::WebP));

    // align: views of the keyframe through a small homography, as files and raw pixels.
    let to_key = Homography::from_rows([[0.97, 0.05, 4.0], [-0.04, 0.98, 3.0], [0.0001, 0.0, 1.0]]).unwrap();
    let mut view = synth::render_view(&key, &to_key, KEY_W, KEY_H, [0.5; 3]);
    synth::expose(&mut view, 0.9, 0.02);
    let view8 = DynamicImage::ImageRgb8(to_rgb8(&view));
    let a = out.join("align");
    for (name, mode, bytes) in [
        ("view.png", 0u8, encode(&view8, ImageFormat::Png)),
        ("view.jpg", 0, encode(&view8, ImageFormat::Jpeg)),
        ("view.raw", 1, raw(&view)),
    ] {
        write(&a, name, &[&[mode][..], &bytes].concat());
    }
    let near_identity = [0x80 | 1, 0, 6, 0, 10, 0, 0, 8, 0];
    write(&a, "view_prior.raw", &[&near_identity[..], &raw(&view)].concat());
    let mut both = vec![2u8];
    both.extend(raw(&key));
    both.extend(raw(&view));
    write(&a, "both.raw", &both);

    // config: the shipped file, and a video source.
    let c = out.join("config");
    write(&c, "clearview.toml", include_bytes!("../config/clearview.toml"));
    write(
        &c,
        "video.toml",
        b"[watch]\nenabled = false\n[[video]]\ninput = \"rtsp://camera/stream\"\nsession = \"street\"\nkeyframe_at_s = 1.5\n",
    );

    // mask: the keyframe's size (a tree's shape, all black, all white), a wrong size, RGB.
    let mut tree = Mask::new(KEY_W, KEY_H, 0);
    let mut scratch = key.clone();
    synth::paint_occluder(&mut scratch, Some(&mut tree), Occluder::Tree, 80.0, 70.0, 50.0, 1);
    let m = out.join("mask");
    let luma = |mask: &Mask| DynamicImage::ImageLuma8(mask_to_luma8(mask));
    write(&m, "tree.png", &encode(&luma(&tree), ImageFormat::Png));
    write(&m, "black.png", &encode(&luma(&Mask::new(KEY_W, KEY_H, 0)), ImageFormat::Png));
    write(&m, "white.png", &encode(&luma(&Mask::new(KEY_W, KEY_H, 255)), ImageFormat::Png));
    write(&m, "wrong_size.png", &encode(&luma(&Mask::new(KEY_W - 1, KEY_H, 255)), ImageFormat::Png));
    write(&m, "tree_rgb.jpg", &encode(&DynamicImage::ImageRgb8(luma(&tree).to_rgb8()), ImageFormat::Jpeg));
    let mut png = Vec::new();
    PngEncoder::new(&mut png)
        .write_image(mask_to_luma8(&tree).as_raw(), KEY_W as u32, KEY_H as u32, ExtendedColorType::L8)
        .unwrap();
    write(&m, "tree_l8.png", &png);

    // state: what the service saves after aligning a view, and a rejection.
    let mut state = SessionState { key_file: Some("key.png".into()), ..SessionState::default() };
    let accepted = AlignRecord {
        accepted: true,
        reason: None,
        homography: Some(to_key.inverse().unwrap().rows()),
        inliers: 60,
        matches: 80,
        checked: 90,
        median_residual_px: Some(0.3),
        coverage: 0.6,
        from_prior: false,
        view_size: (KEY_W, KEY_H),
    };
    let rejected = AlignRecord {
        accepted: false,
        reason: Some("too few inliers".into()),
        homography: None,
        median_residual_px: None,
        ..accepted.clone()
    };
    state.remember("view.png|1234|1700000000".into(), "key|1|1".into(), accepted);
    state.remember("other.png|99|1700000001".into(), "key|1|1".into(), rejected);
    let s = out.join("state");
    write(&s, "state.json", &serde_json::to_vec_pretty(&state).unwrap());
    println!("seeds written under {}", out.display());
}
