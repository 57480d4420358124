#!/usr/bin/env python3
"""A dense photometric check of rival homographies on a prepared 12 MP pair (issue 13).

Where the SIFT-based reference and clearview's estimate disagree on a scene that is not one
plane, which is right where? On a prepared pair of real photos (mv12, mvnat, mvskip12,
mvcrop), at the pair's native size (the source photos), each candidate
(key -> view) warps the view onto the keyframe; we report the normalised cross-correlation
(NCC) of the warped view with the keyframe over the whole overlap and per cell of a 4 x 4 grid
over the keyframe (textured cells only: a cell whose keyframe standard deviation is under 8
grey levels is "-"), and where ECC (gain-invariant, 2 levels) converges from each candidate and
how far it moves (a candidate ECC leaves in place is a local optimum of the photometric fit).

Usage:
  bench/.venv/bin/python bench/align_photometric.py PAIR [PAIR...] [--set mv12] [--work DIR]
      [--data DIR] [--binary PATH]
"""

import argparse
import json
import subprocess
from pathlib import Path

import cv2
import numpy as np

import align_eval as ae
from align_mv12_diag import resize_affine, source_images

ROOT = Path(__file__).resolve().parent.parent


def warped(g1, g2, h):
    hgt, w = g1.shape
    wv = cv2.warpPerspective(g2, h, (w, hgt), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    valid = cv2.warpPerspective(np.full(g2.shape, 255, np.uint8), h, (w, hgt),
                                flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP) > 0
    return wv.astype(np.float64), valid


def ncc(a, b):
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum() + 1e-12))


def cells(g1, wv, valid, n=4):
    hgt, w = g1.shape
    rows = []
    for j in range(n):
        row = []
        for i in range(n):
            ys, xs = slice(j * hgt // n, (j + 1) * hgt // n), slice(i * w // n, (i + 1) * w // n)
            a, b, v = g1[ys, xs].astype(np.float64), wv[ys, xs], valid[ys, xs]
            if v.mean() < 0.5 or a[v].std() < 8:
                row.append("-")
            else:
                row.append(f"{ncc(a[v], b[v]):.3f}")
        rows.append(" ".join(row))
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("pairs", nargs="+")
    ap.add_argument("--work", default="/tmp/clearview-eval")
    ap.add_argument("--set", default="mv12", help="a set of real pairs with a meta.json (mv12, mvnat, mvskip12)")
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data"))
    ap.add_argument("--binary", default=str(ROOT / "target" / "release" / "clearview"))
    args = ap.parse_args()
    for name in args.pairs:
        d = Path(args.work) / args.set / name
        key = next(p for p in d.glob("key.*") if ".mask." not in p.name)
        view = next(d.glob("view.*"))
        meta = json.loads((d / "meta.json").read_text())
        c1, c2 = source_images(args.data, meta)
        if "crop" in meta:  # a view cut from the source view (mvcrop: native pixels)
            if args.set != "mvcrop":
                raise SystemExit(f"{args.set}: only the native crops (mvcrop) are supported")
            x0, y0, x1, y1 = meta["crop"]
            c2 = c2[y0:y1, x0:x1]
        g1, g2 = cv2.cvtColor(c1, cv2.COLOR_BGR2GRAY), cv2.cvtColor(c2, cv2.COLOR_BGR2GRAY)
        big1 = cv2.imread(str(key), cv2.IMREAD_GRAYSCALE).shape[::-1]
        big2 = cv2.imread(str(view), cv2.IMREAD_GRAYSCALE).shape[::-1]
        a1, a2 = resize_affine(g1.shape, big1), resize_affine(g2.shape, big2)
        to_native = lambda h12: np.linalg.inv(a2) @ h12 @ a1  # noqa: E731
        p = subprocess.run([args.binary, "align", "--json", str(key), str(view)],
                           capture_output=True, text=True)
        r = json.loads(p.stdout)
        cands = {"reference": to_native(ae.read_h(d / "H"))}
        if r.get("homography"):
            cands["clearview"] = to_native(np.array(r["homography"]))
        print(f"### {name} ({meta['source']}, native {g1.shape[1]}x{g1.shape[0]})\n")
        print("| candidate | NCC overlap | NCC per cell (4 rows of 4) | ECC from it: NCC | ECC moved px | "
              "ECC end vs reference px | vs clearview px |")
        print("|---|---:|---|---:|---:|---:|---:|")
        for label, h in cands.items():
            wv, valid = warped(g1, g2, h)
            whole = ncc(g1[valid].astype(np.float64), wv[valid])
            he, ok = ae.ecc_refine(g1, g2, h)
            moved = ae.transfer_error(he, h, g1.shape[::-1], g2.shape[::-1]) if ok else float("nan")
            we, ve = warped(g1, g2, he)
            e_ncc = ncc(g1[ve].astype(np.float64), we[ve]) if ok else float("nan")
            vs = [ae.transfer_error(he, cands[k], g1.shape[::-1], g2.shape[::-1]) if k in cands else float("nan")
                  for k in ("reference", "clearview")]
            print(f"| {label} | {whole:.4f} | {' / '.join(cells(g1, wv, valid))} | {e_ncc:.4f} | {moved:.2f} | "
                  f"{vs[0]:.2f} | {vs[1]:.2f} |")
        print()


if __name__ == "__main__":
    main()
