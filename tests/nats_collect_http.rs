//! `clearview collect --http` (issue 17): the preview page served from the collected
//! folder, with the release binary, one `nats-server`, `ingest`, one `worker` and
//! `collect --http`. The page, the session list, the session, the result, mask and
//! provenance images, the keyframe and a view's thumbnail are served and equal what was
//! collected (and the inputs); changes are refused with a reason; the token and host rules
//! hold; a restarted collector shows the session again; and the session reads as
//! `clearview run --http` shows it for the same files.
//!
//! Needs `nats-server` (Debian's package; `.ci/setup` installs it).

mod daemon_common;

use std::path::Path;
use std::time::{Duration, Instant};

use daemon_common::nats::{Proc, events, single_server, start_ingest, start_worker, write_config};
use daemon_common::{Reply, Scene, Service, bin, folders, get, mask_png, png, put, raw_status, request};
use serde_json::Value;

const SESSION: &str = "site0";
const VIEWS: u64 = 2;

/// The URL `collect` printed: the base (`http://127.0.0.1:PORT`) and the token.
fn page_url(p: &Proc, root: &Path) -> (String, String) {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let out = std::fs::read_to_string(root.join(format!("{}.stdout", p.name))).unwrap_or_default();
        if let Some(url) = out.lines().find_map(|l| l.strip_prefix("clearview: preview page at ")) {
            let rest = url.trim().strip_prefix("http://").unwrap();
            let (addr, query) = rest.split_once('/').unwrap();
            return (format!("http://{addr}"), query.strip_prefix("?token=").unwrap_or("").to_owned());
        }
        assert!(Instant::now() < deadline, "collect printed no URL:\n{}", p.log());
        std::thread::sleep(Duration::from_millis(50));
    }
}

fn collect(root: &Path, c: &str, urls: &str, out: &Path) -> Proc {
    let args = ["collect", "-c", c, "--nats", urls, "--out", out.to_str().unwrap(), "--http", "127.0.0.1:0"];
    Proc::start("collect", Path::new(bin()), &args, root)
}

fn ok(r: Reply, what: &str) -> Reply {
    assert_eq!(r.status, 200, "{what}: {}", r.text());
    r
}

#[test]
fn collect_serves_the_preview_page_of_what_it_collected() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let (inbox, out) = (root.join("inbox"), root.join("out"));
    std::fs::create_dir_all(&inbox).unwrap();
    let (_nats, urls, _) = single_server(root);
    let c = &write_config(root, "[output]\nhistory = 10\n[nats]\nreplicas = 1\n");
    let mut collector = collect(root, c, &urls, &out);
    let worker = start_worker(c, &urls, "w1", root);
    let ingest_state = root.join("ingest");
    let ingest = start_ingest(c, &urls, &inbox, &ingest_state, root);
    let deadline = Instant::now() + Duration::from_secs(30);
    for p in [&collector, &worker, &ingest] {
        while !p.log().contains(" started") {
            assert!(Instant::now() < deadline, "{} did not start:\n{}", p.name, p.log());
            std::thread::sleep(Duration::from_millis(50));
        }
    }
    let (base, token) = page_url(&collector, root);
    assert!(!token.is_empty(), "a generated token is printed with the URL");

    // One session: its mask, keyframe and views, each written under a hidden name first.
    let mut scene = Scene::new(17);
    let dir = inbox.join(SESSION);
    put(&dir.join("key.mask.png"), &mask_png(&scene.mask));
    put(&dir.join("key.png"), &png(&scene.key));
    let views: Vec<String> = (0..VIEWS).map(|i| format!("view{i}.png")).collect();
    for (i, v) in views.iter().enumerate() {
        put(&dir.join(v), &png(&scene.view(i as u64, 60.0 + 120.0 * i as f32, 40.0)));
    }

    // Until the page shows the session with both views and the result the folder has.
    let session_url = format!("{base}/api/sessions/{SESSION}");
    let on_disk = || -> Option<u64> {
        let b = std::fs::read(out.join(SESSION).join("result.json")).ok()?;
        serde_json::from_slice::<Value>(&b).ok()?["number"].as_u64()
    };
    let deadline = Instant::now() + Duration::from_secs(40);
    let shown = loop {
        let r = get(&session_url);
        if r.status == 200 {
            let s = r.json();
            let named =
                events(&out).iter().filter(|e| e["session"] == SESSION && e["file"].is_string()).count();
            if s["views"].as_array().map_or(0, Vec::len) == views.len()
                && s["result"]["number"].as_u64().is_some()
                && s["result"]["number"].as_u64() == on_disk()
                && named > 0
            {
                break s;
            }
        }
        collector.check_alive();
        assert!(
            Instant::now() < deadline,
            "the page never showed the session's result: {} {}\nworker:\n{}\ncollect:\n{}",
            r.status,
            r.text(),
            worker.log(),
            collector.log()
        );
        std::thread::sleep(Duration::from_millis(100));
    };
    let number = shown["result"]["number"].as_u64().unwrap();
    let res = out.join(SESSION);

    // The page and its assets, as `run` serves them.
    let page = ok(get(&format!("{base}/")), "page");
    assert!(page.content_type.starts_with("text/html") && page.text().contains("/app.js"), "the page");
    ok(get(&format!("{base}/app.js")), "script");
    ok(get(&format!("{base}/app.css")), "style");
    let list = ok(get(&format!("{base}/api/sessions")), "sessions").json();
    let listed = &list["sessions"][0];
    assert_eq!((listed["id"].as_str(), listed["result"].as_u64()), (Some(SESSION), Some(number)), "{list}");
    assert_eq!(listed["views"].as_u64(), Some(VIEWS), "{list}");
    assert_eq!(list["read_only"], true, "the page hides its change buttons: {list}");
    // The images are the collected files, byte for byte; the keyframe is the user's file.
    for (path, file) in [("result", "result.png"), ("mask", "mask.png"), ("provenance", "provenance.png")] {
        let r = ok(get(&format!("{session_url}/{path}")), path);
        assert_eq!(r.body, std::fs::read(res.join(file)).unwrap(), "{path} is the collected {file}");
        assert_eq!(r.content_type, "image/png", "{path}");
    }
    let key = ok(get(&format!("{session_url}/keyframe")), "keyframe");
    assert_eq!(key.body, std::fs::read(dir.join("key.png")).unwrap(), "the keyframe is the ingested file");
    assert_eq!(key.content_type, "image/png");
    for v in &views {
        let t = ok(get(&format!("{session_url}/views/{v}/thumb")), "thumbnail");
        assert_eq!(t.content_type, "image/jpeg");
        assert!(image::load_from_memory(&t.body).is_ok(), "{v}: a thumbnail");
    }
    assert_eq!(get(&format!("{session_url}/views/nothere.png/thumb")).status, 404);
    let legend = ok(get(&format!("{session_url}/provenance.json")), "legend").json();
    assert_eq!(legend["result"].as_u64(), Some(number));
    assert!(legend["legend"].as_array().is_some_and(|l| !l.is_empty()), "{legend}");
    let report: Value = serde_json::from_slice(&std::fs::read(res.join("result.json")).unwrap()).unwrap();
    assert_eq!(shown["result"], report, "the session's result is the collected result.json");
    let health = ok(get(&format!("{base}/healthz")), "healthz").json();
    assert_eq!(health["sessions"].as_u64(), Some(1));
    ok(get(&format!("{base}/metrics")), "metrics");

    // Changes: the token first, then a clear refusal (there is no inbox here).
    let mask_url = format!("{session_url}/mask");
    let body = mask_png(&scene.mask);
    assert_eq!(request("PUT", &mask_url, None, Some(("image/png", &body))).status, 401);
    assert_eq!(request("PUT", &mask_url, Some("wrong-token"), Some(("image/png", &body))).status, 403);
    for (url, ct, body) in [
        (mask_url.clone(), "image/png", body.clone()),
        (format!("{session_url}/keyframe"), "application/json", br#"{"file":"view0.png"}"#.to_vec()),
    ] {
        let r = request("PUT", &url, Some(&token), Some((ct, &body)));
        assert_eq!(r.status, 405, "{url}: {}", r.text());
        let why = r.json()["error"].as_str().unwrap_or_default().to_owned();
        assert!(why.contains("clearview collect") && why.contains("ingest"), "a reason is given: {why}");
    }
    assert!(!dir.join("key.mask.png.user-1").exists(), "nothing of the user's was touched");
    let addr = base.strip_prefix("http://").unwrap();
    assert_eq!(raw_status(addr, "GET /api/sessions HTTP/1.1\r\nHost: evil.example\r\n\r\n"), 403);

    // A restarted collector shows the session at once (kept snapshots, kept copies).
    for p in [ingest, worker] {
        assert_eq!(p.terminate(), Some(0));
    }
    assert_eq!(collector.terminate(), Some(0));
    let collector = collect(root, c, &urls, &out);
    let (base2, _) = page_url(&collector, root);
    let again = ok(get(&format!("{base2}/api/sessions/{SESSION}")), "session after a restart").json();
    assert_eq!(again["result"]["number"].as_u64(), Some(number));
    let key = ok(get(&format!("{base2}/api/sessions/{SESSION}/keyframe")), "keyframe after a restart");
    assert_eq!(key.body, std::fs::read(dir.join("key.png")).unwrap());

    // An event the stream delivers again (here published twice more, without a message
    // id, as a worker may after a leader change) is in events.jsonl once, also after the
    // restart; a new event after them is written.
    let log = out.join("events.jsonl");
    let text = std::fs::read_to_string(&log).unwrap();
    let again =
        text.lines().find(|l| l.contains("\"view_accepted\"")).expect("a view_accepted event").to_owned();
    let fresh = again.replacen("\"view_accepted\"", "\"view_accepted_probe\"", 1);
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    rt.block_on(async {
        let js = async_nats::jetstream::new(async_nats::connect(urls.as_str()).await.unwrap());
        for line in [&again, &again, &fresh] {
            js.publish(format!("clearview.events.{SESSION}"), line.clone().into())
                .await
                .unwrap()
                .await
                .unwrap();
        }
    });
    let deadline = Instant::now() + Duration::from_secs(20);
    while !std::fs::read_to_string(&log).unwrap().contains("view_accepted_probe") {
        assert!(Instant::now() < deadline, "the new event was not collected:\n{}", collector.log());
        std::thread::sleep(Duration::from_millis(100));
    }
    let text = std::fs::read_to_string(&log).unwrap();
    assert_eq!(text.lines().filter(|l| *l == again).count(), 1, "an event delivered again is written once");
    assert_eq!(collector.terminate(), Some(0));

    // `clearview run --http` on the same files shows the same session.
    let f = folders("");
    let local = f.inbox.join(SESSION);
    for name in ["key.mask.png", "key.png"].into_iter().map(str::to_owned).chain(views.clone()) {
        put(&local.join(&name), &std::fs::read(dir.join(&name)).unwrap());
    }
    let run = Service::start_http(&f, "127.0.0.1:0", &[]);
    daemon_common::wait_session(&run, SESSION, "run's result with both views", 30, |s| {
        s["views"].as_array().map_or(0, Vec::len) == views.len() && s["result"]["number"].is_u64()
    });
    // The step that admitted the views has filled by now (a fill follows in the same step).
    std::thread::sleep(Duration::from_secs(1));
    let theirs = ok(get(&format!("{}/api/sessions/{SESSION}", run.base)), "run's session").json();
    let run_list = ok(get(&format!("{}/api/sessions", run.base)), "run's sessions").json();
    assert_eq!(run_list["read_only"], false, "run's page paints masks");
    for field in ["id", "keyframe", "key_size", "mask", "masked_px"] {
        assert_eq!(shown[field], theirs[field], "{field}: collect {} / run {}", shown[field], theirs[field]);
    }
    let summary = |s: &Value| -> Vec<(String, bool, u64)> {
        let mut v: Vec<_> = s["views"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| {
                (
                    v["file"].as_str().unwrap().to_owned(),
                    v["accepted"] == true,
                    v["inliers"].as_u64().unwrap(),
                )
            })
            .collect();
        v.sort();
        v
    };
    assert_eq!(summary(&shown), summary(&theirs), "the views, accepted, with the same alignments");
    let theirs_png = ok(get(&format!("{}/api/sessions/{SESSION}/result", run.base)), "run's result");
    let decoded = |b: &[u8]| image::load_from_memory(b).unwrap().to_rgb8();
    let (a, b) = (decoded(&std::fs::read(res.join("result.png")).unwrap()), decoded(&theirs_png.body));
    let worst = a.as_raw().iter().zip(b.as_raw()).map(|(x, y)| x.abs_diff(*y)).max().unwrap_or(0);
    println!(
        "collect: result #{number}, run: result #{}; bytes equal: {}, largest pixel difference {worst}",
        theirs["result"]["number"],
        theirs_png.body == std::fs::read(res.join("result.png")).unwrap()
    );
    assert_eq!(run.terminate(), 0);
}
