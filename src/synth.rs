//! Synthetic scenes whose true geometry is known: a rendered facade, views of it through
//! chosen homographies, and occluders pasted in front (pure layer, seeded).
//!
//! The demo, the tests and the benchmarks all use these, so nobody needs a file to try
//! clearview and every test knows the exact answer.

pub mod facade;

use nalgebra::Point2;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::geometry::Homography;
use crate::imaging::{GrayF32, Mask, RgbF32, bilinear_rgb};

/// Smooth value noise in 0..=1 with `octaves` octaves starting at `cell` pixels.
pub(crate) fn value_noise(
    width: usize,
    height: usize,
    cell: f32,
    octaves: usize,
    rng: &mut ChaCha8Rng,
) -> GrayF32 {
    let mut out = GrayF32::new(width, height, 0.0);
    let mut amplitude = 1.0;
    let mut total = 0.0;
    let mut cell = cell;
    for _ in 0..octaves {
        let gw = (width as f32 / cell).ceil() as usize + 2;
        let gh = (height as f32 / cell).ceil() as usize + 2;
        let grid: Vec<f32> = (0..gw * gh).map(|_| rng.random::<f32>()).collect();
        for y in 0..height {
            let gy = y as f32 / cell;
            let (y0, fy) = (gy as usize, gy.fract());
            let sy = fy * fy * (3.0 - 2.0 * fy);
            for x in 0..width {
                let gx = x as f32 / cell;
                let (x0, fx) = (gx as usize, gx.fract());
                let sx = fx * fx * (3.0 - 2.0 * fx);
                let a = grid[y0 * gw + x0];
                let b = grid[y0 * gw + x0 + 1];
                let c = grid[(y0 + 1) * gw + x0];
                let d = grid[(y0 + 1) * gw + x0 + 1];
                let v = (a + (b - a) * sx) * (1.0 - sy) + (c + (d - c) * sx) * sy;
                let o = out.get(x, y);
                out.set(x, y, o + amplitude * v);
            }
        }
        total += amplitude;
        amplitude *= 0.5;
        cell *= 0.5;
        if cell < 1.5 {
            break;
        }
    }
    out.map(|v| v / total)
}

/// A building facade: rendered brick or stone courses with mortar, a grid of windows with
/// frames, sills and mullions, a cornice, weathering. Plenty of corners at every scale, as
/// on a real facade, and not a repeating tile (a real facade repeats, but never exactly).
pub fn facade(width: usize, height: usize, seed: u64) -> RgbF32 {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let stain = value_noise(width, height, 64.0, 5, &mut rng);
    let grain = value_noise(width, height, 6.0, 2, &mut rng);
    let hue = rng.random_range(0.0..1.0f32);
    let wall = [0.55 + 0.25 * hue, 0.42 + 0.1 * hue, 0.32 + 0.05 * (1.0 - hue)];
    let brick_h = rng.random_range(7.0..11.0f32) * (height as f32 / 480.0).max(0.5);
    let brick_w = brick_h * rng.random_range(2.2..3.0f32);
    let bricks_per_row = (width as f32 / brick_w).ceil() as usize + 2;
    let rows = (height as f32 / brick_h).ceil() as usize + 1;
    let shades: Vec<f32> = (0..bricks_per_row * rows).map(|_| rng.random_range(0.75..1.15f32)).collect();

    // Window grid.
    let cols = rng.random_range(3..6usize);
    let floors = rng.random_range(2..4usize);
    let cell_w = width as f32 / cols as f32;
    let cell_h = height as f32 / (floors as f32 + 0.6);
    let win_w = cell_w * rng.random_range(0.4..0.55f32);
    let win_h = cell_h * rng.random_range(0.5..0.65f32);
    let glass: Vec<[f32; 3]> = (0..cols * floors)
        .map(|_| {
            let t = rng.random_range(0.1..0.35f32);
            [t * 0.8, t * 0.9, t * 1.1]
        })
        .collect();
    let frame = [0.9, 0.88, 0.82];

    RgbF32::from_fn(width, height, |x, y| {
        let (xf, yf) = (x as f32, y as f32);
        let weather = 0.8 + 0.4 * stain.get(x, y);
        let g = 0.9 + 0.2 * grain.get(x, y);
        // Cornice band near the top.
        let cornice_y = cell_h * 0.45;
        if yf < cornice_y {
            let band = ((yf / cornice_y) * 4.0) as usize;
            let v = [0.78, 0.72, 0.6, 0.85][band.min(3)] * weather * g;
            let dentil = if band == 2 && ((xf / 9.0) as usize).is_multiple_of(2) { 0.7 } else { 1.0 };
            return [v * dentil, v * 0.97 * dentil, v * 0.9 * dentil];
        }
        // Windows.
        let cx = (xf / cell_w) as usize;
        let fy = (yf - cornice_y) / cell_h;
        let cy = fy as usize;
        if cx < cols && cy < floors {
            let lx = xf - (cx as f32 + 0.5) * cell_w;
            let ly = (fy - cy as f32 - 0.5) * cell_h;
            let (hw, hh) = (win_w / 2.0, win_h / 2.0);
            let border = 3.0f32.max(win_w * 0.06);
            if lx.abs() < hw && ly.abs() < hh {
                let inner = lx.abs() < hw - border && ly.abs() < hh - border;
                let mullion = lx.abs() < border * 0.4 || (ly + hh * 0.3).abs() < border * 0.4;
                if inner && !mullion {
                    let c = glass[cy * cols + cx];
                    let refl = 0.7 + 0.6 * stain.get(x, y) * (1.0 - (ly + hh) / (2.0 * hh));
                    return c.map(|v| v * refl * g);
                }
                return frame.map(|v| v * weather.min(1.0) * g);
            }
            // Sill below the window.
            if ly >= hh && ly < hh + border * 1.6 && lx.abs() < hw + border * 1.5 {
                return [0.82 * g, 0.8 * g, 0.74 * g];
            }
        }
        // Brick courses with running bond.
        let row = (yf / brick_h) as usize;
        let offset = if row % 2 == 1 { brick_w * 0.5 } else { 0.0 };
        let bx = ((xf + offset) / brick_w) as usize;
        let in_mortar_y = yf - row as f32 * brick_h < 1.4;
        let in_mortar_x = (xf + offset) - bx as f32 * brick_w < 1.4;
        if in_mortar_x || in_mortar_y {
            let m = 0.75 * weather;
            return [m, m * 0.97, m * 0.92];
        }
        let s = shades[(row * bricks_per_row + bx) % shades.len()] * weather * g;
        [wall[0] * s, wall[1] * s, wall[2] * s]
    })
}

/// Renders what a camera sees of `scene` when `view_to_scene` maps view pixels to scene
/// pixels; pixels that fall outside the scene get `background`.
pub fn render_view(
    scene: &RgbF32,
    view_to_scene: &Homography,
    width: usize,
    height: usize,
    background: [f32; 3],
) -> RgbF32 {
    RgbF32::from_fn(width, height, |x, y| {
        view_to_scene
            .apply(Point2::new(x as f64, y as f64))
            .and_then(|p| bilinear_rgb(scene, p.x as f32, p.y as f32))
            .unwrap_or(background)
    })
}

/// Multiplies every channel by `gain` and adds `bias` (an exposure change).
pub fn expose(img: &mut RgbF32, gain: f32, bias: f32) {
    for p in img.as_mut_slice() {
        *p = p.map(|v| (v * gain + bias).clamp(0.0, 1.0));
    }
}

/// Adds uniform-ish noise of standard deviation about `sigma`.
pub fn add_noise(img: &mut RgbF32, sigma: f32, seed: u64) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let a = sigma * 3.0f32.sqrt();
    for p in img.as_mut_slice() {
        let n = rng.random_range(-a..=a);
        *p = p.map(|v| (v + n).clamp(0.0, 1.0));
    }
}

/// The kinds of thing that stand in front of facades.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Occluder {
    /// A round, leafy crown on a trunk.
    Tree,
    /// A standing figure.
    Person,
    /// A car body.
    Car,
}

/// Paints an occluder of `kind` with its centre near `(cx, cy)` and about `size` pixels
/// tall into `img`, and marks it in `mask` (255) when given. Returns the pixel count.
pub fn paint_occluder(
    img: &mut RgbF32,
    mut mask: Option<&mut Mask>,
    kind: Occluder,
    cx: f32,
    cy: f32,
    size: f32,
    seed: u64,
) -> usize {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (w, h) = (img.width(), img.height());
    let leaf = value_noise(w, h, (size / 10.0).max(2.0), 3, &mut rng);
    let tint = rng.random_range(0.8..1.2f32);
    let body = [rng.random_range(0.1..0.9f32), rng.random_range(0.1..0.9f32), rng.random_range(0.1..0.9f32)];
    // Blobs making up a tree crown.
    let blobs: Vec<(f32, f32, f32)> = (0..7)
        .map(|_| {
            let a = rng.random_range(0.0..std::f32::consts::TAU);
            let r = rng.random_range(0.0..size * 0.22);
            (cx + r * a.cos(), cy - size * 0.15 + r * a.sin(), size * rng.random_range(0.18..0.3))
        })
        .collect();
    let mut count = 0;
    let x0 = (cx - size).max(0.0) as usize;
    let x1 = ((cx + size).max(0.0) as usize).min(w);
    let y0 = (cy - size).max(0.0) as usize;
    let y1 = ((cy + size).max(0.0) as usize).min(h);
    for y in y0..y1 {
        for x in x0..x1 {
            let (xf, yf) = (x as f32, y as f32);
            let colour = match kind {
                Occluder::Tree => {
                    let in_crown =
                        blobs.iter().any(|&(bx, by, r)| (xf - bx).powi(2) + (yf - by).powi(2) < r * r);
                    let in_trunk = (xf - cx).abs() < size * 0.05 && yf > cy && yf < cy + size * 0.5;
                    if in_crown {
                        let l = leaf.get(x, y);
                        Some([0.08 + 0.2 * l, (0.25 + 0.35 * l) * tint, 0.06 + 0.1 * l])
                    } else if in_trunk {
                        Some([0.3, 0.2, 0.12])
                    } else {
                        None
                    }
                }
                Occluder::Person => {
                    let head = (xf - cx).powi(2) + (yf - (cy - size * 0.38)).powi(2) < (size * 0.09).powi(2);
                    let torso = (xf - cx).abs() < size * 0.13 && yf > cy - size * 0.3 && yf < cy + size * 0.1;
                    let legs = (xf - cx).abs() < size * 0.11
                        && (xf - cx).abs() > size * 0.015
                        && yf >= cy + size * 0.1
                        && yf < cy + size * 0.5;
                    if head {
                        Some([0.85, 0.65, 0.5])
                    } else if torso {
                        Some(body.map(|v| v * (0.85 + 0.3 * leaf.get(x, y))))
                    } else if legs {
                        Some([0.15, 0.17, 0.3])
                    } else {
                        None
                    }
                }
                Occluder::Car => {
                    let lower = (xf - cx).abs() < size * 0.9 && (yf - cy).abs() < size * 0.18;
                    let cabin = (xf - cx).abs() < size * 0.5 - (cy - size * 0.18 - yf).max(0.0)
                        && yf < cy - size * 0.18
                        && yf > cy - size * 0.45;
                    if lower {
                        Some(body.map(|v| v * (0.9 + 0.2 * leaf.get(x, y))))
                    } else if cabin {
                        Some([0.2, 0.25, 0.3])
                    } else {
                        None
                    }
                }
            };
            if let Some(c) = colour {
                img.set(x, y, c);
                if let Some(m) = mask.as_deref_mut() {
                    m.set(x, y, 255);
                }
                count += 1;
            }
        }
    }
    count
}

/// The families of [`occlusion_case`]: what stands in front of the facade, and where.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CaseFamily {
    /// A flat facade; the keyframe and every view have occluders of their own, at places of
    /// their own (some over the keyframe's).
    Planar,
    /// As `Planar`, but the keyframe's tree stands a little off the wall: every view shows it
    /// too, displaced by parallax, so part of the mask is never seen by any view.
    Shared,
    /// A facade with a pier standing out of the wall (a second plane): under the wall's
    /// homography its content shifts by a few pixels in every view.
    NonPlanar,
}

impl CaseFamily {
    pub const ALL: [Self; 3] = [Self::Planar, Self::Shared, Self::NonPlanar];

    pub fn name(self) -> &'static str {
        match self {
            Self::Planar => "planar",
            Self::Shared => "shared",
            Self::NonPlanar => "nonplanar",
        }
    }
}

/// A generated case whose every occluder is known: the keyframe, the mask a person would
/// paint (the keyframe's occluders, dilated), the occluder-free truth, and the views with
/// their true keyframe → view homographies and where, in keyframe coordinates, each view
/// shows something other than the wall.
#[derive(Debug, Clone)]
pub struct OcclusionCase {
    pub key: RgbF32,
    pub mask: Mask,
    /// The keyframe's occluders exactly (undilated).
    pub key_occluders: Mask,
    pub truth: RgbF32,
    pub views: Vec<RgbF32>,
    pub homographies: Vec<Homography>,
    /// Per view, keyframe-sized: 255 where the view shows an occluder at that keyframe pixel.
    pub view_occluders: Vec<Mask>,
}

impl OcclusionCase {
    /// The views with their true homographies, as the fill takes them.
    pub fn sources(&self) -> Vec<crate::inpaint::Source<'_>> {
        self.views
            .iter()
            .zip(&self.homographies)
            .map(|(image, &homography)| crate::inpaint::Source { image, homography })
            .collect()
    }
}

/// Dilates a mask by a `(2r + 1)²` square (as a person paints around an object).
pub fn dilate_mask(m: &Mask, r: usize) -> Mask {
    let (w, h) = (m.width(), m.height());
    let ri = r as isize;
    let rows = Mask::from_fn(w, h, |x, y| {
        let x0 = x.saturating_sub(r);
        let x1 = (x + r + 1).min(w);
        if m.row(y)[x0..x1].iter().any(|&v| v > 127) { 255 } else { 0 }
    });
    Mask::from_fn(w, h, |x, y| {
        let hit = (-ri..=ri).any(|d| rows.get_checked(x as isize, y as isize + d).is_some_and(|v| v > 127));
        if hit { 255 } else { 0 }
    })
}

/// A `width × height` case of `family` with `n` views, fully determined by `seed`. Rendered
/// at twice the size and box-averaged, so that the images are band-limited as a camera's
/// are (a sharp mortar line resampled by a warp is otherwise wrong by more than any fill's
/// fault).
pub fn occlusion_case(family: CaseFamily, width: usize, height: usize, n: usize, seed: u64) -> OcclusionCase {
    let fine = occlusion_case_at(family, 2 * width, 2 * height, n, seed);
    let s2 = doubling();
    let s2_inv = s2.inverse().expect("regular");
    let key_occluders = half_mask(&fine.key_occluders);
    OcclusionCase {
        key: half(&fine.key),
        mask: dilate_mask(&key_occluders, 2),
        key_occluders,
        truth: half(&fine.truth),
        views: fine.views.iter().map(half).collect(),
        homographies: fine.homographies.iter().map(|h| s2_inv.after(h).after(&s2)).collect(),
        view_occluders: fine.view_occluders.iter().map(half_mask).collect(),
    }
}

/// A keyframe with a tree in front of a facade, the tree's mask, the truth behind it, and
/// three views from elsewhere, each with a person in a different place and its own
/// exposure (the one-shot command's standard case).
pub struct TreeScene {
    pub truth: RgbF32,
    pub key: RgbF32,
    pub mask: Mask,
    pub views: Vec<RgbF32>,
}

/// [`TreeScene`] of `width × height` on facade `facade_seed`, views placed by `view_seed`.
pub fn tree_scene(width: usize, height: usize, facade_seed: u64, view_seed: u64) -> TreeScene {
    let (w, h) = (width, height);
    let facade = facade(w * 2, h * 2, facade_seed);
    let centre = Homography::translation(w as f64 / 2.0, h as f64 / 2.0);
    let truth = render_view(&facade, &centre, w, h, [0.5; 3]);
    let mut key = truth.clone();
    let mut mask = Mask::new(w, h, 0);
    paint_occluder(&mut key, Some(&mut mask), Occluder::Tree, 240.0, 190.0, 150.0, 3);
    let mut rng = ChaCha8Rng::seed_from_u64(view_seed);
    let views = (0..3u64)
        .map(|i| {
            let k2v = random_homography(&mut rng, w, h, 0.1, 0.25, (0.9, 1.1));
            let mut v = render_view(&facade, &centre.after(&k2v.inverse().expect("regular")), w, h, [0.5; 3]);
            paint_occluder(&mut v, None, Occluder::Person, 60.0 + 170.0 * i as f32, 200.0, 150.0, 10 + i);
            expose(&mut v, 0.9 + 0.1 * i as f32, 0.0);
            v
        })
        .collect();
    TreeScene { truth, key, mask, views }
}

/// From an image's pixels to those of the same image at twice the size, pixel centres kept
/// (x₂ = 2·x + 0.5): what [`half`] undoes.
pub fn doubling() -> Homography {
    Homography::from_rows([[2.0, 0.0, 0.5], [0.0, 2.0, 0.5], [0.0, 0.0, 1.0]]).expect("regular")
}

/// [`render_view`] band-limited, as a camera's pixels integrate light: `fine_scene` is the
/// scene at twice the size of the one `view_to_scene` maps into, the view is rendered at
/// twice `width × height` ([`doubling`] on both sides) and box-averaged ([`half`]). A warp
/// of it resamples a sharp mortar line without the aliasing a direct rendering has.
pub fn render_view_band(
    fine_scene: &RgbF32,
    view_to_scene: &Homography,
    width: usize,
    height: usize,
    background: [f32; 3],
) -> RgbF32 {
    let s2 = doubling();
    let fine = s2.after(view_to_scene).after(&s2.inverse().expect("regular"));
    half(&render_view(fine_scene, &fine, 2 * width, 2 * height, background))
}

/// Box average of 2×2 blocks.
pub fn half(img: &RgbF32) -> RgbF32 {
    RgbF32::from_fn(img.width() / 2, img.height() / 2, |x, y| {
        let (a, b, c, d) = (
            img.get(2 * x, 2 * y),
            img.get(2 * x + 1, 2 * y),
            img.get(2 * x, 2 * y + 1),
            img.get(2 * x + 1, 2 * y + 1),
        );
        std::array::from_fn(|k| 0.25 * (a[k] + b[k] + c[k] + d[k]))
    })
}

/// A mask halved: a pixel is marked when any of its 2×2 block is.
fn half_mask(m: &Mask) -> Mask {
    Mask::from_fn(m.width() / 2, m.height() / 2, |x, y| {
        let any =
            [(0, 0), (1, 0), (0, 1), (1, 1)].iter().any(|&(dx, dy)| m.get(2 * x + dx, 2 * y + dy) > 127);
        if any { 255 } else { 0 }
    })
}

fn occlusion_case_at(family: CaseFamily, width: usize, height: usize, n: usize, seed: u64) -> OcclusionCase {
    let (w, h) = (width, height);
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x0cc1_u64.wrapping_mul(family as u64 + 1));
    let scene = facade(w * 3 / 2, h * 3 / 2, seed);
    let centre = Homography::translation(w as f64 / 4.0, h as f64 / 4.0);
    // The pier: a band of scene columns standing out of the wall (NonPlanar only).
    let pier = (family == CaseFamily::NonPlanar).then(|| {
        let x0 = rng.random_range(0.35..0.5f64) * w as f64 + w as f64 / 4.0;
        (x0, x0 + 0.18 * w as f64)
    });
    // Renders the scene as seen through key → view `hv`; the pier's content moves by
    // `parallax` (keyframe pixels) relative to the wall.
    let render = |hv: &Homography, parallax: (f64, f64)| -> RgbF32 {
        let to_scene = centre.after(&hv.inverse().expect("regular"));
        RgbF32::from_fn(w, h, |x, y| {
            let Some(p) = to_scene.apply(Point2::new(x as f64, y as f64)) else { return [0.5; 3] };
            let (mut sx, mut sy) = (p.x, p.y);
            if let Some((x0, x1)) = pier {
                // Where the pier's face is seen, the wall's point is off by the parallax.
                let (px, py) = (sx - parallax.0, sy - parallax.1);
                if px >= x0 && px < x1 {
                    (sx, sy) = (px, py);
                }
            }
            bilinear_rgb(&scene, sx as f32, sy as f32).unwrap_or([0.5; 3])
        })
    };
    let truth = render(&Homography::identity(), (0.0, 0.0));
    let mut key = truth.clone();
    let mut key_occ = Mask::new(w, h, 0);
    let s = w.min(h) as f32;
    let tree =
        (rng.random_range(0.3..0.6f32) * w as f32, 0.55 * h as f32, rng.random_range(0.45..0.6f32) * s);
    let tree_seed = seed.wrapping_mul(31) + 7;
    paint_occluder(&mut key, Some(&mut key_occ), Occluder::Tree, tree.0, tree.1, tree.2, tree_seed);
    let other = [Occluder::Car, Occluder::Person][(seed % 2) as usize];
    let ox = if tree.0 > 0.5 * w as f32 { 0.2 } else { 0.78 } * w as f32;
    paint_occluder(&mut key, Some(&mut key_occ), other, ox, 0.72 * h as f32, 0.3 * s, seed + 11);
    add_noise(&mut key, 0.006, seed * 7 + 1);
    let mask = dilate_mask(&key_occ, 4);

    let mut views = Vec::with_capacity(n);
    let mut homographies = Vec::with_capacity(n);
    let mut view_occluders = Vec::with_capacity(n);
    for i in 0..n {
        let hv = random_homography(&mut rng, w, h, 0.08, 0.2, (0.9, 1.1));
        let parallax = match family {
            CaseFamily::NonPlanar => (rng.random_range(-8.0..8.0), rng.random_range(-4.0..4.0)),
            _ => (0.0, 0.0),
        };
        let mut v = render(&hv, parallax);
        // Occluders painted in keyframe coordinates and carried into the view, so that
        // their place on the keyframe is known exactly.
        let mut occ_key = RgbF32::new(w, h, [0.0; 3]);
        let mut occ_mask = Mask::new(w, h, 0);
        if family == CaseFamily::Shared {
            // The keyframe's tree, off the wall: shifted by parallax in each view.
            let shift = tree.2 * rng.random_range(0.15..0.35) * if i % 2 == 0 { 1.0 } else { -1.0 };
            paint_occluder(
                &mut occ_key,
                Some(&mut occ_mask),
                Occluder::Tree,
                tree.0 + shift,
                tree.1 + rng.random_range(-0.03..0.03) * s,
                tree.2,
                tree_seed,
            );
        }
        let kind = [Occluder::Person, Occluder::Tree, Occluder::Car][(i + seed as usize) % 3];
        let (cx, cy) =
            (rng.random_range(0.15..0.85f32) * w as f32, rng.random_range(0.45..0.7f32) * h as f32);
        paint_occluder(
            &mut occ_key,
            Some(&mut occ_mask),
            kind,
            cx,
            cy,
            rng.random_range(0.3..0.5f32) * s,
            seed * 100 + i as u64,
        );
        // Into the view: view pixel q shows keyframe point H⁻¹ q.
        let back = hv.inverse().expect("regular");
        for y in 0..h {
            for x in 0..w {
                let Some(p) = back.apply(Point2::new(x as f64, y as f64)) else { continue };
                let (kx, ky) = (p.x.round(), p.y.round());
                if kx >= 0.0 && ky >= 0.0 && (kx as usize) < w && (ky as usize) < h {
                    let (kx, ky) = (kx as usize, ky as usize);
                    if occ_mask.get(kx, ky) > 127 {
                        v.set(x, y, occ_key.get(kx, ky));
                    }
                }
            }
        }
        expose(&mut v, rng.random_range(0.85..1.15), rng.random_range(-0.03..0.03));
        add_noise(&mut v, 0.006, seed * 1000 + i as u64);
        views.push(v);
        homographies.push(hv);
        view_occluders.push(occ_mask);
    }
    OcclusionCase { key, mask, key_occluders: key_occ, truth, views, homographies, view_occluders }
}

/// A random homography of the kind a hand-held camera produces between two shots of a
/// facade: rotation up to `max_rot` radians, out-of-plane tilt up to `max_tilt` radians,
/// scale in `scale`, a shift of up to 10 % of the frame; about the image centre.
pub fn random_homography(
    rng: &mut impl Rng,
    width: usize,
    height: usize,
    max_rot: f64,
    max_tilt: f64,
    scale: (f64, f64),
) -> Homography {
    let (w, h) = (width as f64, height as f64);
    let f = w.max(h) * 1.2; // focal length in pixels
    let rot = rng.random_range(-max_rot..=max_rot);
    let tilt = rng.random_range(-max_tilt..=max_tilt);
    let tilt_dir = rng.random_range(0.0..std::f64::consts::TAU);
    let s = rng.random_range(scale.0..=scale.1);
    let (tx, ty) = (rng.random_range(-0.1..0.1) * w, rng.random_range(-0.1..0.1) * h);
    // Plane rotation about an axis in the image plane: the homography K R K⁻¹ of a camera
    // turning by `tilt` about that axis.
    let (ax, ay) = (tilt_dir.cos(), tilt_dir.sin());
    let (c, sn) = (tilt.cos(), tilt.sin());
    let r = nalgebra::Matrix3::new(
        c + ax * ax * (1.0 - c),
        ax * ay * (1.0 - c),
        ay * sn,
        ax * ay * (1.0 - c),
        c + ay * ay * (1.0 - c),
        -ax * sn,
        -ay * sn,
        ax * sn,
        c,
    );
    let k = nalgebra::Matrix3::new(f, 0.0, 0.0, 0.0, f, 0.0, 0.0, 0.0, 1.0);
    let k_inv = nalgebra::Matrix3::new(1.0 / f, 0.0, 0.0, 0.0, 1.0 / f, 0.0, 0.0, 0.0, 1.0);
    let tilt_h = Homography::from_matrix(k * r * k_inv).expect("rotation homography is regular");
    let sim = Homography::from_rows([
        [s * rot.cos(), -s * rot.sin(), tx],
        [s * rot.sin(), s * rot.cos(), ty],
        [0.0, 0.0, 1.0],
    ])
    .expect("similarity is regular");
    Homography::translation(w / 2.0, h / 2.0)
        .after(&sim)
        .after(&tilt_h)
        .after(&Homography::translation(-w / 2.0, -h / 2.0))
}

/// The EXIF block (a little-endian TIFF header with one IFD entry) that tags an image with
/// orientation `o` (1–8), as a camera writes it.
pub fn exif_orientation(o: u16) -> Vec<u8> {
    let mut e = b"II*\0".to_vec();
    e.extend(8u32.to_le_bytes());
    e.extend(1u16.to_le_bytes());
    e.extend(0x0112u16.to_le_bytes());
    e.extend(3u16.to_le_bytes());
    e.extend(1u32.to_le_bytes());
    e.extend(u32::from(o).to_le_bytes());
    e.extend(0u32.to_le_bytes());
    e
}

/// Where display pixel `(x, y)` comes from in a stored `w × h` image tagged with EXIF
/// orientation `o` (1–8; anything else is 1).
pub fn stored_position(o: u16, x: usize, y: usize, w: usize, h: usize) -> (usize, usize) {
    match o {
        2 => (w - 1 - x, y),
        3 => (w - 1 - x, h - 1 - y),
        4 => (x, h - 1 - y),
        5 => (y, x),
        6 => (y, h - 1 - x),
        7 => (w - 1 - y, h - 1 - x),
        8 => (w - 1 - y, x),
        _ => (x, y),
    }
}

/// The pixels a camera stores for the upright image `upright` when it tags them with
/// orientation `o`: a viewer that applies the tag shows `upright` again.
pub fn stored_for_orientation(upright: &RgbF32, o: u16) -> RgbF32 {
    let (w, h) = (upright.width(), upright.height());
    let (sw, sh) = if (5..=8).contains(&o) { (h, w) } else { (w, h) };
    let mut stored = RgbF32::new(sw, sh, [0.0; 3]);
    for y in 0..h {
        for x in 0..w {
            let (sx, sy) = stored_position(o, x, y, sw, sh);
            stored.set(sx, sy, upright.get(x, y));
        }
    }
    stored
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn facade_is_deterministic_and_textured() {
        let a = facade(160, 120, 3);
        let b = facade(160, 120, 3);
        assert!(a == b);
        let mean = a.as_slice().iter().map(|p| p[1]).sum::<f32>() / a.len() as f32;
        let var = a.as_slice().iter().map(|p| (p[1] - mean).powi(2)).sum::<f32>() / a.len() as f32;
        assert!(var > 0.005, "facade should have contrast, variance {var}");
    }

    #[test]
    fn rendering_through_identity_copies() {
        let a = facade(64, 48, 1);
        let v = render_view(&a, &Homography::identity(), 64, 48, [0.0; 3]);
        assert!(a == v);
    }

    #[test]
    fn a_stored_orientation_maps_back_to_the_upright_image() {
        let up = RgbF32::from_fn(5, 3, |x, y| [x as f32, y as f32, 0.0]);
        for o in 1..=8 {
            let stored = stored_for_orientation(&up, o);
            let (sw, sh) = (stored.width(), stored.height());
            assert_eq!((sw, sh), if o >= 5 { (3, 5) } else { (5, 3) });
            for y in 0..3 {
                for x in 0..5 {
                    let (sx, sy) = stored_position(o, x, y, sw, sh);
                    assert_eq!(stored.get(sx, sy), up.get(x, y), "orientation {o} at ({x}, {y})");
                }
            }
        }
    }

    #[test]
    fn occluders_are_masked_where_painted() {
        for kind in [Occluder::Tree, Occluder::Person, Occluder::Car] {
            let mut img = RgbF32::new(100, 100, [1.0; 3]);
            let mut mask = Mask::new(100, 100, 0);
            let n = paint_occluder(&mut img, Some(&mut mask), kind, 50.0, 50.0, 60.0, 1);
            assert!(n > 300, "{kind:?} painted {n}");
            assert_eq!(mask.hole_count(), n);
        }
    }
}
