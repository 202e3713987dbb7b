"""Many scenes (issue 64): the scene list `rg eval SCENE [SCENE ...]` takes, each scene's figures in a
few numbers, and their pooling over the dataset.

Pooled, per query kind (explicit, implicit, relational) and over all: mIoU and localization over
every (query, view) pair of every scene (each scene weighs by its pairs, as one big scene would),
confidence AUROC and ECE over every answer (a threshold is set on all of them at once, not per
scene), and seconds per scene. The pool keeps a few bytes per answer and per scene, never the
reports, so a driver's memory stays flat however many scenes it reads."""
from __future__ import annotations

import os
import re
from array import array
from pathlib import Path

import numpy as np

from ..io.captures import scene_kind
from ..io.images import SceneError
from .grounding import KINDS, auroc, expected_calibration_error

GROUPS = KINDS + ("all",)


def _is_list_file(p: Path) -> bool:
    return p.is_file() and scene_kind(p) is None


def _scene_folders(p: Path) -> list[Path]:
    """The scene folders directly inside `p` (a folder of scenes), sorted by name."""
    return sorted(c for c in p.iterdir() if c.is_dir() and scene_kind(c) is not None)


LIST_SUFFIXES = (".txt", ".lst", ".list")


def is_collection(p: str | Path) -> bool:
    """Whether one path names many scenes: a text file listing them (or a missing one: expand says
    so), or a folder of scene folders."""
    p = Path(p)
    return (_is_list_file(p) or (not p.exists() and p.suffix in LIST_SUFFIXES)
            or (p.is_dir() and scene_kind(p) is None and bool(_scene_folders(p))))


def expand(paths: list[str]) -> list[Path]:
    """Scene paths from the command line's: a scene (kept even when it is no scene: its task records
    why), a folder of scene folders, or a text file with one path a line (relative to the file's
    folder; blank lines and # comments skipped). Duplicates are dropped, the order kept."""
    out: list[Path] = []
    for arg in paths:
        p = Path(arg)
        if _is_list_file(p):
            for line in p.read_text(encoding="utf-8", errors="replace").splitlines():
                line = line.split("#", 1)[0].strip()
                if line:
                    q = Path(line)
                    out.append(q if q.is_absolute() else p.parent / q)
        elif p.is_dir() and scene_kind(p) is None and _scene_folders(p):
            out += _scene_folders(p)
        elif not p.exists() and p.suffix in LIST_SUFFIXES:
            raise SceneError(f"{p}: scene list file does not exist (expected a text file with one scene path a line)")
        else:
            out.append(p)
    seen, unique = set(), []
    for p in out:   # the same path twice; a symlink under another name is another scene (its own record)
        key = os.path.abspath(p)
        if key not in seen:
            seen.add(key)
            unique.append(p)
    if not unique:
        raise SceneError(f"no scenes in {' '.join(paths)} (expected scene folders, a folder of them, or a list file)")
    return unique


def names(paths: list[Path]) -> list[str]:
    """Each scene's record name: its folder name. Two scenes of one name would share a record: an error."""
    by: dict[str, Path] = {}
    for p in paths:
        n = p.name or str(p)
        if n in by:
            raise SceneError(f"two scenes are named {n!r} ({by[n]} and {p}): give scenes distinct folder names, "
                             "since each scene's result is <results>/scenes/<name>.json")
        by[n] = p
    return list(by)


def figures(report: dict, seconds: float | None) -> dict:
    """One scene's figures: per kind it was asked and over all, pairs, mIoU, localization, answers,
    AUROC, ECE; and seconds (the task's wall time)."""
    ev = report.get("eval", {})
    conf = ev.get("confidence", {})
    out = {}
    for k in GROUPS:
        b, c = ev.get(k), conf.get(k, {})
        if not b or not b.get("pairs"):
            continue
        out[k] = {"pairs": b["pairs"], "miou": b["miou_visible"], "localization": b["localization"],
                  "answers": c.get("answers", 0), "auroc": c.get("auroc", float("nan")),
                  "ece": c.get("ece", float("nan"))}
    out["seconds"] = seconds
    return out


class Pool:
    """Figures pooled over scenes, fed one record at a time."""

    def __init__(self):
        self.status = {"ok": 0, "failed": 0}
        self.pairs = {k: 0 for k in GROUPS}
        self.iou_sum = {k: 0.0 for k in GROUPS}
        self.loc_sum = {k: 0.0 for k in GROUPS}
        self.conf = {k: array("d") for k in KINDS}    # per answer: confidence, and whether it was right
        self.right = {k: array("b") for k in KINDS}
        self.scene_miou = {k: array("d") for k in GROUPS}   # per scene (the distribution plot)
        self.seconds = array("d")

    def add(self, record: dict) -> dict | None:
        """Count one scene record; returns its figures (None for a failed scene)."""
        st = record.get("status", "failed")
        self.status[st if st in self.status else "failed"] += 1
        if st != "ok":
            return None
        report = record.get("result") or {}
        fig = figures(report, record.get("seconds"))
        for k in GROUPS:
            if k in fig:
                n = fig[k]["pairs"]
                self.pairs[k] += n
                self.iou_sum[k] += fig[k]["miou"] * n
                self.loc_sum[k] += fig[k]["localization"] * n
                self.scene_miou[k].append(fig[k]["miou"])
        for q in report.get("eval", {}).get("queries", []):
            if q.get("kind") in self.conf:
                self.conf[q["kind"]].append(float(q["confidence"]))
                self.right[q["kind"]].append(bool(q["right"]))
        if record.get("seconds") is not None:
            self.seconds.append(float(record["seconds"]))
        return fig

    def summary(self) -> dict:
        """{"scenes": counts, kind: {pairs, miou, localization, answers, auroc, ece}, "seconds": {...}}."""
        out: dict = {"scenes": dict(self.status)}
        for k in GROUPS:
            kinds = KINDS if k == "all" else (k,)
            p = np.concatenate([np.frombuffer(self.conf[x], np.float64) for x in kinds])
            y = np.concatenate([np.frombuffer(self.right[x], np.int8) for x in kinds]).astype(bool)
            n = self.pairs[k]
            if not n and not len(p):
                continue
            out[k] = {"pairs": n, "miou": round(self.iou_sum[k] / n, 2) if n else float("nan"),
                      "localization": round(self.loc_sum[k] / n, 2) if n else float("nan"),
                      "answers": int(len(p)), "right": int(y.sum()),
                      "auroc": round(auroc(p, y), 4), "ece": round(expected_calibration_error(p, y), 4)}
        s = np.frombuffer(self.seconds, np.float64)
        out["seconds"] = {"total": round(float(s.sum()), 2), "per_scene_median": round(float(np.median(s)), 2) if len(s) else 0.0,
                          "per_scene_max": round(float(s.max()), 2) if len(s) else 0.0}
        return out


def _num(v, width: int, digits: int = 1) -> str:
    if v is None or (isinstance(v, float) and np.isnan(v)):
        return "-".rjust(width)
    return f"{v:.{digits}f}".rjust(width)


TABLE_HEAD = ("scene".ljust(24) + " status  " + "".join(f"{k[:5]:>5} mIoU   loc " for k in KINDS)
              + "  all mIoU   loc  AUROC   ECE  seconds")


def table_row(name: str, record: dict, fig: dict | None) -> str:
    """One scene's line of the table: its figures, or its error."""
    head = f"{name[:24]:<24} {record.get('status', 'failed'):<7}"
    if fig is None:
        err = " ".join(str(record.get("error") or "failed").split())
        err = re.sub(r"\S*/" + re.escape(name) + r"(?=[:/ ])", name, err)   # a long path would hide the reason
        return f"{head} {err[:110]}"
    cells = "".join(_num(fig.get(k, {}).get("miou"), 10) + _num(fig.get(k, {}).get("localization"), 6) + " "
                    for k in KINDS)
    a = fig.get("all", {})
    return (f"{head} {cells} {_num(a.get('miou'), 8)}{_num(a.get('localization'), 6)}{_num(a.get('auroc'), 7, 3)}"
            f"{_num(a.get('ece'), 6, 3)}{_num(fig.get('seconds'), 9)}")


def table_footer(summary: dict) -> list[str]:
    """The pooled lines under the scene lines: per kind and all, then the seconds."""
    sc = summary["scenes"]
    lines = ["", f"pooled over {sc['ok']} scenes ({sc['failed']} failed):",
             f"{'kind':<12}{'pairs':>7}{'mIoU':>7}{'loc':>7}{'answers':>9}{'AUROC':>7}{'ECE':>7}"]
    for k in GROUPS:
        if k in summary:
            b = summary[k]
            lines.append(f"{k:<12}{b['pairs']:>7}{_num(b['miou'], 7)}{_num(b['localization'], 7)}{b['answers']:>9}"
                         f"{_num(b['auroc'], 7, 3)}{_num(b['ece'], 7, 3)}")
    s = summary["seconds"]
    lines.append(f"seconds: {s['total']:.1f} of task time, median {s['per_scene_median']:.1f} and max "
                 f"{s['per_scene_max']:.1f} per scene")
    return lines
