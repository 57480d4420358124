//! Fault injection on the real service (`clearview run`): a full or read-only out folder
//! and state folder, SIGKILL while results are written, corrupt state, a session folder
//! deleted mid-session, the watched folder removed and recreated (issue 7, "Faults").
//!
//! The disk faults need mounts (a small tmpfs, a read-only bind mount): they run as root
//! (as on this project's machines and CI) and skip with a printed reason elsewhere.

mod daemon_common;

use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use daemon_common::*;
use serde_json::Value;

/// A mount made by a test, undone when dropped (also when the test panics).
struct Mount(PathBuf);

impl Mount {
    fn run(args: &[&str], dir: &Path) -> Result<(), String> {
        let out = Command::new("mount").args(args).arg(dir).output().map_err(|e| format!("mount: {e}"))?;
        if out.status.success() {
            Ok(())
        } else {
            Err(format!("mount {args:?}: {}", String::from_utf8_lossy(&out.stderr).trim()))
        }
    }

    /// A tmpfs of `kib` KiB on `dir`, or `None` (with the reason printed) when mounting is
    /// not permitted here.
    fn tmpfs(dir: &Path, kib: u64) -> Option<Self> {
        std::fs::create_dir_all(dir).unwrap();
        match Self::run(&["-t", "tmpfs", "-o", &format!("size={kib}k"), "tmpfs"], dir) {
            Ok(()) => Some(Self(dir.to_owned())),
            Err(e) => {
                eprintln!("skipping: cannot mount a tmpfs (needs root or CAP_SYS_ADMIN): {e}");
                None
            }
        }
    }

    /// `dir` mounted over itself read-only.
    fn read_only_bind(dir: &Path) -> Self {
        Self::run(&["--bind", &dir.to_string_lossy()], dir).unwrap();
        let m = Self(dir.to_owned());
        Self::run(&["-o", "remount,bind,ro"], dir).unwrap();
        m
    }

    fn remount(&self, how: &str) {
        Self::run(&["-o", &format!("remount,{how}")], &self.0).unwrap();
    }
}

impl Drop for Mount {
    fn drop(&mut self) {
        let ok = Command::new("umount").arg(&self.0).status().is_ok_and(|s| s.success());
        if !ok {
            let _ = Command::new("umount").arg("-l").arg(&self.0).status();
        }
    }
}

/// Every file under `dir` with its bytes.
fn snapshot(dir: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
    let mut out = BTreeMap::new();
    for e in std::fs::read_dir(dir).unwrap().flatten() {
        if e.file_type().unwrap().is_dir() {
            out.extend(snapshot(&e.path()));
        } else {
            out.insert(e.path(), std::fs::read(e.path()).unwrap());
        }
    }
    out
}

/// Grows `path` until the file system refuses (ENOSPC).
fn fill_up(path: &Path) {
    let mut f = std::fs::OpenOptions::new().create(true).append(true).open(path).unwrap();
    for chunk in [1 << 16, 4096, 1] {
        let buf = vec![0u8; chunk];
        while f.write_all(&buf).is_ok() {}
    }
    let _ = f.sync_all();
}

/// FNV-1a, as 16 hex digits (what `result.json` records of its image).
fn fnv64(bytes: &[u8]) -> String {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in bytes {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    format!("{h:016x}")
}

/// `result.json` of the session in `dir`, checked against the image it names and its
/// history copy; returns its number.
fn whole_result(dir: &Path) -> u64 {
    let json: Value = serde_json::from_slice(&std::fs::read(dir.join("result.json")).unwrap())
        .unwrap_or_else(|e| panic!("{}: result.json does not parse: {e}", dir.display()));
    let number = json["number"].as_u64().unwrap();
    let png = std::fs::read(dir.join("result.png")).unwrap();
    image::load_from_memory(&png).unwrap_or_else(|e| panic!("{}: result.png: {e}", dir.display()));
    assert_eq!(
        json["image"]["bytes"].as_u64(),
        Some(png.len() as u64),
        "result.json describes another image"
    );
    assert_eq!(
        json["image"]["fnv64"].as_str(),
        Some(fnv64(&png).as_str()),
        "result.json describes another image"
    );
    let hist = dir.join(format!("history/result-{number:04}.png"));
    assert_eq!(std::fs::read(&hist).unwrap(), png, "{} is not the current result", hist.display());
    number
}

/// Waits until the service's log contains `needle`.
fn wait_log(s: &Service, needle: &str, secs: u64) -> String {
    let deadline = Instant::now() + Duration::from_secs(secs);
    loop {
        let log = s.log();
        if log.contains(needle) {
            return log;
        }
        assert!(Instant::now() < deadline, "no {needle:?} in the log:\n{log}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

fn session_events<'a>(ev: &'a [Value], session: &str, kind: &str) -> Vec<&'a Value> {
    of_kind(ev, kind).into_iter().filter(|e| e["session"] == session).collect()
}

#[test]
fn a_full_or_read_only_out_folder_keeps_the_result_and_writing_resumes_when_it_clears() {
    let f = folders("");
    let Some(_out) = Mount::tmpfs(&f.outbox, 4096) else { return };
    let Some(state_mount) = Mount::tmpfs(&f.state, 1024) else { return };
    let mut service = Service::start(&f);
    let mut scene = Scene::new(101);
    let inbox = f.inbox.join("full");
    let out = f.outbox.join("full");
    put_key_and_mask(&inbox, &scene);
    put(&inbox.join("v1.png"), &png(&scene.view(1, 120.0, 70.0)));
    wait_for(&f, "a result with the first view", 30, |e| {
        session_events(e, "full", "result_updated").iter().any(|r| r["views"] == 1)
    });
    let before = snapshot(&out);
    let first = whole_result(&out);

    // 1. The disk fills, with a little room left (the event log can still grow).
    let filler = f.outbox.join("filler");
    fill_up(&filler);
    let len = std::fs::metadata(&filler).unwrap().len();
    std::fs::OpenOptions::new().write(true).open(&filler).unwrap().set_len(len - 48 * 1024).unwrap();
    put(&inbox.join("v2.png"), &png(&scene.view(2, 300.0, 60.0)));
    let ev = wait_for(&f, "the failed write to be reported", 30, |e| {
        !session_events(e, "full", "result_failed").is_empty()
    });
    let failed = session_events(&ev, "full", "result_failed")[0];
    assert_eq!(failed["number"], first + 1, "{failed}");
    assert!(
        failed["file"].as_str().unwrap().ends_with("full/result.png"),
        "the event names the file: {failed}"
    );
    assert!(failed["reason"].as_str().unwrap().contains("No space left"), "the OS reason: {failed}");
    let log = wait_log(&service, "cannot write the result", 10);
    assert!(log.contains("No space left on device"), "{log}");
    assert_eq!(snapshot(&out), before, "the result on disk changed while the disk was full");
    no_temporaries(&f.outbox);

    // 2. Completely full: the event log cannot take a line. Its last page is padded so the
    // next line must cross into a page the disk cannot give: a short write, then an error.
    let events_path = f.outbox.join("events.jsonl");
    let size = std::fs::metadata(&events_path).unwrap().len();
    // The line is 34 bytes and the padding; it ends 20 bytes before a page boundary.
    let pad = (2 * 4096 - 20 - 34 - size % 4096) % 4096;
    let line = format!("{{\"event\":\"test_padding\",\"pad\":\"{}\"}}\n", "x".repeat(pad as usize));
    std::fs::OpenOptions::new().append(true).open(&events_path).unwrap().write_all(line.as_bytes()).unwrap();
    fill_up(&filler);
    let padded = std::fs::metadata(&events_path).unwrap().len();
    assert_eq!(padded % 4096, 4096 - 20, "padding missed");
    wait_log(&service, "cannot append to the event log", 20);
    assert_eq!(std::fs::metadata(&events_path).unwrap().len(), padded, "half a line left in the event log");
    assert!(service.alive(), "the service died on a full disk");

    // 3. The space comes back: the waiting result is written without any new file.
    std::fs::remove_file(&filler).unwrap();
    let ev = wait_for(&f, "the waiting result to be written", 40, |e| {
        session_events(e, "full", "result_updated").iter().any(|r| r["number"] == first + 1)
    });
    let retried =
        session_events(&ev, "full", "result_updated").into_iter().find(|r| r["number"] == first + 1).unwrap();
    assert!(retried["tries"].as_u64().unwrap() >= 2, "{retried}\n{ev:#?}");
    assert_eq!(whole_result(&out), first + 1);

    // 4. The state folder turns read-only: results go on (the state only saves work), and
    // the state is saved once the folder is writable again, without any new file.
    state_mount.remount("ro");
    put(&inbox.join("v3.png"), &png(&scene.view(3, 60.0, 50.0)));
    wait_for(&f, "a result with the third view", 30, |e| {
        session_events(e, "full", "result_updated").iter().any(|r| r["number"] == first + 2)
    });
    wait_log(&service, "cannot save state", 10);
    let state_file = f.state.join("sessions/full.json");
    assert!(!std::fs::read_to_string(&state_file).unwrap().contains("v3.png"));
    state_mount.remount("rw");
    let deadline = Instant::now() + Duration::from_secs(20);
    while !std::fs::read_to_string(&state_file).unwrap().contains("v3.png") {
        assert!(Instant::now() < deadline, "the state was not saved once its folder came back");
        std::thread::sleep(Duration::from_millis(100));
    }

    // 5. The session's out folder turns read-only.
    let after_three = snapshot(&out);
    let ro = Mount::read_only_bind(&out);
    let seen = events(&f).len();
    // A new keyframe (brighter) makes a new result.
    let mut brighter = scene.key.clone();
    clearview::synth::expose(&mut brighter, 1.1, 0.0);
    put(&inbox.join("key.png"), &png(&brighter));
    let ev = wait_for(&f, "the read-only folder to be reported", 30, |e| {
        e.len() > seen && !session_events(&e[seen..], "full", "result_failed").is_empty()
    });
    let failed = session_events(&ev[seen..], "full", "result_failed")[0];
    assert!(failed["reason"].as_str().unwrap().contains("Read-only file system"), "{failed}");
    assert_eq!(snapshot(&out), after_three, "the result changed in a read-only folder");
    drop(ro);
    let ev = wait_for(&f, "the waiting result after the folder came back", 40, |e| {
        session_events(e, "full", "result_updated").iter().any(|r| r["number"] == first + 3)
    });
    assert_eq!(whole_result(&out), first + 3);
    // Every line of the event log is whole (`events` fails on one that is not).
    assert!(ev.iter().all(|e| e["event"].is_string()));
    assert_eq!(service.terminate(), 0);
    no_temporaries(&f.outbox);
    no_temporaries(&f.state);
}

/// Temporaries of the atomic writer anywhere under `dirs`.
fn temporaries(dirs: &[&Path]) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for d in dirs {
        let Ok(entries) = std::fs::read_dir(d) else { continue };
        for e in entries.flatten() {
            if e.file_name().to_string_lossy().contains("clearview-tmp") {
                out.push(e.path());
            } else if e.file_type().is_ok_and(|t| t.is_dir()) {
                out.extend(temporaries(&[&e.path()]));
            }
        }
    }
    out
}

/// Every visible result, history entry and state file is whole.
fn everything_visible_is_whole(f: &Folders, session: &str) {
    let out = f.outbox.join(session);
    if out.join("result.json").exists() {
        let _: Value = serde_json::from_slice(&std::fs::read(out.join("result.json")).unwrap())
            .expect("result.json is whole");
    }
    for name in ["result.png", "mask.png", "provenance.png", "confidence.png", "surfaces.png"] {
        let p = out.join(name);
        if p.exists() {
            image::open(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
        }
    }
    if let Ok(hist) = std::fs::read_dir(out.join("history")) {
        for e in hist.flatten().filter(|e| !e.file_name().to_string_lossy().starts_with('.')) {
            image::open(e.path()).unwrap_or_else(|err| panic!("{}: {err}", e.path().display()));
        }
    }
    for e in std::fs::read_dir(f.state.join("sessions")).unwrap().flatten() {
        if !e.file_name().to_string_lossy().starts_with('.') {
            let _: Value =
                serde_json::from_slice(&std::fs::read(e.path()).unwrap()).expect("whole state file");
        }
    }
}

#[test]
fn sigkill_while_results_are_written_leaves_only_whole_files_and_a_restart_agrees_with_them() {
    use rand::{Rng, SeedableRng};
    let f = folders("");
    let mut scene = Scene::new(201);
    let inbox = f.inbox.join("k");
    let out = f.outbox.join("k");
    put_key_and_mask(&inbox, &scene);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let (mut caught_mid_write, runs) = (0, 8);
    for run in 0..runs {
        let mut service = Service::start(&f);
        wait_for(&f, "the service to start", 20, |e| of_kind(e, "service_started").len() > run);
        // A restart leaves no temporary behind, in the out folder or the state folder.
        assert_eq!(temporaries(&[&f.outbox, &f.state]), Vec::<PathBuf>::new(), "run {run}");
        let i = run as u64 + 1;
        put(&inbox.join(format!("v{i}.png")), &png(&scene.view(i, 60.0 + 40.0 * i as f32, 50.0)));
        if run % 2 == 0 {
            // Killed the moment a temporary appears: in the middle of writing a file.
            let deadline = Instant::now() + Duration::from_secs(15);
            while temporaries(&[&out, &f.state]).is_empty() && Instant::now() < deadline {
                std::hint::spin_loop();
            }
            caught_mid_write += usize::from(!temporaries(&[&out, &f.state]).is_empty());
        } else {
            std::thread::sleep(Duration::from_millis(rng.random_range(150..1500)));
        }
        service.child.kill().unwrap();
        service.child.wait().unwrap();
        everything_visible_is_whole(&f, "k");
    }
    eprintln!("{caught_mid_write} of {} kills landed while a file was being written", runs / 2);
    assert!(caught_mid_write >= 1, "no kill landed in the middle of a write");

    // The last start settles: the result agrees with result.json, with the history and
    // with the state, and numbering never went back.
    let service = Service::start(&f);
    wait_for(&f, "the service to start", 20, |e| of_kind(e, "service_started").len() > runs);
    assert_eq!(temporaries(&[&f.outbox, &f.state]), Vec::<PathBuf>::new());
    let names: Vec<String> = (1..=runs).map(|i| format!("v{i}.png")).collect();
    let seen = events(&f).len();
    wait_for(&f, "every view to be handled after the last start", 60, |e| {
        names.iter().all(|n| e[seen..].iter().any(|x| x["file"] == n.as_str()))
            && (e[seen..].iter().any(|x| x["event"] == "result_updated" || x["event"] == "result_unchanged"))
    });
    assert_eq!(service.terminate(), 0);
    let number = whole_result(&out);
    let state: Value =
        serde_json::from_slice(&std::fs::read(f.state.join("sessions/k.json")).unwrap()).unwrap();
    assert_eq!(state["result"]["number"].as_u64(), Some(number), "the state names another result");
    assert_eq!(state["last_number"].as_u64(), Some(number));
    let ev = events(&f);
    let numbers: Vec<u64> =
        of_kind(&ev, "result_updated").iter().map(|r| r["number"].as_u64().unwrap()).collect();
    assert!(numbers.windows(2).all(|w| w[1] > w[0]), "a result number was used twice: {numbers:?}");
    no_temporaries(&f.outbox);
    no_temporaries(&f.state);
}

/// Runs the service on `f` until the session `s` has handled its `views` views after
/// this start and has its result; returns this start's events.
fn restart_and_settle(f: &Folders, views: usize) -> Vec<Value> {
    let seen = events(f).len();
    let service = Service::start(f);
    // Settled: every view accepted, and a fill decided after the last of them (a result
    // after an earlier view is not the session's last).
    let ev = wait_for(f, "the session to settle", 40, |e| {
        let new = &e[seen.min(e.len())..];
        let accepted: Vec<usize> = (0..new.len()).filter(|&i| new[i]["event"] == "view_accepted").collect();
        accepted.len() >= views
            && new[accepted[views - 1]..].iter().any(|x| {
                ["result_updated", "result_unchanged", "result_not_better"]
                    .contains(&x["event"].as_str().unwrap_or(""))
            })
    });
    assert_eq!(service.terminate(), 0);
    ev[seen..].to_vec()
}

#[test]
fn a_damaged_edited_or_outdated_state_is_rebuilt_from_the_images() {
    let f = folders("");
    let mut scene = Scene::new(301);
    let inbox = f.inbox.join("s");
    let out = f.outbox.join("s");
    // The keyframe is padded after its end so that a different one can take its exact
    // size later (the decoder ignores bytes after IEND).
    let mut key = png(&scene.key);
    let mut brighter = scene.key.clone();
    clearview::synth::expose(&mut brighter, 1.08, 0.0);
    let mut other_key = png(&brighter);
    let size = key.len().max(other_key.len()) + 64;
    key.resize(size, 0);
    other_key.resize(size, 0);
    put(&inbox.join("key.mask.png"), &mask_png(&scene.mask));
    put(&inbox.join("key.png"), &key);
    for i in 1..=3 {
        put(&inbox.join(format!("v{i}.png")), &png(&scene.view(i, 90.0 * i as f32, 60.0)));
    }
    let ev = restart_and_settle(&f, 3);
    assert!(of_kind(&ev, "view_accepted").iter().all(|e| e["from_state"] == false));
    let first = whole_result(&out);
    let state_file = f.state.join("sessions/s.json");
    let good_state = std::fs::read(&state_file).unwrap();

    // Sanity: an intact state is used (nothing realigned, nothing rewritten).
    let ev = restart_and_settle(&f, 3);
    assert!(
        of_kind(&ev, "view_accepted").iter().all(|e| e["from_state"] == true),
        "{ev:#?}\n{}",
        std::fs::read_to_string(f.root.join("service-2.log")).unwrap_or_default()
    );
    assert!(!of_kind(&ev, "result_unchanged").is_empty());

    let mut number = first;
    let edited_homographies = {
        let mut v: Value = serde_json::from_slice(&good_state).unwrap();
        for (_, a) in v["alignments"].as_object_mut().unwrap() {
            a["record"]["homography"][0][2] =
                Value::from(a["record"]["homography"][0][2].as_f64().unwrap() + 40.0);
        }
        serde_json::to_vec(&v).unwrap()
    };
    let cases: [(&str, Vec<u8>); 3] = [
        ("cut in half", good_state[..good_state.len() / 2].to_vec()),
        ("garbage", b"\x00\x17garbage{{{".to_vec()),
        ("valid JSON with wrong homographies", edited_homographies),
    ];
    for (what, bytes) in cases {
        std::fs::write(&state_file, &bytes).unwrap();
        let ev = restart_and_settle(&f, 3);
        let accepted = of_kind(&ev, "view_accepted");
        assert!(
            accepted.iter().all(|e| e["from_state"] == false),
            "{what}: a view was not realigned: {accepted:#?}"
        );
        // The result is made again from the images, numbered after the one on disk.
        let updated = of_kind(&ev, "result_updated");
        assert_eq!(
            updated.last().map(|r| r["number"].as_u64().unwrap()),
            Some(number + 1),
            "{what}: {ev:#?}"
        );
        number += 1;
        assert_eq!(whole_result(&out), number);
        let result = image::open(out.join("result.png")).unwrap().to_rgb8();
        let e_key = scene.masked_error(&clearview::imaging::convert::to_rgb8(&scene.key));
        let e_result = scene.masked_error(&result);
        assert!(e_result < 0.5 * e_key, "{what}: the result is poor: {e_key} -> {e_result}");
    }

    // The keyframe replaced by another of the same size and time: its name, size and
    // time say "same file", its pixels do not. Realigned, and a new result.
    let key_path = inbox.join("key.png");
    let mtime = std::fs::metadata(&key_path).unwrap().modified().unwrap();
    std::fs::write(&key_path, &other_key).unwrap();
    std::fs::File::options().write(true).open(&key_path).unwrap().set_modified(mtime).unwrap();
    assert_eq!(std::fs::metadata(&key_path).unwrap().len(), size as u64);
    let ev = restart_and_settle(&f, 3);
    assert!(
        of_kind(&ev, "view_accepted").iter().all(|e| e["from_state"] == false),
        "views kept alignments to a keyframe that changed: {ev:#?}"
    );
    assert!(of_kind(&ev, "result_unchanged").is_empty(), "the result of the old keyframe was kept");
    assert_eq!(whole_result(&out), number + 1);
}

#[test]
fn a_session_folder_deleted_mid_session_ends_that_session_only_and_keeps_its_results() {
    let f = folders("workers = 2\n");
    let mut a = Scene::new(401);
    let mut b = Scene::new(402);
    let mut service = Service::start(&f);
    put_key_and_mask(&f.inbox.join("a"), &a);
    put_key_and_mask(&f.inbox.join("b"), &b);
    put(&f.inbox.join("b/v1.png"), &png(&b.view(1, 100.0, 60.0)));
    wait_for(&f, "b's first result", 30, |e| {
        of_kind(e, "result_updated").iter().any(|r| r["session"] == "b" && r["views"] == 1)
    });
    for i in 2..=5 {
        put(&f.inbox.join(format!("b/v{i}.png")), &png(&b.view(i, 60.0 * i as f32, 50.0)));
    }
    // Removed while its views are being aligned and filled.
    wait_for(&f, "b's views to be handled", 30, |e| {
        of_kind(e, "view_accepted").iter().any(|v| v["session"] == "b" && v["file"] != "v1.png")
    });
    std::fs::remove_dir_all(f.inbox.join("b")).unwrap();
    let ev = wait_for(&f, "b's end", 20, |e| session_events(e, "b", "session_removed").len() == 1);
    assert!(service.alive());
    let removed = session_events(&ev, "b", "session_removed")[0];
    assert!(removed["reason"].as_str().unwrap().contains("removed"), "{removed}");
    // Its results are kept, whole.
    let kept = whole_result(&f.outbox.join("b"));
    assert!(kept >= 1);
    // The other session goes on.
    put(&f.inbox.join("a/v1.png"), &png(&a.view(1, 120.0, 60.0)));
    wait_for(&f, "a's result", 30, |e| {
        of_kind(e, "result_updated").iter().any(|r| r["session"] == "a" && r["views"] == 1)
    });
    // The folder comes back: the session starts again, numbered after what it kept.
    put_key_and_mask(&f.inbox.join("b"), &b);
    put(&f.inbox.join("b/v9.png"), &png(&b.view(9, 200.0, 60.0)));
    let ev = wait_for(&f, "b to start again", 30, |e| {
        session_events(e, "b", "session_started").len() == 2
            && session_events(e, "b", "result_updated")
                .iter()
                .any(|r| r["views"] == 1 && r["number"].as_u64().unwrap() > kept)
    });
    assert_eq!(session_events(&ev, "b", "session_removed").len(), 1);
    assert!(whole_result(&f.outbox.join("b")) > kept);
    assert_eq!(service.terminate(), 0);
}

fn the_watched_folder_removed_and_recreated_is_watched_again(mode: &str) {
    // A rescan interval far beyond the test: only re-arming finds the new files.
    let f = folders("");
    let text = std::fs::read_to_string(&f.config).unwrap();
    let watch = match mode {
        "poll" => "mode = \"poll\"\npoll_interval_ms = 200\n",
        _ => "rescan_interval_s = 3600\n",
    };
    std::fs::write(
        &f.config,
        text.replace("quiet_period_ms = 300\n", &format!("quiet_period_ms = 300\n{watch}")),
    )
    .unwrap();
    let mut scene = Scene::new(501);
    let mut service = Service::start(&f);
    put_key_and_mask(&f.inbox.join("c"), &scene);
    wait_for(&f, "the session to start", 30, |e| !of_kind(e, "mask_set").is_empty());
    std::fs::remove_dir_all(&f.inbox).unwrap();
    let ev = wait_for(&f, "the folder's loss to be reported", 20, |e| {
        !of_kind(e, "watch_dir_vanished").is_empty()
    });
    assert!(of_kind(&ev, "watch_dir_vanished")[0]["dir"].as_str().unwrap().ends_with("inbox"));
    wait_for(&f, "the session to end with its folder", 20, |e| {
        !session_events(e, "c", "session_removed").is_empty()
    });
    std::thread::sleep(Duration::from_millis(500));
    assert!(service.alive());
    put_key_and_mask(&f.inbox.join("c"), &scene);
    put(&f.inbox.join("c/v1.png"), &png(&scene.view(1, 120.0, 60.0)));
    wait_for(&f, "a result from files in the recreated folder", 30, |e| {
        !of_kind(e, "watch_dir_restored").is_empty()
            && session_events(e, "c", "result_updated").iter().any(|r| r["views"] == 1)
    });
    // And a file that lands later still arrives by notification.
    put(&f.inbox.join("c/v2.png"), &png(&scene.view(2, 300.0, 60.0)));
    wait_for(&f, "the later view", 30, |e| !about(e, "v2.png").is_empty());
    assert_eq!(service.terminate(), 0);
}

#[test]
fn the_watched_folder_removed_and_recreated_is_watched_again_with_notify() {
    the_watched_folder_removed_and_recreated_is_watched_again("notify");
}

#[test]
fn the_watched_folder_removed_and_recreated_is_scanned_again_when_polled() {
    the_watched_folder_removed_and_recreated_is_watched_again("poll");
}
