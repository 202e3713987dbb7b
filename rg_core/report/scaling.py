"""Time and peak memory of mapping a scene's first n frames, each in a fresh process (peak RSS is
per process, so every point gets its own), and the log-log growth exponent."""
from __future__ import annotations

import multiprocessing as mp
from concurrent.futures import ProcessPoolExecutor

import numpy as np


def _hwm_mb() -> float:
    """Peak RSS of this process image (VmHWM; ru_maxrss would carry the parent's peak over exec)."""
    try:
        for line in open("/proc/self/status"):
            if line.startswith("VmHWM:"):
                return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    from ..util import peak_rss_mb

    return peak_rss_mb()


def _point(scene_dir: str, n_frames: int, width: int, map_over: dict, threads: int) -> dict:
    """Runs in the child: stream the first n frames (train and test, in index order), no refinement."""
    import time

    import torch

    from ..config import MapConfig
    from ..io.captures import read_scene
    from ..map.mapper import Mapper
    from ..map.run import stream_frames
    torch.set_num_threads(threads)
    frames = read_scene(scene_dir).frames[:n_frames]
    if len(frames) < n_frames:
        raise ValueError(f"{scene_dir}: {len(frames)} frames, {n_frames} asked")
    base = _hwm_mb()
    m = Mapper(MapConfig(**{**map_over, "width": width}))
    t = time.perf_counter()
    stream_frames(m, frames, progress=False)
    return {"frames": n_frames, "width": width, "seconds": round(time.perf_counter() - t, 3),
            "peak_rss_mb": round(_hwm_mb(), 1), "rss_before_mb": round(base, 1),
            "keyframes": len(m.keyframes), "gaussians": len(m.gaussians)}


def run_point(scene_dir, n_frames: int, width: int, map_over: dict, threads: int = 1, timeout: float = 1800,
              fresh: bool = True) -> dict:
    if not fresh:  # peak memory is then the whole run's so far
        import torch

        n = torch.get_num_threads()
        try:
            return _point(str(scene_dir), n_frames, width, map_over, threads)
        finally:
            torch.set_num_threads(n)
    with ProcessPoolExecutor(1, mp_context=mp.get_context("spawn")) as ex:
        return ex.submit(_point, str(scene_dir), n_frames, width, map_over, threads).result(timeout=timeout)


def growth_exponent(x, y) -> float:
    """Slope of log y against log x (y ~ x^k); NaN with fewer than two usable points."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    ok = (x > 0) & (y > 0) & np.isfinite(x) & np.isfinite(y)
    if ok.sum() < 2 or len(set(x[ok])) < 2:
        return float("nan")
    return float(np.polyfit(np.log(x[ok]), np.log(y[ok]), 1)[0])
