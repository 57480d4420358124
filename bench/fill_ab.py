#!/usr/bin/env python3
"""One-shot `clearview fill` of every case with several binaries, side by side: masked PSNR
against the truth per case and binary, the last binary's difference from the first, and the
mean difference. A change to the fill is judged on the whole set, not on the case it was made
for: the cases it loses more than 0.3 dB on are marked `<<`, those it gains on `>>`.

Cases: folders with key.png, mask.png, truth.png and view-1.png.. (`service_cases`,
`fill_cases`). A binary may be a wrapper script (to set an environment variable). The views
are given in their numbers' order; `BIN@reversed` gives them to BIN the other way round, and
`BIN@shuffled:K` in an order shuffled by seed K and the case's path (the same every run).
Usage:
    bench/.venv/bin/python bench/fill_ab.py BIN1,BIN2[,...] CASE [CASE...] [--jobs 2]
"""
import argparse
import pathlib
import random
import subprocess
import tempfile
import zlib
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np

from fill_peer import load, masked_psnr

SIGNIFICANT_DB = 0.3


def views_of(case):
    return sorted(case.glob("view-*.png"), key=lambda p: int(p.stem.split("-")[1]))


def parse_order(spec):
    """A binary's `@` suffix: None (as numbered), "reversed", or the seed K of "shuffled:K";
    anything else stops the run before any case is filled."""
    if spec in ("", "reversed"):
        return spec or None
    kind, _, seed = spec.partition(":")
    if kind == "shuffled" and seed.isdigit():
        return int(seed)
    raise SystemExit(f"unknown order @{spec}: give @reversed or @shuffled:K (K a whole number)")


def views_in(case, order):
    """The case's views in `order` (`parse_order`): as numbered, reversed, or shuffled by
    the seed and the case's path (the same every run)."""
    views = views_of(case)
    if order == "reversed":
        return views[::-1]
    if isinstance(order, int):
        random.Random(order * 1000003 + zlib.crc32(str(case).encode())).shuffle(views)
    return views


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("binaries")
    ap.add_argument("cases", nargs="+", type=pathlib.Path)
    ap.add_argument("--jobs", type=int, default=2)
    args = ap.parse_args()
    binaries = [(b, parse_order(spec)) for b, _, spec in (x.partition("@") for x in args.binaries.split(","))]
    work = pathlib.Path(tempfile.mkdtemp(prefix="fill-ab-"))

    def run(job):
        k, (b, order), case = job
        out = work / f"{case.parent.name}_{case.name}_{k}.png"
        cmd = [b, "fill", "--keyframe", str(case / "key.png"), "--mask", str(case / "mask.png"), "--out", str(out)]
        if subprocess.run(cmd + [str(v) for v in views_in(case, order)], capture_output=True).returncode != 0:
            return float("nan")
        mask = load(case / "mask.png", cv2.IMREAD_GRAYSCALE) > 127
        return masked_psnr(load(out), load(case / "truth.png"), mask)

    jobs = [(k, b, c) for c in args.cases for k, b in enumerate(binaries)]
    with ThreadPoolExecutor(args.jobs) as ex:
        scores = list(ex.map(run, jobs))
    per_case = {}
    for (k, _, c), s in zip(jobs, scores):
        per_case.setdefault(c, [None] * len(binaries))[k] = s
    diffs = []
    for c, row in per_case.items():
        d = row[-1] - row[0]
        diffs.append(d)
        mark = " <<" if d < -SIGNIFICANT_DB else (" >>" if d > SIGNIFICANT_DB else "")
        cells = " ".join(f"{v:6.2f}" for v in row)
        print(f"{c.parent.name}/{c.name:28s} {cells}  {d:+.2f}{mark}")
    means = " ".join(f"{np.nanmean([r[k] for r in per_case.values()]):.3f}" for k in range(len(binaries)))
    print(f"mean diff {np.nanmean(diffs):+.3f} over {len(diffs)}; means {means}")


if __name__ == "__main__":
    main()
