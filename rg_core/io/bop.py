"""Reader for BOP-format scenes (https://bop.felk.cvut.cz, e.g. YCB-Video test scenes): real photos
with ground-truth object poses and masks, so `rg map`, `rg eval` and `rg report` measure on them.

Layout of one scene folder (BOP conventions: millimetres, rotations row-major, x right / y down /
z forward camera axes, i.e. OpenCV)::

    scene_camera.json   {im_id: {cam_K [9], depth_scale, cam_R_w2c [9]?, cam_t_w2c [3]? (mm)}}
    scene_gt.json       {im_id: [{obj_id, cam_R_m2c [9], cam_t_m2c [3] (mm)}, ...]}
    rgb/NNNNNN.png      colour (or .jpg);  depth/NNNNNN.png  uint16, depth_mm = value * depth_scale
    mask_visib/IMG_GT.png, mask/IMG_GT.png   visible / amodal masks, IMG_GT = {im_id:06d}_{gt_idx:06d}
    models/obj_XXXXXX.ply  object meshes in mm (or ../models, ../../models: BOP's dataset layout)
    obj_names.json      optional {obj_id: "006_mustard_bottle"}

Camera poses come from cam_R_w2c / cam_t_w2c (world -> camera, mm) turned into our camera-to-world
in metres. BOP test scenes often have none: then the world is the frame of one object present in
every image (`BopOptions.anchor_object`, default the most visible one), which is only right when
the objects do not move relative to each other; that is checked, and a scene where they move is
refused (or read one image alone with `BopOptions.single_image`).
"""
from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..geometry.conventions import PoseError, check_rigid
from .images import SceneError, read_mask
from .queries import default_queries, description_categories
from .scene import Frame, Intrinsics, Scene, SceneObject, _load_json
from .ycb import ycb_class_name

# BOP's YCB-V object ids 1..21 (the 21 YCB-Video classes, in YCB-Video's own order).
YCBV_NAMES = ("002_master_chef_can", "003_cracker_box", "004_sugar_box", "005_tomato_soup_can",
              "006_mustard_bottle", "007_tuna_fish_can", "008_pudding_box", "009_gelatin_box",
              "010_potted_meat_can", "011_banana", "019_pitcher_base", "021_bleach_cleanser", "024_bowl",
              "025_mug", "035_power_drill", "036_wood_block", "037_scissors", "040_large_marker",
              "051_large_clamp", "052_extra_large_clamp", "061_foam_brick")

MIN_DEPTH_M, MAX_DEPTH_M = 0.05, 20.0  # a plausible median depth of an RGB-D photo


@dataclass
class BopOptions:
    """How a BOP scene is read (defaults: every 8th image a test view, as for capture folders)."""

    test_every: int = 8                 # position % test_every == 0 -> test view; <= 0: no test views
    anchor_object: int | None = None    # obj_id whose frame is the world when there are no camera poses
    single_image: int | None = None     # im_id: read this image alone (it is then train and test view)
    static_tol_m: float = 0.01          # objects whose relative pose changes more are "moving"
    static_tol_deg: float = 2.0
    fallback_names: str = "ycbv"        # names by id when obj_names.json is absent: "ycbv" or "" (object N)


@dataclass(frozen=True)
class ObjectPose:
    """One scene_gt.json entry: object `obj_id` is the `gt_idx`-th annotation of its image."""

    obj_id: int
    gt_idx: int
    model_to_cam: np.ndarray  # [4, 4] metres, OpenCV camera axes


@dataclass
class BopFrame(Frame):
    """A BOP image: masks are one binary PNG per annotation, composed on load into the instance-id
    image every other scene kind gives (ids = obj_id), so evaluation and oracle supervision treat
    BOP scenes like synthetic ones."""

    im_id: int = 0
    gt: list[ObjectPose] = field(default_factory=list)
    mask_visib_dir: Path | None = None
    mask_dir: Path | None = None

    def pose_of(self, obj_id: int) -> ObjectPose | None:
        return next((g for g in self.gt if g.obj_id == obj_id), None)

    def _mask(self, folder: Path | None, g: ObjectPose, kind: str) -> np.ndarray:  # [H, W] bool
        if folder is None:
            raise SceneError(f"image {self.im_id}: the scene has no {kind}/ folder")
        path = folder / f"{self.im_id:06d}_{g.gt_idx:06d}.png"
        m = read_mask(path)
        self._check_size(m, path)
        return m > 127

    def load_visible_mask(self) -> np.ndarray:  # [H, W] uint8 obj ids, 0 = background
        ids = np.zeros((self.intrinsics.height, self.intrinsics.width), np.uint8)
        for g in self.gt:
            ids[self._mask(self.mask_visib_dir, g, "mask_visib")] = g.obj_id
        return ids

    def load_object_visible_mask(self, obj_id: int) -> np.ndarray:  # [H, W] bool (overlaps kept)
        g = self.pose_of(obj_id)
        if g is None:
            return np.zeros((self.intrinsics.height, self.intrinsics.width), bool)
        return self._mask(self.mask_visib_dir, g, "mask_visib")

    def load_complete_mask(self, object_id: int) -> np.ndarray:  # [H, W] bool amodal
        g = self.pose_of(object_id)
        if g is None:
            return np.zeros((self.intrinsics.height, self.intrinsics.width), bool)
        return self._mask(self.mask_dir, g, "mask")


@dataclass
class BopScene(Scene):
    models: dict[int, Path] = field(default_factory=dict)  # obj_id -> model PLY (mm)
    bop: dict = field(default_factory=dict)                # how the scene was read (poses source, anchor)

    @property
    def frames(self) -> list[Frame]:  # one image alone is both train and test view: listed once
        return sorted({f.index: f for f in self.train + self.test}.values(), key=lambda f: f.index)


def is_bop(root: str | Path) -> bool:
    root = Path(root)
    return (root / "scene_camera.json").is_file() and (root / "scene_gt.json").is_file()


def _image_size(path: Path) -> tuple[int, int]:
    """(width, height) from a PNG's IHDR without decoding it; other formats are decoded."""
    if not path.is_file():
        raise SceneError(f"{path}: file not found")
    with open(path, "rb") as fh:
        head = fh.read(24)
    if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
        return struct.unpack(">II", head[16:24])
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SceneError(f"{path}: not a readable image")
    return img.shape[1], img.shape[0]


def _pose(R, t, where: str) -> np.ndarray:
    """BOP rotation (9 numbers, row-major) and translation (mm) -> [4, 4] in metres."""
    try:
        T = np.eye(4)
        T[:3, :3] = np.asarray(R, np.float64).reshape(3, 3)
        T[:3, 3] = np.asarray(t, np.float64).reshape(3) / 1000.0
        return check_rigid(T, where)
    except (PoseError, ValueError, TypeError) as exc:
        raise SceneError(f"{where}: bad pose ({exc})") from exc


def _rel_change(A: np.ndarray, B: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation (deg) between two [4, 4] poses."""
    D = np.linalg.inv(A) @ B
    cos = np.clip((np.trace(D[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.linalg.norm(A[:3, 3] - B[:3, 3])), float(np.degrees(np.arccos(cos)))


def check_static(gt: dict[int, list[ObjectPose]], names: dict[int, str], where: Path,
                 tol_m: float, tol_deg: float) -> None:
    """Refuse a scene whose objects move relative to each other between images: compare every
    pair's relative pose in each image with the pair's first image. Names the object that takes
    part in most violations."""
    ims = sorted(gt)
    ids = sorted({g.obj_id for i in ims for g in gt[i]})
    bad, count = [], {o: 0 for o in ids}
    for ai, a in enumerate(ids):
        for b in ids[ai + 1:]:
            ref = None
            for i in ims:
                pa, pb = (next((g for g in gt[i] if g.obj_id == o), None) for o in (a, b))
                if pa is None or pb is None:
                    continue
                rel = np.linalg.inv(pa.model_to_cam) @ pb.model_to_cam
                if ref is None:
                    ref = (i, rel)
                    continue
                dt, dr = _rel_change(ref[1], rel)
                if dt > tol_m or dr > tol_deg:
                    bad.append((a, b, ref[0], i, dt, dr))
                    count[a] += 1
                    count[b] += 1
                    break
    if bad:
        mover = max(count, key=count.get)
        a, b, i0, i1, dt, dr = next(v for v in bad if mover in v[:2])
        raise SceneError(
            f"{where}: objects move relative to each other between images ({names[mover]!r}, obj_id {mover}, "
            f"in {count[mover]} pair(s)); e.g. {names[b]!r} relative to {names[a]!r} changes by {dt * 1000:.1f} mm / "
            f"{dr:.1f} deg between images {i0} and {i1} (tolerance {tol_m * 1000:.0f} mm / {tol_deg:g} deg). "
            "Camera poses cannot come from a static object: add cam_R_w2c/cam_t_w2c to scene_camera.json, "
            "or read one image alone (BopOptions.single_image)")


def _anchor(gt: dict[int, list[ObjectPose]], root: Path, opts: BopOptions) -> int:
    everywhere = set.intersection(*({g.obj_id for g in gt[i]} for i in gt))
    if opts.anchor_object is not None:
        if opts.anchor_object not in everywhere:
            raise SceneError(f"{root / 'scene_gt.json'}: anchor object {opts.anchor_object} is not in every image "
                             f"(objects in every image: {sorted(everywhere)})")
        return opts.anchor_object
    if not everywhere:
        raise SceneError(f"{root / 'scene_gt.json'}: no camera poses in scene_camera.json and no object is in "
                         "every image to define the world; read one image alone (BopOptions.single_image)")
    visible = {o: 0.0 for o in everywhere}  # prefer the most visible: its pose is the best measured
    info = root / "scene_gt_info.json"
    if info.is_file():
        data = _load_json(info)
        for i in gt:
            for g, inf in zip(gt[i], data.get(str(i), [])):
                if g.obj_id in visible:
                    visible[g.obj_id] += float(inf.get("px_count_visib", 0))
    return max(sorted(everywhere), key=lambda o: visible[o])


def _names(root: Path, ids: list[int], opts: BopOptions) -> dict[int, str]:
    raw: dict[int, str] = {}
    for path, key in ((root / "obj_names.json", None), (_models_dir(root) / "models_info.json", "name")):
        if path is not None and path.is_file():
            data = _load_json(path)
            for k, v in data.items():
                v = v.get(key) if key and isinstance(v, dict) else (v if key is None else None)
                if isinstance(v, str) and int(k) not in raw:
                    raw[int(k)] = v
    out = {}
    for o in ids:
        if o in raw:
            out[o] = ycb_class_name(raw[o])
        elif opts.fallback_names == "ycbv" and 1 <= o <= len(YCBV_NAMES):
            out[o] = ycb_class_name(YCBV_NAMES[o - 1])
        else:
            out[o] = f"object {o}"
    return out


def _models_dir(root: Path) -> Path:
    for d in (root / "models", root.parent / "models", root.parent.parent / "models"):
        if d.is_dir():
            return d
    return root / "models"


def _find_image(folder: Path, im_id: int) -> Path | None:
    for ext in (".png", ".jpg", ".jpeg", ".tif"):
        p = folder / f"{im_id:06d}{ext}"
        if p.is_file():
            return p
    return None


def _check_depth_scale(depth_path: Path, bop_scale: float, cam_path: Path, im_id: int) -> float:
    """Median valid depth in metres of one image; outside [5 cm, 20 m] means depth_scale is in the
    wrong unit: the error suggests the power of ten that brings the median to about a metre."""
    from .images import _imread

    raw = _imread(depth_path, -1)
    if raw.ndim != 2 or raw.dtype != np.uint16:
        raise SceneError(f"{depth_path}: depth must be a single-channel uint16 PNG, got {raw.dtype} {raw.shape}")
    valid = raw[raw > 0]
    if not valid.size:
        raise SceneError(f"{depth_path}: depth has no valid pixel")
    med = float(np.median(valid)) * bop_scale / 1000.0
    if not MIN_DEPTH_M <= med <= MAX_DEPTH_M:
        suggest = bop_scale * 10.0 ** (-round(np.log10(med)))
        raise SceneError(
            f"{cam_path}: image {im_id}: depth_scale {bop_scale:g} gives a median depth of {med:.4g} m in {depth_path.name} "
            f"(expected {MIN_DEPTH_M:g}-{MAX_DEPTH_M:g} m). BOP depth_scale converts PNG values to millimetres "
            f"(depth_mm = value * depth_scale); did you mean depth_scale {suggest:g}?")
    return med


def read_bop(root: str | Path, options: BopOptions | None = None) -> BopScene:
    """Read one BOP scene folder (see the module docstring); errors name the file and the problem."""
    opts = options or BopOptions()
    root = Path(root)
    if not root.is_dir():
        raise SceneError(f"{root}: BOP scene folder not found")
    cam_path, gt_path = root / "scene_camera.json", root / "scene_gt.json"
    cams, gts = _load_json(cam_path), _load_json(gt_path)
    try:
        cams = {int(k): v for k, v in cams.items()}
        gts = {int(k): v for k, v in gts.items()}
    except (ValueError, AttributeError) as exc:
        raise SceneError(f"{cam_path} / {gt_path}: keys must be image ids ({exc})") from exc
    for i in sorted(gts):
        if i not in cams:
            raise SceneError(f"{gt_path}: image {i} has annotations but no entry in scene_camera.json")
        if _find_image(root / "rgb", i) is None:
            raise SceneError(f"{gt_path}: image {i} has annotations but {root / 'rgb' / f'{i:06d}.png'} does not exist")
    ims = sorted(cams)
    if opts.single_image is not None:
        if opts.single_image not in cams:
            raise SceneError(f"{cam_path}: no image {opts.single_image} (images {ims[0]}..{ims[-1]})")
        ims = [opts.single_image]
    if not ims:
        raise SceneError(f"{cam_path}: no images")

    gt: dict[int, list[ObjectPose]] = {}
    for i in ims:
        poses = []
        for k, e in enumerate(gts.get(i, [])):
            where = f"{gt_path}: image {i} entry {k}"
            try:
                poses.append(ObjectPose(int(e["obj_id"]), k, _pose(e["cam_R_m2c"], e["cam_t_m2c"], where)))
            except (KeyError, TypeError) as exc:
                raise SceneError(f"{where}: needs obj_id, cam_R_m2c, cam_t_m2c ({exc})") from exc
        seen = [g.obj_id for g in poses]
        if len(seen) != len(set(seen)):
            raise SceneError(f"{gt_path}: image {i} holds several instances of one object ({sorted(seen)}); "
                             "instances of the same object are not supported yet")
        gt[i] = poses
    ids = sorted({g.obj_id for i in ims for g in gt[i]})
    names = _names(root, ids, opts)

    has_pose = ["cam_R_w2c" in cams[i] and "cam_t_w2c" in cams[i] for i in ims]
    if any(has_pose) and not all(has_pose):
        raise SceneError(f"{cam_path}: cam_R_w2c/cam_t_w2c given for some images only")
    c2w: dict[int, np.ndarray] = {}
    read_info: dict = {"images": len(ims), "objects": len(ids)}
    if all(has_pose):
        for i in ims:
            c2w[i] = np.linalg.inv(_pose(cams[i]["cam_R_w2c"], cams[i]["cam_t_w2c"], f"{cam_path}: image {i}"))
        read_info["camera_poses"] = "scene_camera.json"
    else:
        if len(ims) > 1:
            check_static(gt, names, gt_path, opts.static_tol_m, opts.static_tol_deg)
        anchor = _anchor(gt, root, opts)
        for i in ims:
            c2w[i] = np.linalg.inv(next(g for g in gt[i] if g.obj_id == anchor).model_to_cam)
        read_info["camera_poses"] = f"static object {anchor} ({names[anchor]}): world = its model frame"
        read_info["anchor_object"] = anchor

    rgb0 = _find_image(root / "rgb", ims[0])
    if rgb0 is None:
        raise SceneError(f"{root / 'rgb' / f'{ims[0]:06d}.png'}: file not found (image {ims[0]} of scene_camera.json)")
    W, H = _image_size(rgb0)
    vis_dir = root / "mask_visib" if (root / "mask_visib").is_dir() else None
    amo_dir = root / "mask" if (root / "mask").is_dir() else None
    frames = []
    for pos, i in enumerate(ims):
        cam = cams[i]
        rgb = _find_image(root / "rgb", i)
        if rgb is None:
            raise SceneError(f"{root / 'rgb' / f'{i:06d}.png'}: file not found (image {i} of scene_camera.json)")
        depth = root / "depth" / f"{i:06d}.png"
        if not depth.is_file():
            raise SceneError(f"{depth}: file not found (image {i} of scene_camera.json has no depth)")
        for p in [rgb, depth] + [d / f"{i:06d}_{g.gt_idx:06d}.png" for d in (vis_dir, amo_dir) if d for g in gt[i]]:
            if _image_size(p) != (W, H):
                raise SceneError(f"{p}: image is {'x'.join(map(str, _image_size(p)))}, expected {W}x{H}")
        try:
            K = np.asarray(cam["cam_K"], np.float64).reshape(3, 3)
            scale = float(cam.get("depth_scale", 1.0))
        except (KeyError, ValueError, TypeError) as exc:
            raise SceneError(f"{cam_path}: image {i}: needs cam_K (9 numbers) and depth_scale ({exc})") from exc
        if K[0, 0] <= 0 or K[1, 1] <= 0 or scale <= 0:
            raise SceneError(f"{cam_path}: image {i}: focal lengths and depth_scale must be positive")
        if pos == 0 or scale != float(cams[ims[0]].get("depth_scale", 1.0)):
            read_info.setdefault("median_depth_m", round(_check_depth_scale(depth, scale, cam_path, i), 3))
        frames.append(BopFrame(index=i, intrinsics=Intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], W, H),
                               cam_to_world=c2w[i], image_path=rgb, depth_path=depth, depth_scale=1000.0 / scale,
                               stamp=float(pos), visible_mask_path=vis_dir, complete_mask_dir=amo_dir,
                               im_id=i, gt=gt[i], mask_visib_dir=vis_dir, mask_dir=amo_dir))

    from .ply import read_ply_mesh

    models, objects = {}, []
    mdir = _models_dir(root)
    cats = description_categories()
    for o in ids:
        path = mdir / f"obj_{o:06d}.ply"
        verts, _ = read_ply_mesh(path)  # [N, 3] mm, model frame
        f0 = next(f for f in frames if f.pose_of(o) is not None)
        T = f0.cam_to_world @ f0.pose_of(o).model_to_cam  # model -> world, metres
        pts = verts / 1000.0 @ T[:3, :3].T + T[:3, 3]
        models[o] = path
        objects.append(SceneObject(o, names[o], cats.get(names[o], "object"), pts.min(0).tolist(), pts.max(0).tolist()))
    if opts.single_image is not None:
        train = test = frames
    else:
        n = opts.test_every
        train = [f for k, f in enumerate(frames) if n <= 0 or k % n != 0]
        test = [f for k, f in enumerate(frames) if n > 0 and k % n == 0]
    return BopScene(root=root, train=train, test=test, objects=objects,
                    queries=default_queries(objects), kind="bop", models=models, bop=read_info)
