"""EWA projection of 3D Gaussians to screen space (pure torch, differentiable, shared by all CPU
backends). Computed in float64 and returned in float32: flat covariances, huge/tiny scales and
quaternions of huge norm stay finite and exact where float32 would cancel or overflow.

Every clamp below says why it is there.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from .camera import Camera

ALPHA_MIN = 1.0 / 255.0   # 3DGS: contributions below this are skipped
ALPHA_MAX = 0.99          # 3DGS: keeps 1 - alpha >= 0.01 so the backward pass can divide by it
T_MIN = 1e-4              # 3DGS: a pixel stops compositing once transmittance would fall below this
EPS2D = 0.3  # px^2 added to each projected covariance: a low-pass filter at the image's pixel size


@dataclass
class Projected:
    """Screen-space Gaussians (pixel-centre coordinates). Invalid ones have radius 0."""

    means2d: torch.Tensor    # [N, 2] float32
    conics: torch.Tensor     # [N, 3] float32, upper triangle (a, b, c) of the inverse 2D covariance
    depths: torch.Tensor     # [N] float32, camera z
    opacities: torch.Tensor  # [N] float32 in [0, 1]
    radii: torch.Tensor      # [N] int32, half-size of the square that holds every pixel with alpha >= 1/255


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """[N, 4] (w, x, y, z), any norm -> [N, 3, 3]. A zero quaternion means no rotation."""
    norm = quats.norm(dim=-1, keepdim=True)
    # Zero (or denormal) norm has no direction: use the identity instead of dividing by ~0, which
    # would give an inf gradient.
    ok = norm > 1e-30
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=quats.dtype, device=quats.device)
    q = torch.where(ok, quats / torch.where(ok, norm, torch.ones_like(norm)), identity)
    w, x, y, z = q.unbind(-1)
    R = torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1)
    return R.reshape(quats.shape[:-1] + (3, 3))


def covariance_3d(scales: torch.Tensor, quats: torch.Tensor) -> torch.Tensor:
    """[N, 3] scales (std devs, m), [N, 4] quats -> [N, 3, 3] covariance R S S^T R^T."""
    M = quat_to_rotmat(quats) * scales[:, None, :]
    return M @ M.transpose(1, 2)


def _fov_limits(camera: Camera) -> tuple[float, float, float, float]:
    """|x / z| and |y / z| where the Jacobian is evaluated (3DGS / gsplat: 1.3x the field of view):
    (x right, x left, y down, y up)."""
    fx, fy, cx, cy = (float(v) for v in (camera.K[0, 0], camera.K[1, 1], camera.K[0, 2], camera.K[1, 2]))
    W, H = camera.width, camera.height
    tan_fovx, tan_fovy = 0.5 * W / fx, 0.5 * H / fy
    return ((W - (cx + 0.5)) / fx + 0.3 * tan_fovx, (cx + 0.5) / fx + 0.3 * tan_fovx,
            (H - (cy + 0.5)) / fy + 0.3 * tan_fovy, (cy + 0.5) / fy + 0.3 * tan_fovy)


@torch.no_grad()
def frustum_cull(means: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor, camera: Camera) -> torch.Tensor:
    """Indices [M] of the Gaussians that can touch `camera`'s image: a conservative bound on
    project_gaussians' footprint (between the clip planes, opacity >= ALPHA_MIN, the square of half
    size 3.4 s_max f / z, times the Jacobian's largest stretch inside the clamped field of view, plus
    the dilation, overlapping the image). Rendering only these gives the same image and ids as
    rendering all: a room-sized map seen from one camera renders its visible part, not all of it.
    means [N, 3], scales [N, 3], opacities [N]."""
    R = camera.world_to_cam[:3, :3].to(means.dtype)
    t = camera.world_to_cam[:3, 3].to(means.dtype)
    pc = means @ R.T + t                                                     # [N, 3] camera frame
    z = pc[:, 2]
    fx, fy, cx, cy = (float(v) for v in (camera.K[0, 0], camera.K[1, 1], camera.K[0, 2], camera.K[1, 2]))
    W, H = camera.width, camera.height
    xp, xn, yp, yn = _fov_limits(camera)                                    # project_gaussians' clamp
    lim_x, lim_y = max(xp, xn), max(yp, yn)
    stretch = max(fx, fy) * (1.0 + lim_x * lim_x + lim_y * lim_y) ** 0.5
    keep = (z >= camera.near) & (z <= camera.far) & (opacities >= ALPHA_MIN)
    zs = torch.where(keep, z, torch.ones_like(z))
    reach = 3.4 * scales.abs().amax(1) * stretch / zs + 3.0 + 3.4 * EPS2D ** 0.5   # [N] px, >= the footprint
    u = fx * pc[:, 0] / zs + cx
    v = fy * pc[:, 1] / zs + cy
    keep &= (u + reach > -1.0) & (u - reach < W) & (v + reach > -1.0) & (v - reach < H)
    return torch.nonzero(keep).squeeze(1)


def project_gaussians(means: torch.Tensor, scales: torch.Tensor, quats: torch.Tensor,
                      opacities: torch.Tensor, camera: Camera, eps2d: float = EPS2D) -> Projected:
    """Project Gaussians into `camera`. means [N, 3], scales [N, 3], quats [N, 4], opacities [N]."""
    N = means.shape[0]
    assert means.shape == (N, 3) and scales.shape == (N, 3), (means.shape, scales.shape)
    assert quats.shape == (N, 4) and opacities.shape == (N,), (quats.shape, opacities.shape)
    f64 = torch.float64
    m, s, q, o = means.to(f64), scales.to(f64), quats.to(f64), opacities.to(f64)

    # Non-finite inputs are dropped (radius 0). They are replaced by harmless values *before* any
    # arithmetic so that no NaN reaches the gradient through torch.where's unused branch.
    finite = (torch.isfinite(m).all(-1) & torch.isfinite(s).all(-1) & torch.isfinite(q).all(-1)
              & torch.isfinite(o))
    fin3 = finite[:, None]
    m = torch.where(fin3, m, 0.0)
    q = torch.where(finite[:, None], q, 0.0)
    # Scales: |s| (a negative std dev is the same Gaussian) clamped to [1e-9, 1e6] m. Below 1e-9 m
    # a Gaussian is a point anyway (the 2D dilation dominates); above 1e6 m its 3D covariance
    # (s^2 = 1e12) times the Jacobian (f/z)^2 could exceed float32 once cast back.
    s = torch.where(fin3, s, 1.0).abs().clamp(1e-9, 1e6)
    # Opacity outside [0, 1] is meaningless for compositing: clamp (gradient passes inside).
    o = torch.where(finite, o, 0.0).clamp(0.0, 1.0)

    K = camera.K.to(f64)
    R = camera.world_to_cam[:3, :3].to(f64)
    t = camera.world_to_cam[:3, 3].to(f64)
    pc = m @ R.T + t                                   # [N, 3] camera coordinates
    x, y, z = pc.unbind(-1)
    in_depth = (z >= camera.near) & (z <= camera.far)
    # Only Gaussians between the clip planes are projected; others get z = 1 in the arithmetic so
    # that nothing divides by ~0 (they are masked out below).
    zs = torch.where(in_depth, z, torch.ones_like(z))
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    W, H = camera.width, camera.height

    # 3DGS / gsplat: the Jacobian is evaluated at a position clamped to 1.3x the field of view.
    # Without it, a Gaussian far outside the image (or grazing the near plane at a steep angle)
    # gets a huge, wrong screen footprint from the linearisation and covers the whole screen.
    lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg = _fov_limits(camera)
    tx = zs * torch.clamp(x / zs, min=-lim_x_neg, max=lim_x_pos)
    ty = zs * torch.clamp(y / zs, min=-lim_y_neg, max=lim_y_pos)
    # 2D covariance = T T^T with T = J R_cam R_q S ([N, 2, 3]), written out row by row instead of
    # batched 3x3 products: fewer operations, and positive semi-definite by construction.
    j0 = (fx / zs)[:, None] * R[0] - (fx * tx / zs**2)[:, None] * R[2]   # [N, 3] row 0 of J R_cam
    j1 = (fy / zs)[:, None] * R[1] - (fy * ty / zs**2)[:, None] * R[2]   # [N, 3] row 1
    M = quat_to_rotmat(q) * s[:, None, :]                                  # [N, 3, 3] R_q S
    t0 = (j0[:, :, None] * M).sum(1)                                       # [N, 3]
    t1 = (j1[:, :, None] * M).sum(1)
    cov2d = torch.stack([(t0 * t0).sum(-1), (t0 * t1).sum(-1), (t1 * t1).sum(-1)], -1)  # [N, 3] a b c
    # Low-pass dilation (3DGS): every Gaussian covers at least ~one pixel, so tiny or perfectly
    # flat ones stay visible and their 2D covariance stays invertible.
    a = cov2d[:, 0] + eps2d
    b = cov2d[:, 1]
    c = cov2d[:, 2] + eps2d
    det = a * c - b * b
    # det >= eps2d^2 in exact arithmetic; the clamp only guards rounding in float64.
    det_ok = det > 1e-12
    det_s = torch.where(det_ok, det, torch.ones_like(det))
    conics = torch.stack([c / det_s, -b / det_s, a / det_s], -1)

    u = fx * x / zs + cx
    v = fy * y / zs + cy
    means2d = torch.stack([u, v], -1)

    # Extent: pixels where opacity * exp(-0.5 d^T S^-1 d) >= 1/255 lie within the square of half
    # size sqrt(2 ln(255 o) lambda_max): rendering then does not depend on the tile size.
    mid = 0.5 * (a + c)
    lam = mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.0))
    o_ok = o >= ALPHA_MIN
    reach = torch.sqrt(2.0 * torch.log(torch.where(o_ok, o, torch.ones_like(o)) / ALPHA_MIN) * lam)
    # Footprints are clamped to 4x the image diagonal: the square only needs to cover the screen,
    # and an int32 radius must not overflow for a Gaussian of 1e6 m right in front of the lens.
    radius = torch.ceil(reach.clamp(max=4.0 * (W * W + H * H) ** 0.5)).detach()
    on_screen = (u + radius > -0.5) & (u - radius < W - 0.5) & (v + radius > -0.5) & (v - radius < H - 0.5)
    valid = finite & in_depth & det_ok & o_ok & on_screen & torch.isfinite(means2d).all(-1)
    radii = torch.where(valid, radius, torch.zeros_like(radius)).to(torch.int32)

    vf = valid[:, None]
    f32 = torch.float32
    # Invalid entries get zeros (their gradient is zero and they are never rasterised).
    return Projected(
        means2d=torch.where(vf, means2d, 0.0).to(f32),
        conics=torch.where(vf, conics, 0.0).to(f32),
        depths=torch.where(valid, z, 0.0).to(f32),
        opacities=torch.where(valid, o, 0.0).to(f32),
        radii=radii,
    )
