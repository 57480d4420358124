//! End-to-end tests of `clearview run` and `clearview check-config`: the real binary on a
//! temporary folder, fed like a camera would feed it.

mod daemon_common;

use std::io::Write;
use std::path::Path;
use std::process::Command;
use std::time::Duration;

use clearview::imaging::convert::to_rgb8;
use clearview::synth;
use daemon_common::*;
use serde_json::Value;

#[test]
fn check_config_accepts_the_shipped_file_and_refuses_bad_ones() {
    let shipped = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/clearview.toml");
    let s = Command::new(bin()).arg("check-config").arg(&shipped).output().unwrap();
    assert_eq!(s.status.code(), Some(0), "{}", String::from_utf8_lossy(&s.stderr));
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.toml");
    std::fs::write(&bad, "[watch]\nquiet_period = 3\n").unwrap();
    let s = Command::new(bin()).arg("check-config").arg(&bad).output().unwrap();
    assert_eq!(s.status.code(), Some(64));
    assert!(String::from_utf8_lossy(&s.stderr).contains("quiet_period"), "the error names the key");
    let s = Command::new(bin()).args(["run", "--config"]).arg(&bad).output().unwrap();
    assert_eq!(s.status.code(), Some(64), "run refuses a bad configuration with 64");
    let s = Command::new(bin()).arg("check-config").arg(dir.path().join("missing.toml")).output().unwrap();
    assert_eq!(s.status.code(), Some(64));
}

#[test]
fn a_session_improves_as_views_arrive_and_bad_files_are_skipped() {
    let f = folders("");
    let service = Service::start(&f);
    let mut scene = Scene::new(11);
    let session = f.inbox.join("facade");
    put_key_and_mask(&session, &scene);
    wait_for(&f, "the session to start", 20, |e| !of_kind(e, "mask_set").is_empty());

    // View 1 arrives slowly, in pieces, under its final name: it must not be read early.
    let v1 = png(&scene.view(1, 120.0, 70.0));
    let mut file = std::fs::File::create(session.join("v1.png")).unwrap();
    for chunk in v1.chunks(v1.len() / 4 + 1) {
        file.write_all(chunk).unwrap();
        file.flush().unwrap();
        std::thread::sleep(Duration::from_millis(120));
    }
    drop(file);
    let ev = wait_for(&f, "a first result", 20, |e| !of_kind(e, "result_updated").is_empty());
    let first = image::open(f.outbox.join("facade/history/result-0001.png")).unwrap().to_rgb8();
    let e_invented = scene.masked_error(&first);
    assert!(about(&ev, "v1.png").iter().all(|e| e["event"] != "file_skipped"), "v1 was read half-written");

    // View 2 uploaded as .part and renamed; a corrupt file, an empty one, another scene.
    let v2 = png(&scene.view(2, 300.0, 60.0));
    std::fs::write(session.join("v2.png.part"), &v2).unwrap();
    std::thread::sleep(Duration::from_millis(400));
    std::fs::rename(session.join("v2.png.part"), session.join("v2.png")).unwrap();
    let mut corrupt = png(&scene.view(9, 0.0, 0.0));
    corrupt.truncate(corrupt.len() / 3);
    put(&session.join("corrupt.png"), &corrupt);
    put(&session.join("empty.png"), b"");
    let other = Scene::new(999);
    put(&session.join("other.png"), &png(&other.key));
    put(&session.join("v3.png"), &png(&scene.view(3, 60.0, 50.0)));

    let ev = wait_for(&f, "every file to be handled", 40, |e| {
        ["v2.png", "v3.png", "corrupt.png", "empty.png", "other.png"].iter().all(|n| !about(e, n).is_empty())
    });
    assert!(about(&ev, "v2.png.part").is_empty(), "a .part file was read");
    for bad in ["corrupt.png", "empty.png"] {
        let e = about(&ev, bad);
        assert_eq!(e.len(), 1, "{bad} reported once: {e:?}");
        assert_eq!(e[0]["event"], "file_skipped");
        assert!(e[0]["reason"].as_str().is_some_and(|r| !r.is_empty()));
    }
    let other_ev = about(&ev, "other.png");
    assert_eq!(other_ev[0]["event"], "view_rejected", "{other_ev:?}");
    for good in ["v1.png", "v2.png", "v3.png"] {
        assert_eq!(about(&ev, good)[0]["event"], "view_accepted", "{good}");
    }
    // Wait for the result that used all three views.
    let ev = wait_for(&f, "a result from all three views", 30, |e| {
        std::fs::read(f.outbox.join("facade/result.json"))
            .ok()
            .and_then(|b| serde_json::from_slice::<Value>(&b).ok())
            .is_some_and(|j| {
                j["views"].as_array().unwrap().iter().filter(|v| v["status"] == "used").count() == 3
            })
            && !of_kind(e, "result_updated").is_empty()
    });
    // Each fill says what the publish rule compared: how much of the mask the views back in
    // the new fill and in the current result. The new fill was published exactly when it was
    // not clearly less backed.
    let judged: Vec<&Value> =
        ev.iter().filter(|e| e["event"] == "result_updated" || e["event"] == "result_not_better").collect();
    assert!(judged.iter().any(|e| e["current_backed"].is_f64()), "never judged against a result: {judged:?}");
    for e in judged {
        let backed = e["backed"].as_f64().unwrap();
        assert!((0.0..=1.0).contains(&backed), "{e}");
        if let Some(current) = e["current_backed"].as_f64() {
            let published = e["event"] == "result_updated";
            assert_eq!(published, backed >= current - clearview::session::KEEP_MARGIN, "{e}");
        }
    }
    let report: Value =
        serde_json::from_slice(&std::fs::read(f.outbox.join("facade/result.json")).unwrap()).unwrap();
    assert_eq!(report["version"], 1);
    assert_eq!(report["keyframe"], "key.png");
    assert_eq!(report["mask"], "file:key.mask.png");
    assert_eq!(report["masked"].as_u64().unwrap() as usize, scene.mask.hole_count());
    let from_views = report["from_views"].as_f64().unwrap();
    let from_fallback = report["from_fallback"].as_f64().unwrap();
    assert!((from_views + from_fallback - 1.0).abs() < 1e-6, "{from_views} + {from_fallback}");
    let listed: Vec<&Value> = report["views"].as_array().unwrap().iter().collect();
    let other_listed = listed.iter().find(|v| v["file"] == "other.png").expect("the rejected view is listed");
    assert_eq!(other_listed["accepted"], false);
    assert!(other_listed["reason"].as_str().is_some());
    let used = listed.iter().find(|v| v["file"] == "v3.png").unwrap();
    assert!(used["homography"].is_array() && used["quality"]["inliers"].as_u64().unwrap() >= 20);

    // The results are valid images of the keyframe's size; history is numbered.
    let result = image::open(f.outbox.join("facade/result.png")).unwrap().to_rgb8();
    assert_eq!((result.width() as usize, result.height() as usize), (W, H));
    let numbers: Vec<u64> =
        of_kind(&ev, "result_updated").iter().map(|e| e["number"].as_u64().unwrap()).collect();
    assert!(numbers.windows(2).all(|w| w[1] == w[0] + 1), "{numbers:?}");
    let last = *numbers.last().unwrap();
    assert!(f.outbox.join(format!("facade/history/result-{last:04}.png")).is_file());
    // Outside the mask the keyframe is untouched.
    let key8 = to_rgb8(&scene.key);
    for (x, y) in [(5, 5), (W - 3, H - 3), (20, 250)] {
        assert_eq!(result.get_pixel(x as u32, y as u32), key8.get_pixel(x as u32, y as u32));
    }
    // A result is never replaced by a worse one, and the masked region's error against the
    // truth falls from the keyframe-only result (everything invented) as views arrive.
    let scores: Vec<f64> =
        of_kind(&ev, "result_updated").iter().map(|e| e["score"].as_f64().unwrap()).collect();

    assert!(
        scores.windows(2).all(|w| w[1] >= w[0] - 1e-9),
        "a result was replaced by a worse one: {scores:?}"
    );
    let e_last = scene.masked_error(&result);
    eprintln!(
        "masked error: keyframe only {e_invented:.4}, after three views {e_last:.4}; from views {scores:?}"
    );
    assert!(from_views > 0.9, "only {from_views} of the mask from views");
    assert!(e_last < 0.6 * e_invented, "error {e_invented} -> {e_last}: the views did not help");
    for e in &ev {
        eprintln!("{e}");
    }
    assert_eq!(service.terminate(), 0);
    // The score is the expected quality (mean confidence), written beside the result as
    // confidence.png: keyframe-sized, 0 outside the mask (read once the service has stopped,
    // so that both files are of the last result).
    let report: Value =
        serde_json::from_slice(&std::fs::read(f.outbox.join("facade/result.json")).unwrap()).unwrap();
    let confident = report["confident"].as_f64().unwrap();
    assert!((confident + report["doubtful"].as_f64().unwrap() - 1.0).abs() < 1e-6);
    assert!(confident > 0.5, "only {confident} of the mask confident");
    let conf = image::open(f.outbox.join("facade/confidence.png")).unwrap().to_luma8();
    assert_eq!((conf.width() as usize, conf.height() as usize), (W, H));
    assert_eq!(conf.get_pixel(5, 5).0[0], 0, "confidence outside the mask");
    let sure = (0..H)
        .flat_map(|y| (0..W).map(move |x| (x, y)))
        .filter(|&(x, y)| scene.mask.is_hole(x, y) && conf.get_pixel(x as u32, y as u32).0[0] >= 128)
        .count();
    assert_eq!(sure as u64, report["confident_px"].as_u64().unwrap());
    // The map holds the confidence's grades, not only sure or not: its mean over the mask
    // is the score (it was written as a mask, 0 or 255).
    let mean = (0..H)
        .flat_map(|y| (0..W).map(move |x| (x, y)))
        .filter(|&(x, y)| scene.mask.is_hole(x, y))
        .map(|(x, y)| f64::from(conf.get_pixel(x as u32, y as u32).0[0]) / 255.0)
        .sum::<f64>()
        / scene.mask.hole_count() as f64;
    let score = report["score"].as_f64().unwrap();
    assert!((mean - score).abs() < 1e-6, "confidence.png's mean {mean:.4}, the score {score:.4}");
    no_temporaries(&f.outbox);
    no_temporaries(&f.state);
}

#[test]
fn sigterm_mid_session_exits_0_and_leaves_nothing_half_written() {
    let f = folders("");
    let service = Service::start(&f);
    let mut scene = Scene::new(21);
    let session = f.inbox.join("s");
    put_key_and_mask(&session, &scene);
    for i in 1..=4 {
        put(&session.join(format!("v{i}.png")), &png(&scene.view(i, 100.0 + 60.0 * i as f32, 60.0)));
    }
    wait_for(&f, "a first view", 30, |e| !of_kind(e, "view_accepted").is_empty());
    assert_eq!(service.terminate(), 0, "SIGTERM is a clean stop");
    let ev = events(&f);
    let stopped = of_kind(&ev, "service_stopped");
    assert_eq!(stopped.len(), 1);
    assert_eq!(stopped[0]["clean"], true);
    no_temporaries(&f.outbox);
    no_temporaries(&f.state);
    // Whatever was written is whole.
    if f.outbox.join("s/result.png").exists() {
        image::open(f.outbox.join("s/result.png")).expect("a complete image");
        let _: Value =
            serde_json::from_slice(&std::fs::read(f.outbox.join("s/result.json")).unwrap()).unwrap();
    }
    for entry in std::fs::read_dir(f.state.join("sessions")).unwrap().flatten() {
        let _: Value =
            serde_json::from_slice(&std::fs::read(entry.path()).unwrap()).expect("whole state file");
    }
}

#[test]
fn a_restart_resumes_from_saved_alignments_without_rewriting_results() {
    let f = folders("");
    let mut scene = Scene::new(31);
    let session = f.inbox.join("s");
    put_key_and_mask(&session, &scene);
    let views: Vec<Vec<u8>> = (1..=4).map(|i| png(&scene.view(i, 90.0 * i as f32, 60.0))).collect();
    for (i, v) in views.iter().take(3).enumerate() {
        put(&session.join(format!("v{}.png", i + 1)), v);
    }
    let service = Service::start(&f);
    let ev = wait_for(&f, "a result from three views", 30, |e| {
        of_kind(e, "result_updated").iter().any(|r| r["views"] == 3)
    });
    let first_run_results = of_kind(&ev, "result_updated").len();
    let first_views = of_kind(&ev, "view_accepted").len();
    assert_eq!(first_views, 3);
    assert!(of_kind(&ev, "view_accepted").iter().all(|e| e["from_state"] == false));
    assert_eq!(service.terminate(), 0);
    let before = std::fs::read(f.outbox.join("s/result.json")).unwrap();

    // Second run: the same files, nothing new.
    let lines_before = events(&f).len();
    let service = Service::start(&f);
    let ev = wait_for(&f, "the session to resume", 30, |e| {
        e.len() > lines_before && !of_kind(&e[lines_before..], "result_unchanged").is_empty()
    });
    let resumed = &ev[lines_before..];
    let accepted = of_kind(resumed, "view_accepted");
    assert_eq!(accepted.len(), 3, "{resumed:#?}");
    assert!(accepted.iter().all(|e| e["from_state"] == true), "an alignment was recomputed: {accepted:#?}");
    assert!(of_kind(resumed, "result_updated").is_empty(), "an unchanged result was written again");
    assert_eq!(std::fs::read(f.outbox.join("s/result.json")).unwrap(), before);

    // A new view after the restart: a new result, numbered on from the last.
    put(&session.join("v4.png"), &views[3]);
    let ev = wait_for(&f, "a result with the new view", 30, |e| {
        of_kind(&e[lines_before..], "result_updated").iter().any(|r| r["views"] == 4)
    });
    let new = of_kind(&ev[lines_before..], "result_updated");
    assert_eq!(new[0]["number"].as_u64().unwrap() as usize, first_run_results + 1);
    assert_eq!(service.terminate(), 0);

    // A corrupt state file is ignored and rebuilt: alignments are recomputed, nothing fails.
    let state_file = f.state.join("sessions/s.json");
    std::fs::write(&state_file, b"{\"version\": 1, \"alignments\": {\"v1.png").unwrap();
    let lines_before = events(&f).len();
    let service = Service::start(&f);
    let ev = wait_for(&f, "the session to be rebuilt", 30, |e| {
        e.len() > lines_before
            && of_kind(&e[lines_before..], "view_accepted").len() == 4
            && !of_kind(&e[lines_before..], "result_updated").is_empty()
    });
    assert!(of_kind(&ev[lines_before..], "view_accepted").iter().all(|e| e["from_state"] == false));
    assert_eq!(service.terminate(), 0);
    let _: Value = serde_json::from_slice(&std::fs::read(&state_file).unwrap()).expect("rebuilt state");
}

#[test]
fn a_burst_on_a_polled_folder_with_a_tiny_queue_is_batched_and_nothing_is_lost() {
    // One worker with a queue of one: a burst of views cannot all be queued. The decision
    // under test: the files wait on disk, every one is handled in the end, and the fills
    // are batched (fewer fills than views).
    let f = folders("workers = 1\nqueue = 1\n");
    let text = std::fs::read_to_string(&f.config).unwrap();
    let polled = text
        .replace("quiet_period_ms = 300", "quiet_period_ms = 200\nmode = \"poll\"\npoll_interval_ms = 100");
    std::fs::write(&f.config, polled).unwrap();
    let mut scene = Scene::new(41);
    let session = f.inbox.join("burst");
    put_key_and_mask(&session, &scene);
    let service = Service::start(&f);
    wait_for(&f, "the first result", 30, |e| !of_kind(e, "result_updated").is_empty());
    let names: Vec<String> = (1..=6).map(|i| format!("b{i}.png")).collect();
    for (i, name) in names.iter().enumerate() {
        put(&session.join(name), &png(&scene.view(i as u64 + 1, 80.0 + 50.0 * i as f32, 50.0)));
    }
    // Filled after the last of them: a new result from all six, or a fill of all six that
    // scored no better than the one published (under load the batches differ, and so may
    // the scores).
    let ev = wait_for(&f, "every view to be handled and filled", 60, |e| {
        let last = e.iter().rposition(|x| names.iter().any(|n| x["file"] == n.as_str()));
        names.iter().all(|n| !about(e, n).is_empty())
            && last.is_some_and(|l| {
                e[l..].iter().any(|x| {
                    (x["event"] == "result_updated" && x["views"] == 6) || x["event"] == "result_not_better"
                })
            })
    });
    for n in &names {
        assert_eq!(about(&ev, n).len(), 1, "{n} handled once");
    }
    let fills_for_burst = of_kind(&ev, "result_updated").len() - 1 + of_kind(&ev, "result_not_better").len();
    assert!(fills_for_burst < names.len(), "{fills_for_burst} fills for {} views: not batched", names.len());
    assert_eq!(service.terminate(), 0);
}

#[test]
fn a_late_mask_fills_from_the_buffered_views_and_a_new_keyframe_restarts_the_session() {
    let f = folders("");
    let mut scene = Scene::new(51);
    let session = f.inbox.join("late");
    put(&session.join("key.png"), &png(&scene.key));
    let service = Service::start(&f);
    wait_for(&f, "the session to start", 30, |e| !of_kind(e, "session_started").is_empty());
    for i in 1..=2 {
        put(&session.join(format!("v{i}.png")), &png(&scene.view(i, 100.0 * i as f32, 60.0)));
    }
    let ev = wait_for(&f, "both views", 30, |e| of_kind(e, "view_accepted").len() == 2);
    assert!(of_kind(&ev, "result_updated").is_empty(), "a result without a mask");

    // The mask arrives after the views: they are aligned again (the keyframe's corners
    // under the mask are not matched, so an alignment made without it is not the one the
    // mask-first order gives), then filled. It was painted in red on a transparent layer:
    // what was painted is the mask (read by luminance, the transparency stored as white
    // was the mask and the red stroke was not).
    put(&session.join("key.mask.png"), &painted_layer_png(&scene.mask));
    let ev = wait_for(&f, "a result from the buffered views", 30, |e| {
        of_kind(e, "result_updated").iter().any(|r| r["views"] == 2)
    });
    assert_eq!(of_kind(&ev, "mask_set")[0]["masked"].as_u64(), Some(scene.mask.hole_count() as u64));
    let after_mask: Vec<&Value> = ev
        .iter()
        .skip_while(|e| e["event"] != "mask_set")
        .filter(|e| e["event"] == "view_accepted")
        .collect();
    assert_eq!(after_mask.len(), 2, "the views are offered again with their pixels");
    assert!(
        after_mask.iter().all(|e| e["from_state"] == false),
        "not aligned again with the mask: {after_mask:#?}"
    );

    // A new keyframe (same name, new contents): realigned, and a fresh result.
    let seen = ev.len();
    let mut brighter = scene.key.clone();
    synth::expose(&mut brighter, 1.1, 0.0);
    put(&session.join("key.png"), &png(&brighter));
    let ev = wait_for(&f, "a result for the new keyframe", 30, |e| {
        e.len() > seen
            && !of_kind(&e[seen..], "keyframe_changed").is_empty()
            && of_kind(&e[seen..], "result_updated").iter().any(|r| r["views"] == 2)
    });
    let realigned = of_kind(&ev[seen..], "view_accepted");
    assert!(realigned.iter().filter(|e| e["from_state"] == false).count() >= 2, "{realigned:#?}");
    assert_eq!(service.terminate(), 0);
}

#[test]
fn without_a_key_file_the_first_image_is_the_keyframe_and_its_mask_follows_its_name() {
    let f = folders("");
    let mut scene = Scene::new(61);
    let service = Service::start(&f);
    // Directly in the watched folder: the `_root` session.
    put(&f.inbox.join("IMG_0001.png"), &png(&scene.key));
    let ev = wait_for(&f, "the session to start", 30, |e| !of_kind(e, "session_started").is_empty());
    let started = of_kind(&ev, "session_started");
    assert_eq!(started[0]["keyframe"], "IMG_0001.png");
    assert_eq!(started[0]["session"], "_root");
    put(&f.inbox.join("IMG_0001.mask.png"), &mask_png(&scene.mask));
    put(&f.inbox.join("IMG_0002.png"), &png(&scene.view(1, 120.0, 60.0)));
    let ev = wait_for(&f, "a result with the view", 30, |e| {
        of_kind(e, "result_updated").iter().any(|r| r["views"] == 1)
    });
    assert_eq!(of_kind(&ev, "mask_set")[0]["mask"], "IMG_0001.mask.png");
    let report: Value =
        serde_json::from_slice(&std::fs::read(f.outbox.join("_root/result.json")).unwrap()).unwrap();
    assert_eq!(report["keyframe"], "IMG_0001.png");
    assert_eq!(service.terminate(), 0);
}

#[test]
fn with_an_automatic_mask_the_occluder_is_found_and_removed() {
    let f = folders("[session]\nmask = \"auto\"\nauto_mask_views = 2\n");
    let mut scene = Scene::new(71);
    let session = f.inbox.join("auto");
    put(&session.join("key.png"), &png(&scene.key));
    let service = Service::start(&f);
    wait_for(&f, "the session to start", 30, |e| !of_kind(e, "session_started").is_empty());
    for i in 1..=3 {
        put(&session.join(format!("v{i}.png")), &png(&scene.view(i, 60.0 + 130.0 * i as f32, 50.0)));
    }
    let ev = wait_for(&f, "a result from the automatic mask", 40, |e| {
        of_kind(e, "result_updated").iter().any(|r| r["views"] == 3)
    });
    let mask_set = of_kind(&ev, "mask_set");
    assert_eq!(mask_set[0]["source"], "auto");
    assert!(mask_set[0]["masked"].as_u64().unwrap() > 1000, "{mask_set:?}");
    let report: Value =
        serde_json::from_slice(&std::fs::read(f.outbox.join("auto/result.json")).unwrap()).unwrap();
    assert_eq!(report["mask"], "auto");
    // Where the tree stood, the result is close to the facade behind it.
    let result = image::open(f.outbox.join("auto/result.png")).unwrap().to_rgb8();
    let (e_key, e_result) = (scene.masked_error(&to_rgb8(&scene.key)), scene.masked_error(&result));
    eprintln!("error where the tree stood: keyframe {e_key:.4}, result {e_result:.4}");
    assert!(e_result < 0.5 * e_key, "the tree is still there: {e_key} -> {e_result}");
    assert_eq!(service.terminate(), 0);
}

/// With `mask = "auto"`, the mask is found from the first two accepted views and again as
/// the views double. A passer-by of the keyframe's had not moved when the first view was
/// taken: of the first two views one shows him and one the wall, they disagree, and the
/// first mask leaves him. The next two views show the wall behind him; the mask found from
/// the four takes him, and the result shows the wall where he stood.
#[test]
fn an_automatic_mask_is_found_again_as_the_views_double() {
    let f = folders("[session]\nmask = \"auto\"\nauto_mask_views = 2\n");
    let mut scene = Scene::new(73);
    let mut walker = clearview::imaging::Mask::new(W, H, 0);
    synth::paint_occluder(&mut scene.key, Some(&mut walker), synth::Occluder::Person, 330.0, 170.0, 60.0, 7);
    let walker_share = |mask: &image::GrayImage| {
        let (mut on, mut n) = (0usize, 0usize);
        for (x, y, p) in mask.enumerate_pixels() {
            if walker.is_hole(x as usize, y as usize) {
                n += 1;
                on += usize::from(p.0[0] > 127);
            }
        }
        on as f64 / n as f64
    };
    let session = f.inbox.join("walker");
    put(&session.join("key.png"), &png(&scene.key));
    let service = Service::start(&f);
    wait_for(&f, "the session to start", 30, |e| !of_kind(e, "session_started").is_empty());
    put(&session.join("v1.png"), &png(&scene.view_with_keys_person(1, 330.0, 170.0, 60.0, 7)));
    put(&session.join("v2.png"), &png(&scene.clear_view(2)));
    wait_for(&f, "a result from two views", 40, |e| {
        of_kind(e, "result_updated").iter().any(|r| r["views"] == 2)
    });
    let first = image::open(f.outbox.join("walker/mask.png")).unwrap().to_luma8();
    let before = walker_share(&first);
    eprintln!("the passer-by's pixels masked from two views: {before:.3}");
    assert!(before < 0.5, "the case does not hold: two views found the passer-by ({before:.3})");
    for i in 3..=4 {
        put(&session.join(format!("v{i}.png")), &png(&scene.clear_view(i)));
    }
    let ev = wait_for(&f, "the mask found again from four views", 60, |e| {
        of_kind(e, "mask_set").iter().any(|m| m["views"] == 4)
            && of_kind(e, "result_updated").iter().any(|r| r["views"].as_u64().unwrap_or(0) >= 3)
    });
    let sets: Vec<_> =
        of_kind(&ev, "mask_set").iter().map(|m| (m["views"].clone(), m["masked"].clone())).collect();
    eprintln!("masks set (views, masked): {sets:?}");
    let again = image::open(f.outbox.join("walker/mask.png")).unwrap().to_luma8();
    let after = walker_share(&again);
    eprintln!("the passer-by's pixels masked from four views: {after:.3}");
    assert!(after > 0.9, "the mask from four views leaves the passer-by: {after:.3}");
    // The result, once the fill with the new mask is published, shows the wall there.
    let ev = wait_for(&f, "a result with the new mask", 60, |e| {
        let set_at = e.iter().rposition(|x| x["event"] == "mask_set");
        set_at.is_some_and(|i| e[i..].iter().any(|x| x["event"] == "result_updated"))
    });
    drop(ev);
    let result = image::open(f.outbox.join("walker/result.png")).unwrap().to_rgb8();
    let error = |img: &image::RgbImage| {
        let (mut sum, mut n) = (0.0, 0usize);
        for (x, y, p) in img.enumerate_pixels() {
            if walker.is_hole(x as usize, y as usize) {
                let t = scene.truth.get(x as usize, y as usize);
                sum += (0..3).map(|c| (t[c] as f64 - p.0[c] as f64 / 255.0).abs()).sum::<f64>() / 3.0;
                n += 1;
            }
        }
        sum / n as f64
    };
    let (e_key, e_result) = (error(&to_rgb8(&scene.key)), error(&result));
    eprintln!("error where the passer-by stood: keyframe {e_key:.4}, result {e_result:.4}");
    assert!(e_result < 0.3 * e_key, "the passer-by is still there: {e_key} -> {e_result}");
    assert_eq!(service.terminate(), 0);
}

#[test]
fn idle_sessions_sleep_beyond_the_memory_budget_and_wake_without_realigning() {
    let f = folders("workers = 1\nresident_sessions = 1\n");
    let mut a = Scene::new(81);
    let mut b = Scene::new(82);
    let service = Service::start(&f);
    put_key_and_mask(&f.inbox.join("a"), &a);
    put(&f.inbox.join("a/v1.png"), &png(&a.view(1, 100.0, 60.0)));
    wait_for(&f, "a's first view in a result", 30, |e| {
        of_kind(e, "result_updated").iter().any(|r| r["session"] == "a" && r["views"] == 1)
    });
    put_key_and_mask(&f.inbox.join("b"), &b);
    put(&f.inbox.join("b/v1.png"), &png(&b.view(1, 100.0, 60.0)));
    let ev = wait_for(&f, "b's first view in a result", 30, |e| {
        of_kind(e, "result_updated").iter().any(|r| r["session"] == "b" && r["views"] == 1)
    });
    let seen = ev.len();
    put(&f.inbox.join("a/v2.png"), &png(&a.view(2, 300.0, 60.0)));
    let ev = wait_for(&f, "a's second view in a result", 30, |e| {
        of_kind(e, "result_updated").iter().any(|r| r["session"] == "a" && r["views"] == 2)
    });
    let a_after: Vec<&Value> = ev[seen..].iter().filter(|e| e["session"] == "a").collect();
    let v1: Vec<&&Value> =
        a_after.iter().filter(|e| e["event"] == "view_accepted" && e["file"] == "v1.png").collect();
    assert_eq!(v1.len(), 1, "a was rebuilt from disk: {a_after:#?}");
    assert_eq!(v1[0]["from_state"], true, "v1 was realigned");
    let numbers: Vec<u64> = of_kind(&ev, "result_updated")
        .iter()
        .filter(|r| r["session"] == "a")
        .map(|r| r["number"].as_u64().unwrap())
        .collect();
    assert!(numbers.windows(2).all(|w| w[1] == w[0] + 1), "a's numbering restarted: {numbers:?}");
    assert_eq!(service.terminate(), 0);
}

/// The service says what its sweep for surfaces off the wall did, as `clearview fill
/// --report` and `--surfaces` do: on a facade with slabs standing off it (three views),
/// `result.json` lists the surfaces found, in the keyframe's coordinates, that the result
/// was filled through them, and the masked pixels each filled; `surfaces.png` says which
/// filled each pixel.
#[test]
fn result_json_lists_the_surfaces_off_the_wall_it_filled_through() {
    let f = folders("");
    let c = synth::facade::parallax_case(640, 480, 3, 13, false);
    let session = f.inbox.join("slabs");
    put(&session.join("key.mask.png"), &mask_png(&c.mask));
    put(&session.join("key.png"), &png(&c.key));
    let service = Service::start(&f);
    wait_for(&f, "the session to start", 30, |e| !of_kind(e, "mask_set").is_empty());
    for (i, v) in c.views.iter().enumerate() {
        put(&session.join(format!("v{i}.png")), &png(v));
    }
    let read = || -> Option<Value> {
        serde_json::from_slice(&std::fs::read(f.outbox.join("slabs/result.json")).ok()?).ok()
    };
    wait_for(&f, "a result filled through the surfaces", 90, |_| {
        read().is_some_and(|j| j["planes"]["used"] == true)
    });
    let report = read().unwrap();
    let surfaces = report["planes"]["surfaces"].as_array().expect("surfaces listed");
    let filled: u64 = surfaces.iter().map(|p| p["filled_pixels"].as_u64().unwrap()).sum();
    let masked = report["masked"].as_u64().unwrap();
    assert!(filled > 0 && filled < masked, "{filled} of {masked} masked pixels through surfaces: {report}");
    for p in surfaces {
        let r: Vec<u64> = p["region"].as_array().unwrap().iter().map(|v| v.as_u64().unwrap()).collect();
        assert!(r.len() == 4 && r[0] + r[2] <= 640 && r[1] + r[3] <= 480, "{p}");
        assert!(p["views"].as_u64().unwrap() >= 2, "a surface seen by one view: {p}");
    }
    assert_eq!(service.terminate(), 0);
    // `surfaces.png` beside the result says it pixel by pixel, as `clearview fill --surfaces`
    // does: nothing outside the mask, 1 through the wall, 2 + s through surface s (read once
    // the service has stopped: the last result's map, which the last result.json describes).
    let report = read().unwrap();
    assert_eq!(report["surfaces"], "surfaces.png", "{report}");
    let map = image::open(f.outbox.join("slabs/surfaces.png")).unwrap().into_luma8();
    assert_eq!(map.dimensions(), (640, 480));
    let mut n = [0u64; 256];
    for (&v, &m) in map.as_raw().iter().zip(c.mask.as_slice()) {
        assert_eq!(m > 127, v > 0, "surface {v} where the mask is {m}");
        n[usize::from(v)] += 1;
    }
    let surfaces = report["planes"]["surfaces"].as_array().unwrap();
    let filled: u64 = surfaces.iter().map(|p| p["filled_pixels"].as_u64().unwrap()).sum();
    assert_eq!(n[1], report["masked"].as_u64().unwrap() - filled, "through the wall");
    for (k, p) in surfaces.iter().enumerate() {
        assert_eq!(n[2 + k], p["filled_pixels"].as_u64().unwrap(), "surface {k}: {p}");
    }
    assert_eq!(n[2 + surfaces.len()..].iter().sum::<u64>(), 0, "a surface the report does not list");
}
