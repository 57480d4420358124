#!/usr/bin/env python3
"""The 12 MP command case (issue 12's speed target): `clearview fill` from JPEGs, whole
command, against the OpenCV multi-view median's whole pipeline (JPEG decoding, SIFT + MAGSAC
per view, warps, per-pixel median, Telea where no view sees, JPEG encoding), interleaved runs
in the same session; medians and their ratio.

Usage: cargo run --release --example fill_cases -- --large /tmp/large
       bench/.venv/bin/python bench/speed_12mp.py /tmp/large/large-12mp [--runs 3]
"""
import argparse
import pathlib
import statistics
import subprocess
import sys
import time

import cv2

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from fill_peer import load, masked_psnr, multiview  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("case", type=pathlib.Path)
    ap.add_argument("--clearview", default="target/release/clearview")
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    c = args.case
    views = sorted(c.glob("view-*.jpg"))
    ours, peer = [], []
    for run in range(args.runs):
        t0 = time.perf_counter()
        cmd = [args.clearview, "fill", "--keyframe", c / "key.jpg", "--mask", c / "mask.png", "--out", "/tmp/cv-12mp.jpg", *views]
        r = subprocess.run([str(x) for x in cmd], capture_output=True, text=True)
        if r.returncode not in (0, 3):
            raise SystemExit(r.stderr)
        ours.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        key, mask8 = load(c / "key.jpg"), load(c / "mask.png", cv2.IMREAD_GRAYSCALE)
        out = multiview(key, mask8, [load(v) for v in views])
        cv2.imwrite("/tmp/cv-12mp-opencv.jpg", out, [cv2.IMWRITE_JPEG_QUALITY, 92])
        peer.append(time.perf_counter() - t0)
        print(f"run {run + 1}: clearview {ours[-1]:.2f} s, opencv median {peer[-1]:.2f} s", flush=True)
    mo, mp = statistics.median(ours), statistics.median(peer)
    print(f"median: clearview fill {mo:.2f} s, OpenCV median pipeline {mp:.2f} s, ratio {mp / mo:.2f}x (target >= 3x)")
    print(f"opencv {cv2.__version__}")


if __name__ == "__main__":
    main()
