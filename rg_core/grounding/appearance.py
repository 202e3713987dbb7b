"""What an object looks like to the camera: the keyframe pixels where its Gaussians are seen, and
their basic colour term (perception.colour_names): the scene graph's colour attribute."""
from __future__ import annotations

import numpy as np

from ..perception.colour_names import colour_term
from .boxes import robust_inliers
from .result import GroundedObject


def observed_pixels(mapper, points: np.ndarray, tol: float = 0.02, max_pixels: int = 20000) -> np.ndarray:
    """The keyframe pixels (uint8 [M, 3]) where `points` [N, 3] are seen: projected into every
    keyframe, kept where the keyframe's depth agrees within tol + 2 % (not occluded); from every
    keyframe that sees them (an object's colour is what the camera saw of it from all sides; the
    Gaussians' own colours are a fit that blends neighbours and the background), evenly thinned to
    at most max_pixels."""
    from ..geometry.conventions import in_image, project

    if not len(points):
        return np.zeros((0, 3), np.uint8)
    seen = []
    for kf in mapper.keyframes:
        w, h = kf.size
        uv, z = project(np.asarray(points, np.float64), np.asarray(kf.K, np.float64), kf.cam_to_world)
        ok = in_image(uv, z, w, h)
        u, v = np.round(uv[ok]).astype(int).T
        d = kf.depth.numpy()[v, u]
        vis = (d > 0) & (np.abs(d - z[ok]) <= tol + 0.02 * z[ok])
        if vis.any():
            seen.append(kf.rgb.numpy()[v[vis], u[vis]])
    px = np.concatenate(seen) if seen else np.zeros((0, 3), np.float32)
    px = px[:: max(1, -(-len(px) // max_pixels))]
    return (np.clip(px, 0, 1) * 255).round().astype(np.uint8)


def object_colour(g, o: GroundedObject) -> str:
    """The basic colour term of what the keyframes saw of the object's robust core ("" if nothing)."""
    gs = g.mapper.gaussians
    keep = o.gaussian_ids[robust_inliers(gs.means.detach().numpy()[o.gaussian_ids])]
    px = observed_pixels(g.mapper, gs.means.detach().numpy()[keep])
    if not len(px) and len(keep):   # seen in no keyframe (occluded everywhere): the Gaussians' own colours
        px = (gs.colors.detach()[keep].clamp(0, 1) * 255).round().byte().numpy()
    return colour_term(px) if len(px) else ""
