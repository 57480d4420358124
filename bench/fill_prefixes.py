#!/usr/bin/env python3
"""Does every view make the one-shot fill better? `clearview fill` with views 1..k, k = 1..n.

Issue 12 asks the service never to publish a result worse (by more than 0.3 dB, masked PSNR
against the truth) after a view, and to end within 0.5 dB of `clearview fill` with all the
views. Both hold at once only where the fill itself does not get worse as views are added:
where the fill with all views is more than 0.5 dB below the best fill with fewer, no publish
rule can meet both. This measures the fill alone, without the service.

Cases: folders with key.png, mask.png, truth.png and view-1.png.. (`service_cases`,
`fill_cases`). Usage:
    bench/.venv/bin/python bench/fill_prefixes.py DIR [DIR...] [--clearview BIN]
Each DIR is a case or a folder of cases.
"""
import argparse
import pathlib
import subprocess
import tempfile

import cv2

from fill_peer import load, masked_psnr


def cases(paths):
    for p in paths:
        if (p / "key.png").exists():
            yield p
        else:
            yield from sorted(c for c in p.iterdir() if (c / "key.png").exists())


def prefixes(binary, case, out):
    truth = load(case / "truth.png")
    mask = load(case / "mask.png", cv2.IMREAD_GRAYSCALE) > 127
    views = sorted(case.glob("view-*.png"), key=lambda p: int(p.stem.split("-")[1]))
    scores = []
    for k in range(1, len(views) + 1):
        cmd = [binary, "fill", "--keyframe", case / "key.png", "--mask", case / "mask.png", "--out", out, *views[:k]]
        r = subprocess.run([str(c) for c in cmd], capture_output=True, text=True)
        if r.returncode not in (0, 3):
            raise SystemExit(f"{case}: clearview fill exited {r.returncode}: {r.stderr}")
        scores.append(masked_psnr(load(out), truth, mask))
    return scores


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("dirs", type=pathlib.Path, nargs="+")
    ap.add_argument("--clearview", default="target/release/clearview")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        out = pathlib.Path(tmp) / "result.png"
        for case in cases(args.dirs):
            rows.append((case.name, prefixes(args.clearview, case, out)))
    print("| case | masked PSNR with views 1..k, k = 1.. | worst drop from a view | all − best dB |")
    print("|---|---|---:|---:|")
    dropped = apart = 0
    for name, s in rows:
        drop = max([0.0] + [s[i - 1] - s[i] for i in range(1, len(s))])
        gap = s[-1] - max(s)
        dropped += drop > 0.3
        apart += gap < -0.5
        print(f"| {name} | {' → '.join(f'{v:.2f}' for v in s)} | {drop:.2f} | {gap:+.2f} |")
    mean_all = sum(s[-1] for _, s in rows) / max(len(rows), 1)
    print(
        f"\n{len(rows)} cases: a view makes the fill worse by more than 0.3 dB in {dropped}; the fill with "
        f"all views is more than 0.5 dB below the best with fewer in {apart}; mean with all views {mean_all:.2f} dB"
    )


if __name__ == "__main__":
    main()
