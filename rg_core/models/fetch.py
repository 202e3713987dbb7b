"""`rg models fetch NAME`: download a registry model's files through huggingface_hub.

Why huggingface_hub: it speaks the hub's protocol (HEAD on /{repo}/resolve/{rev}/{file} for the
commit, ETag and size; the LFS redirect; GET with Range to resume an interrupted download) and it
honours HF_ENDPOINT (mirrors, a local server). HF_HUB_OFFLINE and HF_ENDPOINT are read here at call
time (huggingface_hub reads them once at import). After each download the file's SHA-256 is compared
with the registry's value or, failing that, with the hub's LFS ETag (the file's SHA-256); small
non-LFS files are compared with their git blob hash. A file that does not match is deleted and the
fetch fails, naming the file. What was fetched is recorded in NAME/rg_fetch.json (commit, hashes),
which `list` and `verify` read.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
import time
from pathlib import Path

from .registry import ChecksumError, ModelError, ModelMissingError, get_spec, model_dir

MANIFEST = "rg_fetch.json"
DEFAULT_ENDPOINT = "https://huggingface.co"
_SHA256 = re.compile(r"[0-9a-f]{64}")
_SHA1 = re.compile(r"[0-9a-f]{40}")


def offline() -> bool:
    return os.environ.get("HF_HUB_OFFLINE", "").strip().upper() in {"1", "ON", "YES", "TRUE"}


def endpoint() -> str:
    return (os.environ.get("HF_ENDPOINT") or DEFAULT_ENDPOINT).rstrip("/")


def file_hashes(path: Path) -> tuple[str, str]:
    """(sha256, git blob sha1) of a file, read once in 1 MiB chunks."""
    size = path.stat().st_size
    h256, h1 = hashlib.sha256(), hashlib.sha1(b"blob %d\0" % size)
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h256.update(chunk)
            h1.update(chunk)
    return h256.hexdigest(), h1.hexdigest()


def read_manifest(name: str, root: Path | None = None) -> dict | None:
    p = model_dir(name, root) / MANIFEST
    if not p.is_file():
        return None
    try:
        return json.loads(p.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def _check(path: Path, expected: str, what: str) -> str:
    """Hash `path` and compare with `expected` (64 hex: SHA-256; 40 hex: git blob sha1). Returns the SHA-256."""
    sha256, sha1 = file_hashes(path)
    got = sha256 if _SHA256.fullmatch(expected) else sha1
    if got != expected:
        raise ChecksumError(f"{path.name}: checksum mismatch ({what} says {expected}, the file has {got})")
    return sha256


def _forget(local: Path, filename: str) -> None:
    """Remove a bad file and huggingface_hub's record of it (else it would be trusted next time)."""
    local.joinpath(filename).unlink(missing_ok=True)
    meta = local / ".cache" / "huggingface" / "download"
    for p in (meta / f"{filename}.metadata", meta / f"{filename}.lock"):
        p.unlink(missing_ok=True)


def _missing_offline(name: str, local: Path, what: str) -> ModelMissingError:
    return ModelMissingError(
        f"{name}: {what} is not in the model cache {local} and HF_HUB_OFFLINE is set, so nothing can be "
        f"downloaded; run `rg models fetch {name}` on a machine with internet (or unset HF_HUB_OFFLINE), "
        f"or point RG_MODELS_DIR at a cache that holds it")


def fetch(name: str, root: Path | None = None, progress: bool = True) -> dict:
    """Download (or re-check) every file of model `name`; returns the manifest."""
    from huggingface_hub import get_hf_file_metadata, hf_hub_download, hf_hub_url
    from huggingface_hub.errors import EntryNotFoundError, HfHubHTTPError, OfflineModeIsEnabled

    spec = get_spec(name)
    local = model_dir(name, root)
    old = read_manifest(name, root) or {}
    if offline():
        if not old.get("files"):
            present = [local / (e if isinstance(e, str) else next((c for c in e if (local / c).is_file()), e[0]))
                       for e in spec.files]
            if not all(p.is_file() for p in present):
                raise _missing_offline(name, local, "the model")
            # Files placed by hand (no manifest): hash them now; nothing to compare with offline.
            files = {p.name: {"sha256": file_hashes(p)[0], "size": p.stat().st_size, "expected": None} for p in present}
            manifest = {"name": name, "repo_id": spec.repo_id, "revision": spec.revision, "commit": None,
                        "endpoint": None, "files": files, "note": "placed by hand: not checked against the hub"}
            (local / MANIFEST).write_text(json.dumps(manifest, indent=1))
            return manifest
        for fname, rec in old["files"].items():
            if not (local / fname).is_file():
                raise _missing_offline(name, local, fname)
            _check(local / fname, rec["sha256"], "the fetch manifest")
        return old
    ep = endpoint()
    local.mkdir(parents=True, exist_ok=True)
    if not progress:
        from huggingface_hub.utils import disable_progress_bars

        disable_progress_bars()
    t0 = time.perf_counter()
    files: dict[str, dict] = {}
    commit = None
    try:
        for entry in spec.files:
            choices = entry if isinstance(entry, tuple) else (entry,)
            meta, fname = None, None
            for fname in choices:
                url = hf_hub_url(spec.repo_id, fname, revision=spec.revision, endpoint=ep)
                try:
                    meta = get_hf_file_metadata(url, endpoint=ep)
                    break
                except EntryNotFoundError:
                    continue
            if meta is None:
                raise ModelError(f"{name}: {spec.repo_id}@{spec.revision} on {ep} holds none of {list(choices)}")
            commit = meta.commit_hash or commit
            expected = spec.sha256.get(fname) or (meta.etag or "").lower()
            if not (_SHA256.fullmatch(expected) or _SHA1.fullmatch(expected)):
                raise ModelError(f"{name}: the hub gave no usable hash for {fname} (ETag {meta.etag!r}); "
                                 f"cannot verify the download")
            target, force = local / fname, False
            if target.is_file():
                try:
                    sha = _check(target, expected, f"{ep} ({spec.repo_id}@{spec.revision})")
                    files[fname] = {"sha256": sha, "size": target.stat().st_size, "expected": expected}
                    continue  # already here and intact
                except ChecksumError:
                    force = True  # corrupted or outdated copy: download it again
            path = Path(hf_hub_download(spec.repo_id, fname, revision=spec.revision, local_dir=str(local),
                                        endpoint=ep, force_download=force))
            try:
                sha = _check(path, expected, f"{ep} ({spec.repo_id}@{spec.revision})")
            except ChecksumError as exc:
                _forget(local, fname)
                raise ChecksumError(f"{name}: downloaded {exc}; the file was deleted, run `rg models fetch "
                                    f"{name}` again (a persistent mismatch means the mirror serves other bytes)") from None
            files[fname] = {"sha256": sha, "size": path.stat().st_size, "expected": expected}
    except (HfHubHTTPError, OfflineModeIsEnabled, OSError) as exc:
        if isinstance(exc, ModelError):
            raise
        raise ModelError(f"{name}: download from {ep} failed ({type(exc).__name__}: {exc}); files already "
                         f"complete are kept and a partial one resumes when `rg models fetch {name}` runs again") from exc
    manifest = {"name": name, "repo_id": spec.repo_id, "revision": spec.revision, "commit": commit,
                "endpoint": ep, "files": files, "seconds": round(time.perf_counter() - t0, 3)}
    (local / MANIFEST).write_text(json.dumps(manifest, indent=1))
    return manifest


def fetched_file(name: str, choices, root: Path | None = None) -> Path:
    """Path of a fetched file (the first of `choices` present); a clear error naming the fetch command."""
    local = model_dir(name, root)
    for c in (choices if isinstance(choices, tuple) else (choices,)):
        if (local / c).is_file():
            return local / c
    raise ModelMissingError(f"{name}: {' or '.join(choices if isinstance(choices, tuple) else (choices,))} not "
                            f"found in {local}; run `rg models fetch {name}`")
