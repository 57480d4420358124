#!/usr/bin/env python3
# Needs the probe binary of branch `twentyfirst-judge-trials` (CV_DEBUG=DIR dumps each trial).
# Usage: bench/.venv/bin/python bench/results/session21/judge.py BIN CASE... > trials.jsonl
"""judge.py BIN case... : per trial of the fill's view selection, the judge's q against the bar and the
trial's masked PSNR against the kept fill's. Prints JSON lines."""
import sys, subprocess, glob, pathlib, tempfile, re, json
import cv2, numpy as np
from concurrent.futures import ThreadPoolExecutor
b = sys.argv[1]
def psnr(o, t, m):
    mse = ((o[m] - t[m]) ** 2).mean() / 255.0**2
    return 10 * np.log10(1 / mse)
def run(c):
    c = pathlib.Path(c)
    views = sorted(glob.glob(str(c / "view-*.png")), key=lambda s: int(s.split("-")[-1].split(".")[0]))
    d = tempfile.mkdtemp(prefix="jd")
    r = subprocess.run([b, "fill", "--keyframe", str(c/"key.png"), "--mask", str(c/"mask.png"), "--out", d + "/out.png", *views],
                       capture_output=True, text=True, env={"CV_DEBUG": d, "PATH": "/usr/bin"})
    t = cv2.imread(str(c/"truth.png")).astype(float); m = cv2.imread(str(c/"mask.png"), 0) > 127
    out = []
    for line in r.stderr.splitlines():
        mm = re.match(r"trial \[([\d, ]*)\] q ([\d.]+) bar (None|Some\(([\d.]+)\))(?: g30 ([\d.]+) g60 ([\d.]+) g15 ([\d.]+))?", line)
        if not mm: continue
        vs = [int(x) for x in mm.group(1).split(",")]
        img = cv2.imread(f"{d}/trial_{'_'.join(map(str, vs))}.png").astype(float)
        out.append(dict(case=f"{c.parent.name}/{c.name}", views=vs, q=float(mm.group(2)),
                        bar=None if mm.group(3) == "None" else float(mm.group(4)), psnr=psnr(img, t, m), g30=mm.group(5) and float(mm.group(5)), g60=mm.group(6) and float(mm.group(6)), g15=mm.group(7) and float(mm.group(7))))
    return out
with ThreadPoolExecutor(2) as ex:
    for rows in ex.map(run, sys.argv[2:]):
        for r in rows: print(json.dumps(r), flush=True)
