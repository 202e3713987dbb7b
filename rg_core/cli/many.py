"""Many scenes for `rg eval SCENE [SCENE ...]` and `rg synth OUT --seeds A-B` (issue 64): one task per
scene, run one after another in this process or on Ray (rg_core/batch), each recorded in the
results folder when it finishes; the eval's aggregate (rg_core/eval/many.py) is streamed from those
records to aggregate.json, table.txt and scenes.png, so the driver holds no report in memory."""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

from ..batch import ResultsDir, Task, engine_info, run_tasks
from ..batch.engines import cores
from ..util import peak_rss_mb
from .options import positive

# The task functions, named (not imported: those modules import this one) for the engine to import
EVAL_TASK = "rg_core.cli.evaluation:eval_task"
SYNTH_TASK = "rg_core.cli.synthesis:synth_task"
LOCAL = "local"   # --ray without an address: Ray started here with --workers CPUs
# argparse fields that say how to run, not what a scene's figures are (left out of the settings)
_RUN_ONLY = {"func", "human", "json", "quiet", "ray", "workers", "results", "retry_failed", "out", "scene", "config",
             "command", "seeds"}


def add_engine_args(p, workers_help: str | None, threads: bool = False) -> None:
    """--ray [ADDRESS], --workers N (unless the command has its own), --threads N (torch's, per task),
    --results DIR, --retry-failed."""
    p.add_argument("--ray", nargs="?", const=LOCAL, metavar="ADDRESS",
                   help="run the scenes as Ray tasks: without ADDRESS on --workers local workers, 'auto' or "
                        "HOST:PORT to join a running cluster (needs pip install .[ray])")
    if workers_help:
        p.add_argument("--workers", type=positive, help=workers_help)
    if threads:
        p.add_argument("--threads", type=positive, default=1, metavar="N",
                       help="many scenes: torch threads of each scene's task, and the CPUs it takes on Ray "
                            "(default 1: the figures are the same on any engine, worker count or cluster, since "
                            "a thread count changes float rounding; scenes run side by side instead)")
    p.add_argument("--results", metavar="DIR", help="one JSON per scene, written when it finishes; a rerun skips "
                                                    "the finished scenes")
    p.add_argument("--retry-failed", action="store_true", help="with --results: run the failed scenes again")


def _engine(args, workers: int | None, threads: int = 1) -> tuple[str, int, str | None]:
    """(engine name, local Ray workers, cluster address) from --ray / --workers; local workers
    default to as many as the cores hold tasks of `threads` threads."""
    if args.ray is None:
        return "local", 1, None
    if args.ray == LOCAL:
        if workers and workers * threads > cores():
            print(f"rg: --workers {workers} x --threads {threads} is more threads than this machine's {cores()} "
                  "cores: the tasks will share them", file=sys.stderr)
        return "ray", workers or max(1, cores() // threads), None
    if workers:
        raise ValueError(f"--workers is for local Ray workers; the cluster at --ray {args.ray} has its own CPUs "
                         "(one scene a CPU)")
    return "ray", 0, args.ray


def _results_dir(args) -> tuple[ResultsDir, object]:
    """The --results folder, or a temporary one (kept alive by the returned handle)."""
    if args.results:
        return ResultsDir(args.results), None
    tmp = tempfile.TemporaryDirectory(prefix="rg_results_")
    return ResultsDir(tmp.name), tmp


# ------------------------------------------------------------------------------------ rg eval

def is_many(args) -> bool:
    """A many-scene run: several paths, a folder of scenes or a list file, or any of the engine flags."""
    from ..eval.many import is_collection

    return (len(args.scene) > 1 or args.ray is not None or bool(args.results) or args.retry_failed
            or args.workers is not None or is_collection(args.scene[0]))


def eval_many(args, cfg, task: str = EVAL_TASK) -> "ManyResult":
    """Every scene of args.scene as a task of `task` ("module:attr"; tests pass one that kills its
    worker), then the aggregate."""
    from ..config import config_to_dict
    from ..eval.many import expand, names

    for flag, why in (("map", "--map scores one scene's map"), ("queries", "--queries belongs to one scene"),
                      ("ablation", "--ablation's table is one scene's")):
        if getattr(args, flag):
            raise ValueError(f"{why}; with many scenes each builds its own (give one scene, or leave out --{flag})")
    if args.retry_failed and not args.results:
        raise ValueError("--retry-failed needs --results DIR (the folder of the run to complete)")
    engine, workers, address = _engine(args, args.workers, args.threads)
    if engine == "local" and args.workers:
        raise ValueError("--workers needs --ray (without it the scenes run one after another in this process)")
    info = engine_info(engine)   # first: without Ray, say how to install it before anything else
    paths = expand(args.scene)
    scene_names = names(paths)
    base = {k: v for k, v in vars(args).items() if k not in ("func", "human")}
    base.update(quiet=True, json=False, out=None, ray=None, results=None, workers=None, retry_failed=False)
    conf = config_to_dict(cfg)
    settings = {"args": {k: v for k, v in sorted(base.items()) if k not in _RUN_ONLY}, "config": conf}   # threads too
    tasks = [Task(n, {"args": {**base, "scene": str(p)}, "config": conf}, settings) for n, p in zip(scene_names, paths)]
    rd, keep = _results_dir(args)
    todo, skipped = rd.pending(tasks, args.retry_failed)

    def on_record(t, rec):
        rd.write({**rec, "path": t.payload["args"]["scene"], "engine": info, "settings": t.settings})

    run_tasks(task, todo, on_record, engine, workers, address, progress=not args.quiet, threads=args.threads)
    run = {"tasks": len(todo), "threads": args.threads, "skipped_ok": skipped["ok"], "skipped_failed": skipped["failed"],
           "workers": workers if engine == "ray" and address is None else None, "address": address,
           "driver_peak_rss_mb": round(peak_rss_mb(), 1)}   # this process: flat in the number of scenes
    out_dir = Path(args.out) if args.out else rd.root
    return write_aggregate(rd, scene_names, info, run, out_dir, keep)


class ManyResult(dict):
    """A many-scene run's result: its summary as a dict; printed (write_to) from the files it wrote,
    so that printing the per-scene lines needs no memory per scene."""

    def write_to(self, stream, as_json: bool) -> None:
        with open(self["aggregate_json" if as_json else "table"], encoding="utf-8") as f:
            for chunk in iter(lambda: f.read(1 << 16), ""):
                stream.write(chunk)
        if as_json:
            stream.write("\n")


def write_aggregate(rd: ResultsDir, scene_names: list[str], info: dict, run: dict, out_dir: Path,
                    keep=None) -> ManyResult:
    """aggregate.json ({"engine", "run", "results", "plot", "scenes": [{"scene", "status", "eval",
    ...}], "aggregate"}), table.txt and scenes.png in out_dir, one record read at a time."""
    from ..eval.many import TABLE_HEAD, Pool, table_footer, table_row
    from ..report.plots import scenes_png

    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {k: out_dir / n for k, n in (("json", "aggregate.json"), ("table", "table.txt"), ("png", "scenes.png"))}
    pool = Pool()
    dumps = lambda o: json.dumps(o, default=str)                                        # noqa: E731
    tmp_json, tmp_table = paths["json"].with_suffix(".json.tmp"), paths["table"].with_suffix(".txt.tmp")
    with open(tmp_json, "w", encoding="utf-8") as jf, open(tmp_table, "w", encoding="utf-8") as tf:
        jf.write(f'{{"engine": {dumps(info)}, "run": {dumps(run)}, "results": {dumps(str(rd.root))}, '
                 f'"plot": {dumps(str(paths["png"]))}, "scenes": [')
        tf.write(TABLE_HEAD + "\n")
        for i, n in enumerate(scene_names):
            rec = rd.read(n) or {"scene": n, "status": "failed", "error": "no record: the run stopped before this scene"}
            fig = pool.add(rec)
            entry = {"scene": n, "status": rec.get("status"), "eval": fig, "error": rec.get("error"),
                     "node": rec.get("node"), "seconds": rec.get("seconds"), "path": rec.get("path")}
            jf.write(("," if i else "") + dumps(entry))
            tf.write(table_row(n, rec, fig) + "\n")
        summary = pool.summary()
        jf.write(f'], "aggregate": {dumps(summary)}}}')
        tf.write("\n".join(table_footer(summary)) + "\n")
    os.replace(tmp_json, paths["json"])
    os.replace(tmp_table, paths["table"])
    sc = summary["scenes"]
    scenes_png({k: v for k, v in pool.scene_miou.items()}, pool.seconds, paths["png"],
               f"{sc['ok']} scenes ({sc['failed']} failed), engine {info['name']}")
    res = ManyResult(engine=info, run=run, results=str(rd.root), aggregate=summary,
                     aggregate_json=str(paths["json"]), table=str(paths["table"]), plot=str(paths["png"]))
    res._keep = keep    # a temporary results folder lives as long as the result
    if sc["failed"]:
        print(f"rg: {sc['failed']} of {sc['ok'] + sc['failed']} scenes failed (their errors: {paths['table']}); "
              "rerun with --results DIR --retry-failed to run them again", file=sys.stderr)
    return res


# ------------------------------------------------------------------------------------ rg synth

def seeds(text: str) -> list[int]:
    """'A-B' (inclusive), 'A,B,C' or a mix ('0-9,20') -> the seeds in order, each once."""
    out: list[int] = []
    try:
        for part in text.split(","):
            a, sep, b = part.strip().partition("-")
            lo, hi = int(a), int(b) if sep else int(a)
            if hi < lo:
                raise ValueError
            out += range(lo, hi + 1)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--seeds wants A-B (inclusive), A,B,C or a mix such as 0-9,20; "
                                         f"got {text!r}") from None
    return list(dict.fromkeys(out))


def synth_many(args, cfg, objects_dir: Path | None, task: str = SYNTH_TASK) -> dict:
    """One scene per seed, OUT/scene_<seed> (5 digits), as tasks; records in --results (default
    OUT/.rg_synth). With --ray on local workers, --workers counts Ray workers and each scene renders
    in one process (the scene's bytes do not depend on it)."""
    from ..config import config_to_dict
    from .config_args import was_given

    out = Path(args.out)
    workers = cfg.synth.workers if (args.ray == LOCAL and was_given(args, "synth.workers")) else None
    engine, n_workers, address = _engine(args, workers)
    if args.ray is not None and address is not None and was_given(args, "synth.workers"):
        raise ValueError(f"--workers is for local Ray workers; the cluster at --ray {args.ray} has its own CPUs")
    info = engine_info(engine)
    conf = config_to_dict(cfg.synth)
    if engine == "ray":
        conf["workers"] = 1
    settings = {"synth": {k: v for k, v in conf.items() if k not in ("seed", "workers")},
                "objects_dir": str(objects_dir) if objects_dir else None}
    tasks = [Task(f"scene_{s:05d}", {"out": str(out / f"scene_{s:05d}"), "config": {**conf, "seed": s},
                                     "objects_dir": settings["objects_dir"]}, settings) for s in args.seeds]
    rd = ResultsDir(args.results or out / ".rg_synth")
    todo, skipped = rd.pending(tasks, args.retry_failed)
    counts, failed = {"ok": 0, "failed": 0}, []

    def on_record(t, rec):
        rd.write({**rec, "path": t.payload["out"], "engine": info, "settings": t.settings})
        counts[rec["status"]] += 1
        if rec["status"] != "ok":
            failed.append({"scene": t.name, "error": rec["error"]})

    run_tasks(task, todo, on_record, engine, n_workers, address, progress=not args.quiet)
    return {"engine": info, "out": str(out), "results": str(rd.root), "seeds": [args.seeds[0], args.seeds[-1]],
            "scenes": {**counts, "skipped_ok": skipped["ok"], "skipped_failed": skipped["failed"]}, "failed": failed}
