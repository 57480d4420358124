"""Masked PSNR (dB) of a result against the truth, over the mask's pixels > 127, as
`clearview::imaging::metrics::masked_psnr` computes it on 8-bit images. Given the result's
confidence map (`clearview fill --confidence`), also its honesty as
`clearview::imaging::metrics::honesty` counts it: the share of the mask it is sure of (>= 128),
the share of those grossly wrong (a channel more than 30 levels off) and the share of the
grossly wrong ones it flags.

Usage: bench/.venv/bin/python bench/masked_psnr.py RESULT.png TRUTH.png MASK.png [CONFIDENCE.png]
"""
import sys

import cv2
import numpy as np

out, truth, mask = (cv2.imread(p).astype(np.float64) for p in sys.argv[1:4])
m = mask[..., 0] > 127
mse = ((out[m] - truth[m]) ** 2).mean() / 255.0**2
print(f"{10 * np.log10(1 / mse):.2f}")
if len(sys.argv) > 4:
    sure = cv2.imread(sys.argv[4], cv2.IMREAD_GRAYSCALE)[m] >= 128
    gross = (np.abs(out[m] - truth[m]) > 30).any(axis=1)
    print(
        f"confident {sure.mean():.3f}, confident error rate {(sure & gross).sum() / max(sure.sum(), 1):.3f}, "
        f"flagged recall {(gross & ~sure).sum() / max(gross.sum(), 1):.3f} ({gross.sum()} gross)"
    )
