#!/usr/bin/env python3
"""Issue 13's video target over many rendered walks at once: runs bench/align_video.py for each
seed (both cases: the first frame with no flag, and `--keyframe-frame 30`), `--jobs` at a time,
into WORK/<seed>/, then prints one row per seed (masked PSNR, target met or not) and the
totals: cases, targets met, mean masked PSNR. With `--base DIR` (the WORK of an earlier run,
another binary), each case is printed beside the base's figure with the difference, and on
the cases both runs have, the two totals side by side and the cases that gained or lost more
than 0.3 dB: a change to the walk is judged on the
whole set, not on the walks it was made for.

A seed whose WORK/<seed>/results.json already exists is not run again (delete it to re-run),
so a stopped run resumes, and a base run is read as it was left. Runs are deterministic: the
same binary gives the same figures.

Usage:
  bench/.venv/bin/python bench/walk_set.py --binary PATH --work DIR [--seeds 13-20,25-40]
      [--jobs 2] [--base DIR]
"""

import argparse
import json
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CASES = ["key0-noflag", "key30-flag"]
SIGNIFICANT_DB = 0.3


def seeds_of(spec):
    """`13-20,25,27-28` as a list of seeds."""
    out = []
    for part in spec.split(","):
        a, _, b = part.partition("-")
        out.extend(range(int(a), int(b or a) + 1))
    return out


def run_seed(binary, work, seed):
    results = work / str(seed) / "results.json"
    if not results.exists():
        log = work / f"{seed}.md"
        with open(log, "w") as out:
            subprocess.run([sys.executable, str(ROOT / "bench" / "align_video.py"), "--binary", str(binary),
                            "--seed", str(seed), "--work", str(work / str(seed))],
                           stdout=out, stderr=subprocess.STDOUT, check=False)
    return read(work, seed)


def read(work, seed):
    """{case: (psnr, met)} of one seed's run, or {} when it has none."""
    path = Path(work) / str(seed) / "results.json"
    if not path.exists():
        return {}
    rows = json.loads(path.read_text())
    return {r["case"]: (r["psnr"], r["met"]) for r in rows if "psnr" in r}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--binary", default=str(ROOT / "target" / "release" / "clearview"))
    ap.add_argument("--work", required=True)
    ap.add_argument("--seeds", default="13-20,25-40")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--base", help="the WORK folder of an earlier run to compare with")
    args = ap.parse_args()
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    seeds = seeds_of(args.seeds)
    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        runs = dict(zip(seeds, pool.map(lambda s: run_seed(args.binary, work, s), seeds)))

    base = {s: read(args.base, s) for s in seeds} if args.base else {}
    head = "| seed | " + " | ".join(f"{c} dB{' (base, diff)' if base else ''} | met" for c in CASES) + " |"
    print(head)
    print("|---" * (1 + 2 * len(CASES)) + "|")
    psnrs, met = [], 0
    # Cases both runs have: (this run's psnr and met, the base's).
    pairs = []
    for s in seeds:
        cells = []
        for c in CASES:
            if c not in runs[s]:
                cells += ["–", "–"]
                continue
            p, ok = runs[s][c]
            psnrs.append(p)
            met += ok
            cell = f"{p:.2f}"
            if c in base.get(s, {}):
                b, b_ok = base[s][c]
                pairs.append(((p, ok), (b, b_ok)))
                cell += f" ({b:.2f}, {p - b:+.2f})"
            cells += [cell, "yes" if ok else "**no**"]
        print(f"| {s} | " + " | ".join(cells) + " |")
    print()
    print(f"cases {len(psnrs)}, target met {met}, mean masked PSNR {mean(psnrs):.2f} dB")
    if pairs:
        ours, theirs = zip(*pairs)
        diffs = [p - b for (p, _), (b, _) in pairs]
        print(f"on the {len(pairs)} cases the base has: target met {sum(ok for _, ok in ours)} against "
              f"{sum(ok for _, ok in theirs)}, mean {mean([p for p, _ in ours]):.2f} against "
              f"{mean([b for b, _ in theirs]):.2f} dB; gained > {SIGNIFICANT_DB} dB: "
              f"{sum(d > SIGNIFICANT_DB for d in diffs)}, lost > {SIGNIFICANT_DB} dB: "
              f"{sum(d < -SIGNIFICANT_DB for d in diffs)}")


def mean(values):
    return sum(values) / max(1, len(values))

if __name__ == "__main__":
    main()
