"""Ground truth of the open-vocabulary segmentation benchmarks, read beside a scene.

- LERF-OVS as LangSplat released it: one JSON per labelled frame, `{"info": {"name", "width",
  "height"}, "objects": [{"category", "group", "segmentation": [[x, y], ...], "bbox": [x1, y1, x2,
  y2], "area", "iscrowd"}]}`, in the scene's `label/` folder or in `../label/<scene name>/`
  (LangSplat's layout: `lerf_ovs/label/figurines/frame_00041.json` beside `lerf_ovs/figurines/`).
  `info.name` names the image; the objects of one category are unioned into one mask.
- 3D-OVS: `segmentations/classes.txt` (one class a line) and `segmentations/<NN>/<class>.png` per
  labelled view, NN the image's position in name order; every class has a mask in every view.

Masks are rasterized at the labels' own size (polygons with cv2.fillPoly, vertices truncated to
whole pixels as LangSplat's scorer does), resized (nearest) to the photo's size and undistorted like
the photo, so they lie on the images the frames load.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from .images import SceneError, read_mask


@dataclass
class ViewLabels:
    """One labelled view: per category its polygons and boxes (LERF-OVS) or its mask file (3D-OVS)."""

    frame: object                    # scene.Frame
    source: Path
    size: tuple[int, int]            # (width, height) the labels were drawn at
    polygons: dict[str, list[np.ndarray]] = field(default_factory=dict)   # category -> [[P, 2] x, y]
    boxes: dict[str, np.ndarray] = field(default_factory=dict)            # category -> [K, 4] x1 y1 x2 y2
    mask_files: dict[str, Path] = field(default_factory=dict)             # class -> PNG (3D-OVS)

    @property
    def categories(self) -> list[str]:
        return list(self.polygons or self.mask_files)

    def masks(self) -> dict[str, np.ndarray]:
        """category -> bool [H, W] on the frame's (undistorted) image."""
        w, h = self.size
        out = {}
        for c in self.categories:
            if c in self.polygons:
                m = np.zeros((h, w), np.uint8)
                cv2.fillPoly(m, [p.astype(np.int32) for p in self.polygons[c]], 1)
            else:
                m = (read_mask(self.mask_files[c]) > 127).astype(np.uint8)
                if m.shape != (h, w):
                    raise SceneError(f"{self.mask_files[c]}: mask is {m.shape[1]}x{m.shape[0]}, the view's "
                                     f"other masks are {w}x{h}")
            out[c] = self._to_frame(m)
        return out

    def frame_boxes(self) -> dict[str, np.ndarray]:
        """category -> [K, 4] x1 y1 x2 y2 (x1 <= x2, y1 <= y2) in the frame's image pixels."""
        intr = self.frame.intrinsics
        sx, sy = intr.width / self.size[0], intr.height / self.size[1]
        out = {}
        for c, b in self.boxes.items():
            lo, hi = np.minimum(b[:, :2], b[:, 2:]), np.maximum(b[:, :2], b[:, 2:])
            lo, hi = (lo + 0.5) * [sx, sy] - 0.5, (hi + 0.5) * [sx, sy] - 0.5   # about pixel centres, as K scales
            und = getattr(self.frame, "undistort", None)
            if und is not None:   # the box of the box's outline, undistorted
                t = np.linspace(0.0, 1.0, 17)[:, None]
                rows = []
                for a, z in zip(lo, hi):
                    edge = np.concatenate([a + t * [z[0] - a[0], 0], a + t * [0, z[1] - a[1]],
                                           z - t * [z[0] - a[0], 0], z - t * [0, z[1] - a[1]]])
                    p = und.points(edge)
                    rows.append(np.concatenate([p.min(0), p.max(0)]))
                out[c] = np.array(rows)
            else:
                out[c] = np.concatenate([lo, hi], 1)
        return out

    def _to_frame(self, m: np.ndarray) -> np.ndarray:   # uint8 [h, w] at label size -> bool [H, W]
        intr = self.frame.intrinsics
        if m.shape != (intr.height, intr.width):
            m = cv2.resize(m, (intr.width, intr.height), interpolation=cv2.INTER_NEAREST)
        und = getattr(self.frame, "undistort", None)
        if und is not None:
            m = und.mask(m, self.source)
        return m > 0


@dataclass
class BenchmarkLabels:
    benchmark: str                   # "lerf_ovs" or "3d_ovs"
    views: list[ViewLabels]
    classes: list[str]               # 3D-OVS: the scene's classes; LERF-OVS: every category labelled
    source: Path


def _num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v)


def parse_lerf_label(path: Path) -> tuple[str, tuple[int, int], dict, dict]:
    """One LangSplat label file -> (image name, (width, height), category -> polygons [[P, 2]],
    category -> boxes [K, 4]); SceneError naming the file, the object and what is wrong."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise SceneError(f"{path}: not a readable JSON label file ({exc})") from exc
    info = data.get("info") if isinstance(data, dict) else None
    if not isinstance(info, dict) or not isinstance(data.get("objects"), list):
        raise SceneError(f'{path}: expected {{"info": {{"name", "width", "height"}}, "objects": [...]}} (LangSplat\'s '
                         "LERF-OVS label format)")
    name, w, h = info.get("name"), info.get("width"), info.get("height")
    if not isinstance(name, str) or not name or not isinstance(w, int) or not isinstance(h, int) or w <= 0 or h <= 0:
        raise SceneError(f"{path}: info needs a non-empty 'name' and positive integer 'width' and 'height', "
                         f"got {name!r}, {w!r}, {h!r}")
    polys: dict[str, list[np.ndarray]] = {}
    boxes: dict[str, list] = {}
    for i, ob in enumerate(data["objects"]):
        cat = ob.get("category") if isinstance(ob, dict) else None
        where = f"{path}: objects[{i}]"
        if not isinstance(cat, str) or not cat.strip():
            raise SceneError(f"{where}: needs a non-empty 'category'")
        where += f" ({cat!r})"
        seg = ob.get("segmentation")
        if not isinstance(seg, list) or not all(isinstance(p, (list, tuple)) and len(p) == 2 and all(map(_num, p))
                                               for p in seg):
            raise SceneError(f"{where}: 'segmentation' must be a polygon [[x, y], ...] of finite numbers")
        if len(seg) < 3:
            raise SceneError(f"{where}: the polygon has {len(seg)} point(s), at least 3 are needed")
        poly = np.asarray(seg, np.float64)   # [P, 2] x, y
        box = ob.get("bbox")
        if box is None:   # the polygon's bounds
            box = [*poly.min(0), *poly.max(0)]
        elif not (isinstance(box, (list, tuple)) and len(box) == 4 and all(map(_num, box))):
            raise SceneError(f"{where}: 'bbox' must be [x1, y1, x2, y2], got {box!r}")
        polys.setdefault(cat, []).append(poly)
        boxes.setdefault(cat, []).append([float(v) for v in box])
    return name, (w, h), polys, {c: np.asarray(b, np.float64) for c, b in boxes.items()}


def lerf_label_folder(root: Path) -> Path | None:
    """Where a scene's LERF-OVS label files are: `root/label/` or LangSplat's `root/../label/<name>/`."""
    for d in (root / "label", root.parent / "label" / root.name):
        if d.is_dir() and any(d.glob("*.json")):
            return d
    return None


def _by_name(frames: list) -> dict[str, object]:
    out = {}
    for f in frames:
        out.setdefault(f.image_path.name, f)
        out.setdefault(f.image_path.stem, f)
    return out


def read_lerf_labels(folder: Path, frames: list) -> BenchmarkLabels:
    """The label files of `folder`, each matched to the frame whose image it names."""
    names = _by_name(frames)
    views = []
    for path in sorted(Path(folder).glob("*.json")):
        name, size, polys, boxes = parse_lerf_label(path)
        f = names.get(name) or names.get(Path(name).stem)
        if f is None:
            some = ", ".join(sorted(x.image_path.name for x in frames)[:3])
            raise SceneError(f"{path}: labels image {name!r}, which is not among the scene's {len(frames)} images "
                             f"({some}, ...)")
        views.append(ViewLabels(f, path, size, polys, boxes))
    classes = sorted({c for v in views for c in v.polygons})
    return BenchmarkLabels("lerf_ovs", sorted(views, key=lambda v: v.frame.index), classes, Path(folder))


def read_3dovs_segmentations(root: Path, frames: list) -> BenchmarkLabels | None:
    """3D-OVS's segmentations/ folder of an LLFF scene (`frames` in image name order), or None."""
    seg = Path(root) / "segmentations"
    if not (seg / "classes.txt").is_file():
        return None
    classes = sorted({ln.strip() for ln in (seg / "classes.txt").read_text().splitlines() if ln.strip()})
    if not classes:
        raise SceneError(f"{seg / 'classes.txt'}: no class names (one a line)")
    views = []
    for d in sorted(p for p in seg.iterdir() if p.is_dir()):
        if not d.name.isdigit() or int(d.name) >= len(frames):
            raise SceneError(f"{d}: a view folder must be named by the image's position in name order "
                             f"(0-{len(frames) - 1}), got {d.name!r}")
        files = {c: d / f"{c}.png" for c in classes}
        missing = [c for c, p in files.items() if not p.is_file()]
        if missing:
            raise SceneError(f"{d}: no mask for class(es) {', '.join(missing)} (expected {d}/<class>.png for "
                             "every class of classes.txt)")
        f = frames[int(d.name)]
        first = read_mask(files[classes[0]])
        views.append(ViewLabels(f, d, (first.shape[1], first.shape[0]), mask_files=files))
    if not views:
        raise SceneError(f"{seg}: classes.txt but no view folder (segmentations/<NN>/<class>.png)")
    return BenchmarkLabels("3d_ovs", views, classes, seg)


def find_labels(root: Path, frames: list) -> BenchmarkLabels | None:
    """A scene's benchmark labels: LERF-OVS label files, else 3D-OVS segmentations, else None."""
    folder = lerf_label_folder(Path(root))
    if folder is not None:
        return read_lerf_labels(folder, frames)
    return read_3dovs_segmentations(Path(root), frames)

