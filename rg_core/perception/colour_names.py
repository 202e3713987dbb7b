"""Basic colour terms (the eleven of Berlin and Kay) of pixels.

- `colour_histogram`: per-pixel word frequencies in OpenCV's HSV, for ConSE's text-space colour term
  (embed.ConSEEmbedder; the fitted confidence model was measured with it).
- `colour_term`: the one word a person would give a whole object, in CIELAB's lightness, chroma and
  hue (LCh): the surface colour, not its shading (lightness from the lit part of the object).
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


# LCh hue sectors (degrees, CIELAB D65) -> term; sRGB red sits near 40, orange 61, yellow 96, green 141,
# blue 295 (navy 306), purple 319, pink 352.
_HUE_SECTORS = ((50, "red"), (75, "orange"), (110, "yellow"), (200, "green"), (312, "blue"), (345, "purple"),
                (360, "red"))
_MIN_CHROMA = 15.0          # C* below: achromatic
_CHROMATIC_SHARE = 0.35     # share of chromatic pixels that makes the object chromatic
_WHITE_L, _BLACK_L = 75.0, 25.0


def lch(pixels: np.ndarray) -> np.ndarray:
    """uint8 RGB [N, 3] -> CIELAB lightness L* (0..100), chroma C*, hue h (degrees) [N, 3]."""
    import cv2

    lab = cv2.cvtColor(np.ascontiguousarray(pixels, np.float32).reshape(-1, 1, 3) / 255.0,
                       cv2.COLOR_RGB2Lab).reshape(-1, 3).astype(np.float64)
    return np.stack([lab[:, 0], np.hypot(lab[:, 1], lab[:, 2]),
                     np.degrees(np.arctan2(lab[:, 2], lab[:, 1])) % 360.0], 1)


def colour_term(pixels: np.ndarray) -> str:
    """uint8 RGB [N, 3] of one object -> a basic colour term, "light"/"dark" before a chromatic one.

    Chromatic when >= 35 % of the pixels have C* >= 15: hue = chroma-weighted circular mean, then
    red/orange/yellow hues darker than L* 50 are brown and light red/purple ones pink. Achromatic:
    white / grey / black from the 75th percentile of L*, so a shaded white bowl stays white."""
    if not isinstance(pixels, np.ndarray) or pixels.ndim != 2 or pixels.shape[1] != 3 or not len(pixels):
        raise ValueError(f"colour_term: expected RGB pixels [N>0, 3], got {getattr(pixels, 'shape', type(pixels))}")
    if not np.isfinite(pixels).all():
        raise ValueError("colour_term: pixels hold NaN or inf; expected finite 0..255 RGB")
    p = lch(np.clip(pixels, 0, 255))
    chromatic = p[:, 1] >= _MIN_CHROMA
    if chromatic.mean() < _CHROMATIC_SHARE:
        light = float(np.percentile(p[:, 0], 75))
        return "white" if light >= _WHITE_L else "black" if light < _BLACK_L else "grey"
    c = p[chromatic]
    ang = np.radians(c[:, 2])
    hue = float(np.degrees(np.arctan2((c[:, 1] * np.sin(ang)).sum(), (c[:, 1] * np.cos(ang)).sum())) % 360.0)
    light = float(np.median(c[:, 0]))
    term = next(t for upper, t in _HUE_SECTORS if hue < upper)
    if term in ("red", "orange", "yellow") and light < 50 and not (term == "red" and float(np.median(c[:, 1])) > 55):
        term = "brown"
    elif term in ("red", "purple") and light > 65:
        term = "pink"
    if term in ("brown", "pink"):
        return term
    return f"light {term}" if light > 75 and term != "yellow" else f"dark {term}" if light < 30 else term
