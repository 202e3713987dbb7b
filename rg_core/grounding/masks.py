"""Visible masks sharpened by the camera's own depth image. Near the mask, each pixel with a reading
goes to whichever surface of the map its sensor depth is nearer: the group's (rendered alone) or the
rest of the map's (rendered without the group); where the two are too close in depth to tell apart
(an object's foot on the table) the rendered answer stands. A pixel touching the mask whose reading
lies in front of the rest's surface and continues the reading of a mask pixel that depth placed on
the group is the object's own surface that the map has not covered: it joins (docs/pipeline.md,
"Grounding"). A mask pixel whose reading lies well in front of the group's surface, at a 3D point
the rest of the map's Gaussians hold more than the group's, is an occluder the map renders too thin
(`leave_occluded`). With the camera's colour image the mask's rim then follows the image's colour
edges (`snap_to_image`). `result_masks` renders a result's masks in a camera and applies these.
"""
from __future__ import annotations

import cv2
import numpy as np
import torch
from scipy.ndimage import binary_dilation, binary_erosion

from ..geometry.conventions import pixels_to_points
from ..geometry.points import nearest
from ..render import rasterize
from ..render.projection import quat_to_rotmat


@torch.no_grad()
def result_masks(mapper, gcfg, result, K: np.ndarray, cam_to_world: np.ndarray, width: int, height: int,
                 depth: np.ndarray | None = None,
                 image: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Grounder.mask_layers: a GroundingResult's groups in a camera of `mapper`'s map, `gcfg` its
    GroundConfig: amodal (rendered alone), visible as rendered (the groups' share of the blending
    weight above `visible_share`), and visible following the camera's `depth` and `image` (the
    functions below; None without either), each bool [height, width]."""
    g = mapper.gaussians
    N = len(g)
    empty = np.zeros((height, width), bool)
    sensed = depth is not None or image is not None
    ids = np.concatenate([o.gaussian_ids for o in result.objects]) if result.objects else np.zeros(0, np.int64)
    if not len(ids) or not N:
        return empty, empty.copy(), empty.copy() if sensed else None
    if int(ids.max()) >= N:
        raise ValueError(f"masks: the result names Gaussian {int(ids.max())} but the map now has {N}; ground again")
    cam = mapper.camera(K, cam_to_world, width, height)
    member = torch.zeros(N, 1)
    member[torch.from_numpy(ids)] = 1.0
    args = (g.means.detach(), g.scales.detach(), g.quats.detach(), g.opacities.detach())
    aa = mapper.cfg.antialiased
    full = rasterize(*args, member, cam, antialiased=aa)
    alone = rasterize(*args, member, cam, subset=torch.from_numpy(ids), antialiased=aa)
    a = gcfg.mask_alpha
    share = full.channels[..., 0] / full.alpha.clamp(min=1e-6)
    visible = ((full.alpha > a) & (share > gcfg.visible_share)).numpy()
    amodal = (alone.alpha > a).numpy()
    if not sensed:
        return amodal, visible, None
    out = visible.copy()
    apart = None
    if depth is not None and gcfg.visible_depth_tol > 0:
        others = torch.ones(N, dtype=torch.bool)
        others[torch.from_numpy(ids)] = False
        rest = rasterize(*args, member, cam, subset=others, antialiased=aa)
        out = refine_visible(visible, alone.alpha.numpy(), alone.depth.numpy(), rest.alpha.numpy(),
                             rest.depth.numpy(), depth, gcfg.visible_depth_tol)
        apart = surfaces_apart(alone.alpha.numpy(), alone.depth.numpy(), rest.alpha.numpy(), rest.depth.numpy(),
                               gcfg.visible_depth_tol)
    if depth is not None and (gcfg.visible_front_tol > 0 or apart is not None):
        out = leave_occluded(out, depth, alone.alpha.numpy(), alone.depth.numpy(), K, cam_to_world, args,
                             member[:, 0].numpy() > 0, gcfg.visible_front_tol or np.inf,
                             rim_ratio=gcfg.visible_rim_ratio if apart is not None else 0.0,
                             rim_where=apart)
    if image is not None and gcfg.visible_edge_eps > 0:
        out = snap_to_image(out, image, eps=gcfg.visible_edge_eps)
    return amodal, visible, out


def refine_visible(visible: np.ndarray, group_alpha: np.ndarray, group_depth: np.ndarray, rest_alpha: np.ndarray,
                   rest_depth: np.ndarray, depth: np.ndarray, rel_tol: float, abs_tol: float = 0.01,
                   rim_alpha: float = 0.1, rim_px: int = 2) -> np.ndarray:
    """visible [H, W] bool; the group rendered alone and the rest of the map rendered without it:
    alpha and expected depth [H, W]; the camera's depth image [H, W] metres (0, NaN, inf: no
    reading). Where the two rendered surfaces lie more than max(abs_tol, rel_tol * the group's depth)
    apart (or the rest covers nothing there), a mask pixel whose reading is nearer the rest's surface
    leaves the mask, and a pixel touching the mask whose reading is nearer the group's (covered with
    alpha > rim_alpha) joins it, and so does one whose reading lies in front of the rest's surface
    by more than that tolerance and within it of the reading of a 4-neighbour mask pixel that is
    nearer the group's surface (a rim the map missed), repeated out to `rim_px` pixels: the mapper
    seeds one Gaussian per 2x2 block, so a rim it missed can be two pixels wide. Pixels without a
    reading, or where the surfaces cannot be told apart, keep the rendered answer."""
    visible = np.asarray(visible, bool)
    if np.shape(depth) != visible.shape:
        raise ValueError(f"refine_visible: depth image is {np.shape(depth)[1]}x{np.shape(depth)[0]} but the mask "
                         f"is {visible.shape[1]}x{visible.shape[0]}; give the depth registered to the camera the "
                         "mask is rendered for")
    with np.errstate(invalid="ignore", over="ignore"):
        d = np.asarray(depth, np.float64)
        reading = np.isfinite(d) & (d > 0)
        d = np.where(reading, d, 0.0)

        g, r = _surface(group_alpha, group_depth), _surface(rest_alpha, rest_depth)
        apart = surfaces_apart(group_alpha, group_depth, rest_alpha, rest_depth, rel_tol, abs_tol)
        nearer_group = np.abs(d - g) < np.abs(d - r)
        tol = np.maximum(abs_tol, rel_tol * d)                                          # [H, W] metres
        unmapped = reading & (d < r - tol)          # in front of all the rest renders there (r: inf = none)
    decide = reading & apart
    out = visible & ~(decide & ~nearer_group)
    out |= binary_dilation(visible) & decide & nearer_group & (np.asarray(group_alpha) > rim_alpha)
    grown = out & decide & nearer_group
    for _ in range(max(int(rim_px), 0)):
        new = unmapped & ~out & _continues(grown, d, tol)
        if not new.any():
            break
        grown |= new
        out |= new
    return out


def surfaces_apart(group_alpha: np.ndarray, group_depth: np.ndarray, rest_alpha: np.ndarray,
                   rest_depth: np.ndarray, rel_tol: float, abs_tol: float = 0.01) -> np.ndarray:
    """The group rendered alone and the rest of the map rendered without it: alpha and expected depth
    [H, W]. [H, W] bool: where the group's surface lies more than max(abs_tol, rel_tol * its depth)
    from the rest's (or the rest covers nothing there), so that a depth reading can tell them apart."""
    g, r = _surface(group_alpha, group_depth), _surface(rest_alpha, rest_depth)
    with np.errstate(invalid="ignore"):
        return np.isfinite(g) & ~(np.abs(g - r) <= np.maximum(abs_tol, rel_tol * np.where(np.isfinite(g), g, 0.0)))


def _surface(alpha: np.ndarray, sdepth: np.ndarray) -> np.ndarray:
    """A render's alpha and expected depth [H, W] -> its surface depth [H, W] metres, inf where it
    covers nothing (alpha <= 0.05) or has no finite positive depth."""
    with np.errstate(invalid="ignore"):
        sdepth = np.asarray(sdepth, np.float64)
        return np.where((np.asarray(alpha) > 0.05) & np.isfinite(sdepth) & (sdepth > 0), sdepth, np.inf)


def _continues(mask: np.ndarray, d: np.ndarray, tol: np.ndarray) -> np.ndarray:
    """[H, W] bool: pixels with a 4-neighbour in `mask` whose reading d (0: none) lies within tol of theirs."""
    H, W = mask.shape
    md = np.pad(np.where(mask, d, 0.0), 1)                                                # [H+2, W+2]
    hit = np.zeros((H, W), bool)
    for dy, dx in ((0, 1), (2, 1), (1, 0), (1, 2)):
        nd = md[dy:dy + H, dx:dx + W]
        hit |= (nd > 0) & (np.abs(d - nd) < tol)
    return hit


def leave_occluded(mask: np.ndarray, depth: np.ndarray, group_alpha: np.ndarray, group_depth: np.ndarray,
                   K: np.ndarray, cam_to_world: np.ndarray, gaussians: tuple, member: np.ndarray, rel_tol: float,
                   abs_tol: float = 0.01, k: int = 24, rim_ratio: float = 0.0, rim_px: int = 2,
                   rim_where: np.ndarray | None = None) -> np.ndarray:
    """mask [H, W] bool; the camera's depth [H, W] (0, NaN, inf: no reading); the group rendered
    alone: alpha and expected depth [H, W]; K [3, 3], cam_to_world [4, 4]; gaussians (means [N, 3],
    scales [N, 3], quats [N, 4], opacities [N]) and member bool [N] (the group). A mask pixel whose
    reading lies more than max(abs_tol, rel_tol * reading) in front of the group's surface shows
    something in front of the group. It leaves when, at its back-projected reading, the k nearest
    Gaussians' densities (opacity x exp(-d^2 / 2) in each one's own axes) sum higher over the rest
    than over the group: a thin occluder the map renders with little alpha, whose blended depth
    with what lies behind the group places the rest's surface behind the group's (`refine_visible`
    then keeps the pixel). With rim_ratio > 0 a mask pixel within rim_px of the mask's edge also
    leaves, whatever its depth, where the rest's densities sum more than rim_ratio times the
    group's: a rim the renders smear over a neighbour that the camera's reading places on it; only
    where `rim_where` [H, W] bool (None: everywhere) holds, e.g. `surfaces_apart`, since a flat
    object's own surface lies within millimetres of the table's Gaussians. Where no Gaussian is
    near, the pixel stays."""
    mask = np.asarray(mask, bool)
    if np.shape(depth) != mask.shape:
        raise ValueError(f"leave_occluded: depth image is {np.shape(depth)[1]}x{np.shape(depth)[0]} but the mask "
                         f"is {mask.shape[1]}x{mask.shape[0]}; give the depth registered to the camera the mask is "
                         "rendered for")
    means, scales, quats, opacities = (torch.as_tensor(t).detach() for t in gaussians)
    member = np.asarray(member, bool)
    with np.errstate(invalid="ignore", over="ignore"):
        d = np.asarray(depth, np.float64)
        reading = np.isfinite(d) & (d > 0)
        g = _surface(group_alpha, group_depth)
        front = mask & reading & (d < g - np.maximum(abs_tol, rel_tol * np.where(reading, d, 0.0)))
    rim = np.zeros_like(mask)                               # [H, W] asked at rim_ratio instead of 1
    if rim_ratio > 0 and rim_px > 0:
        rim = mask & reading & ~front & ~binary_erosion(mask, iterations=int(rim_px), border_value=1)
        if rim_where is not None:
            rim &= np.asarray(rim_where, bool)
    ask = front | rim
    if not ask.any() or not len(means):
        return mask.copy()
    vs, us = np.nonzero(ask)
    pts = pixels_to_points(us, vs, d[vs, us], np.asarray(K, np.float64), np.asarray(cam_to_world, np.float64))  # [M, 3]
    _, idx = nearest(means.numpy(), pts, k)                                                  # [M, k]
    near, inv = np.unique(idx, return_inverse=True)        # each neighbour's rotation computed once
    sel, j = torch.from_numpy(near), inv.reshape(idx.shape)                                  # j [M, k] into near
    R = quat_to_rotmat(quats[sel].double()).numpy()[j]                                       # [M, k, 3, 3]
    s = np.maximum(scales[sel].double().numpy(), 1e-9)[j]                                   # [M, k, 3]
    local = np.einsum("mkji,mkj->mki", R, pts[:, None, :] - means[sel].double().numpy()[j]) / s
    w = np.nan_to_num(opacities[sel].double().numpy()[j]
                      * np.exp(-0.5 * np.minimum((local ** 2).sum(-1), 1e6)))               # [M, k]
    mine = member[idx]
    occluded = (w * ~mine).sum(1) > np.where(rim[vs, us], rim_ratio, 1.0) * (w * mine).sum(1)
    out = mask.copy()
    out[vs[occluded], us[occluded]] = False
    return out


def snap_to_image(mask: np.ndarray, image: np.ndarray, radius: int = 1, eps: float = 0.01,
                  margin: float = 0.1) -> np.ndarray:
    """mask [H, W] bool; the camera's colour image [H, W, 3] (uint8, or float in [0, 1]; clipped). The
    mask as 0/1, guided-filtered by the image (He et al. 2010: locally an affine function of the colour
    within `radius` pixels, `eps` the regularisation), thresholded at a half: a pixel whose mask value
    disagrees with most of its like-coloured neighbours flips, so a rim the map renders a pixel off
    here and there (small objects seen from afar) straightens along the colour edge; where the colour
    is flat the mask only smooths. Then each rim pixel goes to the side whose settled colour within
    2 px is nearer by more than `margin` (`_nearer_side`): the filter averages a 3x3 window and so
    leaves rims on thin objects. Non-finite colours count as black."""
    mask = np.asarray(mask, bool)
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.shape[:2] != mask.shape:
        raise ValueError(f"snap_to_image: colour image is {list(img.shape)} but the mask is {mask.shape[1]}x"
                         f"{mask.shape[0]}; give the [H, W, 3] image of the camera the mask is rendered for")
    if radius < 1 or eps <= 0 or not mask.any():
        return mask.copy()
    if img.dtype == np.uint8:
        guide = img.astype(np.float32) / 255.0
    else:
        guide = np.clip(np.nan_to_num(img.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0), 0.0, 1.0)
    out = cv2.ximgproc.guidedFilter(np.ascontiguousarray(guide), mask.astype(np.float32), int(radius), float(eps))
    return _nearer_side(out > 0.5, guide, margin)


def _nearer_side(mask: np.ndarray, guide: np.ndarray, margin: float, r: int = 2) -> np.ndarray:
    """mask [H, W] bool, guide [H, W, 3] float in [0, 1]. A mask pixel touching the outside (or an
    outside pixel touching the mask; 4-neighbours) compares its colour with the nearest-coloured
    settled pixel of each side within r px: the mask's interior (the mask itself where it is too thin
    to have one within r) and the outside not touching the mask. It goes to the side nearer by more than
    `margin` (Euclidean, RGB in [0, 1]); otherwise it stays."""
    if not mask.any():
        return mask
    ys, xs = np.nonzero(binary_dilation(mask))
    y0, y1, x0, x1 = max(ys.min() - r, 0), ys.max() + r + 1, max(xs.min() - r, 0), xs.max() + r + 1
    m, img = mask[y0:y1, x0:x1], guide[y0:y1, x0:x1]                               # the mask's box
    grown = binary_dilation(m)
    inner = m & ~binary_dilation(~m, border_value=0)
    rys, rxs = np.nonzero(grown & ~inner)                                           # the rim [R]
    pimg = np.pad(img, ((r, r), (r, r), (0, 0)), mode="edge")
    settled = [np.pad(s, r) for s in (inner, m, ~grown)]                            # in, mask, out
    near = np.full((3, len(rys)), np.inf, np.float32)                               # [3, R]
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            if dy or dx:
                ny, nx = rys + r + dy, rxs + r + dx
                dist = np.sqrt(((pimg[ny, nx] - img[rys, rxs]) ** 2).sum(-1))           # [R]
                for k, s in enumerate(settled):
                    np.minimum(near[k], np.where(s[ny, nx], dist, np.inf), out=near[k])
    d_in = np.where(np.isfinite(near[0]), near[0], near[1])             # no interior within r: thin
    inside = m[rys, rxs]
    keep = np.where(inside, ~(near[2] + margin < d_in), d_in + margin < near[2])
    out = mask.copy()
    out[y0 + rys, x0 + rxs] = keep
    return out
