#!/usr/bin/env python3
"""Masked-region quality of clearview's fill against two OpenCV peers, in one run.

Cases come from `cargo run --release --example fill_cases -- DIR` (keyframe with
occluders, mask, occluder-free truth, views). For every case:
  - telea:     cv2.inpaint(key, mask, 5, INPAINT_TELEA): single image;
  - multiview: SIFT + findHomography(USAC_MAGSAC) per view, warpPerspective into the
               keyframe, per-pixel median of the views that cover a pixel, Telea for
               what no view covers;
  - clearview: `clearview fill` (the release binary).
PSNR and SSIM are measured over the masked pixels only, against the truth.

Usage: bench/.venv/bin/python bench/fill_peer.py DIR [--clearview target/release/clearview]
"""
import argparse
import json
import pathlib
import statistics
import subprocess
import time
import warnings

import cv2
import numpy as np


def load(path, flags=cv2.IMREAD_COLOR):
    img = cv2.imread(str(path), flags)
    if img is None:
        raise SystemExit(f"{path}: cannot read")
    return img


def masked_psnr(a, b, mask):
    d = (a.astype(np.float64) - b.astype(np.float64))[mask]
    mse = np.mean(d * d)
    return float("inf") if mse == 0 else 10 * np.log10(255.0 ** 2 / mse)


def masked_ssim(a, b, mask):
    """SSIM (Wang et al. 2004: Gaussian window sigma 1.5, grey) averaged over the mask."""
    a = cv2.cvtColor(a, cv2.COLOR_BGR2GRAY).astype(np.float64)
    b = cv2.cvtColor(b, cv2.COLOR_BGR2GRAY).astype(np.float64)
    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2
    blur = lambda x: cv2.GaussianBlur(x, (11, 11), 1.5)
    ma, mb = blur(a), blur(b)
    va, vb, cov = blur(a * a) - ma * ma, blur(b * b) - mb * mb, blur(a * b) - ma * mb
    s = ((2 * ma * mb + c1) * (2 * cov + c2)) / ((ma * ma + mb * mb + c1) * (va + vb + c2))
    return float(np.mean(s[mask]))


def telea(key, mask8):
    return cv2.inpaint(key, mask8, 5, cv2.INPAINT_TELEA)


def multiview(key, mask8, views):
    sift = cv2.SIFT_create()
    gk = cv2.cvtColor(key, cv2.COLOR_BGR2GRAY)
    kk, dk = sift.detectAndCompute(gk, None)
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    h, w = key.shape[:2]
    warped, valid = [], []
    for v in views:
        kv, dv = sift.detectAndCompute(cv2.cvtColor(v, cv2.COLOR_BGR2GRAY), None)
        if dv is None or dk is None:
            continue
        good = [m for m, n in (p for p in matcher.knnMatch(dv, dk, k=2) if len(p) == 2) if m.distance < 0.75 * n.distance]
        if len(good) < 8:
            continue
        src = np.float32([kv[m.queryIdx].pt for m in good])
        dst = np.float32([kk[m.trainIdx].pt for m in good])
        H, _ = cv2.findHomography(src, dst, cv2.USAC_MAGSAC, 3.0)
        if H is None:
            continue
        warped.append(cv2.warpPerspective(v, H, (w, h), flags=cv2.INTER_LINEAR))
        ones = np.full(v.shape[:2], 255, np.uint8)
        valid.append(cv2.warpPerspective(ones, H, (w, h), flags=cv2.INTER_NEAREST) == 255)
    out = key.copy()
    hole = mask8 > 127
    uncovered = hole.copy()
    if warped:
        stack = np.stack(warped).astype(np.float32)
        ok = np.stack(valid)
        stack[~ok] = np.nan
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # pixels no view covers
            med = np.nanmedian(stack, axis=0)
        seen = ok.any(axis=0)
        fill = hole & seen
        out[fill] = np.clip(np.round(med[fill]), 0, 255).astype(np.uint8)
        uncovered = hole & ~seen
    if uncovered.any():
        rest = telea(out, (uncovered * 255).astype(np.uint8))
        out[uncovered] = rest[uncovered]
    return out


def clearview(binary, case, out):
    views = sorted(case.glob("view-*.png"))
    report = out.with_suffix(".json")
    cmd = [binary, "fill", "--keyframe", case / "key.png", "--mask", case / "mask.png", "--out", out, "--report", report, *views]
    r = subprocess.run([str(c) for c in cmd], capture_output=True, text=True)
    if r.returncode not in (0, 3):
        raise SystemExit(f"{case}: clearview fill exited {r.returncode}: {r.stderr}")
    return load(out), json.loads(report.read_text())


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("cases", type=pathlib.Path)
    ap.add_argument("--clearview", default="target/release/clearview")
    args = ap.parse_args()
    rows = []
    for case in sorted(p for p in args.cases.iterdir() if (p / "key.png").exists()):
        key, truth = load(case / "key.png"), load(case / "truth.png")
        mask8 = load(case / "mask.png", cv2.IMREAD_GRAYSCALE)
        mask = mask8 > 127
        views = [load(p) for p in sorted(case.glob("view-*.png"))]
        results = {}
        for name, fn in [
            ("telea", lambda: telea(key, mask8)),
            ("multiview", lambda: multiview(key, mask8, views)),
            ("clearview", lambda: clearview(args.clearview, case, case / "clearview.png")[0]),
        ]:
            t0 = time.perf_counter()
            img = fn()
            dt = time.perf_counter() - t0
            cv2.imwrite(str(case / f"{name}.png"), img)
            results[name] = (masked_psnr(img, truth, mask), masked_ssim(img, truth, mask), dt)
        rows.append((case.name, int(mask.sum()), len(views), results))

    names = ["telea", "multiview", "clearview"]
    print("| case | masked px | views | " + " | ".join(f"{n} PSNR dB / SSIM" for n in names) + " | clearview − multiview dB |")
    print("|---|---:|---:|" + "---:|" * len(names) + "---:|")
    for case, n, v, r in rows:
        cells = " | ".join(f"{r[m][0]:.2f} / {r[m][1]:.3f}" for m in names)
        print(f"| {case} | {n} | {v} | {cells} | {r['clearview'][0] - r['multiview'][0]:+.2f} |")
    means = {m: (statistics.mean(r[3][m][0] for r in rows), statistics.mean(r[3][m][1] for r in rows)) for m in names}
    cells = " | ".join(f"{means[m][0]:.2f} / {means[m][1]:.3f}" for m in names)
    print(f"| **mean** | | | {cells} | {means['clearview'][0] - means['multiview'][0]:+.2f} |")
    times = " | ".join(f"{m} {statistics.median(r[3][m][2] for r in rows) * 1e3:.0f} ms" for m in names)
    print(f"\nmedian wall time per case (clearview includes decoding, alignment and encoding): {times}")
    print(f"opencv {cv2.__version__}, numpy {np.__version__}")


if __name__ == "__main__":
    main()
