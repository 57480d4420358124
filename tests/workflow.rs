//! The capture workflow photographers follow (issue 15), against the real service: a whole
//! session folder copied in at once, masks named as people name them, a session that
//! waits for its mask says so.

mod daemon_common;

use daemon_common::*;

#[test]
fn a_folder_copied_at_once_gives_a_result_for_the_masked_image_whatever_the_mask_is_called() {
    let f = folders("");
    let s = Service::start(&f);
    let sessions = [("dot", "hunt3.mask.png"), ("under", "hunt3_mask.png"), ("dash", "hunt3-mask.png")];
    for (i, (session, mask_name)) in sessions.iter().enumerate() {
        let mut scene = Scene::new(40 + i as u64);
        // Written elsewhere, then moved in together (a copy of a whole folder).
        let staging = f.root.join(format!("staging-{session}"));
        std::fs::create_dir_all(&staging).unwrap();
        for k in 1..=5u64 {
            let img = if k == 3 { png(&scene.key) } else { png(&scene.clear_view(k)) };
            std::fs::write(staging.join(format!("hunt{k}.png")), img).unwrap();
        }
        std::fs::write(staging.join(mask_name), mask_png(&scene.mask)).unwrap();
        std::fs::create_dir_all(&f.inbox).unwrap();
        std::fs::rename(&staging, f.inbox.join(session)).unwrap();
    }
    let ev = wait_for(&f, "a result in every session", 120, |ev| {
        sessions.iter().all(|(s, _)| of_kind(ev, "result_updated").iter().any(|e| e["session"] == *s))
    });
    for (session, mask_name) in sessions {
        let mine: Vec<_> = ev.iter().filter(|e| e["session"] == session).collect();
        let started = mine
            .iter()
            .rev()
            .find(|e| e["event"] == "session_started" || e["event"] == "keyframe_changed")
            .unwrap();
        assert_eq!(started["keyframe"], "hunt3.png", "{session}: {mine:#?}");
        let mask = mine.iter().find(|e| e["event"] == "mask_set").unwrap();
        assert_eq!(mask["file"], mask_name, "{session}");
        assert!(
            !mine.iter().any(|e| e["file"] == mask_name && e["event"].as_str().unwrap().starts_with("view_")),
            "{session}: the mask was aligned as a view: {mine:#?}"
        );
        let report: serde_json::Value =
            serde_json::from_slice(&std::fs::read(f.outbox.join(session).join("result.json")).unwrap())
                .unwrap();
        assert_eq!(report["keyframe"], "hunt3.png");
        assert!(report["from_views"].as_f64().unwrap() > 0.9, "{report:#}");
    }
    drop(s);
}

#[test]
fn a_session_without_a_mask_says_once_that_it_waits_for_one() {
    let f = folders("");
    let s = Service::start(&f);
    let mut scene = Scene::new(50);
    let dir = f.inbox.join("s1");
    put(&dir.join("key.png"), &png(&scene.key));
    put(&dir.join("v1.png"), &png(&scene.clear_view(1)));
    put(&dir.join("v2.png"), &png(&scene.clear_view(2)));
    let ev = wait_for(&f, "the views and the waiting", 60, |ev| {
        !of_kind(ev, "session_waiting").is_empty() && of_kind(ev, "view_accepted").len() == 2
    });
    let waiting = of_kind(&ev, "session_waiting");
    assert_eq!(waiting.len(), 1, "{waiting:#?}");
    assert!(waiting[0]["reason"].as_str().unwrap().contains("key.mask.png"), "{:#}", waiting[0]);
    assert!(of_kind(&ev, "result_updated").is_empty());
    put(&dir.join("key_mask.png"), &mask_png(&scene.mask));
    wait_for(&f, "a result once the mask lands", 60, |ev| !of_kind(ev, "result_updated").is_empty());
    drop(s);
}
