"""Masked PSNR (dB) of a result against the truth, over the mask's pixels > 127, as
`clearview::imaging::metrics::masked_psnr` computes it on 8-bit images.

Usage: bench/.venv/bin/python bench/masked_psnr.py RESULT.png TRUTH.png MASK.png
"""
import sys

import cv2
import numpy as np

out, truth, mask = (cv2.imread(p).astype(np.float64) for p in sys.argv[1:4])
m = mask[..., 0] > 127
mse = ((out[m] - truth[m]) ** 2).mean() / 255.0**2
print(f"{10 * np.log10(1 / mse):.2f}")
