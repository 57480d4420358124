//! A worker whose link to the cluster stalls in the middle of a step (issue 17): the
//! step fails on a timeout, which is the cluster's failure and not the message's, so the
//! message comes again and the session gets its result; it is never dead-lettered, even
//! with `max_deliver = 1`. A file whose content the object store really lost is a lasting
//! failure: that message is dead-lettered, with the file and the reason. A worker paused
//! past its lease (SIGSTOP) loses its step to another and says nothing of it.
//!
//! One `nats-server`; the worker reaches it through a relay that holds its bytes back for
//! 12 s (longer than the client's request timeouts) at its first object read. Needs
//! `nats-server` (Debian's package; `.ci/setup` installs it).

mod daemon_common;

use std::path::Path;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use daemon_common::nats::{
    Proc, Stall, events, single_server, start_collect, start_ingest, start_worker, wait_started, wait_until,
    write_config,
};
use daemon_common::{Scene, bin, mask_png, png, put};
use serde_json::Value;

const VIEWS: u64 = 2;

/// A session's mask, keyframe and views, each written under a hidden name first.
fn drop_session(inbox: &Path, name: &str, seed: u64) -> Vec<String> {
    let mut scene = Scene::new(seed);
    let dir = inbox.join(name);
    put(&dir.join("key.mask.png"), &mask_png(&scene.mask));
    put(&dir.join("key.png"), &png(&scene.key));
    (0..VIEWS)
        .map(|i| {
            let file = format!("view{i}.png");
            put(&dir.join(&file), &png(&scene.view(i, 60.0 + 120.0 * i as f32, 40.0)));
            file
        })
        .collect()
}

#[test]
fn a_stalled_link_is_not_poison_and_a_lost_file_is() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let (inbox, out) = (root.join("inbox"), root.join("out"));
    std::fs::create_dir_all(&inbox).unwrap();
    let (_nats, urls, port) = single_server(root);
    // The worker's object reads are direct gets of the object store's meta subjects.
    let stall = Stall::start(port, b"$O.clearview-files.M.", Duration::from_secs(12));
    let c = &write_config(
        root,
        "[nats]\nreplicas = 1\nlease_ttl_ms = 3000\nack_wait_ms = 4000\nmax_deliver = 1\n",
    );
    let collect = start_collect(c, &urls, &out, root);
    let worker = |relay: u16| {
        let scratch = root.join("scratch");
        let via = format!("nats://127.0.0.1:{relay}");
        Proc::start(
            "worker",
            Path::new(bin()),
            &["worker", "-c", c, "--nats", &via, "--id", "w1", "--scratch", scratch.to_str().unwrap()],
            root,
        )
    };
    let w = worker(stall.port);
    let ingest = start_ingest(c, &urls, &inbox, &root.join("ingest"), root);
    wait_started(&[&collect, &w, &ingest], 40);
    stall.arm();

    // 1. The link stalls at the worker's first object read: a timeout, then the message
    //    again, then the result; nothing dead-lettered.
    let views = drop_session(&inbox, "site0", 31);
    let named = |ev: &[Value], s: &str, f: &str| ev.iter().any(|e| e["session"] == s && e["file"] == f);
    wait_until("a result after every view of site0", 90, &[&w, &collect], || {
        let ev = events(&out);
        views.iter().all(|v| named(&ev, "site0", v)) && out.join("site0").join("result.json").is_file()
    });
    let dead = |ev: &[Value]| -> Vec<Value> {
        ev.iter().filter(|e| e["event"] == "message_dead_lettered").cloned().collect()
    };
    assert!(
        dead(&events(&out)).is_empty(),
        "a stalled link made a message poison: {:?}",
        dead(&events(&out))
    );

    assert_eq!(stall.stalled.load(Ordering::SeqCst), 1, "the link never stalled:\n{}", w.log());
    let log = w.log();
    assert!(
        log.contains("step failed: the message comes again") && log.contains("lasting=false"),
        "the stall did not fail a step (the test did not test anything):\n{log}"
    );

    // 2. A file the object store lost: the worker is stopped, the session's files are
    //    ingested, one view's content is deleted from the store, the worker comes back.
    assert_eq!(w.terminate(), Some(0));
    let views = drop_session(&inbox, "site1", 32);
    let lost = &views[1];
    let digest = {
        let mut digest = None;
        wait_until("every file of site1 ingested", 30, &[&ingest], || {
            digest = ingest.log().lines().find_map(|l| {
                (l.contains("file ingested")
                    && l.contains("session=site1")
                    && l.contains(&format!("file={lost}")))
                .then(|| {
                    l.split("digest=")
                        .nth(1)
                        .unwrap()
                        .split_whitespace()
                        .next()
                        .unwrap()
                        .trim_matches('"')
                        .to_owned()
                })
            });
            digest.is_some() && ingest.log().matches("file ingested").count() >= 2 * (VIEWS as usize + 2)
        });
        digest.unwrap()
    };
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    rt.block_on(async {
        let js = async_nats::jetstream::new(async_nats::connect(urls.as_str()).await.unwrap());
        let objects = js.get_object_store("clearview-files").await.unwrap();
        let name = format!("file/{digest}");
        objects.delete(&name).await.unwrap_or_else(|e| panic!("{name}: {e}\n{}", ingest.log()));
    });
    let w = worker(port);
    wait_until("the message of site1's lost file dead-lettered", 60, &[&w, &collect], || {
        dead(&events(&out)).iter().any(|e| e["session"] == "site1")
    });
    let letters = dead(&events(&out));
    assert!(letters.iter().all(|e| e["session"] == "site1"), "only site1's messages: {letters:?}");
    let reason = letters[0]["reason"].as_str().unwrap();
    assert!(
        reason.contains(lost.as_str()) && reason.contains("is not in the object store"),
        "the dead letter names the file and why: {reason}"
    );
    for p in [w, ingest, collect] {
        let (name, log) = (p.name.clone(), p.log());
        assert_eq!(p.terminate(), Some(0), "{name}:\n{log}");
    }
}

/// A worker paused in the middle of a step (SIGSTOP: a virtual machine suspended, a laptop
/// lid closed) past its lease and its message's ack wait: another worker does the step and
/// saves the session. When the first resumes, its step loses the record's compare-and-set
/// and is dropped; what it said (the views it accepted, a result it numbered) was never
/// committed and is never published, not even with the next record that worker saves.
#[test]
fn a_worker_paused_past_its_lease_says_nothing_of_the_step_it_lost() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let (inbox, out) = (root.join("inbox"), root.join("out"));
    std::fs::create_dir_all(&inbox).unwrap();
    let (_nats, urls, _) = single_server(root);
    let c = &write_config(root, "[nats]\nreplicas = 1\nlease_ttl_ms = 1000\nack_wait_ms = 2000\n");
    let collect = start_collect(c, &urls, &out, root);
    let w1 = start_worker(c, &urls, "w1", root);
    let ingest = start_ingest(c, &urls, &inbox, &root.join("ingest"), root);
    wait_started(&[&collect, &w1, &ingest], 40);

    // Worker 1 is paused as soon as it has accepted a view of site0: the step's fill (a few
    // hundred milliseconds) is still to come.
    let views = drop_session(&inbox, "site0", 41);
    let deadline = Instant::now() + Duration::from_secs(60);
    while !w1.log().lines().any(|l| l.contains("session{session=site0}") && l.contains("view accepted")) {
        assert!(Instant::now() < deadline, "worker 1 never filled site0:\n{}", w1.log());
        std::thread::sleep(Duration::from_millis(2));
    }
    w1.signal("-STOP");
    let w2 = start_worker(c, &urls, "w2", root);
    let named = |ev: &[Value], s: &str, f: &str| ev.iter().any(|e| e["session"] == s && e["file"] == f);
    wait_until("site0's result from worker 2", 60, &[&w2, &collect], || {
        let ev = events(&out);
        views.iter().all(|v| named(&ev, "site0", v)) && out.join("site0").join("result.json").is_file()
    });
    assert_eq!(w2.terminate(), Some(0));

    // Worker 1 resumes, loses site0's record to worker 2's, and saves site1's.
    w1.signal("-CONT");
    let dropped = "another worker saved the session meanwhile";
    wait_until("worker 1's step of site0 dropped", 30, &[&w1], || w1.log().contains(dropped));
    let views1 = drop_session(&inbox, "site1", 42);
    wait_until("site1's result from worker 1", 60, &[&w1, &collect], || {
        let ev = events(&out);
        views1.iter().all(|v| named(&ev, "site1", v)) && out.join("site1").join("result.json").is_file()
    });
    for p in [w1, ingest, collect] {
        let (name, log) = (p.name.clone(), p.log());
        assert_eq!(p.terminate(), Some(0), "{name}:\n{log}");
    }

    // site0 is told once: each view accepted once, each result number once, and the last
    // result said is the one collected.
    let ev: Vec<Value> = events(&out).into_iter().filter(|e| e["session"] == "site0").collect();
    for v in &views {
        let accepted = ev.iter().filter(|e| e["event"] == "view_accepted" && e["file"] == v.as_str()).count();
        assert_eq!(accepted, 1, "{v} accepted {accepted} times: {ev:#?}");
    }
    let numbers: Vec<u64> =
        ev.iter().filter(|e| e["event"] == "result_updated").map(|e| e["number"].as_u64().unwrap()).collect();
    let on_disk: Value =
        serde_json::from_slice(&std::fs::read(out.join("site0").join("result.json")).unwrap()).unwrap();
    assert_eq!(numbers.last().copied(), on_disk["number"].as_u64(), "results said: {numbers:?}");
    assert!(numbers.windows(2).all(|w| w[0] < w[1]), "a result number said twice: {numbers:?}");
}
