"""Structure from motion for photos without poses (`rg sfm IMAGES_DIR --out SCENE`): pycolmap (the
PyPI wheel, CPU) extracts SIFT features, matches them (every pair, or each photo with the next
`overlap` in name order), verifies the pairs geometrically and maps incrementally; the model that
registered the most photos is written as a COLMAP scene folder, which read_scene reads as kind
"colmap" (io/colmap.py)::

    SCENE/images/<the photos>      copied from IMAGES_DIR (top level, .png / .jpg / .jpeg)
    SCENE/sparse/0/                cameras, images, points3D (COLMAP binary, with rigs and frames)
    SCENE/database.db              COLMAP's features and matches (what `colmap gui` opens)

Errors name the folder and what to change: no folder, no photos, fewer than 2, no model, or a model
that registered fewer than `min_registered` of the photos (naming the ones left out).
"""
from __future__ import annotations

import contextlib
import math
import shutil
import sys
import time
from pathlib import Path

from ..config import SfmConfig
from .images import SceneError

PHOTO_SUFFIXES = (".png", ".jpg", ".jpeg")


def photo_files(folder: str | Path) -> list[Path]:
    """The photos at the top level of `folder`, in name order; SceneError when it is no folder."""
    folder = Path(folder)
    if not folder.is_dir():
        raise SceneError(f"{folder}: image folder not found")
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in PHOTO_SUFFIXES)


@contextlib.contextmanager
def _quiet_colmap(pycolmap):
    """COLMAP's INFO log (a screen a photo) off while it runs: the bar shows the progress."""
    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 1   # WARNING and above still reach stderr
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = level


def _pair_stats(pycolmap, db_path: Path, min_inliers: int) -> tuple[int, int]:
    """(median features per photo, image pairs with at least `min_inliers` verified matches)."""
    db = pycolmap.Database.open(str(db_path))
    try:
        kp = sorted(db.num_keypoints_for_image(im.image_id) for im in db.read_all_images())
        _, geoms = db.read_two_view_geometries()
        good = sum(len(g.inlier_matches) >= min_inliers for g in geoms)
    finally:
        db.close()
    return (kp[len(kp) // 2] if kp else 0), int(good)


def _copy_photos(photos: list[Path], images: Path) -> None:
    images.mkdir(parents=True, exist_ok=True)
    for p in photos:
        dst = images / p.name
        if not (dst.exists() and dst.samefile(p)):
            shutil.copy2(p, dst)


def _features_and_matches(pycolmap, db: Path, images: Path, names: list[str], cfg: SfmConfig, matcher: str,
                          seconds: dict, bar=None, camera_model: str = "SIMPLE_RADIAL", single_camera: bool = True) -> None:
    """SIFT features of `names` (in `images`) and their geometrically verified matches (every pair,
    or sequential) into the database `db`: what `rg sfm` maps and triangulate_posed triangulates."""
    t = time.perf_counter()
    if bar is not None:
        bar.set_postfix(stage="features", photos=len(names))
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    ext = pycolmap.FeatureExtractionOptions()
    ext.num_threads, ext.max_image_size = cfg.threads, cfg.max_image_size
    ext.sift.max_num_features, ext.sift.peak_threshold = cfg.max_features, cfg.peak_threshold
    pycolmap.extract_features(db, images, image_names=names,
                              camera_mode=pycolmap.CameraMode.SINGLE if single_camera else
                              pycolmap.CameraMode.PER_IMAGE, reader_options=reader, extraction_options=ext,
                              device=pycolmap.Device.cpu)
    seconds["features"] = round(time.perf_counter() - t, 3)
    if bar is not None:
        bar.update(1)
        bar.set_postfix(stage=f"matching ({matcher})")
    t = time.perf_counter()
    match = pycolmap.FeatureMatchingOptions()
    match.num_threads = cfg.threads
    if matcher == "exhaustive":
        pycolmap.match_exhaustive(db, matching_options=match, device=pycolmap.Device.cpu)
    else:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = cfg.overlap
        pycolmap.match_sequential(db, matching_options=match, pairing_options=pairing, device=pycolmap.Device.cpu)
    seconds["matching"] = round(time.perf_counter() - t, 3)
    if bar is not None:
        bar.update(1)


def run_sfm(images_dir: str | Path, out: str | Path, cfg: SfmConfig | None = None, progress: bool = True) -> dict:
    """Poses for the photos in `images_dir` -> the scene folder `out` (module docstring); returns a
    summary: photos, registered, points, reprojection error, matcher, seconds per stage."""
    cfg = cfg or SfmConfig()
    images_dir, out = Path(images_dir), Path(out)
    photos = photo_files(images_dir)
    if not photos:
        raise SceneError(f"{images_dir}: holds no photos ({', '.join(PHOTO_SUFFIXES)} at its top level)")
    n = len(photos)
    if n < 2:
        raise SceneError(f"{images_dir}: structure from motion needs at least 2 photos, found 1 ({photos[0].name})")
    if (out / "sparse").exists():
        raise SceneError(f"{out / 'sparse'}: already holds a model; remove it or choose another --out")
    try:
        import pycolmap
    except ImportError as exc:
        raise SceneError("rg sfm needs pycolmap (pip install pycolmap; requirements.txt)") from exc
    from tqdm import tqdm

    images, db, work = out / "images", out / "database.db", out / ".sfm_models"
    _copy_photos(photos, images)
    db.unlink(missing_ok=True)                 # features of another run would be matched too
    shutil.rmtree(work, ignore_errors=True)
    matcher = cfg.matcher if cfg.matcher != "auto" else ("exhaustive" if n <= cfg.exhaustive_max else "sequential")
    pycolmap.set_random_seed(cfg.seed)
    seconds = {}
    bar = tqdm(total=3, desc="sfm", unit="stage", disable=not progress, file=sys.stderr)
    try:
        with _quiet_colmap(pycolmap):
            _features_and_matches(pycolmap, db, images, [p.name for p in photos], cfg, matcher, seconds,
                                  bar=bar, camera_model=cfg.camera_model, single_camera=cfg.single_camera)
            t = time.perf_counter()
            opts = pycolmap.IncrementalPipelineOptions()
            opts.num_threads, opts.random_seed = cfg.threads, cfg.seed
            opts.min_model_size = min(opts.min_model_size, max(2, n // 4))   # small sets keep small models
            tried = [2]   # the initial pair, then one photo a callback

            def next_image():
                tried[0] += 1
                bar.set_postfix(stage="mapping", photos_tried=f"{min(tried[0], n)}/{n}")

            bar.set_postfix(stage="mapping")
            work.mkdir(parents=True)
            models = pycolmap.incremental_mapping(db, images, work, options=opts, next_image_callback=next_image)
            seconds["mapping"] = round(time.perf_counter() - t, 3)
            bar.update(1)
        features, pairs = _pair_stats(pycolmap, db, opts.min_num_matches)
        if not models:
            raise SceneError(
                f"{images_dir}: pycolmap found no model: {pairs} pairs of the {n} photos share >= {opts.min_num_matches} "
                f"verified matches (median {features} features a photo). Photos need overlapping views of textured "
                "surfaces; small or smooth photos find more features with --sfm.peak_threshold 0.002")
        best = max(models.values(), key=lambda r: r.num_reg_images())
        k = best.num_reg_images()
        need = math.ceil(cfg.min_registered * n - 1e-9)
        if k < need:
            left = sorted({p.name for p in photos} - {im.name for im in best.images.values() if im.has_pose})
            shown = ", ".join(left[:8]) + (f" and {len(left) - 8} more" if len(left) > 8 else "")
            raise SceneError(
                f"{images_dir}: pycolmap registered only {k} of {n} images (not {shown}; {len(models)} model(s), "
                f"{pairs} matched pairs, median {features} features a photo); --sfm.min_registered "
                f"{cfg.min_registered} needs {need}. Add photos between those views, try --sfm.peak_threshold 0.002, "
                "or lower --sfm.min_registered to keep the model")
        sparse = out / "sparse" / "0"
        sparse.mkdir(parents=True)
        best.write(str(sparse))
    finally:
        bar.close()
        shutil.rmtree(work, ignore_errors=True)
    return {"scene": str(out), "images": n, "registered": k, "points3D": best.num_points3D(), "models": len(models),
            "mean_reprojection_error_px": round(float(best.compute_mean_reprojection_error()), 4),
            "features_median": features, "matched_pairs": pairs, "matcher": matcher, "camera_model": cfg.camera_model,
            "seconds": {**seconds, "total": round(sum(seconds.values()), 3)}}


def triangulate_posed(frames, cfg: SfmConfig | None = None, min_angle_deg: float = 0.25, min_track: int = 2,
                      max_error_px: float = 2.0):
    """Sparse points for posed photos that came without any (a ReasoningGD or BOP scene with depth
    withheld, a nerfstudio capture without its ply): `rg sfm`'s SIFT features and verified matches
    (_features_and_matches, every pair up to cfg.exhaustive_max), then COLMAP's triangulation at the
    frames' own poses and pinhole intrinsics (pycolmap.triangulate_points, nothing refined). Known
    poses cannot be corrupted by low-parallax points, so `min_angle_deg` is below COLMAP's 1.5 deg:
    near-static cameras (a few mm apart at a metre) still give depth to within a few percent.
    SIFT's contrast threshold defaults to 0.002 (`rg sfm`'s advice for small or smooth photos): a
    320x240 synthetic view gives 3x the points at 0.5 % depth error instead of 3 %.
    Returns io.scene.SparsePoints in the frames' world, or None (pycolmap missing, nothing triangulated)."""
    import tempfile

    import cv2
    import numpy as np

    from .scene import SparsePoints

    cfg = cfg or SfmConfig(peak_threshold=0.002)
    try:
        import pycolmap
    except ImportError:
        return None
    frames = list(frames)
    if len(frames) < 2:
        return None
    with tempfile.TemporaryDirectory(prefix="rg_triangulate_") as tmp, _quiet_colmap(pycolmap):
        tmp = Path(tmp)
        images, db_path, out = tmp / "images", tmp / "database.db", tmp / "model"
        images.mkdir()
        out.mkdir()
        names, sizes = [], []
        for i, f in enumerate(frames):
            rgb = f.load_rgb()
            name = f"{i:05d}.png"
            cv2.imwrite(str(images / name), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
            names.append(name)
            sizes.append(rgb.shape[1::-1])
        pycolmap.set_random_seed(cfg.seed)
        matcher = cfg.matcher if cfg.matcher != "auto" else ("exhaustive" if len(frames) <= cfg.exhaustive_max else "sequential")
        _features_and_matches(pycolmap, db_path, images, names, cfg, matcher, {}, camera_model="PINHOLE",
                              single_camera=False)
        rec = pycolmap.Reconstruction()
        db = pycolmap.Database.open(str(db_path))
        try:
            by_name = {im.name: im for im in db.read_all_images()}
            for name, f, (w, h) in zip(names, frames, sizes):
                im, K = by_name[name], np.asarray(f.intrinsics.K, np.float64)
                cam = pycolmap.Camera(model="PINHOLE", width=int(w), height=int(h),
                                      params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], camera_id=im.camera_id)
                db.update_camera(cam)
                rec.add_camera_with_trivial_rig(cam)
                w2c = np.linalg.inv(np.asarray(f.cam_to_world, np.float64))
                rec.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=im.camera_id, image_id=im.image_id),
                                                 pycolmap.Rigid3d(w2c[:3, :4]))
        finally:
            db.close()
        opts = pycolmap.IncrementalPipelineOptions()
        opts.num_threads = cfg.threads
        opts.triangulation.min_angle = opts.mapper.filter_min_tri_angle = min_angle_deg   # both tests
        rec = pycolmap.triangulate_points(rec, db_path, images, out, options=opts)
        pts = [(p.xyz, p.color) for p in rec.points3D.values()
               if p.track.length() >= min_track and p.error <= max_error_px]
    if len(pts) < 4:
        return None
    xyz = np.array([p[0] for p in pts], np.float64)
    rgb = np.array([p[1] for p in pts], np.uint8)
    return SparsePoints(xyz, rgb, f"triangulated at the known poses (pycolmap): {len(xyz)} points")
