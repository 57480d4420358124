#!/usr/bin/env python3
"""Issue 13's evaluation: clearview against OpenCV SIFT + MAGSAC on the cases where a good view
must not be rejected.

Three sets, built from ../shared/data by `prepare` into a work folder (default
/tmp/clearview-eval), each pair as key.<ext>, view.<ext> and H (keyframe -> view, 0-based
pixel centres, row-major):

  mv12   adjacent pairs of the real photo sets in multiview/ (building, hunt, ece, incline,
         roofs) and transient/ (in1 -> in2, in1 -> in3), upscaled with bicubic interpolation
         to about 12 MP and saved as JPEG quality 90: as soft as a real 12 MP frame.
         Ground truth: there is none in the data, so it is made at native size, where both
         methods are comfortable, and carried to 12 MP exactly (H12 = A H A^-1 with A the
         resize map x' = s (x + 0.5) - 0.5). At native size: SIFT (8000 features, ratio 0.8)
         + MAGSAC++ at 1 px, then least squares on the matches within 1 px of it, then ECC
         (gain-invariant, grey, 2 levels) from there, kept only if the warped overlap's
         normalised correlation improves and the fit moves by at most 1 px. The script prints the distance between the SIFT fit
         and the final reference for each pair (the reference's own uncertainty). The
         reference is SIFT-based, so if anything it favours the peer.
  occl   the 40 Oxford pairs (img1 -> img2..img6 of the 8 sequences) with occluders pasted
         into the keyframe (trees: textured foliage and a trunk; cars; people: about 30 % of
         the frame, seeded per pair) and a smaller one into the view (about 8 %). Ground
         truth: H1toNp.refined.
  clean  the 50 clean pairs: those 40 without occluders and HPatches v_churchill,
         v_wormhole 1 -> 2..6. Ground truth: H1toNp.refined where present, else H1toNp.

Sets for "real multi-view cases with partial overlap: no good view rejected" (`prepare
--sets mvnat,mvskip12,mvcrop,mvcrop12,mvfar`), each with the mv12 kind of reference, made at native
size from the two source photos:
  mvnat     every adjacent and skip-one pair of every multiview set (building, hunt, ece,
            incline, roofs) at native size, PNG (23 pairs);
  mvskip12  the skip-one pairs at about 12 MP, JPEG 90 (9; the adjacent ones are mv12);
  mvcrop    views cut from the adjacent and skip-one pairs' views at native size so that
            they see 30-60 % of the keyframe: per pair, the two windows of CROPS (halves,
            40 % strips, 70 % corners) whose share seen through the reference is in 30-60 %
            and nearest 45 % (42);
  mvcrop12  the same cut from the adjacent pairs at 12 MP (28);
  mvfar     the pairs three or more apart in their set, both ways, at native size, where the view sees
            at least 5 % of the keyframe and the reference rests on at least 40 SIFT +
            MAGSAC inliers (the others are left out, and said so): a view from far along
            the facade that sees its last strip.
A rejection of a view SIFT + MAGSAC aligns within 3 px is the failure these look for.

Error of an estimate: the median, over a grid of keyframe points (every 1 % of the width)
whose true image lies inside the view, of the distance in view pixels between where the
estimate and the truth send the point ("median transfer error over the part of the
keyframe the view sees"). A rejected view or no homography counts as an infinite error.

Both methods run as whole processes, one per pair, decoding included:
  - clearview: `clearview align --json KEY VIEW` (release build);
  - SIFT + MAGSAC: `bench/sift_magsac.py KEY VIEW` (cv2.SIFT_create() defaults, brute-force
    L2 2-NN, ratio 0.75, cv2.findHomography(..., cv2.USAC_MAGSAC, 3.0)).
The wall time of each process is recorded; `speed` times the 12 MP pairs several times.

Usage:
  bench/.venv/bin/python bench/align_eval.py prepare [--work DIR] [--data DIR] [--sets mv12,occl]
      (also simroll, others, mvnat, mvskip12, mvcrop, mvcrop12)
  bench/.venv/bin/python bench/align_eval.py run [--work DIR] [--sets mv12,occl,clean] [--only SUBSTR]
      [--no-peer | --peer-from TABLES.md] [--mask]
  (--mask: clearview is given the keyframe's mask over the pasted occluders, key.mask.png,
  as `fill` would give it; --peer-from: the peer's errors from an earlier run's tables.)
  bench/.venv/bin/python bench/align_eval.py speed [--work DIR] [--runs N] [--pairs a,b]
"""

import argparse
import json
import math
import statistics
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
PY = sys.executable
OXFORD = ["graf", "wall", "boat", "bark", "bikes", "trees", "leuven", "ubc"]
HPATCHES = ["v_churchill", "v_wormhole"]
MULTIVIEW = [
    ("parapano_building", ["building1.png", "building2.png", "building3.png"]),
    ("parapano_hunt", [f"hunt{i}.jpg" for i in range(1, 6)]),
    ("parapano_ece", [f"ece{i}.jpeg" for i in range(1, 8)]),
    ("cmu_incline", ["incline_L.png", "incline_R.png"]),
    ("vlfeat_roofs", ["roofs1.jpg", "roofs2.jpg"]),
]
TRANSIENT = [("night_street_cars", "in1.jpg", "in2.jpg"), ("night_street_cars", "in1.jpg", "in3.jpg")]
TARGET_PIXELS = 12e6


def read_h(path):
    v = [float(t) for t in Path(path).read_text().split()]
    assert len(v) == 9, path
    h = np.array(v, dtype=np.float64).reshape(3, 3)
    return h / h[2, 2]


def write_h(path, h):
    h = h / h[2, 2]
    Path(path).write_text("\n".join(" ".join(f"{x:.12e}" for x in row) for row in h) + "\n")


def image_path(seq, n):
    for ext in ("png", "jpg", "ppm"):
        p = seq / f"img{n}.{ext}"
        if p.exists():
            return p
    raise FileNotFoundError(f"{seq}: no img{n}")


def transfer_error(h, truth, key_size, view_size):
    """Median distance (view pixels) between h and truth over the keyframe points the view sees."""
    if h is None:
        return float("inf")
    w, hgt = key_size
    vw, vh = view_size
    step = max(2.0, w / 100.0)
    xs, ys = np.meshgrid(np.arange(0, w, step), np.arange(0, hgt, step))
    p = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
    t = truth @ p
    ok = t[2] > 1e-9
    t = t[:2] / np.where(ok, t[2], 1.0)
    ok &= (t[0] >= 0) & (t[0] <= vw - 1) & (t[1] >= 0) & (t[1] <= vh - 1)
    if not ok.any():
        return float("nan")
    e = h @ p[:, ok]
    if np.any(e[2] <= 1e-9):
        return float("inf")
    e = e[:2] / e[2]
    return float(np.median(np.linalg.norm(e - t[:, ok], axis=0)))


def seen_share(truth, key_size, view_size):
    w, hgt = key_size
    vw, vh = view_size
    xs, ys = np.meshgrid(np.linspace(0, w - 1, 60), np.linspace(0, hgt - 1, 60))
    p = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
    t = truth @ p
    ok = t[2] > 1e-9
    t = t[:2] / np.where(ok, t[2], 1.0)
    ok &= (t[0] >= 0) & (t[0] <= vw - 1) & (t[1] >= 0) & (t[1] <= vh - 1)
    return float(ok.mean())


# ---------------------------------------------------------------- ground truth (multiview)


def sift_reference(g1, g2):
    sift = cv2.SIFT_create(nfeatures=8000)
    k1, d1 = sift.detectAndCompute(g1, None)
    k2, d2 = sift.detectAndCompute(g2, None)
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d1, d2, k=2)
    good = [m[0] for m in knn if len(m) == 2 and m[0].distance < 0.8 * m[1].distance]
    src = np.float64([k1[m.queryIdx].pt for m in good])
    dst = np.float64([k2[m.trainIdx].pt for m in good])
    h, _ = cv2.findHomography(src, dst, cv2.USAC_MAGSAC, 1.0, maxIters=20000, confidence=0.9999)
    for _ in range(3):
        proj = cv2.perspectiveTransform(src.reshape(-1, 1, 2), h).reshape(-1, 2)
        inl = np.linalg.norm(proj - dst, axis=1) < 1.0
        h, _ = cv2.findHomography(src[inl], dst[inl], 0)
    return h / h[2, 2], int(inl.sum()), len(good)


def warp_ncc(g1, g2, h):
    """NCC of g1 against g2 warped into g1 by h (key -> view), over the overlap."""
    hgt, w = g1.shape
    warped = cv2.warpPerspective(g2, h, (w, hgt), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    valid = cv2.warpPerspective(np.full(g2.shape, 255, np.uint8), h, (w, hgt),
                                flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP) > 0
    a, b = g1[valid].astype(np.float64), warped[valid].astype(np.float64)
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / math.sqrt((a * a).sum() * (b * b).sum() + 1e-12))


def ecc_refine(g1, g2, h):
    """ECC from h (key -> view), coarse to fine over two levels; (H, ok)."""
    try:
        cur = h.copy()
        for lvl in (1, 0):
            s = 0.5 ** lvl
            a = cv2.resize(g1, None, fx=s, fy=s, interpolation=cv2.INTER_AREA) if lvl else g1
            b = cv2.resize(g2, None, fx=s, fy=s, interpolation=cv2.INTER_AREA) if lvl else g2
            sc = np.diag([s, s, 1.0])
            w0 = (sc @ cur @ np.linalg.inv(sc)).astype(np.float32)
            crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 60, 1e-6)
            # findTransformECC warps its second image (input) into the first (template):
            # template = key, input = view, warp maps template coordinates to input ones.
            _, w1 = cv2.findTransformECC(a.astype(np.float32), b.astype(np.float32), w0,
                                         cv2.MOTION_HOMOGRAPHY, crit, None, 5)
            cur = np.linalg.inv(sc) @ w1.astype(np.float64) @ sc
        return cur / cur[2, 2], True
    except cv2.error:
        return h, False


def resize_map(s):
    return np.array([[s, 0, (s - 1) / 2], [0, s, (s - 1) / 2], [0, 0, 1.0]])


# ---------------------------------------------------------------- occluders


def _texture(rng, shape, base, amp, scales=(1.5, 4.0)):
    out = np.zeros(shape + (3,), np.float32)
    for s in scales:
        n = rng.standard_normal(shape).astype(np.float32)
        n = cv2.GaussianBlur(n, (0, 0), s)
        n /= n.std() + 1e-6
        out += n[..., None] * (amp / len(scales))
    return np.clip(out + np.array(base, np.float32), 0, 255)


def _tree(rng, img, cover, x0, y0, size):
    hgt, w = img.shape[:2]
    mask = np.zeros((hgt, w), np.uint8)
    # Trunk.
    tw = max(3, int(size * 0.08))
    cv2.rectangle(mask, (int(x0 - tw / 2), int(y0)), (int(x0 + tw / 2), hgt - 1), 255, -1)
    trunk = mask.copy()
    # Crown: a cluster of discs.
    for _ in range(int(rng.integers(20, 40))):
        dx, dy = rng.normal(0, size * 0.35, 2)
        r = int(rng.uniform(0.12, 0.3) * size)
        cv2.circle(mask, (int(x0 + dx), int(y0 + dy)), max(r, 2), 255, -1)
    crown = (mask > 0) & ~(trunk > 0)
    leaves = _texture(rng, (hgt, w), rng.uniform([20, 60, 20], [60, 120, 60]), 70.0)
    bark = _texture(rng, (hgt, w), [40, 55, 75], 35.0, (1.0, 2.0))
    img[crown] = leaves[crown]
    img[trunk > 0] = bark[trunk > 0]
    cover |= mask > 0


def _car(rng, img, cover, x0, y0, size):
    hgt, w = img.shape[:2]
    cw, ch = int(size * 1.6), int(size * 0.55)
    body = np.zeros((hgt, w), np.uint8)
    cv2.rectangle(body, (int(x0 - cw / 2), int(y0 - ch / 2)), (int(x0 + cw / 2), int(y0 + ch / 2)), 255, -1)
    cv2.rectangle(body, (int(x0 - cw / 3), int(y0 - ch)), (int(x0 + cw / 3), int(y0)), 255, -1)
    colour = rng.uniform(30, 220, 3)
    grad = np.linspace(1.15, 0.8, hgt, dtype=np.float32)[:, None, None]
    paint = np.clip(colour[None, None, :] * grad + rng.normal(0, 3, (hgt, w, 3)), 0, 255)
    b = body > 0
    img[b] = paint[b]
    win = np.zeros((hgt, w), np.uint8)
    cv2.rectangle(win, (int(x0 - cw / 3.6), int(y0 - ch * 0.9)), (int(x0 + cw / 3.6), int(y0 - ch * 0.1)), 255, -1)
    img[win > 0] = (40, 40, 45)
    for wx in (x0 - cw / 3, x0 + cw / 3):
        cv2.circle(img, (int(wx), int(y0 + ch / 2)), int(ch * 0.35), (15, 15, 15), -1)
        cv2.circle(img, (int(wx), int(y0 + ch / 2)), int(ch * 0.15), (150, 150, 150), -1)
        cv2.circle(body, (int(wx), int(y0 + ch / 2)), int(ch * 0.35), 255, -1)
    cover |= body > 0


def _person(rng, img, cover, x0, y0, size):
    hgt, w = img.shape[:2]
    m = np.zeros((hgt, w), np.uint8)
    cv2.ellipse(m, (int(x0), int(y0)), (int(size * 0.18), int(size * 0.5)), 0, 0, 360, 255, -1)
    cv2.circle(m, (int(x0), int(y0 - size * 0.62)), int(size * 0.12), 255, -1)
    cloth = _texture(rng, (hgt, w), rng.uniform(20, 200, 3), 25.0)
    img[m > 0] = cloth[m > 0]
    cover |= m > 0


def paste_occluders(img, seed, share):
    """Pastes trees, cars and people until about `share` of the frame is covered."""
    rng = np.random.default_rng(seed)
    out = img.copy()
    hgt, w = img.shape[:2]
    cover = np.zeros((hgt, w), bool)
    short = min(w, hgt)
    kinds = [_tree, _car, _person]
    while cover.mean() < share:
        kind = kinds[int(rng.integers(0, 3))]
        size = rng.uniform(0.15, 0.35) * short
        x0, y0 = rng.uniform(0.05 * w, 0.95 * w), rng.uniform(0.2 * hgt, 0.9 * hgt)
        kind(rng, out, cover, x0, y0, size)
    return out, float(cover.mean()), cover


# ---------------------------------------------------------------- prepare


def prepare(args):
    data, work = Path(args.data), Path(args.work)
    pairs = []
    for folder, names in MULTIVIEW:
        for a, b in zip(names, names[1:]):
            pairs.append((data / "multiview" / folder, a, b))
    for folder, a, b in TRANSIENT:
        pairs.append((data / "transient" / folder, a, b))
    for folder, a, b in (pairs if "mv12" in args.sets.split(",") else []):
        name = f"{Path(a).stem}-{Path(b).stem}"
        write_multiview_pair(work / "mv12" / name, folder, a, b, scaled=True)
    for seq in (OXFORD if "occl" in args.sets.split(",") else []):
        sdir = data / "oxford" / seq
        key = cv2.imread(str(image_path(sdir, 1)))
        for n in range(2, 7):
            name = f"{seq}-1-{n}"
            view = cv2.imread(str(image_path(sdir, n)))
            d = work / "occl" / name
            d.mkdir(parents=True, exist_ok=True)
            seed = 1000 * OXFORD.index(seq) + n
            k_occ, kc, k_cover = paste_occluders(key, seed, 0.30)
            v_occ, vc, _ = paste_occluders(view, seed + 500, 0.08)
            cv2.imwrite(str(d / "key.png"), k_occ)
            # The mask a user would paint over the keyframe's occluders: their cover, grown
            # by 6 px (a generous brush); `run --mask` gives it to `clearview align --mask`.
            grown = cv2.dilate(k_cover.astype(np.uint8) * 255, np.ones((13, 13), np.uint8))
            cv2.imwrite(str(d / "key.mask.png"), grown)
            cv2.imwrite(str(d / "view.png"), v_occ)
            refined = sdir / f"H1to{n}p.refined"
            write_h(d / "H", read_h(refined if refined.exists() else sdir / f"H1to{n}p"))
            (d / "meta.json").write_text(json.dumps({"key_covered": kc, "view_covered": vc}))
        print(f"occl/{seq}: done", file=sys.stderr)
    if "simroll" in args.sets.split(","):
        prepare_simroll(data, work)
    if "others" in args.sets.split(","):
        prepare_others(data, work)
    for which in ("mvnat", "mvskip12", "mvcrop", "mvcrop12", "mvfar"):
        if which in args.sets.split(","):
            prepare_partial(data, work, which)
    # The clean pairs are read in place.


def multiview_reference(folder, a, b):
    """The reference homography a -> b at native size (SIFT + MAGSAC++ at 1 px, least
    squares, ECC polish kept only where it helps and moves the fit by at most 1 px), the two
    colour images and the reference's meta."""
    c1, c2 = cv2.imread(str(folder / a)), cv2.imread(str(folder / b))
    g1, g2 = cv2.cvtColor(c1, cv2.COLOR_BGR2GRAY), cv2.cvtColor(c2, cv2.COLOR_BGR2GRAY)
    h_sift, inl, n = sift_reference(g1, g2)
    h_ecc, ok = ecc_refine(g1, g2, h_sift)
    ncc0, ncc1 = warp_ncc(g1, g2, h_sift), (warp_ncc(g1, g2, h_ecc) if ok else -1)
    delta = transfer_error(h_ecc, h_sift, g1.shape[::-1], g2.shape[::-1]) if ok else float("nan")
    # ECC is a polish: taken only where it improves the correlation without moving the
    # fit by more than a pixel (a larger move means it locked onto another depth).
    use_ecc = ok and ncc1 > ncc0 and delta <= 1.0
    ref = h_ecc if use_ecc else h_sift
    meta = {"source": f"{folder.name}/{a} -> {b}", "sift_inliers": inl, "sift_matches": n,
            "ncc_sift": ncc0, "ncc_ecc": ncc1, "reference": "ecc" if use_ecc else "sift",
            "ecc_vs_sift_native_px": delta}
    return ref, c1, c2, meta


def upscale(c, ext_pixels=TARGET_PIXELS):
    """`c` upscaled (bicubic) to about 12 MP and the map of its pixel centres."""
    s = math.sqrt(ext_pixels / (c.shape[0] * c.shape[1]))
    big = cv2.resize(c, (round(c.shape[1] * s), round(c.shape[0] * s)), interpolation=cv2.INTER_CUBIC)
    sx, sy = big.shape[1] / c.shape[1], big.shape[0] / c.shape[0]
    return big, np.array([[sx, 0, (sx - 1) / 2], [0, sy, (sy - 1) / 2], [0, 0, 1.0]])


def write_multiview_pair(d, folder, a, b, scaled, crop=None):
    """One pair of real photos with its reference: at native size (PNG) or upscaled to about
    12 MP (JPEG quality 90); with `crop` = (x0, y0, x1, y1), shares of the view's width and
    height, the view is cut to that window (a view that sees part of the keyframe)."""
    d.mkdir(parents=True, exist_ok=True)
    ref, c1, c2, meta = multiview_reference(folder, a, b)
    if scaled:
        big1, a1 = upscale(c1)
        big2, a2 = upscale(c2)
        h = a2 @ ref @ np.linalg.inv(a1)
    else:
        big1, big2, h = c1, c2, ref
    if crop is not None:
        vh, vw = big2.shape[:2]
        x0, y0 = round(crop[0] * vw), round(crop[1] * vh)
        x1, y1 = round(crop[2] * vw), round(crop[3] * vh)
        big2 = big2[y0:y1, x0:x1].copy()
        h = np.array([[1, 0, -x0], [0, 1, -y0], [0, 0, 1.0]]) @ h
        meta["crop"] = [x0, y0, x1, y1]
    ext, opts = (".jpg", [cv2.IMWRITE_JPEG_QUALITY, 90]) if scaled else (".png", [])
    cv2.imwrite(str(d / ("key" + ext)), big1, opts)
    cv2.imwrite(str(d / ("view" + ext)), big2, opts)
    write_h(d / "H", h / h[2, 2])
    meta["size"] = [big1.shape[1], big1.shape[0]]
    meta["seen"] = seen_share(h, big1.shape[:2][::-1], big2.shape[:2][::-1])
    (d / "meta.json").write_text(json.dumps(meta))
    print(f"{d.parent.name}/{d.name}: {meta}", file=sys.stderr)
    return meta


# The view windows tried for the crop sets, as shares of the view (x0, y0, x1, y1).
CROPS = {"left": (0, 0, 0.5, 1), "right": (0.5, 0, 1, 1), "top": (0, 0, 1, 0.55), "bottom": (0, 0.45, 1, 1),
         "left40": (0, 0, 0.4, 1), "right40": (0.6, 0, 1, 1), "topleft": (0, 0, 0.7, 0.7),
         "bottomright": (0.3, 0.3, 1, 1)}


# A far pair (three or more apart in its set) is in mvfar only with a reference this sure.
MVFAR_INLIERS = 40
MVFAR_SEEN = 0.05


def prepare_partial(data, work, which):
    """Issue 13's "real multi-view cases with partial overlap": every adjacent and skip-one
    pair of every multiview set at native size (mvnat); the skip-one pairs at 12 MP
    (mvskip12; the adjacent ones are mv12); and views cut from the adjacent and skip-one
    pairs' views so that they see 30-60 % of the keyframe (mvcrop native, mvcrop12 at 12 MP,
    adjacent pairs only): for each pair the two windows of CROPS whose seen share, through the
    reference, falls in 30-60 % and is nearest 45 %."""
    pairs = []
    for folder, names in MULTIVIEW:
        steps = range(3, len(names)) if which == "mvfar" else (1, 2)
        for step in steps:
            for a, b in zip(names, names[step:]):
                pairs.append((data / "multiview" / folder, a, b, step))
                if which == "mvfar":
                    pairs.append((data / "multiview" / folder, b, a, step))
    for folder, a, b, step in pairs:
        name = f"{Path(a).stem}-{Path(b).stem}"
        if which == "mvfar":
            # Only where the reference can be trusted over the little the view sees: SIFT +
            # MAGSAC agreeing on at least MVFAR_INLIERS matches, the view seeing at least
            # MVFAR_SEEN of the keyframe.
            ref, c1, c2, meta = multiview_reference(folder, a, b)
            seen = seen_share(ref, c1.shape[:2][::-1], c2.shape[:2][::-1])
            if meta["sift_inliers"] >= MVFAR_INLIERS and seen >= MVFAR_SEEN:
                write_multiview_pair(work / which / name, folder, a, b, scaled=False)
            else:
                print(f"mvfar/{name}: left out ({meta['sift_inliers']} SIFT inliers, seen {seen:.0%})",
                      file=sys.stderr)
        elif which == "mvnat":
            write_multiview_pair(work / which / name, folder, a, b, scaled=False)
        elif which == "mvskip12" and step == 2:
            write_multiview_pair(work / which / name, folder, a, b, scaled=True)
        elif which in ("mvcrop", "mvcrop12") and (step == 1 or which == "mvcrop"):
            ref, c1, c2, _ = multiview_reference(folder, a, b)
            vh, vw = c2.shape[:2]
            shares = []
            for label, (x0, y0, x1, y1) in CROPS.items():
                t = np.array([[1, 0, -round(x0 * vw)], [0, 1, -round(y0 * vh)], [0, 0, 1.0]]) @ ref
                cw, ch = round(x1 * vw) - round(x0 * vw), round(y1 * vh) - round(y0 * vh)
                s = seen_share(t, c1.shape[:2][::-1], (cw, ch))
                if 0.3 <= s <= 0.6:
                    shares.append((abs(s - 0.45), label))
            for _, label in sorted(shares)[:2]:
                write_multiview_pair(work / which / f"{name}-{label}", folder, a, b,
                                     scaled=which == "mvcrop12", crop=CROPS[label])


# Real photos (native size) the generated scale/roll pairs are cut from.
SIMROLL_PHOTOS = [("parapano_hunt", "hunt3.jpg"), ("parapano_ece", "ece4.jpeg"), ("parapano_building", "building2.png")]
SIMROLL_SCALES = [0.3, 0.5, 0.7, 1.0, 1.4, 2.0, 2.8, 3.5]
SIMROLL_ROLLS = [0, 30, 60, 90, 135, 180]


def _camera(w, h, scale, roll_deg, tilt_deg, tilt_dir, cx, cy):
    """The map from an image's pixels to the photo's: a camera at (cx, cy) of the photo,
    `scale` photo pixels per image pixel, turned by `roll_deg`, tilted by `tilt_deg` about an
    axis in the image plane (a plane-induced homography K R K^-1 about the image centre)."""
    f = 1.2 * max(w, h)
    t, a = math.radians(tilt_deg), tilt_dir
    ax, ay = math.cos(a), math.sin(a)
    c, sn = math.cos(t), math.sin(t)
    r = np.array([[c + ax * ax * (1 - c), ax * ay * (1 - c), ay * sn],
                  [ax * ay * (1 - c), c + ay * ay * (1 - c), -ax * sn],
                  [-ay * sn, ax * sn, c]])
    k = np.array([[f, 0, 0], [0, f, 0], [0, 0, 1.0]])
    tilt = k @ r @ np.linalg.inv(k)
    rr = math.radians(roll_deg)
    sim = np.array([[scale * math.cos(rr), -scale * math.sin(rr), cx],
                    [scale * math.sin(rr), scale * math.cos(rr), cy], [0, 0, 1.0]])
    centre = np.array([[1, 0, -(w - 1) / 2], [0, 1, -(h - 1) / 2], [0, 0, 1.0]])
    return sim @ tilt @ centre


def _render(photo, m, w, h):
    """The image whose pixel x shows the photo at m x, blurred first so that shrinking does
    not alias (sigma from the map's scale at the centre)."""
    scale = math.sqrt(abs(np.linalg.det(m[:2, :2]) / m[2, 2] ** 2))
    src = photo
    if scale > 1.05:
        sigma = 0.5 * math.sqrt(scale * scale - 1)
        src = cv2.GaussianBlur(photo, (0, 0), sigma)
    return cv2.warpPerspective(src, m, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                               borderMode=cv2.BORDER_REFLECT)


def _inside(m, w, h, pw, ph):
    c = m @ np.array([[0, w - 1, 0, w - 1], [0, 0, h - 1, h - 1], [1, 1, 1, 1.0]])
    c = c[:2] / c[2]
    return c.min() >= 0 and (c[0] <= pw - 1).all() and (c[1] <= ph - 1).all()


def prepare_simroll(data, work):
    """Pairs with known truth at scales 0.3..3.5 (key -> view) and rolls 0..180 degrees, cut
    from real photos at native size (never enlarged beyond the photo's own pixels for the
    zoomed-in side), each with a seeded out-of-plane tilt of up to 8 degrees, noise and an
    exposure change. Both images are as large as the photo allows (at most 640 x 480), so
    at ×3.5 they are small: that is what such a zoom leaves of a 1440 x 1080 photo."""
    rng = np.random.default_rng(13)
    for folder, name in SIMROLL_PHOTOS:
        photo = cv2.imread(str(data / "multiview" / folder / name))
        ph, pw = photo.shape[:2]
        for sc in SIMROLL_SCALES:
            for roll in SIMROLL_ROLLS:
                tilt, tdir = rng.uniform(0, 8), rng.uniform(0, 2 * math.pi)
                # Photo pixels per image pixel: the zoomed-in side at the photo's own
                # resolution (1), the other `sc` (or 1/sc) times coarser.
                if sc < 1:
                    a_key, a_view = 1.0, 1.0 / sc
                else:
                    a_key, a_view = sc, 1.0
                w = 640
                while True:
                    h = w * 3 // 4
                    mk = _camera(w, h, a_key, 0, 0, 0, pw / 2, ph / 2)
                    mv = _camera(w, h, a_view, -roll, tilt, tdir, pw / 2 + rng.uniform(-0.03, 0.03) * pw,
                                 ph / 2 + rng.uniform(-0.03, 0.03) * ph)
                    if (_inside(mk, w, h, pw, ph) and _inside(mv, w, h, pw, ph)) or w <= 160:
                        break
                    w -= 16
                key = _render(photo, mk, w, h)
                view = _render(photo, mv, w, h)
                view = np.clip(view.astype(np.float32) * rng.uniform(0.8, 1.2) + rng.normal(0, 2.0, view.shape),
                               0, 255).astype(np.uint8)
                d = work / "simroll" / f"{Path(name).stem}-s{sc:.1f}-r{roll:03d}"
                d.mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(d / "key.png"), key)
                cv2.imwrite(str(d / "view.png"), view)
                # key -> photo -> view
                write_h(d / "H", np.linalg.inv(mv) @ mk)
                (d / "meta.json").write_text(json.dumps({"scale": sc, "roll": roll, "tilt": tilt, "size": [w, h]}))
        print(f"simroll/{name}: done", file=sys.stderr)


# Unrelated pairs: any acceptance is a false accept.
OTHERS = [("parapano_hunt/hunt3.jpg", "parapano_ece/ece4.jpeg"), ("parapano_building/building2.png", "vlfeat_roofs/roofs1.jpg"),
          ("parapano_ece/ece2.jpeg", "parapano_building/building1.png"), ("cmu_incline/incline_L.png", "parapano_hunt/hunt1.jpg"),
          ("vlfeat_roofs/roofs2.jpg", "parapano_ece/ece6.jpeg"), ("parapano_hunt/hunt5.jpg", "cmu_incline/incline_R.png")]


def prepare_others(data, work):
    """Pairs of different scenes, the view turned by 0, 90 or 150 degrees and zoomed by 1 or
    0.5: no view may be accepted (the H written is a placeholder far outside the view)."""
    for i, (a, b) in enumerate(OTHERS):
        ka, vb = cv2.imread(str(data / "multiview" / a)), cv2.imread(str(data / "multiview" / b))
        for roll, zoom in ((0, 1.0), (90, 1.0), (150, 0.5)):
            ph, pw = vb.shape[:2]
            w = min(640, pw)
            h = w * 3 // 4
            mv = _camera(w, h, 1.0 / zoom * min(pw / w, ph / h) * 0.7, -roll, 0, 0, pw / 2, ph / 2)
            view = _render(vb, mv, w, h)
            key = _render(ka, _camera(w, h, min(ka.shape[1] / w, ka.shape[0] / h) * 0.95, 0, 0, 0,
                                      ka.shape[1] / 2, ka.shape[0] / 2), w, h)
            d = work / "others" / f"{Path(a).stem}-{Path(b).stem}-r{roll:03d}-z{zoom:.1f}"
            d.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(d / "key.png"), key)
            cv2.imwrite(str(d / "view.png"), view)
            write_h(d / "H", np.array([[1, 0, 1e6], [0, 1, 1e6], [0, 0, 1.0]]))
    print("others: done", file=sys.stderr)


def clean_pairs(data):
    out = []
    for group, seqs in (("oxford", OXFORD), ("hpatches", HPATCHES)):
        for seq in seqs:
            sdir = data / group / seq
            for n in range(2, 7):
                refined = sdir / f"H1to{n}p.refined"
                out.append((f"{seq}-1-{n}", image_path(sdir, 1), image_path(sdir, n),
                            refined if refined.exists() else sdir / f"H1to{n}p"))
    return out


def set_pairs(work, data, which):
    if which == "clean":
        return clean_pairs(data)
    out = []
    for d in sorted((work / which).iterdir()):
        key = next(p for p in d.glob("key.*") if ".mask." not in p.name)
        view = next(d.glob("view.*"))
        out.append((d.name, key, view, d / "H"))
    return out


# ---------------------------------------------------------------- run


def run_clearview(binary, key, view, mask=None):
    start = time.perf_counter()
    extra = ["--mask", str(mask)] if mask else []
    p = subprocess.run([str(binary), "align", "--json", *extra, str(key), str(view)], capture_output=True, text=True)
    wall = time.perf_counter() - start
    if p.returncode not in (0, 3):
        return None, False, f"exit {p.returncode}: {p.stderr.strip()}", wall, {}
    r = json.loads(p.stdout)
    h = np.array(r["homography"]) if r.get("homography") else None
    return h, r["accepted"], r.get("reason"), wall, r


def run_sift(key, view):
    start = time.perf_counter()
    p = subprocess.run([PY, str(ROOT / "bench" / "sift_magsac.py"), str(key), str(view)],
                       capture_output=True, text=True)
    wall = time.perf_counter() - start
    r = json.loads(p.stdout)
    h = np.array(r["homography"]) if r.get("homography") else None
    return h, h is not None, None, wall, r


def fmt(e):
    if e is None or not np.isfinite(e):
        return "none"
    return f"{e:.2f}" if e < 100 else f"{e:.0f}"


def read_peer(path):
    """The SIFT + MAGSAC errors of an earlier run's tables (the peer is deterministic,
    `cv2.setRNGSeed(0)`, and slow at 12 MP): {(set, pair): px}, from the column headed
    "SIFT + MAGSAC px"; "none" is a refusal (infinite)."""
    out, which, col = {}, None, None
    for line in path.read_text().splitlines():
        if line.startswith("#### "):
            which, col = line.split()[1], None
        elif line.startswith("| pair |"):
            cells = [c.strip() for c in line.strip("|").split("|")]
            col = cells.index("SIFT + MAGSAC px")
        elif which and col is not None and line.startswith("| ") and not line.startswith("| **"):
            cells = [c.strip() for c in line.strip("|").split("|")]
            v = cells[col].split()[0]
            out[(which, cells[0])] = float("inf") if v == "none" else float(v)
    return out


def run(args):
    work, data, binary = Path(args.work), Path(args.data), Path(args.binary)
    peer = read_peer(Path(args.peer_from)) if args.peer_from else {}
    results = {}
    out = []
    for which in args.sets.split(","):
        rows = []
        for name, key, view, hfile in set_pairs(work, data, which):
            if args.only and args.only not in name:
                continue
            truth = read_h(hfile)
            ks = cv2.imread(str(key), cv2.IMREAD_UNCHANGED).shape[:2][::-1]
            vs = cv2.imread(str(view), cv2.IMREAD_UNCHANGED).shape[:2][::-1]
            mask = key.parent / "key.mask.png" if args.mask else None
            h_cv, acc, reason, t_cv, rep = run_clearview(binary, key, view,
                                                         mask if mask and mask.exists() else None)
            e_cv = transfer_error(h_cv, truth, ks, vs)
            e_cv_acc = e_cv if acc else float("inf")
            if (which, name) in peer:
                e_s, t_s = peer[(which, name)], float("nan")
            elif args.no_peer:
                e_s, t_s = float("nan"), float("nan")
            else:
                h_s, _, _, t_s, _ = run_sift(key, view)
                e_s = transfer_error(h_s, truth, ks, vs)
            seen = seen_share(truth, ks, vs)
            rows.append({"pair": name, "cv": e_cv_acc, "cv_raw": e_cv, "accepted": acc, "reason": reason,
                         "sift": e_s, "t_cv": t_cv, "t_sift": t_s, "seen": seen,
                         "inliers": rep.get("inliers", 0), "checked": rep.get("checked", 0)})
            print(f"{which}/{name}: clearview {fmt(e_cv)} {'ok' if acc else 'REJECTED: ' + str(reason)} "
                  f"({t_cv:.2f} s), SIFT {fmt(e_s)} ({t_s:.2f} s), seen {seen:.0%}", file=sys.stderr)
        results[which] = rows
        out.append(f"\n#### {which} ({len(rows)} pairs)\n")
        out.append("| pair | seen | clearview px | SIFT + MAGSAC px | clearview inliers / checked | clearview s | SIFT + MAGSAC s |")
        out.append("|---|---:|---:|---:|---:|---:|---:|")
        for r in rows:
            cvs = fmt(r["cv_raw"]) + ("" if r["accepted"] else " ✗")
            out.append(f"| {r['pair']} | {r['seen']:.0%} | {cvs} | {fmt(r['sift'])} | {r['inliers']} / {r['checked']} | "
                       f"{r['t_cv']:.2f} | {r['t_sift']:.2f} |")
        cv = [r["cv"] for r in rows]
        sf = [r["sift"] for r in rows]
        for label, f in (("within 1 px", lambda v: sum(e <= 1 for e in v)),
                         ("within 3 px", lambda v: sum(e <= 3 for e in v)),
                         ("within 5 px", lambda v: sum(e <= 5 for e in v)),
                         ("median px", lambda v: fmt(statistics.median(v)) if v else "-"),
                         ("false accepts (> 20 px)", None),
                         ("median process s", None)):
            if label.startswith("false"):
                fa_cv = sum(r["accepted"] and not r["cv_raw"] <= 20 for r in rows)
                fa_s = sum(np.isfinite(r["sift"]) and r["sift"] > 20 for r in rows)
                out.append(f"| **{label}** | | **{fa_cv}** | **{fa_s}** | | | |")
                # Issue 13's "no good view rejected": refusals of views the peer aligns within 3 px.
                good_rej = sum(not r["accepted"] and r["sift"] <= 3 for r in rows)
                out.append(f"| **rejected, SIFT + MAGSAC within 3 px** | | **{good_rej}** | | | | |")
            elif f is None:
                out.append(f"| **{label}** | | **{statistics.median([r['t_cv'] for r in rows]):.2f}** | "
                           f"**{statistics.median([r['t_sift'] for r in rows]):.2f}** | | | |")
            else:
                out.append(f"| **{label}** | | **{f(cv)}** | **{f(sf)}** | | | |")
        rej = [r for r in rows if not r["accepted"]]
        if rej:
            out.append("\nclearview's rejections (✗; its estimate's error is shown, a rejection counts as infinite):\n")
            out += [f"- {r['pair']}: {r['reason']}" for r in rej]
    if args.json_out:
        Path(args.json_out).write_text(json.dumps(results, default=float))
    print("\n".join(out))


def speed(args):
    work, binary = Path(args.work), Path(args.binary)
    names = args.pairs.split(",")
    out = ["| pair | size | clearview process median s | its runs | SIFT + MAGSAC process median s | its runs | ratio |",
           "|---|---|---:|---|---:|---|---:|"]
    for name in names:
        d = work / "mv12" / name
        key, view = d / "key.jpg", d / "view.jpg"
        tc, ts = [], []
        for _ in range(args.runs):
            tc.append(run_clearview(binary, key, view)[3])
            ts.append(run_sift(key, view)[3])
        mc, ms = statistics.median(tc), statistics.median(ts)
        size = json.loads((d / "meta.json").read_text())["size"]
        out.append(f"| {name} | {size[0]}×{size[1]} | {mc:.2f} | {', '.join(f'{t:.2f}' for t in tc)} | {ms:.2f} | "
                   f"{', '.join(f'{t:.2f}' for t in ts)} | {ms / mc:.1f}× |")
        print(out[-1], file=sys.stderr)
    out.append(f"\nWhole processes, alternated, decoding of both JPEGs included; OpenCV {cv2.__version__} "
               f"({cv2.getNumThreads()} threads); {args.runs} runs each.")
    print("\n".join(out))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("cmd", choices=["prepare", "run", "speed"])
    ap.add_argument("--work", default="/tmp/clearview-eval")
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data"))
    ap.add_argument("--binary", default=str(ROOT / "target" / "release" / "clearview"))
    ap.add_argument("--sets", default="mv12,occl,clean", help="also simroll, others, mvnat, mvskip12, mvcrop, mvcrop12, mvfar")
    ap.add_argument("--only", default="")
    ap.add_argument("--no-peer", action="store_true")
    ap.add_argument("--peer-from", default="", help="take SIFT + MAGSAC's errors from an earlier run's tables (.md)")
    ap.add_argument("--mask", action="store_true", help="give clearview the keyframe's mask where the set has one (occl)")
    ap.add_argument("--json-out", default="")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--pairs", default="hunt3-hunt4,roofs1-roofs2")
    args = ap.parse_args()
    {"prepare": prepare, "run": run, "speed": speed}[args.cmd](args)


if __name__ == "__main__":
    main()
