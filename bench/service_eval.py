#!/usr/bin/env python3
"""Views arriving one by one in the service (`clearview run`), against the truth (issue 12).

For every case of `cargo run --release --example service_cases -- DIR [--seed N]` (a
keyframe with occluders, the mask, the occluder-free truth, the views in arrival order):
  1. starts the real service on a fresh folder, drops the mask and the keyframe, then the
     views one at a time, each once the service has handled the one before (its view event
     and, when the view calls for a fill, the fill's result_updated / result_not_better);
  2. after each view reads the *published* result (`result.png`) and measures its PSNR over
     the mask against the truth;
  3. runs `clearview fill` with all the views at once, and the OpenCV multi-view median
     (SIFT + MAGSAC, per-pixel median, Telea where no view sees: bench/fill_peer.py).
The issue's rule: no view makes the published result worse by more than 0.3 dB; the last
result within 0.5 dB of `clearview fill` with all views; the last result >= 1 dB above the
OpenCV median.

Usage: bench/.venv/bin/python bench/service_eval.py DIR [--clearview target/release/clearview]
           [--keep WORK_DIR] [--only NAME_OR_SUBSTRING] [--buffer N]
"""
import argparse
import json
import os
import pathlib
import shutil
import signal
import subprocess
import sys
import tempfile
import time

import cv2
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from fill_peer import load, masked_psnr, multiview  # noqa: E402

WORSE_DB, FILL_DB, PEER_DB = 0.3, 0.5, 1.0


def put(path, src):
    """Copies under a hidden name and renames, as a careful uploader does."""
    tmp = path.with_name(f".{path.name}.upload")
    shutil.copyfile(src, tmp)
    os.rename(tmp, path)


def events(outbox):
    try:
        text = (outbox / "events.jsonl").read_text()
    except FileNotFoundError:
        return []
    out = []
    for line in text.splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            break  # a line being written
    return out


def wait(outbox, what, pred, secs, log):
    deadline = time.time() + secs
    while True:
        ev = events(outbox)
        hit = pred(ev)
        if hit is not None:
            return ev, hit
        if time.time() > deadline:
            raise SystemExit(f"timed out waiting for {what}; log:\n{log.read_text()[-4000:]}")
        time.sleep(0.1)


FILL_DONE = ("result_updated", "result_not_better", "result_unchanged")


def settle(outbox, start, log, secs):
    """Waits until the service has been quiet (no new event, no fill under way) for a while."""
    n, quiet_since = len(events(outbox)), time.time()
    deadline = time.time() + secs
    while time.time() < deadline:
        time.sleep(0.2)
        m = len(events(outbox))
        if m != n:
            n, quiet_since = m, time.time()
        elif time.time() - quiet_since > 1.5:
            return
    raise SystemExit(f"the service did not settle; log:\n{log.read_text()[-4000:]}")


def start_service(binary, work, buffer=None):
    """`clearview run` on a fresh inbox, outbox and state under `work` (with `buffer`, the
    session's buffer of views: smaller than the views, it evicts): the process, the
    session folder, the outbox and the log."""
    inbox, outbox, state = work / "inbox", work / "outbox", work / "state"
    session = inbox / "s"
    for d in (session, outbox, state):
        d.mkdir(parents=True)
    cfg = work / "clearview.toml"
    cfg.write_text(
        f'[watch]\ndir = "{inbox}"\nquiet_period_ms = 300\n[output]\ndir = "{outbox}"\nhistory = 50\n'
        f'[state]\ndir = "{state}"\n[compute]\ngrace_period_ms = 15000\n'
        + (f"[session]\nbuffer = {buffer}\n" if buffer else "")
    )
    log = work / "service.log"
    env = dict(os.environ, CLEARVIEW_LOG=os.environ.get("CLEARVIEW_LOG", "clearview=info"))
    proc = subprocess.Popen([binary, "run", "--config", str(cfg)], stdout=subprocess.DEVNULL, stderr=log.open("w"), env=env)
    return proc, session, outbox, log


def stop_service(proc):
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(60)
    except subprocess.TimeoutExpired:
        proc.kill()


def run_service(binary, case, work, timeout, buffer=None):
    """Returns per step (the keyframe alone, then each view): what happened and the PSNR of
    the published result."""
    proc, session, outbox, log = start_service(binary, work, buffer)
    truth, mask = load(case / "truth.png"), load(case / "mask.png", cv2.IMREAD_GRAYSCALE) > 127
    steps = []
    try:
        put(session / "key.mask.png", case / "mask.png")
        put(session / "key.png", case / "key.png")
        wait(outbox, "the mask", lambda e: True if any(x["event"] == "mask_set" for x in e) else None, timeout, log)
        settle(outbox, 0, log, timeout)
        views = sorted(case.glob("view-*.png"), key=lambda p: int(p.stem.split("-")[1]))
        for i, v in enumerate([None] + views):
            if v is not None:
                name = f"v{i}.png"
                before = len(events(outbox))
                put(session / name, v)

                def handled(e, name=name, before=before):
                    about = [x for x in e[before:] if x.get("file") == name]
                    return about[0] if about else None

                ev, about = wait(outbox, f"{name} handled", handled, timeout, log)
                if about["event"] == "view_accepted" and about.get("improves"):
                    idx = len(ev)
                    wait(
                        outbox,
                        f"the fill after {name}",
                        lambda e, idx=before: True if any(x["event"] in FILL_DONE for x in e[idx:]) else None,
                        timeout,
                        log,
                    )
                settle(outbox, 0, log, timeout)
                new = events(outbox)[before:]
                fills = [x for x in new if x["event"] in FILL_DONE]
                what = about["event"] if about["event"] != "view_accepted" else (
                    "improves" if about.get("improves") else ("buffered" if about.get("buffered") else "not buffered")
                )
                outcome = fills[-1]["event"] if fills else "no fill"
                score = fills[-1].get("score") if fills else None
            else:
                what, outcome, score = "keyframe", None, None
                ups = [x for x in events(outbox) if x["event"] == "result_updated"]
                if ups:
                    outcome, score = "result_updated", ups[-1].get("score")
            res = work / "outbox" / "s" / "result.png"
            psnr = masked_psnr(load(res), truth, mask) if res.exists() else None
            rj = work / "outbox" / "s" / "result.json"
            rep = json.loads(rj.read_text()) if rj.exists() else {}
            used = sum(1 for x in rep.get("views", []) if x.get("status") == "used")
            steps.append(dict(view=what, outcome=outcome, score=score, psnr=psnr, used=used, confident=rep.get("confident")))
    finally:
        stop_service(proc)
    return steps


def run_mask_last(binary, case, work, timeout):
    """The keyframe, then every view (each once handled), then the mask: the published
    result once the service settles. A photographer who paints the mask last should get
    what the mask-first order gives (issue 12: the alignments depend on the mask)."""
    proc, session, outbox, log = start_service(binary, work)
    try:
        put(session / "key.png", case / "key.png")
        wait(outbox, "the keyframe", lambda e: True if any(x["event"] == "session_waiting" for x in e) else None, timeout, log)
        views = sorted(case.glob("view-*.png"), key=lambda p: int(p.stem.split("-")[1]))
        for i, v in enumerate(views, 1):
            name = f"v{i}.png"
            before = len(events(outbox))
            put(session / name, v)
            wait(outbox, f"{name} handled", lambda e, n=name, b=before: True if any(x.get("file") == n for x in e[b:]) else None, timeout, log)
        put(session / "key.mask.png", case / "mask.png")
        wait(outbox, "the mask", lambda e: True if any(x["event"] == "mask_set" for x in e) else None, timeout, log)
        settle(outbox, 0, log, timeout)
        res = outbox / "s" / "result.png"
        return load(res) if res.exists() else None
    finally:
        stop_service(proc)


def fill_all(binary, case, out):
    views = sorted(case.glob("view-*.png"), key=lambda p: int(p.stem.split("-")[1]))
    cmd = [binary, "fill", "--keyframe", case / "key.png", "--mask", case / "mask.png", "--out", out, *views]
    r = subprocess.run([str(c) for c in cmd], capture_output=True, text=True)
    if r.returncode not in (0, 3):
        raise SystemExit(f"{case}: clearview fill exited {r.returncode}: {r.stderr}")
    return load(out)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("cases", type=pathlib.Path)
    ap.add_argument("--clearview", default="target/release/clearview")
    ap.add_argument("--keep", type=pathlib.Path, help="keep the service folders here")
    ap.add_argument("--only", default="", help="only the case of this name, else the cases whose name contains this")
    ap.add_argument("--timeout", type=float, default=180)
    ap.add_argument("--buffer", type=int, help="the session's buffer of views (default: the service's)")
    ap.add_argument("--mask-last", action="store_true", help="also drop the mask after the views, and compare")
    ap.add_argument("--from-log", type=pathlib.Path, help="print the table of an earlier run's stderr (one JSON row a line)")
    args = ap.parse_args()
    if args.from_log:
        table([json.loads(l) for l in args.from_log.read_text().splitlines() if l.startswith("{")])
        return
    binary = str(pathlib.Path(args.clearview).resolve())
    rows = []
    cases = sorted(p for p in args.cases.iterdir() if (p / "key.png").exists())
    # "planar-1" names that case, not also nonplanar-1.
    exact = [p for p in cases if p.name == args.only]
    cases = exact or [p for p in cases if args.only in p.name]
    for case in cases:
        truth, key = load(case / "truth.png"), load(case / "key.png")
        mask8 = load(case / "mask.png", cv2.IMREAD_GRAYSCALE)
        mask = mask8 > 127
        work = (args.keep / case.name) if args.keep else pathlib.Path(tempfile.mkdtemp(prefix="cv-service-"))
        if work.exists() and args.keep:
            shutil.rmtree(work)
        work.mkdir(parents=True, exist_ok=True)
        t0 = time.time()
        steps = run_service(binary, case, work, args.timeout, args.buffer)
        all_img = fill_all(binary, case, work / "fill-all.png")
        views = [load(p) for p in sorted(case.glob("view-*.png"), key=lambda p: int(p.stem.split("-")[1]))]
        peer = multiview(key, mask8, views)
        cv2.imwrite(str(work / "opencv-median.png"), peer)
        p_all, p_peer = masked_psnr(all_img, truth, mask), masked_psnr(peer, truth, mask)
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
        seq = [s["psnr"] for s in steps[1:] if s["psnr"] is not None]
        # A view's effect: the published result after it against the one before it (the
        # first view against the keyframe-only result, when there was one).
        prev = [s["psnr"] for s in steps]
        drops = [prev[i - 1] - prev[i] for i in range(1, len(prev)) if prev[i - 1] is not None and prev[i] is not None]
        worst = max(drops, default=0.0)
        last = seq[-1] if seq else float("nan")
        row = dict(case=case.name, steps=steps, worst=worst, last=last, all=p_all, peer=p_peer, secs=time.time() - t0)
        if args.mask_last:
            late_dir = work.parent / (work.name + "-mask-last")
            shutil.rmtree(late_dir, ignore_errors=True)
            late = run_mask_last(binary, case, late_dir, args.timeout)
            row["mask_last"] = None if late is None else masked_psnr(late, truth, mask)
            if not args.keep:
                shutil.rmtree(late_dir, ignore_errors=True)
        rows.append(row)
        print(json.dumps(row), file=sys.stderr, flush=True)
    table(rows)


def table(rows):
    print("| case | views | published PSNR, keyframe only → after each view (what the view did) | worst drop | last | fill, all views | last − fill | OpenCV median | last − median | rule met |")
    print("|---|---:|---|---:|---:|---:|---:|---:|---:|---|")
    met = 0
    for r in rows:
        cells = []
        for s in r["steps"]:
            p = "—" if s["psnr"] is None else f"{s['psnr']:.2f}"
            tag = {"result_updated": "", "result_not_better": " kept", "no fill": " nofill", None: ""}.get(s["outcome"], f" {s['outcome']}")
            if s["view"] not in ("keyframe", "improves"):
                tag += f" ({s['view']})"
            cells.append(p + tag)
        ok = [r["worst"] <= WORSE_DB, abs(r["last"] - r["all"]) <= FILL_DB, r["last"] >= r["peer"] + PEER_DB]
        met += all(ok)
        flag = "yes" if all(ok) else "NO: " + ", ".join(
            n for n, o in zip(["a view made it worse", "last far from fill", "not 1 dB over median"], ok) if not o
        )
        print(
            f"| {r['case']} | {len(r['steps']) - 1} | {' → '.join(cells)} | {r['worst']:.2f} | {r['last']:.2f} | "
            f"{r['all']:.2f} | {r['last'] - r['all']:+.2f} | {r['peer']:.2f} | {r['last'] - r['peer']:+.2f} | {flag} |"
        )
    late = [r for r in rows if "mask_last" in r]
    if late:
        print()
        print("| case | mask first: last | mask last | fill, all views | mask last − fill |")
        print("|---|---:|---:|---:|---:|")
        for r in late:
            m = r["mask_last"]
            cell = "—" if m is None else f"{m:.2f}"
            diff = "—" if m is None else f"{m - r['all']:+.2f}"
            print(f"| {r['case']} | {r['last']:.2f} | {cell} | {r['all']:.2f} | {diff} |")
        print()
    if rows:
        mean = lambda k: float(np.mean([r[k] for r in rows]))
        print(
            f"| **mean** | | | {max(r['worst'] for r in rows):.2f} (max) | {mean('last'):.2f} | {mean('all'):.2f} | "
            f"{mean('last') - mean('all'):+.2f} | {mean('peer'):.2f} | {mean('last') - mean('peer'):+.2f} | {met}/{len(rows)} |"
        )


if __name__ == "__main__":
    main()
