"""Stream frames through the Mapper (what `rg map`, the benchmarks and the tests run)."""
from __future__ import annotations

import sys
import time

from .mapper import Mapper


def stream_frames(mapper: Mapper, frames, progress: bool = True, desc: str = "map") -> float:
    """Feed frames in order; returns seconds."""
    from tqdm import tqdm

    t = time.perf_counter()
    bar = tqdm(frames, desc=desc, unit="frame", disable=not progress, file=sys.stderr)
    for f in bar:
        mapper.add_frame(f.load_rgb(), f.load_depth(), f.intrinsics.K, f.cam_to_world, f.stamp)
        bar.set_postfix(kf=len(mapper.keyframes), g=len(mapper.gaussians))
    return time.perf_counter() - t
