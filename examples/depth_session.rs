//! Views arriving one by one in a session on facades with slabs off the wall (issues 12 and
//! 14): the rendered facades of `parallax_eval` (`synth::facade::parallax_case`), each view
//! aligned by the session itself and filled after it lands, as the service does.
//!
//! Printed per seed: the masked PSNR of the published result after each view (`*` where the
//! view's fill was not published), and the one-shot fill of all the views
//! (`inpaint::fill_swept` after `inpaint::sweep_surfaces`, as `clearview fill` makes it).
//! The summary counts the views that made the published result worse by more than 0.3 dB
//! (issue 12's bound) and gives the mean of the last results against the one-shot fills'.
//!
//! `cargo run --release --example depth_session -- [--seeds N] [--first K] [--views N]
//! [--size WxH]`

use clearview::geometry::Homography;
use clearview::imaging::convert::luminance;
use clearview::imaging::metrics::masked_psnr;
use clearview::inpaint::parallax::{SweepParams, ViewMatches};
use clearview::inpaint::{self, FillExtras, FillParams, Source};
use clearview::session::{Session, SessionParams};
use clearview::synth::facade::parallax_case;

#[path = "common/facades.rs"]
mod facades;
use facades::Facades;

fn main() {
    // `RUST_LOG=clearview::session=debug` prints each fill's judgement against the current result.
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::from_default_env())
        .with_writer(std::io::stderr)
        .init();
    let args: Vec<String> = std::env::args().skip(1).collect();
    let mut facades = Facades::new(8, 5);
    let mut it = args.iter();
    while let Some(a) = it.next() {
        if !facades.read(a, &mut it) {
            panic!("unknown argument {a}");
        }
    }
    let Facades { seeds, width: w, height: h, views: n, .. } = facades;
    println!("| seed | published after each view (dB; * kept the current) | one-shot | last − one-shot |");
    println!("|---:|---|---:|---:|");
    let (mut worse, mut landings, mut last_sum, mut once_sum) = (0usize, 0usize, 0.0, 0.0);
    for seed in facades.seed_range() {
        let c = parallax_case(w, h, n, seed, false);
        let session = SessionParams::default();
        let seed_of_fill = session.seed;
        let mut s = Session::new(session);
        s.set_key("key".into(), c.key.clone());
        s.set_mask("mask".into(), c.mask.clone()).expect("a mask of the keyframe's size");
        let (mut published, mut cells, mut walls) = (None::<f64>, Vec::new(), Vec::new());
        for (i, v) in c.views.iter().enumerate() {
            let record = s.align(luminance(v)).expect("a keyframe");
            let wall = record.accepted.then_some(record.homography).flatten().and_then(Homography::from_rows);
            let Some(wall) = wall else {
                cells.push("refused".to_string());
                continue;
            };
            walls.push((i, wall));
            let pixels = v.map(|p| p.map(|c| (c.clamp(0.0, 1.0) * 255.0).round() as u8));
            s.admit(format!("view{i}"), record, Some(&pixels)).expect("admitted");
            s.request_fill();
            let outcome = s.fill(&mut ()).expect("a fill");
            let now = match &outcome.image {
                Some(image) => masked_psnr(image, &c.truth, &c.mask),
                None => published.expect("the first fill is published"),
            };
            if let Some(before) = published {
                landings += 1;
                worse += usize::from(now < before - 0.3);
            }
            cells.push(format!("{now:.2}{}", if outcome.image.is_some() { "" } else { "*" }));
            published = Some(now);
        }
        let sources: Vec<Source<'_>> =
            walls.iter().map(|&(i, homography)| Source { image: &c.views[i], homography }).collect();
        let mut memo: Vec<ViewMatches> = sources.iter().map(|_| ViewMatches::default()).collect();
        let planes = inpaint::sweep_surfaces(
            &luminance(&c.key),
            &c.mask,
            &sources,
            &SweepParams::default(),
            seed_of_fill,
            &mut memo,
            &mut (),
        );
        let (none, params) = (FillExtras::default(), FillParams::default());
        let once =
            inpaint::fill_swept(&c.key, &c.mask, &sources, &none, &params, planes, seed_of_fill, &mut ());
        let once = masked_psnr(&once.filled.image, &c.truth, &c.mask);
        let last = published.unwrap_or(f64::NAN);
        (last_sum, once_sum) = (last_sum + last, once_sum + once);
        println!("| {seed} | {} | {once:.2} | {:+.2} |", cells.join(" → "), last - once);
    }
    println!(
        "\n{worse} of {landings} landings made the published result worse by more than 0.3 dB; \
         mean last result {:.2} dB, one-shot {:.2} dB",
        last_sum / seeds as f64,
        once_sum / seeds as f64
    );
}
