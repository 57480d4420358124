#!/usr/bin/env python3
"""Which plane does an mv12 estimate lock to? A per-pair look at issue 13's 12 MP misses.

For each prepared mv12 pair (bench/align_eval.py prepare), against the pair's reference H
(SIFT 8000 + MAGSAC++ at 1 px at native size, carried to 12 MP):
  - clearview's H (`clearview align --json`, or --h-from a JSON of {pair: H});
  - SIFT (8000, ratio 0.8) matches at native size, carried to 12 MP, sorted by which
    homography they agree with within 3 px at 12 MP (about 1 native px): the reference
    only, clearview's only, both, neither. "Agree with the reference only" is the support
    the estimate gave up, "clearview's only" the support it chose instead;
  - the median transfer error per cell of a 4 x 4 grid over the keyframe ("-" = unseen);
  - an overview JPEG (keyframe at about 1000 px wide): green = agrees with the reference
    only, red = clearview's only, yellow = both.

Usage:
  bench/.venv/bin/python bench/align_mv12_diag.py [--work DIR] [--data DIR] [--pairs a,b]
      [--binary PATH] [--out bench/results/mv12_diag] [--h-from FILE.json]
"""

import argparse
import json
import subprocess
from pathlib import Path

import cv2
import numpy as np

import align_eval as ae

ROOT = Path(__file__).resolve().parent.parent


def source_images(data, meta):
    folder, names = meta["source"].split("/", 1)
    a, b = [n.strip() for n in names.split("->")]
    for base in ("multiview", "transient"):
        d = Path(data) / base / folder
        if (d / a).exists():
            return cv2.imread(str(d / a)), cv2.imread(str(d / b))
    raise FileNotFoundError(meta["source"])


def resize_affine(native_shape, big_size):
    sx, sy = big_size[0] / native_shape[1], big_size[1] / native_shape[0]
    return np.array([[sx, 0, (sx - 1) / 2], [0, sy, (sy - 1) / 2], [0, 0, 1.0]])


def project(h, pts):
    p = np.c_[pts, np.ones(len(pts))] @ h.T
    return p[:, :2] / p[:, 2:3]


def cell_errors(h, truth, ks, vs, n=4):
    w, hh = ks
    rows = []
    for j in range(n):
        row = []
        for i in range(n):
            xs, ys = np.meshgrid(np.linspace(i * w / n, (i + 1) * w / n, 12), np.linspace(j * hh / n, (j + 1) * hh / n, 12))
            p = np.c_[xs.ravel(), ys.ravel()]
            t = project(truth, p)
            ok = (t[:, 0] >= 0) & (t[:, 0] <= vs[0] - 1) & (t[:, 1] >= 0) & (t[:, 1] <= vs[1] - 1)
            if ok.mean() < 0.3:
                row.append("–")
                continue
            e = project(h, p[ok])
            row.append(f"{np.median(np.linalg.norm(e - t[ok], axis=1)):.1f}")
        rows.append(" ".join(row))
    return rows


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--work", default="/tmp/clearview-eval")
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data"))
    ap.add_argument("--pairs", default="building1-building2,ece1-ece2,ece2-ece3,ece5-ece6,ece6-ece7")
    ap.add_argument("--binary", default=str(ROOT / "target" / "release" / "clearview"))
    ap.add_argument("--out", default="")
    ap.add_argument("--h-from", default="")
    args = ap.parse_args()
    given = json.loads(Path(args.h_from).read_text()) if args.h_from else {}
    print("| pair | err px | SIFT matches | ref only | clearview only | both | neither | 4×4 error (rows) |")
    print("|---|---:|---:|---:|---:|---:|---:|---|")
    for name in args.pairs.split(","):
        d = Path(args.work) / "mv12" / name
        meta = json.loads((d / "meta.json").read_text())
        truth = ae.read_h(d / "H")
        if name in given:
            h = np.array(given[name], float)
        else:
            p = subprocess.run([args.binary, "align", "--json", str(d / "key.jpg"), str(d / "view.jpg")],
                               capture_output=True, text=True, check=True)
            h = np.array(json.loads(p.stdout)["homography"], float)
        c1, c2 = source_images(args.data, meta)
        ks = tuple(meta["size"])
        view_big = cv2.imread(str(d / "view.jpg"), cv2.IMREAD_REDUCED_GRAYSCALE_4)
        vs = (view_big.shape[1] * 4, view_big.shape[0] * 4)
        a1 = resize_affine(c1.shape, ks)
        a2 = resize_affine(c2.shape, vs)
        g1, g2 = cv2.cvtColor(c1, cv2.COLOR_BGR2GRAY), cv2.cvtColor(c2, cv2.COLOR_BGR2GRAY)
        sift = cv2.SIFT_create(nfeatures=8000)
        k1, d1 = sift.detectAndCompute(g1, None)
        k2, d2 = sift.detectAndCompute(g2, None)
        knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d1, d2, k=2)
        good = [m[0] for m in knn if len(m) == 2 and m[0].distance < 0.8 * m[1].distance]
        src = project(a1, np.float64([k1[m.queryIdx].pt for m in good]))
        dst = project(a2, np.float64([k2[m.trainIdx].pt for m in good]))
        rt = np.linalg.norm(project(truth, src) - dst, axis=1) < 3.0
        rc = np.linalg.norm(project(h, src) - dst, axis=1) < 3.0
        err = ae.transfer_error(h, truth, ks, vs)
        cells = cell_errors(h, truth, ks, vs)
        print(f"| {name} | {err:.2f} | {len(good)} | {(rt & ~rc).sum()} | {(rc & ~rt).sum()} | {(rt & rc).sum()} | "
              f"{(~rt & ~rc).sum()} | {' / '.join(cells)} |")
        if args.out:
            out = Path(args.out)
            out.mkdir(parents=True, exist_ok=True)
            s = 1000.0 / ks[0]
            img = cv2.resize(cv2.imread(str(d / "key.jpg")), None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
            for (x, y), t, c in zip(src, rt, rc):
                col = (0, 220, 220) if t and c else (0, 200, 0) if t else (0, 0, 230) if c else None
                if col:
                    cv2.circle(img, (int(x * s), int(y * s)), 3, col, -1)
            cv2.imwrite(str(out / f"{name}.jpg"), img, [cv2.IMWRITE_JPEG_QUALITY, 80])


if __name__ == "__main__":
    main()
