"""`rg synth`: a table-top or room scene in the ReasoningGD layout, rendered headless with pybullet.

Objects are dropped on a table (layout "room": on several tables) and settled with physics; views on
a ring of varying radius and height look at them (room: a walk from table to table, an arc around each). Each view gets RGB, depth (mm), visible instance ids, and one amodal mask per
object (the object rendered alone). Same seed, same bytes: nothing depends on the clock, the
machine's paths or the number of worker processes.
"""
from __future__ import annotations

import multiprocessing as mp
import os
import sys
from pathlib import Path

import numpy as np

from ..config import SynthConfig
from ..geometry.conventions import backproject, look_at, project
from ..io.images import write_depth, write_mask, write_rgb
from ..io.ply import write_ply
from ..io.scene import Frame, Intrinsics, Query, SceneObject, write_json, write_scene_metadata
from .catalogue import PYBULLET_OBJECTS, SHARED_OBJECTS, CatalogueEntry
from .pybullet_scene import PlacedObject, load_static_scene, mesh_aabb, render, settle, table_top


def default_objects_dir() -> Path | None:
    """`../shared/data/objects` beside the checkout (or $RG_OBJECTS_DIR), if it exists."""
    env = os.environ.get("RG_OBJECTS_DIR")
    cands = [Path(env)] if env else []
    here = Path(__file__).resolve()
    cands += [parent / "shared" / "data" / "objects" for parent in here.parents[2:5]]
    cands += [Path.cwd().parent / "shared" / "data" / "objects"]
    for c in cands:
        if c.is_dir():
            return c
    return None


def choose_objects(n: int, rng: np.random.Generator, objects_dir: Path | None,
                   same_category: int = 0) -> list[tuple[CatalogueEntry, str]]:
    """Pick n catalogue entries (urdf path per entry), one per category while categories last, but
    `same_category` of them from categories already picked, under other names (as far as the picked
    categories have more: cups, bowls, screwdrivers). More objects than the shared meshes: the
    pybullet_data ones whose names are new join the pool."""
    pool: list[tuple[CatalogueEntry, str]] = []
    if objects_dir is not None and objects_dir.is_dir():
        pool = [(e, str(objects_dir / e.folder / "model.urdf")) for e in SHARED_OBJECTS
                if (objects_dir / e.folder / "model.urdf").is_file()]
    if not pool:
        pool = [(e, e.folder) for e in PYBULLET_OBJECTS]
    elif n > len(pool):
        pool += [(e, e.folder) for e in PYBULLET_OBJECTS if e.name not in {q.name for q, _ in pool}]
    order = rng.permutation(len(pool))
    chosen, seen = [], set()
    distinct = n - min(same_category, max(n - 1, 0))
    for i in order:  # distinct categories first ...
        if len(chosen) < distinct and pool[i][0].category not in seen:
            chosen.append(pool[i])
            seen.add(pool[i][0].category)
    names_of = lambda c: {e.name for e, _ in pool if e.category == c}                 # noqa: E731
    if same_category and chosen and all(len(names_of(e.category)) < 2 for e, _ in chosen):
        multi = next((i for i in order if len(names_of(pool[i][0].category)) >= 2), None)
        if multi is not None:   # make room for repeats: the last distinct pick becomes a category with several
            seen.discard(chosen[-1][0].category)
            chosen[-1] = pool[multi]
            seen.add(pool[multi][0].category)
    for i in order:  # ... the requested repeats of categories already there (under another name) ...
        if (same_category and len(chosen) < n and pool[i][0].category in seen
                and pool[i][0].name not in {e.name for e, _ in chosen}):
            chosen.append(pool[i])
    for i in order:  # ... then repeats if the scene asks for more objects than categories
        if len(chosen) >= n:
            break
        if pool[i] not in chosen:
            chosen.append(pool[i])
    while len(chosen) < n:
        chosen.append(pool[int(order[len(chosen) % len(pool)])])
    return chosen


def camera_ring(cfg: SynthConfig, target: np.ndarray, rng: np.random.Generator) -> list[np.ndarray]:
    """Camera-to-world poses (OpenCV axes) on a ring of varying radius and height."""
    poses = []
    r_lo, r_hi = cfg.ring_radius
    h_lo, h_hi = cfg.ring_height
    phase = rng.uniform(0, 2 * np.pi)
    for i in range(cfg.views):
        az = phase + 2 * np.pi * i / cfg.views + rng.uniform(-0.3, 0.3) * np.pi / max(cfg.views, 1)
        r = r_lo + (r_hi - r_lo) * (0.5 + 0.5 * np.sin(3 * az + 1.0)) * rng.uniform(0.8, 1.0)
        h = h_lo + (h_hi - h_lo) * (0.5 + 0.5 * np.cos(2 * az)) * rng.uniform(0.7, 1.0)
        eye = target + np.array([r * np.cos(az), r * np.sin(az), h])
        look = target + rng.uniform(-0.03, 0.03, size=3)
        poses.append(look_at(eye, look))
    return poses


def table_centres(cfg: SynthConfig) -> tuple[tuple[float, float], ...]:
    """Table centres (x, y) of the layout: one at the origin, or a room's grid `table_spacing` apart."""
    if cfg.layout != "room":
        return ((0.0, 0.0),)
    cols = int(np.ceil(np.sqrt(cfg.tables)))
    rows = int(np.ceil(cfg.tables / cols))
    return tuple((float((i % cols - (cols - 1) / 2) * cfg.table_spacing),
                  float((i // cols - (rows - 1) / 2) * cfg.table_spacing)) for i in range(cfg.tables))


def camera_walk(cfg: SynthConfig, tables: tuple[tuple[float, float], ...], top: float,
                rng: np.random.Generator) -> list[np.ndarray]:
    """A room walk: the tables visited in a loop, the views shared among them, each table seen on a
    270-degree arc `room_radius` from its centre at `room_height` above the floor (default 0.9-1.3 m
    and 0.9-1.3 m: a robot's head height), looking at the table top."""
    poses = []
    per = np.array_split(np.arange(cfg.views), len(tables))
    centre = np.mean(np.asarray(tables), 0)
    for t, idx in enumerate(per):
        c = np.array([*tables[t], top + 0.05])
        start = np.arctan2(*(np.asarray(tables[t]) - centre)[::-1]) - 0.75 * np.pi   # arc faces the room's middle
        for j, _ in enumerate(idx):
            az = start + 1.5 * np.pi * j / max(len(idx) - 1, 1) + rng.uniform(-0.02, 0.02)
            r = rng.uniform(*cfg.room_radius)
            eye = c + np.array([r * np.cos(az), r * np.sin(az), 0.0])
            eye[2] = rng.uniform(*cfg.room_height)
            poses.append(look_at(eye, c + rng.uniform(-0.08, 0.08, size=3)))
    return poses


_WORKER: dict = {}


def _init_worker(placed: list[PlacedObject], K: np.ndarray, cfg: SynthConfig, out: str) -> None:
    """Load the settled scene once per process: the full scene and each object alone (with its box,
    so a view that cannot see it skips its render)."""
    p, cid, uids = load_static_scene(placed, tables=table_centres(cfg))
    alone = {o.object_id: load_static_scene([o], with_table=False) for o in placed}
    boxes = {oid: mesh_aabb(pa, ca, ua[oid]) for oid, (pa, ca, ua) in alone.items()}
    _WORKER.update(p=p, cid=cid, uids=uids, alone=alone, boxes=boxes, K=K, cfg=cfg, out=Path(out))


def _box_in_view(lo: np.ndarray, hi: np.ndarray, K: np.ndarray, c2w: np.ndarray, width: int, height: int,
                 near: float) -> bool:
    """Could any part of the box lo..hi [3] show in the view? Conservative: False only when all its
    corners lie behind the near plane or all beyond one image border."""
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    with np.errstate(divide="ignore", invalid="ignore"):
        uv, z = project(corners, np.asarray(K, np.float64), np.asarray(c2w, np.float64))   # [8, 2], [8]
    if (z <= near).all():
        return False
    if (z <= near).any():                                         # straddles the camera plane: may show
        return True
    return not ((uv[:, 0] < 0).all() or (uv[:, 0] >= width).all() or (uv[:, 1] < 0).all()
                or (uv[:, 1] >= height).all())


def _close_worker() -> None:
    w = _WORKER
    for pa, ca, _ in w["alone"].values():
        pa.disconnect(ca)
    w["p"].disconnect(w["cid"])
    w.clear()


def _render_view(item: tuple[int, np.ndarray]) -> tuple[int, np.ndarray, np.ndarray]:
    """Render and write one view; return its sparse coloured points (for points3d.ply)."""
    index, c2w = item
    w = _WORKER
    cfg, K, out = w["cfg"], w["K"], w["out"]
    W, H = cfg.width, cfg.height
    rgb, depth, seg = render(w["p"], w["cid"], K, c2w, W, H, cfg.near, cfg.far)
    visible = np.zeros((H, W), np.uint8)
    for oid, uid in w["uids"].items():
        visible[seg == uid] = oid
    write_rgb(out / "images" / f"{index:04d}.png", rgb)
    write_depth(out / "depth" / f"{index:04d}.png", depth)
    write_mask(out / "mask_visible" / f"{index:04d}.png", visible)
    for oid, (pa, ca, ua) in w["alone"].items():
        if _box_in_view(*w["boxes"][oid], K, c2w, W, H, cfg.near):
            _, _, seg_a = render(pa, ca, K, c2w, W, H, cfg.near, cfg.far)
            amodal = seg_a == ua[oid]
        else:
            amodal = np.zeros((H, W), bool)
        write_mask(out / "mask_complete" / f"{index:04d}" / f"{oid}.png", amodal)
    step = max(1, min(W, H) // 60)
    pts = backproject(depth, K, c2w)[::step, ::step].reshape(-1, 3)
    col = rgb[::step, ::step].reshape(-1, 3)
    ok = depth[::step, ::step].reshape(-1) > 0
    return index, pts[ok], col[ok]


def _voxel_mean(points: np.ndarray, colors: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """Average points and colours per voxel, in a deterministic (sorted) order."""
    keys = np.floor(points / voxel).astype(np.int64)
    uniq, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    cnt = np.bincount(inv).astype(np.float64)[:, None]
    P = np.stack([np.bincount(inv, points[:, k]) for k in range(3)], 1) / cnt
    C = np.stack([np.bincount(inv, colors[:, k].astype(np.float64)) for k in range(3)], 1) / cnt
    return P, np.clip(np.rint(C), 0, 255).astype(np.uint8)


def generate_scene(out: str | Path, cfg: SynthConfig, objects_dir: Path | None = None,
                   progress: bool = True) -> dict:
    """Generate a scene folder; returns a summary dict (counts, object names, paths)."""
    from tqdm import tqdm

    if cfg.views < 1 or cfg.objects < 1 or cfg.width < 8 or cfg.height < 8:
        raise ValueError(f"synth: need views >= 1, objects >= 1 and images of at least 8x8, got {cfg}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(cfg.seed)
    chosen = choose_objects(cfg.objects, rng, objects_dir, cfg.same_category)
    tables = table_centres(cfg)
    placed = settle([(urdf, e.scale) for e, urdf in chosen], rng,
                    cfg.room_spread if cfg.layout == "room" else cfg.spread, cfg.settle_steps, tables)

    lo, hi = table_top()
    if cfg.layout == "room":
        poses = camera_walk(cfg, tables, float(hi[2]), rng)
    else:
        poses = camera_ring(cfg, np.array([0.0, 0.0, hi[2] + 0.05]), rng)
    fy = (cfg.height / 2.0) / np.tan(np.radians(cfg.fov_y_deg) / 2.0)
    intr = Intrinsics(fy, fy, cfg.width / 2.0 - 0.5, cfg.height / 2.0 - 0.5, cfg.width, cfg.height)

    n_workers = max(1, min(cfg.workers, cfg.views))
    indexed = list(enumerate(poses))
    init = (placed, intr.K, cfg, str(out))
    points: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    bar = tqdm(total=cfg.views, desc="render views", unit="view", disable=not progress, file=sys.stderr)
    if n_workers == 1:
        _init_worker(*init)
        results = map(_render_view, indexed)
        for index, pts, col in results:
            points[index] = (pts, col)
            bar.update(1)
        _close_worker()
    else:
        with mp.get_context("spawn").Pool(n_workers, initializer=_init_worker, initargs=init) as pool:
            for index, pts, col in pool.imap_unordered(_render_view, indexed):
                points[index] = (pts, col)
                bar.update(1)
    bar.close()

    frames = [Frame(index=i, intrinsics=intr, cam_to_world=c2w, image_path=out / "images" / f"{i:04d}.png")
              for i, c2w in indexed]
    test = [f for f in frames if f.index % cfg.test_every == 0]
    train = [f for f in frames if f.index % cfg.test_every != 0]
    P = np.concatenate([points[f.index][0] for f in train or frames])
    C = np.concatenate([points[f.index][1] for f in train or frames])
    P, C = _voxel_mean(P, C, cfg.point_cloud_voxel)
    write_ply(out / "points3d.ply", P, C)

    p, cid, uids = load_static_scene(placed, tables=tables)
    objects = []
    for o, (entry, _) in zip(placed, chosen):
        amin, amax = mesh_aabb(p, cid, uids[o.object_id])
        objects.append(SceneObject(o.object_id, entry.name, entry.category,
                                   [round(float(v), 5) for v in amin], [round(float(v), 5) for v in amax]))
    p.disconnect(cid)
    queries = [Query(o.object_id, entry.name, list(entry.implicit)) for o, (entry, _) in zip(placed, chosen)]
    write_scene_metadata(out, train, test, objects, queries)
    write_json(out / "synth.json", {
        "generator": "rg synth", "seed": cfg.seed, "views": cfg.views, "size": [cfg.width, cfg.height],
        "layout": cfg.layout, "tables": [list(t) for t in tables],
        "objects": [{"id": o.object_id, "source": Path(o.urdf).parent.name if o.urdf.endswith("model.urdf")
                     else o.urdf, "scale": o.scale, "position": list(o.position),
                     "orientation_xyzw": list(o.orientation)} for o in placed],
    })
    return {"scene": str(out), "views": cfg.views, "train": len(train), "test": len(test),
            "size": [cfg.width, cfg.height], "objects": [o.name for o in objects], "points": int(len(P)),
            "objects_source": "shared" if chosen and chosen[0][1].endswith("model.urdf") else "pybullet_data"}
