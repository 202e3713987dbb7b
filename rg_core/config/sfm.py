"""Section of structure from motion for photos without poses (`rg sfm`, pycolmap on the CPU)."""
from __future__ import annotations

from typing import Annotated, Literal

from annotated_types import Interval

from .schema import section


@section
class SfmConfig:
    """Structure from motion for photos without poses (`rg sfm`): pycolmap's SIFT features, matching
    and incremental mapping on the CPU, written as a COLMAP scene folder (images/ + sparse/0)."""

    matcher: Literal["auto", "exhaustive", "sequential"] = "auto"
    """Image pairs to match: every pair (exhaustive), or each photo with the next `overlap` in name
    order (sequential: a video's frames, a walk); auto: exhaustive up to `exhaustive_max` photos."""
    exhaustive_max: Annotated[int, Interval(ge=2)] = 100
    """auto matches every pair up to this many photos (pairs grow with the square), sequentially above."""
    overlap: Annotated[int, Interval(ge=1)] = 10
    """Sequential matching: photos each one is matched with, following it in name order."""
    camera_model: Literal["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"] = "SIMPLE_RADIAL"
    """COLMAP camera model of the photos (distortion is refined by bundle adjustment and undone when
    the scene is read)."""
    single_camera: bool = True
    """All photos from one camera (one set of intrinsics); off: one camera per photo."""
    max_image_size: Annotated[int, Interval(ge=64)] = 1600
    """Photos are downscaled to at most this many pixels on their long side for feature extraction."""
    max_features: Annotated[int, Interval(ge=64)] = 8192
    """SIFT features per photo at most."""
    peak_threshold: Annotated[float, Interval(gt=0.0)] = 0.0067
    """SIFT's contrast threshold (COLMAP's 0.02 / 3); small or smooth photos find more features at
    0.002 (320x240 synthetic views registered 7 of 14 at the default, all at 0.002)."""
    min_registered: Annotated[float, Interval(gt=0.0, le=1.0)] = 0.8
    """Share of the photos the model must register; fewer is an error naming the ones left out."""
    threads: int = -1
    """CPU threads of pycolmap (-1: all)."""
    seed: int = 0
    """Random seed of pycolmap's RANSAC and mapper."""
