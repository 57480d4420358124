//! Non-planar facades with known geometry (pure layer, seeded): a textured wall with slabs
//! standing in front of it (balcony fronts, pilasters, sign boards at 4–14 % of the camera
//! distance), trees and people in front of that, seen by a keyframe camera and by views
//! 5–30° around it. Everything is ray-cast from cameras whose intrinsics and poses are
//! known, so the true homography each plane induces between the keyframe and every view
//! is known too (issue 14).
//!
//! Units: the keyframe camera sits at the origin looking down +Z; the wall is the plane
//! `Z = WALL`; X to the right, Y down (as image coordinates).

use nalgebra::{Matrix3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::{Occluder, dilate_mask, facade, half, half_mask, paint_occluder, value_noise};
use crate::geometry::Homography;
use crate::imaging::{Mask, Plane, Rect, RgbF32, bilinear_rgb};
use crate::inpaint::parallax::SurfacePlane;

/// Distance from the keyframe camera to the wall.
pub const WALL: f64 = 10.0;
/// The wall's texture covers `X, Y` in `±WALL_HALF`.
const WALL_HALF: (f64, f64) = (10.0, 7.0);

/// What a slab is (it decides its shape and its texture).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SlabKind {
    /// A wide, low panel with balusters: the front of a balcony.
    Balcony,
    /// A tall narrow pier in stone with flutes.
    Pilaster,
    /// A coloured board with lettering.
    Sign,
}

/// A box standing on the wall: front face at `Z = WALL - depth`, extending back to the wall.
#[derive(Debug, Clone)]
pub struct Slab {
    pub kind: SlabKind,
    /// World extent of the front face.
    pub x0: f64,
    pub x1: f64,
    pub y0: f64,
    pub y1: f64,
    /// How far the front face stands off the wall (world units).
    pub depth: f64,
    texture: RgbF32,
}

/// Texture pixels per world unit: as fine as the twice-size rendering sees the wall.
fn tex_per_unit(width: usize) -> f64 {
    2.0 * 1.1 * width as f64 / WALL
}

/// A flat cut-out (tree, person, car) facing the keyframe camera at depth `z`.
#[derive(Debug, Clone)]
struct Sprite {
    z: f64,
    /// World position of the sprite image's top-left corner, and world units per pixel.
    x0: f64,
    y0: f64,
    scale: f64,
    image: RgbF32,
    alpha: Mask,
}

/// A pinhole camera: intrinsics `k`, world → camera rotation `r`, centre `c`.
#[derive(Debug, Clone, Copy)]
pub struct Camera {
    pub k: Matrix3<f64>,
    pub r: Matrix3<f64>,
    pub c: Vector3<f64>,
}

impl Camera {
    /// The homography the plane `Z = z` induces from the keyframe camera `key` (at the
    /// origin, no rotation) to `self`: keyframe pixel → this camera's pixel.
    pub fn plane_homography(&self, key: &Camera, z: f64) -> Homography {
        let t = -(self.r * self.c);
        let n = Vector3::new(0.0, 0.0, 1.0);
        let m = self.k * (self.r + t * n.transpose() / z) * key.k.try_inverse().expect("regular K");
        Homography::from_matrix(m).expect("plane homography is regular")
    }

    /// The same camera for an image `s` times larger (pixel centres kept at integers).
    fn scaled(&self, s: f64) -> Camera {
        let off = 0.5 * (s - 1.0);
        let sm = Matrix3::new(s, 0.0, off, 0.0, s, off, 0.0, 0.0, 1.0);
        Camera { k: sm * self.k, ..*self }
    }
}

/// What a ray hit first.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Hit {
    /// Plane index (0 = wall, 1 + i = slab i's front) and colour.
    Surface(u16, [f32; 3]),
    /// A slab's side face (no plane of the list).
    Side([f32; 3]),
    Sprite([f32; 3]),
    Nothing,
}

/// A generated non-planar facade case. Planes are numbered 0 (the wall) and `1 + i` (the
/// front of `slabs[i]`).
#[derive(Debug, Clone)]
pub struct ParallaxCase {
    pub key: RgbF32,
    /// The keyframe's occluders, dilated (what a person would paint).
    pub mask: Mask,
    /// The keyframe's occluders exactly.
    pub key_occluders: Mask,
    /// The keyframe without any occluder.
    pub truth: RgbF32,
    pub views: Vec<RgbF32>,
    /// Per view, per plane: the true keyframe → view homography the plane induces.
    pub planes: Vec<Vec<Homography>>,
    /// Keyframe-sized: the plane the truth shows at each pixel ([`SIDE`] on slab sides).
    pub surface: Plane<u16>,
    /// Per view, keyframe-sized: 255 where the view shows an occluder at the keyframe
    /// pixel's place on the wall (through the wall's homography).
    pub view_occluders: Vec<Mask>,
    /// Per view, view-sized: 255 where the view shows an occluder.
    pub occluders: Vec<Mask>,
    pub slabs: Vec<Slab>,
    pub key_camera: Camera,
    pub cameras: Vec<Camera>,
}

/// Marked pixels by what they lie on ([`ParallaxCase::where_marks_lie`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct MarksLie {
    /// On a view's true occluder (grown by 4 px).
    pub occluder: usize,
    /// Off the occluders, on a slab.
    pub slab: usize,
    /// Elsewhere: the wall, a strip the keyframe's slab hides.
    pub elsewhere: usize,
}

/// [`ParallaxCase::surface`] of a slab's side face.
pub const SIDE: u16 = u16::MAX;

impl ParallaxCase {
    /// The true wall homography of each view.
    pub fn wall(&self) -> Vec<Homography> {
        self.planes.iter().map(|p| p[0]).collect()
    }

    /// Where marks of the views' own occluders (per view, view-sized, as
    /// [`crate::inpaint::own_occluders`] gives them) lie: how many marked pixels are on the
    /// view's true occluders grown by 4 px, how many off them on a slab (a pixel whose slab's
    /// homography maps it to where the keyframe shows that slab or a slab's side), and how
    /// many elsewhere.
    pub fn where_marks_lie(&self, marks: &[Option<Mask>]) -> MarksLie {
        let (kw, kh) = (self.key.width() as f64, self.key.height() as f64);
        let mut lie = MarksLie::default();
        for (v, m) in marks.iter().enumerate() {
            let Some(m) = m else { continue };
            let near = dilate_mask(&self.occluders[v], 4);
            let back: Vec<Option<Homography>> = self.planes[v].iter().map(Homography::inverse).collect();
            for y in 0..m.height() {
                for x in 0..m.width() {
                    if m.get(x, y) == 0 {
                        continue;
                    }
                    if near.get(x, y) > 0 {
                        lie.occluder += 1;
                        continue;
                    }
                    let on_slab = back.iter().enumerate().skip(1).any(|(p, h)| {
                        h.and_then(|h| h.apply(nalgebra::Point2::new(x as f64, y as f64))).is_some_and(|q| {
                            q.x >= 0.0 && q.y >= 0.0 && q.x < kw && q.y < kh && {
                                let s = self.surface.get(q.x as usize, q.y as usize);
                                usize::from(s) == p || s == SIDE
                            }
                        })
                    });
                    if on_slab {
                        lie.slab += 1;
                    } else {
                        lie.elsewhere += 1;
                    }
                }
            }
        }
        lie
    }

    /// The true slab planes as the fill takes them, each allowed where the keyframe shows it
    /// outside the mask, grown by half its size and at least `min_grow` pixels (as
    /// [`crate::inpaint::parallax::surface_planes`] grows a fitted plane's support).
    pub fn true_surfaces(&self, min_grow: usize) -> Vec<SurfacePlane> {
        let (w, h) = (self.key.width(), self.key.height());
        (1..self.planes.first().map_or(0, Vec::len))
            .filter_map(|p| {
                let (mut x0, mut y0, mut x1, mut y1) = (w, h, 0, 0);
                for y in 0..h {
                    for x in 0..w {
                        if self.surface.get(x, y) == p as u16 && !self.mask.is_hole(x, y) {
                            (x0, y0, x1, y1) = (x0.min(x), y0.min(y), x1.max(x + 1), y1.max(y + 1));
                        }
                    }
                }
                (x1 > x0).then(|| {
                    let (gx, gy) = (((x1 - x0) / 2).max(min_grow), ((y1 - y0) / 2).max(min_grow));
                    let region = Rect::from_corners(
                        x0.saturating_sub(gx),
                        y0.saturating_sub(gy),
                        (x1 + gx).min(w),
                        (y1 + gy).min(h),
                    );
                    SurfacePlane { views: self.planes.iter().map(|v| Some(v[p])).collect(), region }
                })
            })
            .collect()
    }
}

/// A `width × height` non-planar facade case with `n` views (2–4 make sense), fully
/// determined by `seed`. `flat` leaves the slabs out (the same scene, a flat wall).
/// Rendered at twice the size and box-averaged, as [`super::occlusion_case`].
pub fn parallax_case(width: usize, height: usize, n: usize, seed: u64, flat: bool) -> ParallaxCase {
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x9a4a_11a5);
    let (w, h) = (width, height);
    let f = 1.1 * w as f64;
    let k = Matrix3::new(f, 0.0, (w as f64 - 1.0) / 2.0, 0.0, f, (h as f64 - 1.0) / 2.0, 0.0, 0.0, 1.0);
    let key_cam = Camera { k, r: Matrix3::identity(), c: Vector3::zeros() };
    // World extent the keyframe sees on the wall.
    let half_w = WALL * (w as f64 / 2.0) / f;
    let half_h = WALL * (h as f64 / 2.0) / f;

    let tex = tex_per_unit(w);
    let wall_tex = facade((2.0 * WALL_HALF.0 * tex) as usize, (2.0 * WALL_HALF.1 * tex) as usize, seed);
    let slabs = if flat { Vec::new() } else { make_slabs(&mut rng, half_w, half_h, tex, seed) };

    // The keyframe's tree stands in front of the first slab (so the mask covers parallax),
    // a person elsewhere.
    let (tx, ty) = slabs.first().map_or((rng.random_range(-0.3..0.3) * half_w, 0.2 * half_h), |s| {
        (0.5 * (s.x0 + s.x1) + rng.random_range(-0.3..0.3), 0.5 * (s.y0 + s.y1))
    });
    let tree_z = WALL * rng.random_range(0.45..0.7);
    let tree_px = rng.random_range(0.45..0.6) * h.min(w) as f64;
    let tree = sprite_at(Occluder::Tree, &key_cam, tree_z, tx, ty, tree_px, seed.wrapping_mul(31) + 7);
    let person_z = WALL * rng.random_range(0.5..0.8);
    let px = if tx > 0.0 { -0.6 } else { 0.6 } * half_w;
    let person = sprite_at(Occluder::Person, &key_cam, person_z, px, 0.4 * half_h, 0.4 * h as f64, seed + 11);
    let key_sprites = vec![tree.clone(), person];

    let render = |cam: &Camera, sprites: &[Sprite], noise: u64| -> (RgbF32, Mask, Plane<u16>) {
        let fine = cam.scaled(2.0);
        let kinv = fine.k.try_inverse().expect("regular K");
        let rt = fine.r.transpose();
        let (fw, fh) = (2 * w, 2 * h);
        let mut occ = Mask::new(fw, fh, 0);
        let mut label = Plane::new(fw, fh, 0u16);
        let img = RgbF32::from_fn(fw, fh, |x, y| {
            let d = rt * (kinv * Vector3::new(x as f64, y as f64, 1.0));
            match cast(&fine.c, &d, &wall_tex, tex, &slabs, sprites) {
                Hit::Surface(p, c) => {
                    label.set(x, y, p);
                    c
                }
                Hit::Side(c) => {
                    label.set(x, y, SIDE);
                    c
                }
                Hit::Sprite(c) => {
                    occ.set(x, y, 255);
                    c
                }
                Hit::Nothing => [0.5; 3],
            }
        });
        let mut img = half(&img);
        if noise > 0 {
            super::add_noise(&mut img, 0.006, noise);
        }
        let label = Plane::from_fn(w, h, |x, y| label.get(2 * x, 2 * y));
        (img, half_mask(&occ), label)
    };

    let (truth, _, surface) = render(&key_cam, &[], 0);
    let (key, key_occluders, _) = render(&key_cam, &key_sprites, seed * 7 + 1);
    let mask = dilate_mask(&key_occluders, 2);

    let mut views = Vec::with_capacity(n);
    let mut planes = Vec::with_capacity(n);
    let mut view_occluders = Vec::with_capacity(n);
    let mut occluders = Vec::with_capacity(n);
    let mut cameras = Vec::with_capacity(n);
    for i in 0..n {
        // Around the point of the wall the keyframe looks at: 5–30° to alternate sides.
        let side = if i % 2 == 0 { 1.0 } else { -1.0 };
        let yaw = side * rng.random_range(5.0f64..30.0).to_radians();
        let pitch = rng.random_range(-6.0f64..6.0).to_radians();
        let roll = rng.random_range(-3.0f64..3.0).to_radians();
        let dist = WALL * rng.random_range(0.9..1.1);
        let target =
            Vector3::new(rng.random_range(-0.1..0.1) * half_w, rng.random_range(-0.1..0.1) * half_h, WALL);
        let dir = Vector3::new(yaw.sin() * pitch.cos(), pitch.sin(), yaw.cos() * pitch.cos());
        let c = target - dir * dist;
        let r = look_at(&dir, roll);
        let fv = f * rng.random_range(0.95..1.05);
        let kv =
            Matrix3::new(fv, 0.0, (w as f64 - 1.0) / 2.0, 0.0, fv, (h as f64 - 1.0) / 2.0, 0.0, 0.0, 1.0);
        let cam = Camera { k: kv, r, c };
        // Its own passer-by, somewhere in its frame.
        let kind = [Occluder::Person, Occluder::Car, Occluder::Tree][(i + seed as usize) % 3];
        let z = WALL * rng.random_range(0.4..0.85);
        let (u, v) = (rng.random_range(0.15..0.85) * w as f64, rng.random_range(0.45..0.7) * h as f64);
        let ray = cam.r.transpose() * (cam.k.try_inverse().expect("regular K") * Vector3::new(u, v, 1.0));
        let t = (z - cam.c.z) / ray.z;
        let at = cam.c + ray * t;
        let size = rng.random_range(0.3..0.5) * h.min(w) as f64 * (z - cam.c.z) / f;
        let own = sprite_world(kind, z, at.x, at.y, size, seed * 100 + i as u64);
        let sprites = [tree.clone(), own];
        let (mut img, occ, _) = render(&cam, &sprites, seed * 1000 + i as u64);
        super::expose(&mut img, rng.random_range(0.85..1.15), rng.random_range(-0.03..0.03));
        let hs: Vec<Homography> = std::iter::once(WALL)
            .chain(slabs.iter().map(|s| WALL - s.depth))
            .map(|z| cam.plane_homography(&key_cam, z))
            .collect();
        let wall_h = hs[0];
        let occ_key = Mask::from_fn(w, h, |x, y| {
            let q = wall_h.apply(nalgebra::Point2::new(x as f64, y as f64));
            match q {
                Some(q) if q.x >= -0.5 && q.y >= -0.5 && q.x < w as f64 - 0.5 && q.y < h as f64 - 0.5 => {
                    occ.get(q.x.round() as usize, q.y.round() as usize)
                }
                _ => 0,
            }
        });
        views.push(img);
        planes.push(hs);
        view_occluders.push(occ_key);
        occluders.push(occ);
        cameras.push(cam);
    }
    ParallaxCase {
        key,
        mask,
        key_occluders,
        truth,
        views,
        planes,
        surface,
        view_occluders,
        occluders,
        slabs,
        key_camera: key_cam,
        cameras,
    }
}

/// World → camera rotation of a camera looking along `dir` (unit), rolled by `roll`.
fn look_at(dir: &Vector3<f64>, roll: f64) -> Matrix3<f64> {
    let z = dir.normalize();
    let down = Vector3::new(0.0, 1.0, 0.0);
    let x = down.cross(&z).normalize();
    let y = z.cross(&x);
    let (c, s) = (roll.cos(), roll.sin());
    let (x, y) = (x * c + y * s, y * c - x * s);
    Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()])
}

/// Two to four slabs in the part of the wall the keyframe sees, not overlapping.
fn make_slabs(rng: &mut ChaCha8Rng, half_w: f64, half_h: f64, tex: f64, seed: u64) -> Vec<Slab> {
    let count = rng.random_range(2..=4usize);
    let mut slabs: Vec<Slab> = Vec::new();
    let mut tries = 0;
    while slabs.len() < count && tries < 200 {
        tries += 1;
        let kind = match (slabs.len() + seed as usize) % 3 {
            0 => SlabKind::Balcony,
            1 => SlabKind::Pilaster,
            _ => SlabKind::Sign,
        };
        let (sw, sh) = match kind {
            SlabKind::Balcony => (rng.random_range(0.5..0.8) * half_w, rng.random_range(0.25..0.4) * half_h),
            SlabKind::Pilaster => (rng.random_range(0.1..0.18) * half_w, rng.random_range(1.3..2.0) * half_h),
            SlabKind::Sign => (rng.random_range(0.35..0.55) * half_w, rng.random_range(0.2..0.3) * half_h),
        };
        let cx = rng.random_range(-0.6..0.6) * half_w;
        let cy = rng.random_range(-0.5..0.5) * half_h;
        let (x0, x1, y0, y1) = (cx - sw / 2.0, cx + sw / 2.0, cy - sh / 2.0, cy + sh / 2.0);
        let gap = 0.05 * half_w;
        if slabs.iter().any(|s| x0 < s.x1 + gap && s.x0 < x1 + gap && y0 < s.y1 + gap && s.y0 < y1 + gap) {
            continue;
        }
        let depth = WALL * rng.random_range(0.04..0.14);
        let (tw, th) = (((x1 - x0) * tex) as usize + 2, ((y1 - y0) * tex) as usize + 2);
        let texture = slab_texture(kind, tw, th, seed.wrapping_mul(13) + slabs.len() as u64);
        slabs.push(Slab { kind, x0, x1, y0, y1, depth, texture });
    }
    slabs
}

/// The face of a slab of `kind`, `w × h` texture pixels.
fn slab_texture(kind: SlabKind, w: usize, h: usize, seed: u64) -> RgbF32 {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let stain = value_noise(w, h, 40.0, 4, &mut rng);
    let grain = value_noise(w, h, 4.0, 2, &mut rng);
    let base =
        [rng.random_range(0.6..0.85f32), rng.random_range(0.55..0.8f32), rng.random_range(0.5..0.7f32)];
    match kind {
        SlabKind::Balcony => {
            let pitch = rng.random_range(14.0..22.0f32);
            let rail = (h as f32 * 0.12).max(4.0);
            RgbF32::from_fn(w, h, |x, y| {
                let (xf, yf) = (x as f32, y as f32);
                let s = (0.85 + 0.3 * stain.get(x, y)) * (0.92 + 0.16 * grain.get(x, y));
                let in_rail = yf < rail || yf > h as f32 - rail;
                let phase = (xf % pitch) / pitch;
                // Balusters: light round shafts on a dark ground, shaded across.
                let c = if in_rail {
                    let band = if yf < rail * 0.3 || yf > h as f32 - rail * 0.3 { 0.8 } else { 1.0 };
                    base.map(|v| v * band)
                } else if (0.25..0.75).contains(&phase) {
                    let shade = 0.7 + 0.5 * (std::f32::consts::PI * (phase - 0.25) * 2.0).sin();
                    base.map(|v| v * shade)
                } else {
                    [0.12, 0.11, 0.1]
                };
                c.map(|v| (v * s).min(1.0))
            })
        }
        SlabKind::Pilaster => {
            let flutes = rng.random_range(3..6usize);
            let course = rng.random_range(25.0..45.0f32);
            RgbF32::from_fn(w, h, |x, y| {
                let (xf, yf) = (x as f32, y as f32);
                let s = (0.85 + 0.3 * stain.get(x, y)) * (0.9 + 0.2 * grain.get(x, y));
                let u = xf / w as f32 * flutes as f32;
                let flute = 0.75 + 0.25 * (std::f32::consts::TAU * u).cos();
                let joint = if yf % course < 2.0 { 0.55 } else { 1.0 };
                let edge = if xf < 3.0 || xf > w as f32 - 4.0 { 0.6 } else { 1.0 };
                base.map(|v| v * s * flute * joint * edge)
            })
        }
        SlabKind::Sign => {
            let board = [
                rng.random_range(0.05..0.9f32),
                rng.random_range(0.05..0.6f32),
                rng.random_range(0.1..0.9f32),
            ];
            let ink = board.map(|v| 1.0 - v);
            let letters = rng.random_range(4..9usize);
            let lw = w as f32 * 0.8 / letters as f32;
            let strokes: Vec<u32> = (0..letters).map(|_| rng.random::<u32>()).collect();
            RgbF32::from_fn(w, h, |x, y| {
                let (xf, yf) = (x as f32, y as f32);
                let s = 0.9 + 0.15 * stain.get(x, y);
                let border = xf < 5.0 || yf < 5.0 || xf > w as f32 - 6.0 || yf > h as f32 - 6.0;
                if border {
                    return [0.85 * s, 0.85 * s, 0.8 * s];
                }
                let lx = xf - 0.1 * w as f32;
                let ly = (yf - 0.25 * h as f32) / (0.5 * h as f32);
                if lx >= 0.0 && (0.0..1.0).contains(&ly) {
                    let li = (lx / lw) as usize;
                    if li < letters {
                        // A letter: some of a 3 × 5 grid of strokes.
                        let u = (lx - li as f32 * lw) / (0.75 * lw);
                        if u < 1.0 {
                            let cell = (u * 3.0) as u32 + 3 * (ly * 5.0) as u32;
                            if strokes[li] >> cell & 1 == 1 {
                                return ink.map(|v| v * s);
                            }
                        }
                    }
                }
                board.map(|v| v * s)
            })
        }
    }
}

/// A sprite of `kind` about `size_px` keyframe pixels tall at depth `z`, in front of the
/// wall's point `(x, y)` as the keyframe camera sees it.
fn sprite_at(kind: Occluder, key: &Camera, z: f64, x: f64, y: f64, size_px: f64, seed: u64) -> Sprite {
    let s = z / WALL;
    sprite_world(kind, z, x * s, y * s, size_px * z / key.k[(0, 0)], seed)
}

/// A sprite of `kind`, `size` world units tall, centred on world `(x, y)` at depth `z`.
fn sprite_world(kind: Occluder, z: f64, x: f64, y: f64, size: f64, seed: u64) -> Sprite {
    let px = 320usize;
    let mut image = RgbF32::new(2 * px, 2 * px, [0.0; 3]);
    let mut alpha = Mask::new(2 * px, 2 * px, 0);
    paint_occluder(&mut image, Some(&mut alpha), kind, px as f32, px as f32, px as f32, seed);
    let scale = size / px as f64;
    Sprite { z, x0: x - px as f64 * scale, y0: y - px as f64 * scale, scale, image, alpha }
}

/// The first thing the ray `c + t·d` (t > 0) hits.
fn cast(
    c: &Vector3<f64>,
    d: &Vector3<f64>,
    wall: &RgbF32,
    tex: f64,
    slabs: &[Slab],
    sprites: &[Sprite],
) -> Hit {
    if d.z <= 1e-9 {
        return Hit::Nothing;
    }
    let mut best_t = (WALL - c.z) / d.z;
    let p = c + d * best_t;
    let mut hit = {
        let (u, v) = ((p.x + WALL_HALF.0) * tex, (p.y + WALL_HALF.1) * tex);
        bilinear_rgb(wall, u as f32, v as f32).map_or(Hit::Nothing, |col| Hit::Surface(0, col))
    };
    for (i, s) in slabs.iter().enumerate() {
        // Slab method on the box [x0, x1] × [y0, y1] × [WALL - depth, WALL].
        let lo = Vector3::new(s.x0, s.y0, WALL - s.depth);
        let hi = Vector3::new(s.x1, s.y1, WALL);
        let (mut t0, mut t1, mut axis) = (f64::NEG_INFINITY, f64::INFINITY, 2usize);
        let mut inside = true;
        for a in 0..3 {
            if d[a].abs() < 1e-12 {
                if c[a] < lo[a] || c[a] > hi[a] {
                    inside = false;
                }
                continue;
            }
            let (ta, tb) = ((lo[a] - c[a]) / d[a], (hi[a] - c[a]) / d[a]);
            let (near, far) = if ta < tb { (ta, tb) } else { (tb, ta) };
            if near > t0 {
                t0 = near;
                axis = a;
            }
            t1 = t1.min(far);
        }
        if !inside || t0 > t1 || t0 <= 0.0 || t0 >= best_t {
            continue;
        }
        best_t = t0;
        let q = c + d * t0;
        let (u, v) = ((q.x - s.x0) * tex, (q.y - s.y0) * tex);
        let tw = s.texture.width() as f64 - 1.0;
        let th = s.texture.height() as f64 - 1.0;
        let col = |u: f64, v: f64| {
            bilinear_rgb(&s.texture, u.clamp(0.0, tw) as f32, v.clamp(0.0, th) as f32).unwrap_or([0.5; 3])
        };
        hit = if axis == 2 {
            Hit::Surface(1 + i as u16, col(u, v))
        } else {
            // A side face: the front's texture along its edge, shaded, running back.
            let back = (q.z - (WALL - s.depth)) * tex;
            let (shade, c0) = if axis == 0 {
                (if d.x > 0.0 { 0.55 } else { 0.7 }, col(if d.x > 0.0 { 0.0 } else { tw }, v))
            } else {
                (if d.y > 0.0 { 0.85 } else { 0.45 }, col(u, if d.y > 0.0 { 0.0 } else { th }))
            };
            let ribs = if (back / 9.0) as i64 % 2 == 0 { 1.0 } else { 0.92 };
            Hit::Side(c0.map(|v| v * shade * ribs))
        };
    }
    let mut sprite_t = f64::INFINITY;
    for s in sprites {
        let t = (s.z - c.z) / d.z;
        if t <= 0.0 || t >= best_t || t >= sprite_t {
            continue;
        }
        let q = c + d * t;
        let (u, v) = ((q.x - s.x0) / s.scale, (q.y - s.y0) / s.scale);
        if u < 0.0 || v < 0.0 || u >= s.image.width() as f64 - 1.0 || v >= s.image.height() as f64 - 1.0 {
            continue;
        }
        let (ui, vi) = (u.round() as usize, v.round() as usize);
        if s.alpha.get(ui, vi) > 127 {
            sprite_t = t;
            hit = Hit::Sprite(s.image.get(ui, vi));
        }
    }
    hit
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Point2;

    #[test]
    fn the_true_plane_homographies_map_surface_points_to_where_the_views_see_them() {
        let c = parallax_case(160, 120, 3, 4, false);
        assert!(!c.slabs.is_empty());
        // Project world points of each plane into the key and each view; the plane's
        // homography must carry one to the other.
        for (v, cam) in c.cameras.iter().enumerate() {
            for (p, s) in std::iter::once(None).chain(c.slabs.iter().map(Some)).enumerate() {
                let z = s.map_or(WALL, |s| WALL - s.depth);
                let world = Vector3::new(0.3, -0.2, z);
                let project = |cam: &Camera| {
                    let q = cam.k * (cam.r * (world - cam.c));
                    Point2::new(q.x / q.z, q.y / q.z)
                };
                let (a, b) = (project(&c.key_camera), project(cam));
                let m = c.planes[v][p].apply(a).unwrap();
                assert!((m - b).norm() < 1e-6, "view {v} plane {p}: {m} vs {b}");
            }
        }
    }

    #[test]
    fn slabs_stand_off_the_wall_and_the_case_is_deterministic() {
        let a = parallax_case(160, 120, 2, 9, false);
        let b = parallax_case(160, 120, 2, 9, false);
        assert!(a.key == b.key && a.views[1] == b.views[1]);
        for s in &a.slabs {
            assert!((0.04 * WALL..=0.14 * WALL).contains(&s.depth), "{}", s.depth);
        }
        // The truth shows slab fronts and the mask covers some of them.
        let on_slab =
            (0..160 * 120).filter(|&i| a.surface.as_slice()[i] != 0 && a.mask.as_slice()[i] > 127).count();
        assert!(on_slab > 50, "masked slab pixels {on_slab}");
        let flat = parallax_case(160, 120, 2, 9, true);
        assert!(flat.surface.as_slice().iter().all(|&p| p == 0));
        assert!(flat.planes.iter().all(|p| p.len() == 1));
    }
}
