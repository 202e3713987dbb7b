"""The numpy/scipy oriented box against open3d's OrientedBoundingBox.create_from_points (the
function it replaces on the query path, where importing open3d cost a new process seconds)."""
import numpy as np
import pytest

from rg_core.grounding.boxes import group_boxes, pca_obb

o3d = pytest.importorskip("open3d")


@pytest.mark.parametrize("seed", range(6))
def test_pca_obb_matches_open3d(seed):
    rng = np.random.default_rng(seed)
    n = [5, 12, 200, 3000, 40, 800][seed]
    # A rotated, anisotropic blob (a typical object group) shifted away from the origin.
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    pts = (rng.normal(size=(n, 3)) * [0.2, 0.05, 0.01 + 0.02 * seed]) @ q.T + rng.normal(size=3)
    c, R, ext = pca_obb(pts)
    ref = o3d.geometry.OrientedBoundingBox.create_from_points(o3d.utility.Vector3dVector(pts))
    np.testing.assert_allclose(c, np.asarray(ref.center), atol=1e-9)
    np.testing.assert_allclose(ext, np.asarray(ref.extent), atol=1e-9)
    # Same axes up to sign (eigenvectors have no sign of their own).
    np.testing.assert_allclose(np.abs(R.T @ np.asarray(ref.R)), np.eye(3), atol=1e-7)
    # group_boxes keeps the frame right-handed and every point inside the box.
    _, _, c2, R2, e2 = group_boxes(pts)
    assert np.linalg.det(R2) == pytest.approx(1.0)
    local = (pts - c2) @ R2
    assert (np.abs(local) <= e2 / 2 + 1e-9).all()
