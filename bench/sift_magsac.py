#!/usr/bin/env python3
"""The OpenCV peer as one whole process: KEY VIEW in, {"homography": rows | null, ...} out.

cv2.SIFT_create() defaults, brute-force L2 2-NN, Lowe ratio 0.75,
cv2.findHomography(..., cv2.USAC_MAGSAC, 3.0). Decoding included (cv2.imread, grey).
Used by bench/align_eval.py for accuracy and for the whole-process speed comparison.
"""

import json
import sys

import cv2
import numpy as np


def main():
    cv2.setRNGSeed(0)
    g1 = cv2.imread(sys.argv[1], cv2.IMREAD_GRAYSCALE)
    g2 = cv2.imread(sys.argv[2], cv2.IMREAD_GRAYSCALE)
    sift = cv2.SIFT_create()
    k1, d1 = sift.detectAndCompute(g1, None)
    k2, d2 = sift.detectAndCompute(g2, None)
    h, matches, inliers = None, 0, 0
    if d1 is not None and d2 is not None and len(d1) >= 2 and len(d2) >= 2:
        knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d1, d2, k=2)
        good = [m[0] for m in knn if len(m) == 2 and m[0].distance < 0.75 * m[1].distance]
        matches = len(good)
        if len(good) >= 4:
            src = np.float32([k1[m.queryIdx].pt for m in good]).reshape(-1, 1, 2)
            dst = np.float32([k2[m.trainIdx].pt for m in good]).reshape(-1, 1, 2)
            h, mask = cv2.findHomography(src, dst, cv2.USAC_MAGSAC, 3.0)
            if h is not None:
                inliers = int(mask.sum())
    out = {"homography": None if h is None else (h / h[2, 2]).tolist(), "matches": matches, "inliers": inliers,
           "keypoints": [len(k1), len(k2)]}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
