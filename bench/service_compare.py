#!/usr/bin/env python3
"""Side by side: tables of `bench/service_eval.py` from two or more builds (issues 12, 14).

Each argument is LABEL=TABLE[,TABLE...] (the markdown each run of service_eval.py prints,
one per seed). Per case: the last published result and, in brackets, the worst drop; then,
over the cases every label has, the mean last result, how many meet the drop rule (no view
costs more than 0.3 dB), how many have a view that costs more than 2 dB, and the rows whose
published sequence differs from the first label's.

Usage: python3 bench/service_compare.py now=/work/bv_now1.md,/work/bv_now2.md main=/work/bv_main1.md,...
"""
import re
import sys

WORSE_DB, FALL_DB = 0.3, 2.0


def rows(path):
    """case → (published sequence, worst drop, last) of one service_eval table."""
    out = {}
    with open(path) as f:
        for line in f:
            c = [x.strip() for x in line.split("|")]
            if len(c) > 6 and re.fullmatch(r"[a-z0-9-]+-\d+", c[1]):
                out[c[1]] = (c[3], float(c[4]), float(c[5]))
    return out


def order(case):
    """Seed first, then the family, as the tables list them."""
    family, _, seed = case.rpartition("-")
    return (int(seed), family)


def main(args):
    if len(args) < 2 or any("=" not in a for a in args):
        sys.exit(__doc__)
    labels, runs = [], []
    for a in args:
        label, files = a.split("=", 1)
        merged = {}
        for f in files.split(","):
            merged.update(rows(f))
        labels.append(label)
        runs.append(merged)
    cases = sorted(set().union(*runs), key=order)
    print("| case | " + " | ".join(labels) + " |")
    print("|---|" + "---:|" * len(labels))
    for case in cases:
        cells = [f"{r[case][2]:.2f} ({r[case][1]:.2f})" if case in r else "—" for r in runs]
        print(f"| {case} | " + " | ".join(cells) + " |")
    common = [c for c in cases if all(c in r for r in runs)]
    if not common:
        return
    n = len(common)
    print(f"| **mean over {n}** | " + " | ".join(f"{sum(r[c][2] for c in common) / n:.2f}" for r in runs) + " |")
    print(f"| drop rule met | " + " | ".join(f"{sum(r[c][1] <= WORSE_DB for c in common)} of {n}" for r in runs) + " |")
    print(f"| a view costs > {FALL_DB:g} dB | " + " | ".join(f"{sum(r[c][1] > FALL_DB for c in common)} of {n}" for r in runs) + " |")
    first = runs[0]
    for label, r in zip(labels[1:], runs[1:]):
        moved = [c for c in common if r[c][0] != first[c][0]]
        print(f"\n{label}: {len(moved)} of {n} published sequences differ from {labels[0]}'s" + (": " if moved else ""))
        for c in moved:
            print(f"  {c}: {first[c][0]}\n  {' ' * len(c)}  {r[c][0]}")


if __name__ == "__main__":
    main(sys.argv[1:])
