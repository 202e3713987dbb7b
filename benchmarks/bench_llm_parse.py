"""The LLM query parser (issue 27, `reason.llm_parse`) against the rule parser, on the relational
benchmark's queries: how often the model's JSON is usable, how often it reads the query as the rule
parser does, and seconds per query.

    python benchmarks/bench_llm_parse.py [--seeds 411 ... 420] [--backend llama_cpp] [--gguf PATH]
                                         [--backend openai --openai-url URL --openai-model NAME]
                                         [--limit N] [--json] [--record]

Queries: bench_relations' generated and hand-written ones on the same `rg synth` scenes (ground truth
only; nothing is mapped). The rule parser answers every one of them right with oracle supervision
(docs/benchmarks.md, bench_relations), so "same as rules" is the share the model would answer as well.
Usable: the answer passed `phrases.from_fields` (schema, known relations and words); otherwise the
node falls back to the rule parser, and that share is what the fallback costs in time only. The model
runs in-process (llama.cpp, its output constrained by the schema grammar), 2 threads, greedy.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from rg_core.config import RGConfig  # noqa: E402
from _common import add_output_flags, finish  # noqa: E402
from bench_relations import add_scene_args, gt_colours, make_scene, queries  # noqa: E402


def scene_queries(path: Path, seed: int) -> list[dict]:
    from rg_core.io.captures import read_scene

    scene = read_scene(path)
    f0 = scene.test[0]
    return [{**q, "scene": seed} for q in queries(scene, np.random.default_rng(seed), gt_colours(scene),
                                                  f0.cam_to_world, f0.intrinsics.K)]


def measure(qs: list[dict], reasoner) -> list[dict]:
    from tqdm import tqdm

    from rg_core.grounding.phrases import parse, parse_with

    rows = []
    for q in tqdm(qs, desc="llm parse", unit="query"):
        rule = parse(q["text"])
        t = time.perf_counter()
        got, note = parse_with(reasoner, q["text"])
        dt = time.perf_counter() - t
        usable = note.startswith("parsed by the")
        rows.append({"kind": q["kind"], "template": q["template"], "text": q["text"], "usable": usable,
                     "same": usable and got == rule, "seconds": dt, "note": note,
                     "llm": got.describe() if usable and got is not None else "", "rules": rule.describe() if rule else ""})
    return rows


def summarise(rows: list[dict]) -> dict:
    def pct(xs):
        return round(100 * float(np.mean(xs)), 1) if xs else None

    kinds = {}
    for k in sorted({r["kind"] for r in rows}) + ["every kind"]:
        sel = [r for r in rows if k == "every kind" or r["kind"] == k]
        kinds[k] = {"queries": len(sel), "usable_pct": pct([r["usable"] for r in sel]),
                    "same_pct": pct([r["same"] for r in sel]),
                    "freeform_same_pct": pct([r["same"] for r in sel if r["template"] == "freeform"]),
                    "median_s": round(float(np.median([r["seconds"] for r in sel])), 3),
                    "p95_s": round(float(np.percentile([r["seconds"] for r in sel], 95)), 3)}
    why = {}
    for r in rows:
        if not r["usable"]:
            key = r["note"].split(" parse unusable (", 1)[-1].rsplit("); parsed by rules", 1)[0][:50]
            why[key] = why.get(key, 0) + 1
    return {"kinds": kinds, "unusable_why": why}


def to_rows(report: dict) -> tuple[list[dict], str]:
    s = report["summary"]
    out = [{"relation": k, **{c: "-" if v is None else v for c, v in b.items()}} for k, b in s["kinds"].items()]
    why = ", ".join(f"{k} {v}" for k, v in sorted(s["unusable_why"].items(), key=lambda kv: -kv[1])[:3]) or "none"
    return out, (f"{report['backend']} ({report['model']}), bench_relations' queries on rg synth seeds "
                 f"{report['seeds'][0]}-{report['seeds'][-1]}; same = the rule parser's reading; unusable: {why}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_scene_args(ap)
    ap.add_argument("--backend", default="llama_cpp", choices=("llama_cpp", "openai"))
    ap.add_argument("--gguf", default="", help="llama_cpp: GGUF file (default: the packaged SmolLM2-135M)")
    ap.add_argument("--openai-url", default="", help="openai: the endpoint (default: reason.openai_base_url)")
    ap.add_argument("--openai-model", default="", help="openai: the model (default: reason.openai_model)")
    ap.add_argument("--limit", type=int, default=0, help="at most this many queries (0 = all)")
    add_output_flags(ap)
    args = ap.parse_args()
    cfg = RGConfig()
    cfg.reason.backend, cfg.reason.gguf_path, cfg.reason.llm_parse = args.backend, args.gguf, True
    cfg.reason.openai_base_url = args.openai_url or cfg.reason.openai_base_url
    cfg.reason.openai_model = args.openai_model or cfg.reason.openai_model
    from rg_core.perception.reasoning import reasoner_from_config

    reasoner = reasoner_from_config(cfg.reason)
    qs = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            qs += scene_queries(make_scene(Path(tmp) / f"seed{seed}", seed, args), seed)
    if args.limit:
        qs = [qs[i] for i in np.random.default_rng(0).permutation(len(qs))[:args.limit]]
    rows = measure(qs, reasoner)
    for r in rows:
        if r["usable"] and not r["same"]:
            print(f"   differs: {r['text']!r}: llm {r['llm']} | rules {r['rules']}", file=sys.stderr)
    model = Path(args.gguf).name if args.gguf else ("SmolLM2-135M-Instruct Q4_1" if args.backend == "llama_cpp"
                                                    else cfg.reason.openai_model)
    report = {"backend": args.backend, "model": model, "seeds": args.seeds, "timeout_s": cfg.reason.timeout_s,
              "summary": summarise(rows), "queries": rows}
    print(report["summary"], file=sys.stderr)
    return finish(args, report, "bench_llm_parse", to_rows)


if __name__ == "__main__":
    from rg_core.util import run_json_script

    run_json_script(main)
