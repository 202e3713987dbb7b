"""Model registry, download, ONNX export, verification and named presets (`rg models ...`, `--preset`)."""
from .registry import MODELS, ChecksumError, ModelError, ModelMissingError, ModelSpec, get_spec, models_dir  # noqa: F401
from .presets import PRESETS, apply_reasoner, make_perception, make_text_encoder, perception_spec  # noqa: F401


def list_models(root=None) -> list[dict]:
    """Every registry model: what it is, which backend uses it, and what of it is on this machine."""
    from pathlib import Path

    from .export import read_export
    from .fetch import read_manifest
    from .registry import model_dir

    out = []
    for s in MODELS.values():
        man = read_manifest(s.name, root)
        exp = read_export(s.name, root)
        needs_export = s.kind in ("clip", "sam")
        present = man is not None and all((model_dir(s.name, root) / f).is_file() for f in man["files"])
        status = ("missing" if not present else "fetched, not exported" if needs_export and exp is None else "ready")
        out.append({"name": s.name, "kind": s.kind, "backend": s.backend, "repo": s.repo_id, "revision": s.revision,
                    "licence": s.licence, "size": s.size, "cpu": s.cpu, "status": status,
                    "dir": str(Path(model_dir(s.name, root))), "source": s.source,
                    "next": None if status == "ready" else
                    f"rg models fetch {s.name}" if status == "missing" else f"rg models export {s.name}",
                    "presets": [p.name for p in PRESETS.values() if s.name in (p.sam, p.clip, p.lvlm)]})
    return out
