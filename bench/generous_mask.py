#!/usr/bin/env python3
"""A mask painted generously: what it costs the fill inside the occluder.

A person does not paint an occluder to the pixel, and `--mask auto` finds a superset of it
(its precision is about two thirds). The fill should not care: inside the true occluder it
copies the same views. Per case, `clearview fill` with the case's mask (the pasted occluders
grown by 2 px, as `service_cases` writes it) and with that mask dilated by each radius R
(an ellipse of 2R + 1 px), all scored by masked PSNR against the truth over the case's
mask, the region every fill must clear. Prints per case the PSNRs and each radius's
difference from the case's own mask, then the means and how many cases lose more than the
occlusion issue's 1.5 dB (its bound for a fill with the mask found against the true mask).

Usage: bench/.venv/bin/python bench/generous_mask.py --clearview BIN --work DIR [--radii 8,20] CASE...
(cases from `cargo run --release --example service_cases -- DIR --seed N`). Fills already
in DIR are read, not run again.
"""
import argparse
import pathlib
import subprocess

import cv2
import numpy as np

from automask_cases import LOSS_BOUND_DB, masked_psnr, read_case


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("cases", nargs="+", type=pathlib.Path)
    ap.add_argument("--clearview", default="target/release/clearview")
    ap.add_argument("--work", required=True, type=pathlib.Path)
    ap.add_argument("--radii", default="8,20")
    args = ap.parse_args()
    radii = [int(r) for r in args.radii.split(",")]
    args.work.mkdir(parents=True, exist_ok=True)
    print("| case | " + " | ".join(["case's mask"] + [f"+{r} px" for r in radii]) + " |")
    print("|---|" + "---:|" * (1 + len(radii)))
    rows = []
    for case in args.cases:
        read = read_case(case)
        if read is None:
            continue
        truth, scored, views = read
        row = []
        for r in [0] + radii:
            stem = f"{case.parent.name}-{case.name}.r{r}"
            out, mask = args.work / f"{stem}.png", case / "mask.png"
            if not out.exists():
                if r:
                    mask = args.work / f"{stem}.mask.png"
                    grown = (scored * 255).astype(np.uint8)
                    grown = cv2.dilate(grown, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
                    cv2.imwrite(str(mask), grown)
                cmd = [args.clearview, "fill", "--keyframe", str(case / "key.png"), "--mask", str(mask), "--out", str(out)]
                done = subprocess.run(cmd + views, capture_output=True, text=True)
                # Exit 3: every view refused; the result (the single-image fallback) is still
                # what the user gets, and is scored.
                if done.returncode == 3:
                    print(f"{case}: every view refused with the mask grown by {r} px")
                elif done.returncode != 0 or not out.exists():
                    raise SystemExit(f"{case}: clearview fill failed: {done.stderr[-500:]}")
            row.append(masked_psnr(cv2.imread(str(out)), truth, scored))
        rows.append(row)
        cells = [f"{row[0]:.2f}"] + [f"{x:.2f} ({x - row[0]:+.2f})" for x in row[1:]]
        print(f"| {case.name} | " + " | ".join(cells) + " |", flush=True)
    if not rows:
        return
    a = np.array(rows)
    print()
    print(f"{len(rows)} cases, mean over the case's mask: {a[:, 0].mean():.2f} dB with the case's mask")
    for j, r in enumerate(radii, start=1):
        d = a[:, j] - a[:, 0]
        print(
            f"  grown by {r} px: {a[:, j].mean():.2f} dB ({d.mean():+.2f}), worse by more than "
            f"{LOSS_BOUND_DB} dB in {(d < -LOSS_BOUND_DB).sum()}, worst {d.min():+.2f}"
        )


if __name__ == "__main__":
    main()
