"""Basic colour terms of an object's pixels, as a histogram over eleven words.

ImageNet classes carry no colour, yet object names often do ("blue cup") or imply one ("banana",
"orange"). ConSE turns these word frequencies into a text-space term (see embed.ConSEEmbedder).
Hue bins in OpenCV's HSV (hue 0..180); weakly saturated or dark pixels are achromatic.
"""
from __future__ import annotations

import numpy as np

COLOUR_TERMS = ("red", "orange", "yellow", "green", "blue", "purple", "pink", "brown", "white", "grey", "black")
CHROMATIC_TERMS = COLOUR_TERMS[:8]
_HUE_UPPER = (8, 20, 34, 85, 130, 150, 170)        # red, orange, yellow, green, blue, purple, pink; above: red
_MIN_SATURATION, _MIN_VALUE = 60, 40               # below either: achromatic
_DARK_WARM = 130                                   # red/orange hues darker than this read as brown


def colour_histogram(pixels: np.ndarray) -> np.ndarray:
    """pixels [N, 3] uint8 RGB -> [11] fractions over COLOUR_TERMS (sum 1)."""
    if not isinstance(pixels, np.ndarray) or pixels.dtype != np.uint8 or pixels.ndim != 2 or pixels.shape[1] != 3:
        raise ValueError(f"colour_histogram: expected uint8 [N, 3] RGB pixels, got "
                         f"{getattr(pixels, 'dtype', type(pixels))} {getattr(pixels, 'shape', '')}")
    if len(pixels) == 0:
        raise ValueError("colour_histogram: no pixels")
    import cv2  # here: importing cv2 costs a cold `rg ground` 0.3 s

    hsv = cv2.cvtColor(np.ascontiguousarray(pixels).reshape(-1, 1, 3), cv2.COLOR_RGB2HSV).reshape(-1, 3)
    h, s, v = (hsv[:, i].astype(np.int32) for i in range(3))
    hue_bin = np.searchsorted(np.asarray(_HUE_UPPER), h, side="right")      # 0..7
    label = np.where(hue_bin == len(_HUE_UPPER), 0, hue_bin)               # wrap-around red
    label = np.where((label <= 1) & (v < _DARK_WARM), 7, label)
    achromatic = (s < _MIN_SATURATION) | (v < _MIN_VALUE)
    grey = np.where(v < 60, 10, np.where(v < 170, 9, 8))
    label = np.where(achromatic, grey, label)
    counts = np.bincount(label, minlength=len(COLOUR_TERMS)).astype(np.float64)
    return counts / counts.sum()
