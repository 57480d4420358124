//! Where the views' own-occluder marks lie on the facades with slabs (issue 14), found
//! through the true walls, then judged again through surfaces off the wall
//! (`inpaint::own_occluders_off_surfaces`): the true ones (`--surfaces true`) or those the
//! sweep finds (`--surfaces swept`). Per seed and in total: marked pixels on the views'
//! true occluders, on slabs, elsewhere.
//!
//! `cargo run --release --example own_marks -- [--seeds N] [--first K] [--views N]
//! [--size WxH] [--surfaces walls|true|swept]`

use clearview::imaging::Mask;
use clearview::imaging::convert::luminance;
use clearview::inpaint::parallax::{SweepParams, ViewMatches};
use clearview::inpaint::{self, AutoMaskParams, OwnParams, Source};
use clearview::synth::facade::{MarksLie, parallax_case};

#[path = "common/facades.rs"]
mod facades;
use facades::Facades;

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (mut facades, mut surfaces) = (Facades::new(12, 5), "true".to_string());
    let mut it = args.iter();
    while let Some(a) = it.next() {
        match a.as_str() {
            f if facades.read(f, &mut it) => {}
            "--surfaces" => surfaces = it.next().cloned().expect("--surfaces walls|true|swept"),
            other => panic!("unknown argument {other}"),
        }
    }
    let (own, auto) = (OwnParams::default(), AutoMaskParams::default());
    println!("| seed | surfaces | through walls (occluder / slab / elsewhere) | {surfaces} | s |");
    println!("|---:|---:|---|---|---:|");
    let (mut before, mut after) = (MarksLie::default(), MarksLie::default());
    for seed in facades.seed_range() {
        let c = parallax_case(facades.width, facades.height, facades.views, seed, false);
        let walls = c.wall();
        let sources: Vec<Source<'_>> =
            c.views.iter().zip(&walls).map(|(image, &homography)| Source { image, homography }).collect();
        let through_walls = inpaint::own_occluders(&c.key, &c.mask, &sources, &own, &auto);
        let planes = match surfaces.as_str() {
            "walls" => Vec::new(),
            "true" => c.true_surfaces(24),
            "swept" => {
                let mut memo: Vec<ViewMatches> = sources.iter().map(|_| ViewMatches::default()).collect();
                let sweep = SweepParams::default();
                inpaint::sweep_surfaces(&luminance(&c.key), &c.mask, &sources, &sweep, 7, &mut memo, &mut ())
            }
            other => panic!("--surfaces walls|true|swept, not {other}"),
        };
        let t = std::time::Instant::now();
        let marks: Vec<Option<&Mask>> = through_walls.iter().map(Option::as_ref).collect();
        let off =
            inpaint::own_occluders_off_surfaces(&c.key, &c.mask, &sources, &marks, &planes, &own, &auto);
        let secs = t.elapsed().as_secs_f64();
        let (b, a) = (c.where_marks_lie(&through_walls), c.where_marks_lie(&off));
        println!(
            "| {seed} | {} | {} / {} / {} | {} / {} / {} | {secs:.2} |",
            planes.len(),
            b.occluder,
            b.slab,
            b.elsewhere,
            a.occluder,
            a.slab,
            a.elsewhere
        );
        for (sum, one) in [(&mut before, b), (&mut after, a)] {
            sum.occluder += one.occluder;
            sum.slab += one.slab;
            sum.elsewhere += one.elsewhere;
        }
    }
    println!("\ntotal through walls: {before:?}\ntotal through {surfaces}: {after:?}");
}
