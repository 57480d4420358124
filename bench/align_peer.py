#!/usr/bin/env python3
"""clearview's alignment against OpenCV peers, on real pairs and on the benchmark's rendered pairs.

accuracy: for the 40 Oxford pairs (8 sequences, img1 -> img2..img6) and the 10 HPatches
  pairs (v_churchill, v_wormhole), the mean corner error (mean over img1's four corners of the
  distance between the corner mapped by the estimate and by the ground truth, 0-based pixel
  coordinates, corners at (0,0), (w-1,0), (w-1,h-1), (0,h-1)) of
    - clearview: the release binary, `clearview align --json KEY VIEW`, one process per pair;
    - SIFT + MAGSAC: cv2.SIFT_create() defaults, brute-force L2 2-NN, Lowe ratio 0.75,
      cv2.findHomography(..., cv2.USAC_MAGSAC, 3.0) (OpenCV's defaults otherwise);
    - ORB + LMedS: cv2.ORB_create(nfeatures=5000), brute-force Hamming 2-NN, ratio 0.75,
      cv2.findHomography(..., cv2.LMEDS).
  Ground truth: H1toNp.refined where present, else H1toNp; graf is also scored against the
  original H1toNp (its refined fits were pulled by the off-plane car roof in img1).
  Prints a Markdown section on stdout.

speed: times SIFT + MAGSAC (grey conversion, detection and description of both images,
  matching, estimation; decoding excluded) on PNG pairs written by
  `cargo run --release --example bench_pair`, median of several runs, and prints a Markdown
  table. Also checks the answer against the pair's true homography.

Usage:
  bench/.venv/bin/python bench/align_peer.py accuracy [--data DIR] [--binary PATH]
  bench/.venv/bin/python bench/align_peer.py speed DIR [DIR ...] [--runs N]
"""

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
OXFORD = ["graf", "wall", "boat", "bark", "bikes", "trees", "leuven", "ubc"]
HPATCHES = ["v_churchill", "v_wormhole"]
RATIO = 0.75
MAGSAC_THRESHOLD = 3.0
# An OpenCV estimate further off than this (mean corner error) counts as a failure.
FAIL_PX = 10.0


def read_h(path):
    v = [float(t) for t in path.read_text().split()]
    assert len(v) == 9, path
    return np.array(v, dtype=np.float64).reshape(3, 3)


def image_path(seq, n):
    for ext in ("png", "jpg", "ppm"):
        p = seq / f"img{n}.{ext}"
        if p.exists():
            return p
    raise FileNotFoundError(f"{seq}: no img{n}")


def corner_error(h, truth, w, hgt):
    """Mean distance over the image's corners mapped by h and by truth; inf if either fails."""
    if h is None:
        return float("inf")
    c = np.array([[0, 0, 1], [w - 1, 0, 1], [w - 1, hgt - 1, 1], [0, hgt - 1, 1]], dtype=np.float64).T
    a, b = h @ c, truth @ c
    if np.any(np.abs(a[2]) < 1e-12) or np.any(np.abs(b[2]) < 1e-12):
        return float("inf")
    a, b = a[:2] / a[2], b[:2] / b[2]
    return float(np.mean(np.linalg.norm(a - b, axis=0)))


def ratio_matches(desc1, desc2, norm):
    if desc1 is None or desc2 is None or len(desc1) < 2 or len(desc2) < 2:
        return []
    knn = cv2.BFMatcher(norm).knnMatch(desc1, desc2, k=2)
    return [m[0] for m in knn if len(m) == 2 and m[0].distance < RATIO * m[1].distance]


def estimate(detector, norm, method, g1, g2, threshold=3.0):
    """(H or None, number of ratio-test matches, inliers)."""
    k1, d1 = detector.detectAndCompute(g1, None)
    k2, d2 = detector.detectAndCompute(g2, None)
    good = ratio_matches(d1, d2, norm)
    if len(good) < 4:
        return None, len(good), 0
    src = np.float32([k1[m.queryIdx].pt for m in good]).reshape(-1, 1, 2)
    dst = np.float32([k2[m.trainIdx].pt for m in good]).reshape(-1, 1, 2)
    h, mask = cv2.findHomography(src, dst, method, threshold)
    if h is None:
        return None, len(good), 0
    return h, len(good), int(mask.sum())


def sift_magsac(g1, g2):
    return estimate(cv2.SIFT_create(), cv2.NORM_L2, cv2.USAC_MAGSAC, g1, g2, MAGSAC_THRESHOLD)


def orb_lmeds(g1, g2):
    return estimate(cv2.ORB_create(nfeatures=5000), cv2.NORM_HAMMING, cv2.LMEDS, g1, g2)


def clearview(binary, key, view):
    start = time.perf_counter()
    p = subprocess.run([str(binary), "align", "--json", str(key), str(view)], capture_output=True, text=True)
    wall_ms = (time.perf_counter() - start) * 1e3
    if p.returncode not in (0, 3):
        return {"exit": p.returncode, "error": p.stderr.strip(), "wall_ms": wall_ms}
    r = json.loads(p.stdout)
    r["exit"] = p.returncode
    r["wall_ms"] = wall_ms
    return r


def fmt(err, ok=True):
    if not np.isfinite(err):
        return "none"
    s = f"{err:.2f}" if err < 100 else f"{err:.0f}"
    return s if ok else f"{s} ✗"


def accuracy(args):
    data, binary = Path(args.data), Path(args.binary)
    if not binary.exists():
        sys.exit(f"{binary} is missing: cargo build --release")
    seqs = [(f"oxford/{s}", data / "oxford" / s) for s in OXFORD]
    seqs += [(f"hpatches/{s}", data / "hpatches" / s) for s in HPATCHES]
    rows, extra, notes = [], [], []
    for name, seq in seqs:
        key = image_path(seq, 1)
        g1 = cv2.imread(str(key), cv2.IMREAD_GRAYSCALE)
        hgt, w = g1.shape
        for n in range(2, 7):
            view = image_path(seq, n)
            g2 = cv2.imread(str(view), cv2.IMREAD_GRAYSCALE)
            refined = seq / f"H1to{n}p.refined"
            original = seq / f"H1to{n}p"
            truth = read_h(refined if refined.exists() else original)
            cv = clearview(binary, key, view)
            h_cv = np.array(cv["homography"]) if cv.get("homography") else None
            e_cv = corner_error(h_cv, truth, w, hgt)
            accepted = cv.get("accepted", False)
            h_sift, _, _ = sift_magsac(g1, g2)
            h_orb, _, _ = orb_lmeds(g1, g2)
            e_sift, e_orb = corner_error(h_sift, truth, w, hgt), corner_error(h_orb, truth, w, hgt)
            pair = f"{name} 1→{n}"
            rows.append(
                {
                    "pair": pair,
                    "cv": e_cv,
                    "accepted": accepted,
                    "inliers": cv.get("inliers", 0),
                    "time_ms": cv.get("time_ms", float("nan")),
                    "wall_ms": cv["wall_ms"],
                    "sift": e_sift,
                    "orb": e_orb,
                    "truth": "refined" if refined.exists() else "H1toNp",
                }
            )
            if not accepted:
                notes.append(f"- {pair}: {cv.get('reason') or cv.get('error')}")
            if name == "oxford/graf":
                t0 = read_h(original)
                extra.append(
                    (pair, corner_error(h_cv, t0, w, hgt), accepted, corner_error(h_sift, t0, w, hgt),
                     corner_error(h_orb, t0, w, hgt))
                )
            print(f"{pair}: clearview {e_cv:.3f} ({'accepted' if accepted else 'rejected'}), "
                  f"SIFT {e_sift:.3f}, ORB {e_orb:.3f}", file=sys.stderr)

    out = []
    out.append(f"Ground truth `H1toNp.refined` where present (all Oxford sequences), else `H1toNp` "
               f"(HPatches). Errors in pixels of img1; ✗ marks a miss: clearview rejected the pair "
               f"(its best estimate's error is still shown), or an OpenCV estimate is off by more than "
               f"{FAIL_PX:.0f} px; \"none\" = no homography. clearview ms = its own `time_ms` "
               f"(alignment, decoding excluded) / the process's wall time.\n")
    out.append("| pair | clearview | SIFT + MAGSAC | ORB + LMedS | clearview inliers | clearview ms |")
    out.append("|---|---:|---:|---:|---:|---:|")
    for r in rows:
        out.append(
            f"| {r['pair']} | {fmt(r['cv'], r['accepted'])} | {fmt(r['sift'], r['sift'] <= FAIL_PX)} | "
            f"{fmt(r['orb'], r['orb'] <= FAIL_PX)} | {r['inliers']} | {r['time_ms']:.0f} / {r['wall_ms']:.0f} |"
        )

    def summary(rs, label):
        cv = [r["cv"] if r["accepted"] else float("inf") for r in rs]
        sift = [r["sift"] for r in rs]
        orb = [r["orb"] for r in rs]
        lines = []
        for what, f in (
            ("under 1 px", lambda v: sum(e < 1 for e in v)),
            ("under 3 px", lambda v: sum(e < 3 for e in v)),
            ("median error px", lambda v: f"{statistics.median(v):.2f}"),
        ):
            lines.append(f"| **{label}: {what}** | **{f(cv)}** | **{f(sift)}** | **{f(orb)}** | | |")
        return lines

    oxford = [r for r in rows if r["pair"].startswith("oxford")]
    hp = [r for r in rows if r["pair"].startswith("hpatches")]
    out += summary(oxford, f"Oxford ({len(oxford)})")
    out += summary(hp, f"HPatches ({len(hp)})")
    out += summary(rows, f"all ({len(rows)})")
    rej = sum(not r["accepted"] for r in rows)
    out.append("")
    out.append(f"clearview accepted {len(rows) - rej} of {len(rows)} pairs (a rejected pair counts as a miss "
               f"in the summary: infinite error). SIFT failures (> {FAIL_PX:.0f} px or none): "
               f"{sum(not r['sift'] <= FAIL_PX for r in rows)}; ORB failures: {sum(not r['orb'] <= FAIL_PX for r in rows)}.")
    if notes:
        out.append("\nclearview's rejections, with its reason:\n")
        out += notes
    out.append("\ngraf against the original `H1toNp` (img1's car roof, in front of the wall along the bottom, "
               "pulls the dense refined fit; on the wall itself clearview's estimate agrees with the images "
               "better than the refined truth, see `tests/oxford_align.rs`):\n")
    out.append("| pair | clearview | SIFT + MAGSAC | ORB + LMedS |")
    out.append("|---|---:|---:|---:|")
    for pair, e_cv, acc, e_sift, e_orb in extra:
        out.append(f"| {pair} | {fmt(e_cv, acc)} | {fmt(e_sift, e_sift <= FAIL_PX)} | {fmt(e_orb, e_orb <= FAIL_PX)} |")
    print("\n".join(out))


def speed(args):
    cv2.setRNGSeed(0)
    binary = Path(args.binary)
    out = ["| pair | size | SIFT + MAGSAC median ms | its runs (ms) | of which grey + SIFT detection, median | SIFT keypoints | its error px | clearview CLI `time_ms` median | its error px |",
           "|---|---|---:|---|---:|---|---:|---:|---:|"]
    for d in args.dirs:
        d = Path(d)
        c1, c2 = cv2.imread(str(d / "key.png")), cv2.imread(str(d / "view.png"))
        truth = read_h(d / "H")
        hgt, w = c1.shape[:2]
        times, detect, last = [], [], None
        for _ in range(args.runs):
            start = time.perf_counter()
            g1 = cv2.cvtColor(c1, cv2.COLOR_BGR2GRAY)
            g2 = cv2.cvtColor(c2, cv2.COLOR_BGR2GRAY)
            sift = cv2.SIFT_create()
            k1, d1 = sift.detectAndCompute(g1, None)
            k2, d2 = sift.detectAndCompute(g2, None)
            detected = time.perf_counter()
            good = ratio_matches(d1, d2, cv2.NORM_L2)
            src = np.float32([k1[m.queryIdx].pt for m in good]).reshape(-1, 1, 2)
            dst = np.float32([k2[m.trainIdx].pt for m in good]).reshape(-1, 1, 2)
            h, _ = cv2.findHomography(src, dst, cv2.USAC_MAGSAC, MAGSAC_THRESHOLD)
            end = time.perf_counter()
            times.append((end - start) * 1e3)
            detect.append((detected - start) * 1e3)
            last = (h, len(k1), len(k2))
        err = corner_error(last[0], truth, w, hgt)
        # clearview on the same files, one process each: its own time_ms (luminance,
        # both frames and the alignment; decoding excluded), as a cross-check of criterion.
        cv_times, cv_err = [], float("nan")
        if binary.exists():
            for _ in range(args.runs):
                r = clearview(binary, d / "key.png", d / "view.png")
                cv_times.append(r.get("time_ms", float("nan")))
                h = np.array(r["homography"]) if r.get("homography") else None
                cv_err = corner_error(h, truth, w, hgt)
        cv_med = f"{statistics.median(cv_times):.0f}" if cv_times else "n/a"
        out.append(f"| {d.name} | {w}×{hgt} | {statistics.median(times):.0f} | "
                   f"{', '.join(f'{t:.0f}' for t in times)} | {statistics.median(detect):.0f} | "
                   f"{last[1]} + {last[2]} | {err:.3f} | {cv_med} | {cv_err:.3f} |")
        print(f"{d}: SIFT {statistics.median(times):.0f} ms, clearview CLI {cv_med} ms", file=sys.stderr)
    out.append(f"\nOpenCV {cv2.__version__} ({cv2.getNumThreads()} threads), NumPy {np.__version__}, "
               f"Python {sys.version.split()[0]}; {args.runs} runs each, grey conversion included, decoding excluded.")
    print("\n".join(out))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    a = sub.add_parser("accuracy")
    a.add_argument("--data", default=str(ROOT.parent / "shared" / "data"))
    a.add_argument("--binary", default=str(ROOT / "target" / "release" / "clearview"))
    s = sub.add_parser("speed")
    s.add_argument("dirs", nargs="+")
    s.add_argument("--runs", type=int, default=7)
    s.add_argument("--binary", default=str(ROOT / "target" / "release" / "clearview"))
    args = ap.parse_args()
    accuracy(args) if args.cmd == "accuracy" else speed(args)


if __name__ == "__main__":
    main()
