//! Issue 14's figures on generated non-planar facades (`synth::facade::parallax_case`):
//! masked PSNR against the truth of
//! - `today`: the fill as the `fill` command runs it (views aligned, one homography each);
//! - `reference`: the single-plane fill with the true wall homography and the views' true
//!   occluders (their pixels are never copied) — the reference;
//! - `planes`: the multi-plane fill (planes fitted from the matches the wall leaves out,
//!   each pixel's surface chosen by photo-consistency), from the same alignment as `today`;
//! - `swept`: the multi-plane fill with the surfaces swept densely (plane + parallax,
//!   `swept_planes`), from the same alignment;
//! - `true-planes`: the multi-plane fill given the true planes (an upper bound for the fit).
//!
//! `cargo run --release --example parallax_eval -- [--seeds N] [--first K] [--size WxH] [--views N] [--flat] [--dump DIR]`

use std::path::PathBuf;
use std::time::Instant;

use clearview::align::{AlignParams, Frame, align};
use clearview::geometry::Homography;
use clearview::imaging::RgbF32;
use clearview::imaging::convert::{luminance, to_rgb8};
use clearview::imaging::metrics::masked_psnr;
use clearview::inpaint::parallax::{SurfaceParams, SweepParams, surface_planes, swept_planes};
use clearview::inpaint::{FillExtras, FillParams, Filled, Observer, Source, Stage, fill_with};
use clearview::synth::facade::{ParallaxCase, parallax_case};

/// Milliseconds per stage.
#[derive(Default)]
struct Timer {
    at: Option<(Stage, Instant)>,
    ms: Vec<(Stage, f64)>,
}

impl Observer for Timer {
    fn stage(&mut self, stage: Stage) {
        self.end();
        self.at = Some((stage, Instant::now()));
    }
}

impl Timer {
    fn end(&mut self) {
        if let Some((s, t)) = self.at.take() {
            self.ms.push((s, t.elapsed().as_secs_f64() * 1e3));
        }
    }
}

fn run(
    c: &ParallaxCase,
    hs: &[Homography],
    extras: &FillExtras<'_>,
    params: &FillParams,
    t: &mut Timer,
) -> Filled {
    let sources: Vec<Source<'_>> =
        c.views.iter().zip(hs).map(|(image, &homography)| Source { image, homography }).collect();
    let f = fill_with(&c.key, &c.mask, &sources, extras, params, 1, t);
    t.end();
    f
}

/// For each swept surface (stderr): its region, and the true plane nearest to it at the
/// region's centre (mean over views of the distance between where each puts the centre).
fn describe(c: &ParallaxCase, walls: &[Homography], swept: &[clearview::inpaint::parallax::SurfacePlane]) {
    for (k, s) in swept.iter().enumerate() {
        let r = s.region;
        let p = nalgebra::Point2::new(r.x as f64 + 0.5 * r.width as f64, r.y as f64 + 0.5 * r.height as f64);
        let err = |t: usize| -> f64 {
            let d: Vec<f64> = s
                .views
                .iter()
                .zip(&c.planes)
                .filter_map(|(h, tp)| Some((h.as_ref()?.apply(p)? - tp[t].apply(p)?).norm()))
                .collect();
            d.iter().sum::<f64>() / d.len().max(1) as f64
        };
        let shift: Vec<String> = s
            .views
            .iter()
            .zip(walls)
            .map(|(h, w)| {
                h.and_then(|h| Some(format!("{:.1}", (h.apply(p)? - w.apply(p)?).norm())))
                    .unwrap_or("-".into())
            })
            .collect();
        let truth = c.surface.get(p.x as usize, p.y as usize);
        let errs: Vec<String> = (0..c.planes[0].len()).map(|t| format!("{:.1}", err(t))).collect();
        eprintln!(
            "  swept {k}: region {}x{}+{}+{}, off the wall {} px, truth at centre {truth}, error per true plane [{}]",
            r.width,
            r.height,
            r.x,
            r.y,
            shift.join("/"),
            errs.join(", ")
        );
    }
}

/// How well the fitted plane + parallax family reproduces each true slab plane (stderr):
/// per view, the best γ at the slab's centre and the distance left there.
fn family_check(c: &ParallaxCase, walls: &[Homography], views: &[&clearview::imaging::GrayF32]) {
    let Some((fam, g)) = clearview::inpaint::parallax::parallax_family(
        &luminance(&c.key),
        views,
        walls,
        &c.mask,
        &SweepParams::default(),
        1,
    ) else {
        eprintln!("  no parallax found");
        return;
    };
    let t_inv = g.t.inverse().unwrap();
    eprintln!(
        "  matches per view {:?}, epipoles {:?}, observed γ {:?}",
        g.matches.iter().map(Vec::len).collect::<Vec<_>>(),
        fam.epipoles.iter().map(Option::is_some).collect::<Vec<_>>(),
        fam.observed.iter().map(Vec::len).collect::<Vec<_>>()
    );
    for p in 1..c.planes[0].len() {
        let (mut sx, mut sy, mut k) = (0.0, 0.0, 0.0);
        for (i, &l) in c.surface.as_slice().iter().enumerate() {
            if l as usize == p {
                sx += (i % c.key.width()) as f64;
                sy += (i / c.key.width()) as f64;
                k += 1.0;
            }
        }
        if k == 0.0 {
            continue;
        }
        let at = nalgebra::Point2::new(sx / k, sy / k);
        let mut out = Vec::new();
        for v in 0..walls.len() {
            let truth = c.planes[v][p].apply(at).unwrap();
            let best = (-400..=400)
                .filter_map(|i| {
                    let gm =
                        f64::from(i) * 0.0025 * fam.observed[v].iter().map(|g| g.abs()).fold(0.0, f64::max);
                    let h = t_inv.after(&fam.homography(v, gm)?).after(&g.t);
                    Some((gm, (h.apply(at)? - truth).norm()))
                })
                .min_by(|a, b| a.1.total_cmp(&b.1));
            out.push(best.map_or("-".into(), |(gm, e)| format!("γ {gm:.4} err {e:.2}")));
        }
        eprintln!("  slab {p} at {:.0},{:.0}: {}", at.x, at.y, out.join(" | "));
    }
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (mut seeds, mut w, mut h, mut n, mut flat, mut dump) =
        (8u64, 640usize, 480usize, 3usize, false, None);
    let mut first = 1u64;
    let mut fp = FillParams::default();
    let mut it = args.iter();
    while let Some(a) = it.next() {
        match a.as_str() {
            "--seeds" => seeds = it.next().and_then(|v| v.parse().ok()).expect("--seeds N"),
            "--first" => first = it.next().and_then(|v| v.parse().ok()).expect("--first K"),
            "--views" => n = it.next().and_then(|v| v.parse().ok()).expect("--views N"),
            "--size" => {
                let (a, b) = it.next().and_then(|s| s.split_once('x')).expect("--size WxH");
                (w, h) = (a.parse().expect("width"), b.parse().expect("height"));
            }
            "--flat" => flat = true,
            "--penalty" => fp.parallax.penalty = it.next().and_then(|v| v.parse().ok()).expect("--penalty X"),
            "--bias" => fp.parallax.wall_bias = it.next().and_then(|v| v.parse().ok()).expect("--bias X"),
            "--truncate" => {
                fp.parallax.truncate = it.next().and_then(|v| v.parse().ok()).expect("--truncate X")
            }
            "--window" => fp.parallax.window = it.next().and_then(|v| v.parse().ok()).expect("--window N"),
            "--dump" => dump = Some(PathBuf::from(it.next().expect("--dump DIR"))),
            other => panic!("unknown argument {other}"),
        }
    }
    let names = ["today", "reference", "planes", "swept", "true-planes"];
    let mut sums = [0.0f64; 5];
    let mut stage_ms: Vec<(String, f64)> = Vec::new();
    println!("| seed | slabs | masked px | planes found | swept found | {} |", names.join(" | "));
    println!("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for seed in first..first + seeds {
        let c = parallax_case(w, h, n, seed, flat);
        let params = AlignParams::default();
        let t0 = Instant::now();
        let kf = Frame::new(luminance(&c.key), &params);
        let frames: Vec<Frame> = c.views.iter().map(|v| Frame::new(luminance(v), &params)).collect();
        let walls: Vec<Homography> =
            frames.iter().map(|f| align(&kf, f, &params, None).homography.expect("aligned")).collect();
        let align_ms = t0.elapsed().as_secs_f64() * 1e3;
        let t1 = Instant::now();
        let grays: Vec<_> = c.views.iter().map(luminance).collect();
        let refs: Vec<&_> = grays.iter().collect();
        let planes = surface_planes(&luminance(&c.key), &refs, &walls, &c.mask, &SurfaceParams::default(), 1);
        let fit_ms = t1.elapsed().as_secs_f64() * 1e3;
        let t2 = Instant::now();
        let swept = swept_planes(&luminance(&c.key), &refs, &walls, &c.mask, &SweepParams::default(), 1);
        let sweep_ms = t2.elapsed().as_secs_f64() * 1e3;
        if std::env::var_os("PARALLAX_DEBUG").is_some() {
            family_check(&c, &walls, &refs);
            describe(&c, &walls, &swept);
        }
        let true_planes = c.true_surfaces(24);
        let occ: Vec<Option<&clearview::imaging::Mask>> = c.occluders.iter().map(Some).collect();
        let mut timers: Vec<Timer> = (0..5).map(|_| Timer::default()).collect();
        let results = [
            run(&c, &walls, &FillExtras::default(), &fp, &mut timers[0]),
            run(&c, &c.wall(), &FillExtras { occluders: &occ, ..FillExtras::default() }, &fp, &mut timers[1]),
            run(&c, &walls, &FillExtras { planes: &planes, ..FillExtras::default() }, &fp, &mut timers[2]),
            run(&c, &walls, &FillExtras { planes: &swept, ..FillExtras::default() }, &fp, &mut timers[3]),
            run(
                &c,
                &c.wall(),
                &FillExtras { planes: &true_planes, ..FillExtras::default() },
                &fp,
                &mut timers[4],
            ),
        ];
        let psnr: Vec<f64> = results.iter().map(|f| masked_psnr(&f.image, &c.truth, &c.mask)).collect();
        for (s, p) in sums.iter_mut().zip(&psnr) {
            *s += p;
        }
        stage_ms.push(("align".into(), align_ms));
        stage_ms.push(("plane fit".into(), fit_ms));
        stage_ms.push(("plane sweep".into(), sweep_ms));
        for (s, ms) in &timers[3].ms {
            stage_ms.push((format!("fill: {}", s.name()), *ms));
        }
        println!(
            "| {seed} | {} | {} | {} | {} | {} |",
            c.slabs.len(),
            c.mask.hole_count(),
            planes.len(),
            swept.len(),
            psnr.iter().map(|p| format!("{p:.2}")).collect::<Vec<_>>().join(" | ")
        );
        if let Some(d) = &dump {
            std::fs::create_dir_all(d).unwrap();
            let tag = format!("{}-{seed}", if flat { "flat" } else { "parallax" });
            to_rgb8(&c.truth).save(d.join(format!("{tag}-truth.png"))).unwrap();
            to_rgb8(&c.key).save(d.join(format!("{tag}-key.png"))).unwrap();
            for (name, f) in names.iter().zip(&results) {
                to_rgb8(&f.image).save(d.join(format!("{tag}-{name}.png"))).unwrap();
            }
            // The surfaces the multi-plane fill chose (grey: keyframe; colours: planes).
            let pal = [
                [0.2, 0.2, 0.8],
                [0.9, 0.3, 0.2],
                [0.2, 0.8, 0.2],
                [0.9, 0.8, 0.1],
                [0.7, 0.2, 0.8],
                [0.1, 0.8, 0.8],
                [1.0, 1.0, 1.0],
            ];
            for (name, r) in [("planes", &results[2]), ("swept", &results[3]), ("true-planes", &results[4])] {
                let map = RgbF32::from_fn(w, h, |x, y| {
                    if c.mask.is_hole(x, y) {
                        pal[(r.surface.get(x, y) as usize).min(6)]
                    } else {
                        c.key.get(x, y).map(|v| 0.3 * v)
                    }
                });
                to_rgb8(&map).save(d.join(format!("{tag}-{name}-surfaces.png"))).unwrap();
            }
            let truth_map = RgbF32::from_fn(w, h, |x, y| {
                let s = c.surface.get(x, y);
                if s == clearview::synth::facade::SIDE { [0.5; 3] } else { pal[(s as usize).min(6)] }
            });
            to_rgb8(&truth_map).save(d.join(format!("{tag}-truth-surfaces.png"))).unwrap();
        }
    }
    let k = seeds as f64;
    println!(
        "| **mean** | | | | | {} |",
        sums.iter().map(|s| format!("{:.2}", s / k)).collect::<Vec<_>>().join(" | ")
    );
    // Median cost per stage over the cases.
    let mut keys: Vec<String> = stage_ms.iter().map(|(s, _)| s.clone()).collect();
    keys.dedup();
    let mut seen = std::collections::BTreeSet::new();
    println!("\nmedian ms per stage (multi-plane fill, {w}x{h}, {n} views):");
    for key in keys {
        if !seen.insert(key.clone()) {
            continue;
        }
        let mut v: Vec<f64> = stage_ms.iter().filter(|(s, _)| *s == key).map(|(_, m)| *m).collect();
        v.sort_by(f64::total_cmp);
        println!("  {key}: {:.1}", v[v.len() / 2]);
    }
}
