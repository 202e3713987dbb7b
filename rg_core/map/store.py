"""Map files: one versioned file (torch's safe `weights_only` format: tensors, numbers, strings).

Holds the Gaussians, the configuration and, per keyframe, pose, intrinsics, stamp and the
working-resolution image (uint8) and depth (float32 m), which the feature and grounding stages use;
since version 2 also the feature field (`mapper.field`: latents, mappers, scale transform, config),
since version 3 what people taught it (`mapper.taught`, map/taught.py); optionally how it was made
(`mapper.built`: kind, world scale, the photo fit's curve; absent in older files, read as empty).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..config import ConfigError, MapConfig, config_from_dict, config_to_dict
from .keyframes import Keyframe
from .mapper import Mapper
from .taught import TaughtSet

FORMAT = "rg-map"
VERSION = 3
READABLE = (1, 2, 3)  # version 1: no "field" entry (read as None); before 3: nothing taught


class MapFileError(ValueError):
    """A map file that cannot be read; the message names the file and the problem."""


def save_map(mapper: Mapper, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if getattr(mapper, "field", None) is not None:
        mapper.field.sync()  # latents follow Gaussians added or pruned since the last training step
    data = {
        "format": FORMAT,
        "version": VERSION,
        "config": config_to_dict(mapper.cfg),
        "gaussians": mapper.gaussians.state_dict(),
        "keyframes": [{
            "index": kf.index, "stamp": kf.stamp,
            "cam_to_world": torch.from_numpy(np.asarray(kf.cam_to_world, np.float64)),
            "K": torch.from_numpy(np.asarray(kf.K, np.float64)),
            "rgb": (kf.rgb * 255.0).round().clamp(0, 255).to(torch.uint8),
            "depth": kf.depth.float(),
        } for kf in mapper.keyframes],
        "stats": {"frames": mapper.frames_seen, **{k: int(v) for k, v in mapper.totals.items()}},
        # Masks, scales, embeddings per keyframe and the PCA basis (None until computed).
        "supervision": mapper.supervision.state_dict() if mapper.supervision is not None else None,
        # The feature field (rg_core.field.FeatureField attaches itself as mapper.field); None until built.
        "field": mapper.field.state_dict() if getattr(mapper, "field", None) is not None else None,
        "taught": mapper.taught.state_dict(),
        # How it was made (map.run.build_map): kind, the world's scale (io/world_scale.py), the photo fit's curve.
        "built": dict(getattr(mapper, "built", {}) or {}),
    }
    tmp = path.with_name(path.name + ".tmp")
    try:
        torch.save(data, tmp)
        tmp.replace(path)  # never leave a half-written map behind
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def load_map(path: str | Path) -> Mapper:
    path = Path(path)
    if not path.is_file():
        raise MapFileError(f"{path}: map file not found")
    try:
        data = torch.load(path, weights_only=True, map_location="cpu")
    except Exception as exc:  # noqa: BLE001 - any unpickling failure means the same to the user
        raise MapFileError(f"{path}: not a readable map file ({exc.__class__.__name__}: {exc})") from exc
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise MapFileError(f"{path}: not an {FORMAT} file")
    if data.get("version") not in READABLE:
        raise MapFileError(f"{path}: map format version {data.get('version')}, this build reads versions "
                           f"{', '.join(map(str, READABLE))}")
    try:
        # Maps saved before `antialiased` existed were trained with the classic filter.
        cfg = config_from_dict({"antialiased": False, **data["config"]}, MapConfig)
    except ConfigError as exc:
        raise MapFileError(f"{path}: bad configuration in map: {exc}") from exc
    mapper = Mapper(cfg)
    try:
        mapper.gaussians.load_state_dict(data["gaussians"])
    except (KeyError, ValueError) as exc:
        raise MapFileError(f"{path}: {exc}") from exc
    mapper.optim.sync()
    for kf in data["keyframes"]:
        mapper.keyframes.append(Keyframe(int(kf["index"]), float(kf["stamp"]), kf["cam_to_world"].numpy(),
                                         kf["K"].numpy(), kf["rgb"].float() / 255.0, kf["depth"].float()))
    if data.get("supervision") is not None:
        from ..perception.supervision import SupervisionSet

        try:
            mapper.supervision = SupervisionSet.from_state_dict(data["supervision"])
        except (KeyError, ValueError, TypeError) as exc:
            raise MapFileError(f"{path}: bad supervision data ({exc})") from exc
    try:
        mapper.taught = TaughtSet.from_state_dict(data.get("taught"))
    except (KeyError, ValueError, TypeError, AttributeError) as exc:
        raise MapFileError(f"{path}: bad taught objects ({exc})") from exc
    built = data.get("built")
    mapper.built = dict(built) if isinstance(built, dict) else {}   # maps saved before it: nothing recorded
    stats = data.get("stats", {})
    mapper.frames_seen = int(stats.get("frames", len(mapper.keyframes)))
    for k in mapper.totals:
        mapper.totals[k] = int(stats.get(k, 0))
    if mapper.keyframes:
        mapper.last_stamp = max(kf.stamp for kf in mapper.keyframes)
    mapper.field = None  # after the stats: the field records the map's prune count
    if data.get("field") is not None:
        from ..field import FeatureField

        try:
            FeatureField.from_state_dict(mapper, data["field"])  # attaches itself as mapper.field
        except (KeyError, ValueError, TypeError, RuntimeError, ConfigError) as exc:
            raise MapFileError(f"{path}: bad feature field data ({exc})") from exc
    return mapper
