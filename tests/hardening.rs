//! Hardening II (issue 16) against the real service (`clearview run`): an idle service
//! costs nothing, the folders it is given cannot overlap however they are spelled, the
//! event log and the state folder come back after being deleted, SIGTERM is honoured
//! within the grace period with nothing written after `service_stopped`, a view's file
//! replaced (in place, by rename, after a `chmod`) is read again, special files are
//! reported and never opened, a keyframe chosen on the page stays chosen. The HTTP floods
//! are `examples/http_flood.rs` (a bench, not a test).

mod daemon_common;

use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use daemon_common::*;
use serde_json::Value;

/// CPU time (user + system) the process has used so far, from `/proc/PID/stat`.
fn cpu_time(pid: u32) -> Duration {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap();
    // The fields after the command name (which may hold spaces) in parentheses.
    let rest = &stat[stat.rfind(')').unwrap() + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks: u64 = f[11].parse::<u64>().unwrap() + f[12].parse::<u64>().unwrap();
    // SAFETY: sysconf has no preconditions.
    let hz = unsafe { libc::sysconf(libc::_SC_CLK_TCK) }.max(1) as u64;
    Duration::from_micros(ticks * 1_000_000 / hz)
}

/// The share of one core the service uses over `window`, once it has settled.
fn idle_share(s: &Service, window: Duration) -> f64 {
    let before = cpu_time(s.child.id());
    std::thread::sleep(window);
    (cpu_time(s.child.id()) - before).as_secs_f64() / window.as_secs_f64()
}

fn session_with_a_result(f: &Folders) {
    let mut scene = Scene::new(16);
    let dir = f.inbox.join("s1");
    put_key_and_mask(&dir, &scene);
    put(&dir.join("v1.png"), &png(&scene.clear_view(1)));
    wait_for(f, "a result", 90, |ev| !of_kind(ev, "result_updated").is_empty());
}

/// `watch` is added to the `[watch]` table.
fn idle_costs_nothing(watch: &str) {
    let f = folders("");
    let config = std::fs::read_to_string(&f.config).unwrap();
    std::fs::write(
        &f.config,
        config.replace("quiet_period_ms = 300\n", &format!("quiet_period_ms = 300\n{watch}")),
    )
    .unwrap();
    let s = Service::start(&f);
    session_with_a_result(&f);
    // Settled: views read, nothing arriving. A service that fed on its own reads of the
    // folder spun one core at 94-100 % here.
    std::thread::sleep(Duration::from_secs(1));
    let share = idle_share(&s, Duration::from_secs(3));
    assert!(share < 0.05, "idle service used {:.1} % of a core\nlog:\n{}", share * 100.0, s.log());
    let n = of_kind(&events(&f), "result_updated").len();
    assert_eq!(n, 1, "results without new input");
}

#[test]
fn an_idle_service_costs_nothing_with_notifications() {
    idle_costs_nothing("mode = \"notify\"\n");
}

#[test]
fn an_idle_service_costs_nothing_when_polling() {
    idle_costs_nothing("mode = \"poll\"\npoll_interval_ms = 500\n");
}

/// `clearview run` and `check-config` with `watch`, `out` and `state` spelled as given,
/// run in `cwd`: both must refuse with 64 and name both folders' keys.
fn refused(cwd: &Path, watch: &str, out: &str, state: &str, keys: [&str; 2]) {
    let config = cwd.join("overlap.toml");
    std::fs::write(
        &config,
        format!("[watch]\ndir = {watch:?}\n[output]\ndir = {out:?}\n[state]\ndir = {state:?}\n"),
    )
    .unwrap();
    let check = Command::new(bin()).arg("check-config").arg(&config).current_dir(cwd).output().unwrap();
    let err = String::from_utf8_lossy(&check.stderr);
    assert_eq!(check.status.code(), Some(64), "check-config accepted {watch} {out} {state}: {err}");
    assert!(keys.iter().all(|k| err.contains(k)), "{err}");
    let run = Command::new(bin())
        .args(["run", "--watch", watch, "--out", out, "--state", state])
        .current_dir(cwd)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&run.stderr);
    assert_eq!(run.status.code(), Some(64), "run started with {watch} {out} {state}: {err}");
    assert!(keys.iter().all(|k| err.contains(k)), "{err}");
}

#[test]
fn overlapping_folders_are_refused_however_they_are_spelled() {
    let tmp = tempfile::tempdir().unwrap();
    let cwd = tmp.path();
    std::fs::create_dir_all(cwd.join("inbox/s1")).unwrap();
    std::fs::create_dir_all(cwd.join("x")).unwrap();
    let mask = cwd.join("inbox/s1/mask.png");
    std::fs::write(&mask, b"the user's own file").unwrap();
    std::os::unix::fs::symlink(cwd.join("inbox"), cwd.join("link")).unwrap();
    let abs = cwd.canonicalize().unwrap();
    let abs_inbox = abs.join("inbox").to_string_lossy().into_owned();
    for (w, o, s, keys) in [
        ("inbox", "./inbox", "st", ["watch.dir", "output.dir"]),
        ("inbox", "x/../inbox", "st", ["watch.dir", "output.dir"]),
        ("inbox", abs_inbox.as_str(), "st", ["watch.dir", "output.dir"]),
        ("inbox", "link", "st", ["watch.dir", "output.dir"]),
        ("inbox", "inbox/s1", "st", ["watch.dir", "output.dir"]),
        ("inbox", "out", "inbox/.state", ["watch.dir", "state.dir"]),
        ("inbox", "out", "./out", ["output.dir", "state.dir"]),
        ("inbox/s1", "inbox", "st", ["watch.dir", "output.dir"]),
        ("inbox", "out", "out/state", ["output.dir", "state.dir"]),
    ] {
        refused(cwd, w, o, s, keys);
    }
    // Refused before anything was touched: the user's file is as it was, and no folder
    // was made inside the watched one.
    assert_eq!(std::fs::read(&mask).unwrap(), b"the user's own file");
    let inside: Vec<_> =
        std::fs::read_dir(cwd.join("inbox")).unwrap().flatten().map(|e| e.file_name()).collect();
    assert_eq!(inside, ["s1"]);
}

#[test]
fn events_and_state_survive_their_folders_being_deleted() {
    let f = folders("");
    let s = Service::start(&f);
    let mut scene = Scene::new(17);
    let dir = f.inbox.join("s1");
    put_key_and_mask(&dir, &scene);
    put(&dir.join("v1.png"), &png(&scene.view(1, 120.0, 60.0)));
    wait_for(&f, "a first result", 90, |ev| !of_kind(ev, "result_updated").is_empty());
    // The service may be writing into them as they go (a result, its history): removal is
    // retried, as a user's `rm -rf` racing a writer would be.
    for dir in [&f.outbox, &f.state] {
        let deadline = Instant::now() + Duration::from_secs(10);
        while let Err(e) = std::fs::remove_dir_all(dir) {
            assert!(Instant::now() < deadline, "{}: {e}", dir.display());
            std::thread::sleep(Duration::from_millis(50));
        }
    }
    // A clear view: a better result, its event in a new log, its state in a new folder.
    put(&dir.join("v2.png"), &png(&scene.clear_view(2)));
    let ev = wait_for(&f, "the view's events and its result in a new event log", 90, |ev| {
        about(ev, "v2.png").iter().any(|e| e["event"] == "view_accepted")
            && !of_kind(ev, "result_updated").is_empty()
    });
    assert!(f.outbox.join("s1").is_dir(), "the session's results come back");
    let state = f.state.join("sessions/s1.json");
    let deadline = Instant::now() + Duration::from_secs(30);
    while !state.exists() {
        assert!(Instant::now() < deadline, "the state folder was not made again\nlog:\n{}", s.log());
        std::thread::sleep(Duration::from_millis(100));
    }
    assert!(s.log().contains("event log was deleted"), "{}", s.log());
    drop(ev);
    drop(s);
    // A restart realigns nothing: the state saved after the deletion knows both views.
    let s = Service::start(&f);
    let ev = wait_for(&f, "both views again after the restart", 60, |ev| {
        let restart = ev.iter().rposition(|e| e["event"] == "service_started");
        restart.is_some_and(|r| {
            ev[r..].iter().filter(|e| e["event"] == "view_accepted" || e["event"] == "view_rejected").count()
                >= 2
        })
    });
    let restart = ev.iter().rposition(|e| e["event"] == "service_started").unwrap();
    for e in ev[restart..].iter().filter(|e| e["event"] == "view_accepted" || e["event"] == "view_rejected") {
        assert_eq!(e["from_state"], true, "realigned after the restart: {e}\nlog:\n{}", s.log());
    }
}

/// A keyframe whose mask leaves a large hole that no view sees: the single-image fill
/// takes over a second, long enough to be interrupted.
fn slow_session(f: &Folders) {
    let (w, h) = (2400, 1800);
    let scene = clearview::synth::facade(w, h, 5);
    let mut mask = clearview::imaging::Mask::new(w, h, 0);
    for y in 300..1500 {
        for x in 450..1950 {
            mask.set(x, y, 255);
        }
    }
    let dir = f.inbox.join("big");
    put(&dir.join("key.mask.png"), &mask_png(&mask));
    put(&dir.join("key.png"), &png(&scene));
}

#[test]
fn sigterm_mid_fill_stops_within_the_grace_period_and_writes_nothing_after() {
    let f = folders("");
    let config = std::fs::read_to_string(&f.config)
        .unwrap()
        .replace("grace_period_ms = 15000", "grace_period_ms = 1000");
    std::fs::write(&f.config, config).unwrap();
    let s = Service::start(&f);
    slow_session(&f);
    wait_for(&f, "the mask", 60, |ev| !of_kind(ev, "mask_set").is_empty());
    // Once the fill has begun (on a loaded machine the work before it can take longer than
    // a fixed wait), well inside it: the fallback takes about 1.3 s at load 8.
    let begun = Instant::now();
    while !s.log().contains("fill started") {
        assert!(begun.elapsed() < Duration::from_secs(60), "the fill never started");
        std::thread::sleep(Duration::from_millis(20));
    }
    std::thread::sleep(Duration::from_millis(200));
    let log = s.log.clone();
    let t = Instant::now();
    let code = s.terminate();
    let took = t.elapsed();
    let log = std::fs::read_to_string(log).unwrap_or_default();
    assert_eq!(code, 0, "{log}");
    assert!(
        took < Duration::from_millis(2500),
        "exited {took:?} after SIGTERM with a 1 s grace period\n{log}"
    );
    let ev = events(&f);
    let last = ev.last().unwrap();
    assert_eq!(last["event"], "service_stopped", "{ev:#?}");
    assert!(
        of_kind(&ev, "result_updated").is_empty(),
        "the fill was not interrupted (too fast to test?): {ev:#?}"
    );
    assert!(!f.outbox.join("big/result.png").exists(), "a result was written");
    assert!(
        log.contains("the fill in hand is given up"),
        "the fill was not cancelled, only outlived:\n{log}"
    );
    // Nothing is written later either, by a thread that was still finishing.
    std::thread::sleep(Duration::from_secs(2));
    assert_eq!(events(&f).len(), ev.len());
    assert!(!f.outbox.join("big/result.png").exists(), "a result was written after the service stopped");
}

fn last_verdict<'a>(ev: &'a [Value], file: &str) -> Option<&'a Value> {
    about(ev, file).into_iter().rev().find(|e| {
        ["view_accepted", "view_rejected", "file_skipped", "view_dropped"]
            .contains(&e["event"].as_str().unwrap_or(""))
    })
}

/// The session's `result.json`, or null while there is none (it is replaced atomically, so
/// a file that exists parses).
fn result_report(f: &Folders) -> Value {
    match std::fs::read(f.outbox.join("s1/result.json")) {
        Ok(bytes) => serde_json::from_slice(&bytes).unwrap(),
        Err(_) => Value::Null,
    }
}

/// Masked pixels the current result took from `file`, by its `result.json`.
fn filled_from(f: &Folders, file: &str) -> u64 {
    let r = result_report(f);
    r["views"]
        .as_array()
        .into_iter()
        .flatten()
        .filter(|v| v["file"] == file)
        .map(|v| v["filled"].as_u64().unwrap_or(0))
        .sum()
}

#[test]
fn a_view_replaced_in_place_or_by_rename_is_read_again_and_its_old_pixels_go() {
    let f = folders("");
    let s = Service::start(&f);
    let mut scene = Scene::new(18);
    let dir = f.inbox.join("s1");
    put_key_and_mask(&dir, &scene);
    let v = dir.join("v1.png");
    put(&v, &png(&scene.clear_view(1)));
    wait_for(&f, "v1 accepted", 90, |ev| {
        last_verdict(ev, "v1.png").is_some_and(|e| e["event"] == "view_accepted")
    });
    // The keyframe alone may be published first: wait for the result that uses v1.
    wait_for(&f, "a result from v1", 90, |_| filled_from(&f, "v1.png") > 0);

    // Overwritten in place with another scene: read again and rejected, and the result
    // no longer takes anything from it.
    let other = png(&clearview::synth::facade(W, H, 999));
    std::fs::write(&v, &other).unwrap();
    wait_for(&f, "v1 rejected", 90, |ev| {
        last_verdict(ev, "v1.png").is_some_and(|e| e["event"] == "view_rejected")
    });
    wait_for(&f, "a result without v1", 60, |_| filled_from(&f, "v1.png") == 0);

    // rsync's way: a temporary with the same size and time, renamed over the view.
    let v2 = dir.join("v2.png");
    let good = png(&scene.clear_view(2));
    put(&v2, &good);
    wait_for(&f, "v2 accepted", 90, |ev| {
        last_verdict(ev, "v2.png").is_some_and(|e| e["event"] == "view_accepted")
    });
    let mut bad = png(&clearview::synth::facade(W, H, 998));
    // Same length, as rsync keeps it when only the content differs: pad or cut the PNG
    // after its end (decoders stop at IEND).
    bad.resize(good.len().max(bad.len()), 0);
    let mut good_padded = good.clone();
    good_padded.resize(bad.len(), 0);
    std::fs::write(&v2, &good_padded).unwrap();
    let meta = std::fs::metadata(&v2).unwrap();
    let tmp = dir.join(".v2.png.rsync");
    std::fs::write(&tmp, &bad).unwrap();
    let mtime = meta.modified().unwrap();
    std::fs::File::options().write(true).open(&tmp).unwrap().set_modified(mtime).unwrap();
    std::thread::sleep(Duration::from_secs(2));
    let before = of_kind(&events(&f), "view_rejected").len();
    std::fs::rename(&tmp, &v2).unwrap();
    std::fs::File::options().write(true).open(&v2).unwrap().set_modified(mtime).unwrap();
    assert_eq!(std::fs::metadata(&v2).unwrap().len(), meta.len());
    wait_for(&f, "v2 replaced by rename and read again", 60, |ev| {
        of_kind(ev, "view_rejected").len() > before
    });
    wait_for(&f, "a result without v2", 60, |_| filled_from(&f, "v2.png") == 0);

    // Overwritten with something that is no image at all: its old pixels go too.
    let v3 = dir.join("v3.png");
    put(&v3, &png(&scene.clear_view(3)));
    wait_for(&f, "v3 accepted", 90, |ev| {
        last_verdict(ev, "v3.png").is_some_and(|e| e["event"] == "view_accepted")
    });
    std::fs::write(&v3, b"not an image any more").unwrap();
    wait_for(&f, "v3 dropped", 60, |ev| about(ev, "v3.png").iter().any(|e| e["event"] == "view_dropped"));

    // Deleted: the photographer took it back; nothing of it stays in the result.
    let v4 = dir.join("v4.png");
    put(&v4, &png(&scene.clear_view(4)));
    wait_for(&f, "v4 used", 90, |_| filled_from(&f, "v4.png") > 0);
    std::fs::remove_file(&v4).unwrap();
    let ev =
        wait_for(&f, "v4 dropped", 60, |ev| about(ev, "v4.png").iter().any(|e| e["event"] == "view_dropped"));
    let dropped = about(&ev, "v4.png").into_iter().rfind(|e| e["event"] == "view_dropped").unwrap();
    assert!(dropped["reason"].as_str().unwrap().contains("deleted"), "{dropped}");
    wait_for(&f, "a result without v4", 60, |_| filled_from(&f, "v4.png") == 0);
    drop(s);
}

#[test]
fn an_unreadable_view_is_taken_once_it_can_be_read() {
    // Root reads whatever the mode says: as root, the service runs as `nobody` here.
    const NOBODY: u32 = 65534;
    // SAFETY: geteuid has no preconditions.
    let root = unsafe { libc::geteuid() } == 0;
    let f = folders("");
    let mut scene = Scene::new(19);
    let dir = f.inbox.join("s1");
    put_key_and_mask(&dir, &scene);
    if root {
        let chown = |p: &Path| std::os::unix::fs::chown(p, Some(NOBODY), Some(NOBODY)).unwrap();
        for p in [f.root.clone(), f.inbox.clone(), dir.clone(), dir.join("key.png"), dir.join("key.mask.png")]
        {
            chown(&p);
        }
    }
    let mut s = if root { Service::start_as(&f, NOBODY) } else { Service::start(&f) };
    let v = dir.join("v1.png");
    let tmp = dir.join(".v1.png.up");
    std::fs::write(&tmp, png(&scene.clear_view(1))).unwrap();
    std::fs::set_permissions(&tmp, std::os::unix::fs::PermissionsExt::from_mode(0o000)).unwrap();
    std::fs::rename(&tmp, &v).unwrap();
    let ev = wait_for(&f, "v1 skipped", 60, |ev| {
        last_verdict(ev, "v1.png").is_some_and(|e| e["event"] == "file_skipped")
    });
    let skipped = last_verdict(&ev, "v1.png").unwrap();
    assert!(skipped["reason"].as_str().unwrap().contains("ermission"), "{skipped}");
    assert!(skipped["retried"].as_str().is_some_and(|r| r.contains("permissions")), "{skipped}");
    std::fs::set_permissions(&v, std::os::unix::fs::PermissionsExt::from_mode(0o644)).unwrap();
    wait_for(&f, "v1 accepted after chmod", 60, |ev| {
        last_verdict(ev, "v1.png").is_some_and(|e| e["event"] == "view_accepted")
    });
    assert!(s.alive());
}

#[test]
fn special_files_are_reported_once_and_never_opened() {
    let f = folders("");
    let s = Service::start(&f);
    let scene = Scene::new(20);
    let dir = f.inbox.join("s1");
    put_key_and_mask(&dir, &scene);
    wait_for(&f, "the keyframe", 60, |ev| !of_kind(ev, "mask_set").is_empty());
    let fifo = dir.join("pipe.jpg");
    let c = std::ffi::CString::new(fifo.to_str().unwrap()).unwrap();
    // SAFETY: a valid C string.
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o644) }, 0);
    std::os::unix::net::UnixListener::bind(dir.join("sock.png")).unwrap();
    std::fs::create_dir(dir.join("folder.jpg")).unwrap();
    let ev = wait_for(&f, "three special files reported", 30, |ev| {
        ["pipe.jpg", "sock.png", "folder.jpg"].iter().all(|n| !about(ev, n).is_empty())
    });
    for (name, word) in [("pipe.jpg", "FIFO"), ("sock.png", "socket"), ("folder.jpg", "folder")] {
        let e = about(&ev, name);
        assert_eq!(e[0]["event"], "file_skipped", "{e:?}");
        assert!(e[0]["reason"].as_str().unwrap().contains(word), "{e:?}");
    }
    // Once each, however long they stay (rescans, notifications on the folder).
    std::fs::write(dir.join("unrelated.txt"), b"x").unwrap();
    std::thread::sleep(Duration::from_secs(2));
    let ev = events(&f);
    for name in ["pipe.jpg", "sock.png", "folder.jpg"] {
        assert_eq!(about(&ev, name).len(), 1, "{name}: {:?}", about(&ev, name));
    }
    // Nobody opened the FIFO: a writer would block until a reader came. Open it for
    // writing without blocking: ENXIO says no reader has it open.
    let w = std::fs::OpenOptions::new().write(true).custom_flags(libc::O_NONBLOCK).open(&fifo);
    assert_eq!(w.err().and_then(|e| e.raw_os_error()), Some(libc::ENXIO));
    drop(s);
}

use std::os::unix::fs::OpenOptionsExt;

#[test]
fn a_keyframe_chosen_on_the_page_stays_after_a_restart_whatever_the_old_ones_case() {
    let f = folders("");
    let s = Service::start_http(&f, "127.0.0.1:0", &[]);
    let mut scene = Scene::new(21);
    let dir = f.inbox.join("facade");
    put(&dir.join("key.mask.png"), &mask_png(&scene.mask));
    // An upper-case keyframe, as cameras name them.
    let mut jpg = std::io::Cursor::new(Vec::new());
    clearview::imaging::convert::to_rgb8(&scene.key).write_to(&mut jpg, image::ImageFormat::Jpeg).unwrap();
    put(&dir.join("key.JPG"), jpg.get_ref());
    put(&dir.join("v1.png"), &png(&scene.clear_view(1)));
    wait_session(&s, "facade", "v1 used", 90, |v| {
        v["keyframe"] == "key.JPG"
            && v["views"].as_array().is_some_and(|a| a.iter().any(|w| w["file"] == "v1.png"))
    });
    let body = serde_json::json!({ "file": "v1.png" }).to_string();
    let r = request(
        "PUT",
        &format!("{}/api/sessions/facade/keyframe", s.base),
        Some(&s.token),
        Some(("application/json", body.as_bytes())),
    );
    assert_eq!(r.status, 202, "{}", r.text());
    let kept: Vec<String> =
        r.json()["kept"].as_array().unwrap().iter().map(|k| k.as_str().unwrap().to_owned()).collect();
    assert!(kept.iter().any(|k| k.starts_with("former-key-") && k.ends_with(".JPG")), "{kept:?}");
    assert!(!dir.join("key.JPG").exists(), "the old keyframe stayed as key.JPG");
    assert!(dir.join("key.png").is_file());
    wait_session(&s, "facade", "the new keyframe", 60, |v| v["keyframe"] == "key.png");
    drop(s);
    let s = Service::start_http(&f, "127.0.0.1:0", &[]);
    let v = wait_session(&s, "facade", "the session after a restart", 60, |v| !v["keyframe"].is_null());
    assert_eq!(v["keyframe"], "key.png", "{v:#}");
    drop(s);
}

#[test]
fn an_out_folder_replaced_by_a_link_is_not_written_through() {
    let f = folders("");
    let s = Service::start(&f);
    let mut scene = Scene::new(22);
    let dir = f.inbox.join("s1");
    put_key_and_mask(&dir, &scene);
    put(&dir.join("v1.png"), &png(&scene.view(1, 120.0, 60.0)));
    wait_for(&f, "a first result", 90, |ev| !of_kind(ev, "result_updated").is_empty());
    let elsewhere = f.root.join("elsewhere");
    std::fs::create_dir_all(&elsewhere).unwrap();
    std::fs::rename(&f.outbox, f.root.join("outbox.moved")).unwrap();
    std::os::unix::fs::symlink(&elsewhere, &f.outbox).unwrap();
    put(&dir.join("v2.png"), &png(&scene.clear_view(2)));
    let deadline = Instant::now() + Duration::from_secs(60);
    while !s.log().contains("symbolic link") {
        assert!(Instant::now() < deadline, "nothing said of the link\n{}", s.log());
        std::thread::sleep(Duration::from_millis(100));
    }
    std::thread::sleep(Duration::from_secs(1));
    let written: Vec<_> = std::fs::read_dir(&elsewhere).unwrap().flatten().map(|e| e.path()).collect();
    assert!(written.is_empty(), "written through the link: {written:?}");
}

/// A camera that makes a session folder and renames its first photo into it at once: the
/// rename can land before the kernel watches the new folder, and its event is then lost.
/// Every such photo is still noticed in seconds, not at the next rescan minutes later.
#[test]
fn photos_renamed_into_brand_new_session_folders_are_all_noticed() {
    let f = folders("");
    let s = Service::start(&f);
    let scene = Scene::new(23);
    let key = png(&scene.key);
    let names: Vec<String> = (0..24).map(|i| format!("site{i:02}")).collect();
    for n in &names {
        put(&f.inbox.join(n).join("key.png"), &key);
    }
    wait_for(&f, "every new session folder's keyframe", 30, |ev| {
        names.iter().all(|n| of_kind(ev, "session_started").iter().any(|e| e["session"] == n.as_str()))
    });
    drop(s);
}
