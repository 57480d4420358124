//! The preview page in a real headless Chromium (issue 6): it lists the session, the user
//! paints a mask on the keyframe with the pointer and saves it, and the new result
//! appears on the page by itself (server-sent events), without a reload. Driven through
//! chromedriver's W3C WebDriver protocol (plain JSON over HTTP on the loopback). Skips,
//! saying why, only when `chromium` or `chromedriver` is absent.

mod daemon_common;

use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use daemon_common::*;
use serde_json::{Value, json};

fn find(names: &[&str]) -> Option<PathBuf> {
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path).flat_map(|d| names.iter().map(move |n| d.join(n))).find(|p| p.is_file())
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// chromedriver and one browser session; both ended when dropped.
struct Browser {
    driver: Child,
    base: String,
    session: String,
}

impl Browser {
    fn start(
        chromium: &PathBuf,
        chromedriver: &PathBuf,
        profile: &std::path::Path,
        size: (u32, u32),
    ) -> Self {
        let port = free_port();
        let driver = Command::new(chromedriver)
            .arg(format!("--port={port}"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let base = format!("http://127.0.0.1:{port}");
        let deadline = Instant::now() + Duration::from_secs(20);
        while !ready(&base) {
            assert!(Instant::now() < deadline, "chromedriver did not start");
            std::thread::sleep(Duration::from_millis(100));
        }
        let caps = json!({ "capabilities": { "alwaysMatch": {
            "browserName": "chrome",
            "goog:chromeOptions": {
                "binary": chromium,
                "args": [
                    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                    "--disable-background-networking", "--disable-component-update", "--disable-sync",
                    "--disable-dev-shm-usage",
                    format!("--user-data-dir={}", profile.display()),
                    format!("--window-size={},{}", size.0, size.1),
                ]
            }
        }}});
        let r = post(&format!("{base}/session"), &caps);
        let session =
            r["value"]["sessionId"].as_str().unwrap_or_else(|| panic!("no session: {r}")).to_owned();
        Self { driver, base, session }
    }

    fn url(&self, path: &str) -> String {
        format!("{}/session/{}{path}", self.base, self.session)
    }

    fn go(&self, url: &str) {
        post(&self.url("/url"), &json!({ "url": url }));
    }

    fn js(&self, script: &str, args: Value) -> Value {
        post(&self.url("/execute/sync"), &json!({ "script": script, "args": args }))["value"].clone()
    }

    /// Waits until `script` returns true.
    fn wait(&self, what: &str, secs: u64, script: &str) {
        let deadline = Instant::now() + Duration::from_secs(secs);
        while self.js(script, json!([])) != json!(true) {
            let state = self.js("return document.body.innerText", json!([]));
            assert!(Instant::now() < deadline, "timed out waiting for {what}; page text:\n{state}");
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    fn element(&self, css: &str) -> String {
        let r = post(&self.url("/element"), &json!({ "using": "css selector", "value": css }));
        let v = &r["value"];
        v.as_object()
            .and_then(|o| o.values().next())
            .and_then(Value::as_str)
            .unwrap_or_else(|| panic!("no element {css}: {r}"))
            .to_owned()
    }

    fn click(&self, css: &str) {
        let id = self.element(css);
        post(&self.url(&format!("/element/{id}/click")), &json!({}));
    }

    /// Drags the mouse through `points` (viewport pixels) with the button down.
    fn drag(&self, points: &[(f64, f64)]) {
        self.drag_with("mouse", points);
    }

    /// Drags a pointer of `kind` ("mouse", "touch") through `points` (viewport pixels).
    fn drag_with(&self, kind: &str, points: &[(f64, f64)]) {
        let mut actions = vec![
            json!({ "type": "pointerMove", "x": points[0].0 as i64, "y": points[0].1 as i64, "duration": 0 }),
        ];
        actions.push(json!({ "type": "pointerDown", "button": 0 }));
        for p in &points[1..] {
            actions.push(json!({ "type": "pointerMove", "x": p.0 as i64, "y": p.1 as i64, "duration": 30 }));
        }
        actions.push(json!({ "type": "pointerUp", "button": 0 }));
        let body = json!({ "actions": [{
            "type": "pointer", "id": kind, "parameters": { "pointerType": kind }, "actions": actions
        }]});
        post(&self.url("/actions"), &body);
    }

    fn screenshot(&self, path: &str) {
        let r = request("GET", &self.url("/screenshot"), None, None).json();
        let png = base64(r["value"].as_str().unwrap());
        assert_eq!(&png[1..4], b"PNG");
        std::fs::write(path, png).unwrap();
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = ureq::delete(&format!("{}/session/{}", self.base, self.session)).call();
        let _ = self.driver.kill();
        let _ = self.driver.wait();
    }
}

fn ready(base: &str) -> bool {
    ureq::get(&format!("{base}/status"))
        .call()
        .ok()
        .and_then(|r| r.into_json::<Value>().ok())
        .is_some_and(|v| v["value"]["ready"] == true)
}

fn post(url: &str, body: &Value) -> Value {
    let r = request("POST", url, None, Some(("application/json", body.to_string().as_bytes())));
    assert_eq!(r.status, 200, "{url}: {}", r.text());
    r.json()
}

fn base64(s: &str) -> Vec<u8> {
    let val = |c: u8| match c {
        b'A'..=b'Z' => c - b'A',
        b'a'..=b'z' => c - b'a' + 26,
        b'0'..=b'9' => c - b'0' + 52,
        b'+' => 62,
        b'/' => 63,
        _ => panic!("not base64: {c}"),
    };
    let bytes: Vec<u8> = s.bytes().filter(|&c| c != b'=' && !c.is_ascii_whitespace()).map(val).collect();
    let mut out = Vec::with_capacity(bytes.len() * 3 / 4);
    for chunk in bytes.chunks(4) {
        let n = chunk.iter().enumerate().fold(0u32, |acc, (i, &v)| acc | (u32::from(v) << (18 - 6 * i)));
        out.extend_from_slice(&n.to_be_bytes()[1..chunk.len()]);
    }
    out
}

#[test]
fn paint_a_mask_on_the_page_and_see_the_new_result_arrive() {
    let (Some(chromium), Some(chromedriver)) =
        (find(&["chromium", "chromium-browser", "google-chrome"]), find(&["chromedriver"]))
    else {
        eprintln!(
            "skipping: chromium and chromedriver are needed (apt-get install chromium chromium-driver)"
        );
        return;
    };
    let f = folders("");
    let s = Service::start_http(&f, "127.0.0.1:0", &[]);
    let mut scene = Scene::new(8);
    let dir = f.inbox.join("facade");
    put(&dir.join("key.png"), &png(&scene.key));
    for i in 1..=3 {
        put(&dir.join(format!("v{i}.png")), &png(&scene.clear_view(i)));
    }
    wait_session(&s, "facade", "three accepted views", 60, |v| {
        v["views"].as_array().is_some_and(|a| a.iter().filter(|w| w["accepted"] == true).count() == 3)
    });

    let profile = tempfile::tempdir().unwrap();
    let b = Browser::start(&chromium, &chromedriver, profile.path(), (1280, 1200));
    b.go(&s.url);
    b.wait("the session and its keyframe", 30, "const k = document.getElementById('before'); \
        return document.querySelectorAll('#sessions button').length === 1 && k.complete && k.naturalWidth > 0 \
        && document.querySelectorAll('.view').length === 3");
    assert_eq!(b.js("return location.search", json!([])), "", "the token leaves the address bar");
    assert_eq!(
        b.js("return document.getElementById('viewer').dataset.result", json!([])),
        "",
        "no result yet"
    );
    b.js("window.notReloaded = true", json!([]));

    // Paint the tree's box with the pointer, brush at its widest.
    b.click("#paint-toggle");
    b.wait("the canvas", 10, "const c = document.getElementById('paint'); return c.width > 0 && !c.hidden");
    b.js("const r = document.getElementById('brush'); r.value = r.max;", json!([]));
    let rect = b.js(
        "const r = document.getElementById('paint').getBoundingClientRect(); return [r.left, r.top, r.width, r.height]",
        json!([]),
    );
    let rect: Vec<f64> = rect.as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
    let to_view = |x: f64, y: f64| (rect[0] + x * rect[2] / W as f64, rect[1] + y * rect[3] / H as f64);
    for row in 0..6 {
        let y = 56.0 + 37.5 * f64::from(row);
        b.drag(&[to_view(131.0, y), to_view(200.0, y), to_view(269.0, y)]);
    }
    let painted = b.js(
        "const c = document.getElementById('paint'); const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data; \
         let n = 0; for (let i = 3; i < d.length; i += 4) n += d[i] > 127; return n",
        json!([]),
    );
    assert!(painted.as_u64().unwrap() > 10_000, "painted {painted} px");
    b.click("#save");

    // The new result shows up by itself.
    b.wait("the result on the page", 90, "return document.getElementById('viewer').dataset.result !== ''");
    assert_eq!(b.js("return window.notReloaded === true", json!([])), true, "no reload");
    let shown = "return ['paint', 'paint-controls', 'prov', 'legend', 'surf', 'surf-legend'].filter((id) => \
        getComputedStyle(document.getElementById(id)).display !== 'none')";
    assert_eq!(b.js(shown, json!([])), json!([]), "painting tools and overlay are put away");
    b.wait(
        "the result image",
        20,
        "const a = document.getElementById('after'); return !a.hidden && a.complete && a.naturalWidth > 0",
    );
    let stored = image::open(dir.join("key.mask.png")).unwrap().to_luma8();
    let holes = stored.pixels().filter(|p| p.0[0] > 127).count();
    assert!(holes > 10_000 && holes < W * H / 2, "{holes} px in the stored mask");
    assert!(stored.get_pixel(160, 130).0[0] > 127, "the tree's centre is in the mask");

    // Provenance overlay on, slider a little right of the middle; then the screenshots.
    b.click("#show-prov");
    b.wait(
        "the provenance legend",
        10,
        "return !document.getElementById('legend').hidden && \
        document.getElementById('prov').complete",
    );
    b.js(
        "const s = document.getElementById('slider'); s.value = 60; s.dispatchEvent(new Event('input'));",
        json!([]),
    );
    // The surfaces the fill copied through, over it: here a flat wall, all of it the wall's.
    b.click("#show-surf");
    b.wait(
        "the surface overlay",
        10,
        "const s = document.getElementById('surf'); return !document.getElementById('surf-legend').hidden && \
        s.complete && s.naturalWidth > 0",
    );
    let surf_legend = b.js("return document.getElementById('surf-legend').innerText", json!([]));
    assert!(surf_legend.as_str().is_some_and(|t| t.contains("the wall (")), "{surf_legend}");
    let size = b.js(
        "const s = document.getElementById('surf'), k = document.getElementById('before'); \
         return [s.naturalWidth === k.naturalWidth, s.naturalHeight === k.naturalHeight]",
        json!([]),
    );
    assert_eq!(size, json!([true, true]), "the overlay is the keyframe's size");
    // Left of the divider the keyframe, right of it the result.
    let clip = b.js("return document.getElementById('after').style.clipPath", json!([]));
    assert_eq!(clip, "inset(0px 0px 0px 60%)", "the result shows right of the divider");
    b.js("window.scrollTo(0, 0)", json!([]));
    std::thread::sleep(Duration::from_millis(300));
    b.screenshot("/tmp/clearview-preview.png");
    let text = b.js("return document.body.innerText", json!([])).as_str().unwrap_or("").to_owned();
    assert!(text.contains("result #1"), "{text}");
    drop(b);

    // A phone-sized window: the same page, one column.
    let profile = tempfile::tempdir().unwrap();
    let b = Browser::start(&chromium, &chromedriver, profile.path(), (390, 844));
    b.go(&s.url);
    b.wait(
        "the result on a phone",
        30,
        "const a = document.getElementById('after'); \
        return a.complete && a.naturalWidth > 0 && !a.hidden",
    );
    let overflow = b.js("return document.documentElement.scrollWidth <= window.innerWidth + 1", json!([]));
    assert_eq!(overflow, true, "nothing wider than a phone's screen");
    b.screenshot("/tmp/clearview-preview-phone.png");

    // 1:1 zoom: the keyframe at its own size in a viewer that keeps its height, panned by a
    // mouse drag and a touch drag, kept covering the viewer; off again, fitted again.
    let geometry = "const v = document.getElementById('viewer').getBoundingClientRect(); \
        const k = document.getElementById('before').getBoundingClientRect(); \
        const a = document.getElementById('after').getBoundingClientRect(); \
        return [k.width, k.left - v.left, k.top - v.top, v.width, v.height, a.left - v.left]";
    let nums = |v: Value| -> Vec<f64> { v.as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect() };
    // A viewer narrower than the keyframe whatever the window's scale: 1:1 is then a zoom in.
    b.js(
        "const v = document.getElementById('viewer'); v.style.maxWidth = '240px'; v.scrollIntoView({ block: 'center' })",
        json!([]),
    );
    std::thread::sleep(Duration::from_millis(100));
    let fitted = nums(b.js(geometry, json!([])));
    assert!(fitted[0] < W as f64, "the phone shows the keyframe smaller than 1:1: {fitted:?}");
    b.click("#zoom");
    let z = nums(b.js(geometry, json!([])));
    assert!((z[0] - W as f64).abs() < 0.5, "1:1: {z:?}");
    assert!((z[4] - fitted[4]).abs() < 0.5, "the viewer keeps its height: {z:?} {fitted:?}");
    assert!((z[1] - z[5]).abs() < 0.5, "the result moves with the keyframe: {z:?}");
    let vr = nums(b.js(
        "const r = document.getElementById('viewer').getBoundingClientRect(); return [r.left, r.top]",
        json!([]),
    ));
    let (cx, cy) = (vr[0] + z[3] / 2.0, vr[1] + z[4] / 2.0);
    // Far to the left and up: the image's right and bottom edges stop at the viewer's.
    b.drag(&[(cx, cy), (cx - 50.0, cy - 50.0), (cx - 100.0, cy - 100.0)]);
    let m = nums(b.js(geometry, json!([])));
    assert!((m[1] - (z[3] - W as f64)).abs() < 1.0, "panned to the right edge: {m:?}");
    assert!((m[2] - (z[4] - H as f64)).abs() < 1.0, "panned to the bottom edge: {m:?}");
    // A finger back by 12 px either way.
    b.drag_with("touch", &[(cx, cy), (cx + 6.0, cy + 6.0), (cx + 12.0, cy + 12.0)]);
    let t = nums(b.js(geometry, json!([])));
    assert!((t[1] - m[1] - 12.0).abs() < 1.5 && (t[2] - m[2] - 12.0).abs() < 1.5, "touch pan: {m:?} → {t:?}");
    b.screenshot("/tmp/clearview-preview-phone-1to1.png");
    b.click("#zoom");
    let back = nums(b.js(geometry, json!([])));
    assert!((back[0] - fitted[0]).abs() < 0.5 && back[1].abs() < 0.5, "fitted again: {back:?}");
    drop(b);
    assert_eq!(s.terminate(), 0);
}
