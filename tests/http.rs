//! End-to-end tests of the service's HTTP server (issue 6): every endpoint of the real
//! binary on a temporary folder, the token rules, the body limit, the Prometheus text
//! (checked by a strict parser below), server-sent events, and the two changes a user
//! can make (paint the mask, choose the keyframe) without losing any file of theirs.

mod daemon_common;

use std::collections::BTreeMap;
use std::io::{Read, Write};
use std::process::Command;
use std::time::{Duration, Instant};

use daemon_common::*;

#[test]
fn a_non_local_bind_without_a_token_is_refused_with_64() {
    let f = folders("");
    let out = Command::new(bin())
        .args(["run", "--config"])
        .arg(&f.config)
        .args(["--http", "0.0.0.0:0"])
        .env_remove("CLEARVIEW_HTTP_TOKEN")
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(64));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("requires a token"), "the reason is given: {err}");
    let out = Command::new(bin())
        .args(["run", "--config"])
        .arg(&f.config)
        .args(["--http", "not-an-address"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(64));
    assert!(String::from_utf8_lossy(&out.stderr).contains("http.listen"));
    assert!(!f.inbox.exists(), "nothing started");
}

#[test]
fn beyond_the_loopback_every_read_needs_the_token_too() {
    let f = folders("");
    let token = "a-configured-token-0123456789";
    let s = Service::start_http(&f, "0.0.0.0:0", &[("CLEARVIEW_HTTP_TOKEN", token)]);
    assert!(s.token.is_empty(), "a configured token is not printed: {}", s.url);
    assert_eq!(get(&format!("{}/healthz", s.base)).status, 200);
    for path in ["/api/sessions", "/metrics", "/"] {
        let url = format!("{}{path}", s.base);
        assert_eq!(get(&url).status, 401, "{path}");
        assert_eq!(request("GET", &url, Some("wrong-token-wrong-token"), None).status, 403, "{path}");
        assert_eq!(request("GET", &url, Some(token), None).status, 200, "{path}");
    }
    assert_eq!(get(&format!("{}/api/sessions?token={token}", s.base)).status, 200, "query token");
    assert_eq!(s.terminate(), 0);
}

/// Reads server-sent events in the background: the `event:` names seen so far.
struct EventStream {
    seen: std::sync::Arc<std::sync::Mutex<String>>,
}

impl EventStream {
    fn open(addr: &str) -> Self {
        let mut stream = std::net::TcpStream::connect(addr).unwrap();
        write!(stream, "GET /api/events HTTP/1.1\r\nHost: {addr}\r\nAccept: text/event-stream\r\n\r\n")
            .unwrap();
        let seen = std::sync::Arc::new(std::sync::Mutex::new(String::new()));
        let sink = seen.clone();
        std::thread::spawn(move || {
            let mut buf = [0u8; 4096];
            while let Ok(n) = stream.read(&mut buf) {
                if n == 0 {
                    break;
                }
                sink.lock().unwrap().push_str(&String::from_utf8_lossy(&buf[..n]));
            }
        });
        Self { seen }
    }

    fn wait_for(&self, needle: &str, secs: u64) -> String {
        let deadline = Instant::now() + Duration::from_secs(secs);
        loop {
            let text = self.seen.lock().unwrap().clone();
            if text.contains(needle) {
                return text;
            }
            assert!(Instant::now() < deadline, "no {needle:?} in the event stream:\n{text}");
            std::thread::sleep(Duration::from_millis(50));
        }
    }
}

#[test]
fn every_endpoint_on_a_live_session() {
    let f = folders("[http]\nlisten = \"127.0.0.1:0\"\nmax_body_bytes = 65536\n");
    let s = Service::start_http(&f, "127.0.0.1:0", &[]);
    assert_eq!(s.token.len(), 32, "a generated token is printed in the URL: {}", s.url);
    let api = format!("{}/api/sessions/facade", s.base);
    let token = s.token.clone();

    let mut scene = Scene::new(5);
    let dir = f.inbox.join("facade");
    let user_mask = mask_png(&scene.mask);
    put(&dir.join("key.mask.png"), &user_mask);
    put(&dir.join("key.png"), &png(&scene.key));
    for i in 1..=2 {
        put(&dir.join(format!("v{i}.png")), &png(&scene.clear_view(i)));
    }
    put(&dir.join("other.png"), &png(&Scene::new(999).key));
    let session = wait_session(&s, "facade", "two views used and one rejected", 60, |v| {
        let views = v["views"].as_array().map_or(&[][..], |a| a.as_slice());
        result_number(v).is_some()
            && views.iter().filter(|w| w["accepted"] == true).count() == 2
            && views.iter().any(|w| w["file"] == "other.png")
    });

    // The session's JSON.
    assert_eq!(session["id"], "facade");
    assert_eq!(session["keyframe"], "key.png");
    assert_eq!(session["key_size"], serde_json::json!([W, H]));
    assert_eq!(session["mask"], "file:key.mask.png");
    assert_eq!(session["masked_px"].as_u64().unwrap() as usize, scene.mask.hole_count());
    let coverage = session["coverage"].as_f64().unwrap();
    assert!((0.0..=1.0).contains(&coverage), "{coverage}");
    assert!(!session["history"].as_array().unwrap().is_empty());
    let other = session["views"].as_array().unwrap().iter().find(|w| w["file"] == "other.png").unwrap();
    assert_eq!(other["status"], "rejected");
    assert_eq!(other["accepted"], false);
    assert!(other["reason"].as_str().is_some_and(|r| !r.is_empty()), "{other}");
    for w in session["views"].as_array().unwrap() {
        for key in ["file", "status", "accepted", "reason", "inliers", "matches", "coverage", "homography"] {
            assert!(w.get(key).is_some(), "view lacks {key}: {w}");
        }
        assert!(w.get("path").is_none(), "no file system path is shown");
    }

    // The list, health, and what is not there.
    let list = get(&format!("{}/api/sessions", s.base));
    assert_eq!(list.status, 200);
    assert!(list.content_type.starts_with("application/json"));
    let l = list.json();
    assert_eq!(l["sessions"][0]["id"], "facade");
    assert_eq!(l["sessions"][0]["accepted"], 2);
    assert_eq!(l["sessions"][0]["rejected"], 1);
    let health = get(&format!("{}/healthz", s.base));
    assert_eq!((health.status, health.json()["status"].as_str()), (200, Some("ok")));
    assert_eq!(get(&format!("{}/api/sessions/nothing", s.base)).status, 404);
    assert_eq!(get(&format!("{}/api/sessions/..%2Fstate/result", s.base)).status, 404);
    assert_eq!(get(&format!("{api}/views/..%2Fkey.png/thumb")).status, 404);
    assert_eq!(get(&format!("{api}/views/%2Fetc%2Fpasswd/thumb")).status, 404);

    // Images: keyframe, result, mask, provenance map and its legend, thumbnails.
    let image = |path: &str| {
        let r = get(&format!("{api}{path}"));
        assert_eq!(r.status, 200, "{path}: {}", r.text());
        image::load_from_memory(&r.body).unwrap_or_else(|e| panic!("{path}: {e}"))
    };
    let key = image("/keyframe").to_rgb8();
    assert_eq!((key.width() as usize, key.height() as usize), (W, H));
    let result = image("/result").to_rgb8();
    assert_eq!((result.width() as usize, result.height() as usize), (W, H));
    let mask = image("/mask").to_luma8();
    let holes = mask.pixels().filter(|p| p.0[0] > 127).count();
    assert_eq!(holes, scene.mask.hole_count());
    let prov = image("/provenance").to_rgba8();
    for (x, y, p) in prov.enumerate_pixels() {
        let hole = scene.mask.is_hole(x as usize, y as usize);
        assert_eq!(p.0[3] == 255, hole, "provenance opaque exactly on the mask at ({x}, {y})");
    }
    // A later fill (the second view's) may publish between the session's snapshot and this
    // read: the legend must be the one of the result the session lists at the same moment.
    let deadline = Instant::now() + Duration::from_secs(30);
    let legend = loop {
        let legend = get(&format!("{api}/provenance.json")).json();
        let now = get(&api).json();
        if legend["result"] == now["result"]["number"] {
            break legend;
        }
        assert!(
            Instant::now() < deadline,
            "the legend's result never matched the session's: {legend} / {now}"
        );
        std::thread::sleep(Duration::from_millis(100));
    };
    let entries = legend["legend"].as_array().unwrap();
    let total: u64 = entries.iter().map(|e| e["pixels"].as_u64().unwrap()).sum();
    assert_eq!(total as usize, W * H);
    let own = entries.iter().find(|e| e["source"] == "keyframe").unwrap();
    assert_eq!(own["pixels"].as_u64().unwrap() as usize, W * H - scene.mask.hole_count(), "{legend}");
    for e in entries.iter().filter(|e| e["source"] != "keyframe") {
        // Each filled pixel is from a view of the session or from the fallback, or shown as
        // doubtful (a view's pixel the occlusion model is not sure of).
        let src = e["source"].as_str().unwrap();
        assert!(["v1.png", "v2.png", "fallback", "doubtful"].contains(&src), "{legend}");
    }
    let thumb = image("/views/v1.png/thumb");
    assert!(thumb.width() <= 240 && thumb.height() <= 240);

    // Changes need the token: 401 without, 403 with a wrong one.
    let painted = {
        let mut m = clearview::imaging::Mask::new(W, H, 0);
        for y in 40..200 {
            for x in 100..220 {
                m.set(x, y, 255);
            }
        }
        m
    };
    let body = mask_png(&painted);
    let put_mask =
        |t: Option<&str>, b: &[u8]| request("PUT", &format!("{api}/mask"), t, Some(("image/png", b)));
    assert_eq!(put_mask(None, &body).status, 401);
    assert_eq!(put_mask(Some("0123456789abcdef0123456789abcdef"), &body).status, 403);
    let q = request("PUT", &format!("{api}/mask?token={token}x"), None, Some(("image/png", &body)));
    assert_eq!(q.status, 403);
    // Refused contents: too large a body, not an image, the wrong size.
    // Too large a body is refused from its declared length, before it is read (sent raw:
    // the server answers and closes while a client would still be writing the body).
    let oversize = format!(
        "PUT /api/sessions/facade/mask HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer {token}\r\n\
         Content-Type: image/png\r\nContent-Length: 100000\r\n\r\n"
    );
    assert_eq!(raw_status(&s.addr, &oversize), 413);
    assert_eq!(put_mask(Some(&token), b"not a png").status, 400);
    let small = mask_png(&clearview::imaging::Mask::new(W / 2, H, 255));
    let r = put_mask(Some(&token), &small);
    assert_eq!(r.status, 400);
    assert!(r.json()["error"].as_str().unwrap().contains("keyframe"));
    assert_eq!(
        raw_status(&s.addr, "GET /healthz HTTP/1.1\r\nHost: evil.example\r\n\r\n"),
        403,
        "DNS rebinding"
    );
    assert_eq!(std::fs::read(dir.join("key.mask.png")).unwrap(), user_mask, "nothing changed so far");

    // Painting: the user's mask is kept aside, ours applied, a new result announced.
    let events = EventStream::open(&s.addr);
    events.wait_for("event: hello", 10);
    let before = result_number(&session).unwrap();
    let r = put_mask(Some(&token), &body);
    assert_eq!(r.status, 202, "{}", r.text());
    assert_eq!(r.json()["kept"][0], "key.mask.png.user-1");
    assert_eq!(std::fs::read(dir.join("key.mask.png.user-1")).unwrap(), user_mask, "the user's mask is kept");
    let after = wait_session(&s, "facade", "a result from the painted mask", 60, |v| {
        result_number(v).is_some_and(|n| n > before) && v["masked_px"] == 120 * 160
    });
    let text = events.wait_for("event: result", 20);
    assert!(text.contains("\"session\":\"facade\""), "{text}");
    let mask = image("/mask").to_luma8();
    assert!(
        mask.enumerate_pixels().all(|(x, y, p)| (p.0[0] > 127) == painted.is_hole(x as usize, y as usize))
    );
    // Painting again replaces our own mask without another copy.
    let r = put_mask(Some(&token), &body);
    assert_eq!(r.status, 202);
    assert_eq!(r.json()["kept"], serde_json::json!([]));
    assert!(!dir.join("key.mask.png.user-2").exists());

    // The metrics.
    let m = get(&format!("{}/metrics", s.base));
    assert_eq!(m.status, 200);
    assert!(m.content_type.starts_with("text/plain; version=0.0.4"), "{}", m.content_type);
    let samples = parse_prometheus(&m.text());
    let v = |k: &str| *samples.get(k).unwrap_or_else(|| panic!("no {k} in\n{}", m.text()));
    assert!(v("clearview_views_received_total") >= 3.0);
    assert!(v("clearview_views_accepted_total") >= 2.0);
    let rejected: f64 = samples
        .iter()
        .filter(|(k, _)| k.starts_with("clearview_views_rejected_total{"))
        .map(|(_, v)| v)
        .sum();
    assert!(rejected >= 1.0);
    let written = after["result"]["number"].as_u64().unwrap() as f64;
    assert_eq!(v("clearview_results_written_total"), written);
    assert!(v("clearview_update_latency_seconds_count") >= 1.0);
    assert_eq!(v("clearview_masks_painted_total"), 2.0);
    assert!(samples.contains_key("clearview_queue_depth{worker=\"0\"}"));
    assert!(samples.contains_key("clearview_frames_dropped_total{reason=\"buffer_full\"}"));
    let cov = v("clearview_session_mask_coverage{session=\"facade\"}");
    // The same share, computed on each side (they may differ in the last bit).
    let json_cov = after["coverage"].as_f64().unwrap();
    assert!((cov - json_cov).abs() < 1e-9, "metrics {cov}, status {json_cov}");

    // Choosing the keyframe: the old one stays as a view, nothing is overwritten.
    let choose = |t: Option<&str>, file: &str| {
        let b = serde_json::json!({ "file": file }).to_string();
        request("PUT", &format!("{api}/keyframe"), t, Some(("application/json", b.as_bytes())))
    };
    assert_eq!(choose(None, "v2.png").status, 401);
    assert_eq!(choose(Some(&token), "nothing.png").status, 404);
    assert_eq!(choose(Some(&token), "../key.png").status, 404);
    let v2 = std::fs::read(dir.join("v2.png")).unwrap();
    let r = choose(Some(&token), "v2.png");
    assert_eq!(r.status, 202, "{}", r.text());
    assert_eq!(std::fs::read(dir.join("key.png")).unwrap(), v2);
    assert_eq!(std::fs::read(dir.join("former-key-1.png")).unwrap(), png(&scene.key));
    assert!(dir.join("key.mask.png.user-2").is_file(), "the old keyframe's mask is kept aside");
    wait_session(&s, "facade", "the old keyframe as a view", 60, |v| {
        v["views"].as_array().is_some_and(|a| a.iter().any(|w| w["file"] == "former-key-1.png"))
            && v["mask"].is_null()
    });
    assert_eq!(s.terminate(), 0);
}

/// A strict reader of the Prometheus text format 0.0.4: every sample belongs to a family
/// declared by `# TYPE` before it (HELP optional, each at most once), names and labels are
/// well formed, values parse, no series repeats, counters end in `_total`, histogram
/// buckets are cumulative and end with `+Inf` equal to `_count`. Returns series → value.
fn parse_prometheus(text: &str) -> BTreeMap<String, f64> {
    fn is_name(s: &str, colon: bool) -> bool {
        let mut c = s.chars();
        c.next().is_some_and(|f| f.is_ascii_alphabetic() || f == '_' || (colon && f == ':'))
            && c.all(|ch| ch.is_ascii_alphanumeric() || ch == '_' || (colon && ch == ':'))
    }
    assert!(text.ends_with('\n'), "the text ends with a newline");
    let mut types: BTreeMap<String, String> = BTreeMap::new();
    let mut helps = std::collections::BTreeSet::new();
    let mut out = BTreeMap::new();
    let mut buckets: BTreeMap<String, Vec<(f64, f64)>> = BTreeMap::new();
    for (n, line) in text.lines().enumerate() {
        let at = || format!("line {}: {line:?}", n + 1);
        if let Some(rest) = line.strip_prefix("# ") {
            let mut parts = rest.splitn(3, ' ');
            let (kw, name, tail) = (parts.next().unwrap(), parts.next().unwrap_or(""), parts.next());
            assert!(is_name(name, true), "{}", at());
            match kw {
                "TYPE" => {
                    let t = tail.unwrap_or("");
                    assert!(["counter", "gauge", "histogram", "summary", "untyped"].contains(&t), "{}", at());
                    assert!(types.insert(name.to_owned(), t.to_owned()).is_none(), "TYPE twice: {}", at());
                    if t == "counter" {
                        assert!(name.ends_with("_total"), "a counter's name ends in _total: {}", at());
                    }
                }
                "HELP" => assert!(helps.insert(name.to_owned()), "HELP twice: {}", at()),
                _ => panic!("unknown comment keyword: {}", at()),
            }
            continue;
        }
        assert!(!line.is_empty() && !line.starts_with('#'), "{}", at());
        let (series, value) = line.rsplit_once(' ').unwrap_or_else(|| panic!("no value: {}", at()));
        let value: f64 = match value {
            "+Inf" => f64::INFINITY,
            "-Inf" => f64::NEG_INFINITY,
            "NaN" => f64::NAN,
            v => v.parse().unwrap_or_else(|_| panic!("bad value: {}", at())),
        };
        let (name, labels) = match series.split_once('{') {
            Some((name, rest)) => (name, rest.strip_suffix('}').unwrap_or_else(|| panic!("{}", at()))),
            None => (series, ""),
        };
        assert!(is_name(name, true), "{}", at());
        let mut parsed = Vec::new();
        let mut rest = labels;
        while !rest.is_empty() {
            let (lname, after) = rest.split_once("=\"").unwrap_or_else(|| panic!("bad label: {}", at()));
            assert!(is_name(lname, false), "bad label name: {}", at());
            let mut val = String::new();
            let mut chars = after.char_indices();
            let end = loop {
                match chars.next() {
                    Some((_, '\\')) => match chars.next() {
                        Some((_, 'n')) => val.push('\n'),
                        Some((_, c @ ('\\' | '"'))) => val.push(c),
                        _ => panic!("bad escape: {}", at()),
                    },
                    Some((i, '"')) => break i,
                    Some((_, c)) => val.push(c),
                    None => panic!("unterminated label value: {}", at()),
                }
            };
            parsed.push((lname.to_owned(), val));
            rest = &after[end + 1..];
            rest = rest.strip_prefix(',').unwrap_or(rest);
        }
        let family = types
            .keys()
            .find(|f| {
                name == f.as_str()
                    || (types[*f] == "histogram"
                        && ["_bucket", "_sum", "_count"].iter().any(|s| name == format!("{f}{s}")))
            })
            .unwrap_or_else(|| panic!("sample before its TYPE: {}", at()))
            .clone();
        if name.ends_with("_bucket") && types[&family] == "histogram" {
            let le = parsed.iter().find(|(k, _)| k == "le").unwrap_or_else(|| panic!("no le: {}", at()));
            let le: f64 = if le.1 == "+Inf" { f64::INFINITY } else { le.1.parse().unwrap() };
            buckets.entry(family.clone()).or_default().push((le, value));
        }
        assert!(out.insert(series.to_owned(), value).is_none(), "series twice: {}", at());
    }
    for (family, b) in &buckets {
        assert!(b.windows(2).all(|w| w[0].0 < w[1].0 && w[0].1 <= w[1].1), "{family}: not cumulative");
        let last = b.last().unwrap();
        assert!(last.0.is_infinite(), "{family}: no +Inf bucket");
        assert_eq!(Some(&last.1), out.get(&format!("{family}_count")), "{family}: +Inf bucket != count");
        assert!(out.contains_key(&format!("{family}_sum")), "{family}: no sum");
    }
    out
}

#[test]
fn the_prometheus_reader_is_strict() {
    let good = "# HELP a_total A.\n# TYPE a_total counter\na_total{r=\"x\\\"y\"} 3\n\
                # TYPE h histogram\nh_bucket{le=\"1\"} 1\nh_bucket{le=\"+Inf\"} 2\nh_sum 3.5\nh_count 2\n";
    let p = parse_prometheus(good);
    assert_eq!(p["a_total{r=\"x\\\"y\"}"], 3.0);
    for bad in [
        "a 1\n",                                                                                   // no TYPE
        "# TYPE a counter\na 1\n",      // counter without _total
        "# TYPE a gauge\na 1",          // no final newline
        "# TYPE a gauge\na{l=\"x} 1\n", // unterminated label
        "# TYPE a gauge\na 1\na 2\n",   // repeated series
        "# TYPE a gauge\na one\n",      // bad value
        "# TYPE h histogram\nh_bucket{le=\"1\"} 2\nh_bucket{le=\"+Inf\"} 1\nh_sum 1\nh_count 1\n", // not cumulative
        "# TYPE h histogram\nh_bucket{le=\"1\"} 1\nh_sum 1\nh_count 1\n",                          // no +Inf
    ] {
        assert!(std::panic::catch_unwind(|| parse_prometheus(bad)).is_err(), "accepted: {bad:?}");
    }
}
