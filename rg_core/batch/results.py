"""A results folder: one JSON record per task (`<dir>/scenes/<name>.json`), written atomically (temp
file, then rename) when the task finishes, so a run stopped at any moment leaves only whole records.
A record says {"scene", "status": "ok" | "failed", "error", "settings", "result", "seconds", "node",
"pid"}; a rerun skips the "ok" ones (and, unless retried, the failed ones)."""
from __future__ import annotations

import json
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path


@dataclass
class Task:
    """One unit of work: its name (the record's file name), the payload the task function gets, and
    the settings a finished record must match to be reused."""

    name: str
    payload: dict
    settings: dict = field(default_factory=dict)


def _safe(name: str) -> str:
    bad = set('/\\:*?"<>|\0')
    if not name or name in (".", "..") or any(c in bad for c in name):
        raise ValueError(f"task name {name!r} cannot be a file name (no / \\ : * ? \" < > |)")
    return name


class ResultsDir:
    """`root/scenes/<name>.json` per task; `root` is created when missing."""

    def __init__(self, root: str | Path):
        self.root = Path(root)
        if self.root.exists() and not self.root.is_dir():
            raise ValueError(f"{self.root}: --results must be a folder, and this is a file")
        self.scenes = self.root / "scenes"
        self.scenes.mkdir(parents=True, exist_ok=True)

    def path(self, name: str) -> Path:
        return self.scenes / f"{_safe(name)}.json"

    def read(self, name: str) -> dict | None:
        """The record of `name`, or None when there is none (or it is not valid JSON: rerun it)."""
        p = self.path(name)
        try:
            return json.loads(p.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None

    def write(self, record: dict) -> Path:
        """Write one record atomically: a reader sees the old file or the whole new one."""
        p = self.path(record["scene"])
        fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=self.scenes)
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                json.dump(record, f, default=_jsonable)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, p)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        return p

    def pending(self, tasks: list[Task], retry_failed: bool = False) -> tuple[list[Task], dict[str, int]]:
        """The tasks to run now, and counts of those skipped ({"ok": n, "failed": m}). A finished
        record made with other settings is an error: mixing them would make the aggregate a blend."""
        todo, skipped = [], {"ok": 0, "failed": 0}
        for t in tasks:
            rec = self.read(t.name)
            if rec is None or rec.get("status") not in ("ok", "failed"):
                todo.append(t)
                continue
            if rec.get("settings", {}) != _plain(t.settings):
                diff = sorted(k for k in set(rec.get("settings", {})) | set(t.settings)
                              if rec.get("settings", {}).get(k) != _plain(t.settings).get(k))
                raise ValueError(f"{self.path(t.name)}: made with other settings ({', '.join(diff)} differ); "
                                 "use another --results folder, or delete that record to redo it")
            if rec["status"] == "failed" and retry_failed:
                todo.append(t)
            else:
                skipped[rec["status"]] += 1
        return todo, skipped


def _jsonable(o):
    """numpy scalars and arrays, paths: what an eval report may hold besides plain JSON."""
    if hasattr(o, "tolist"):
        return o.tolist()
    return str(o)


def _plain(d: dict) -> dict:
    """Settings as they read back from JSON (tuples become lists)."""
    return json.loads(json.dumps(d, default=_jsonable))
