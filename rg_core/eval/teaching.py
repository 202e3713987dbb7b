"""What a person gives when teaching, simulated from a scene's ground truth: one click per object.

The click is the training-view pixel deepest inside the object's visible mask (largest distance to
the mask's edge), in the training view where that mask is largest, back-projected with that view's
depth to a point in the map frame: what a person clicking in RViz on the object gives.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.conventions import pixels_to_points


@dataclass
class Click:
    object_id: int
    name: str            # the object's explicit query name (what the person calls it)
    view: int            # the training frame's index
    pixel: tuple[int, int]   # (u, v)
    point: np.ndarray    # [3] map frame


def simulated_clicks(scene, min_pixels: int = 20) -> list[Click]:
    """One Click per object of the scene that some training view sees with depth (module docstring)."""
    from scipy.ndimage import distance_transform_edt

    names = {q.object_id: q.explicit for q in scene.queries}
    best: dict[int, tuple[int, object]] = {}
    masks = {}
    for f in scene.train:
        ids = f.load_visible_mask()
        masks[f.index] = ids
        for o in scene.objects:
            n = int((ids == o.id).sum())
            if n >= min_pixels and n > best.get(o.id, (0, None))[0]:
                best[o.id] = (n, f)
    out = []
    for o in scene.objects:
        if o.id not in best:
            continue
        f = best[o.id][1]
        depth = f.load_depth()
        inside = (masks[f.index] == o.id) & (depth > 0)
        if not inside.any():
            continue
        dist = distance_transform_edt(np.pad(inside, 1))[1:-1, 1:-1]
        v, u = np.unravel_index(int(np.argmax(dist)), dist.shape)
        p = pixels_to_points(np.array([u]), np.array([v]), np.array([depth[v, u]]), f.intrinsics.K, f.cam_to_world)[0]
        out.append(Click(o.id, names.get(o.id, o.name), f.index, (int(u), int(v)), p))
    return out
