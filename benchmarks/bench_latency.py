"""Query latency: cold (`rg ground` as a new process) and warm (one Grounder kept, as the node and
the Python API use it), per stage, for maps of 2k / 20k / 100k Gaussians, explicit and implicit
queries; this code against a baseline measured in the same run (the machine may be shared).

    python benchmarks/bench_latency.py --map MAP --scene SCENE [--baseline-code DIR] [--sizes 2000 20000 100000]
                                       [--tile] [--grow 3]
                                       [--cold-repeats 2] [--out DIR] [--json] [--record]

MAP: a map with a trained field (`rg demo` writes one: rg_demo/scene.rgmap; or rg map --supervise
--train-field S); SCENE: its scene folder (queries.json: each object's explicit query and first
implicit one). Each size is the map resized as `rg report` does (a random subset, or every
Gaussian plus jittered copies up to 100k, latents copied; --tile: whole copies side by side, a larger
area at the same density, as a room-scale map is), saved with the name embeddings this
code stores with a map. Baseline: `--baseline-code DIR`, a checkout of the code to compare with
(e.g. `git worktree add /tmp/base <commit>`), run on the same map files in alternation with this
code; without it the baseline is this code with the Grounder's map caches off (cache=False).

Cold: per query a new process: `python -m rg_core.cli ground MAP QUERY --mode M --json` (wall),
and a child that reports its import, load_map and ground stages. Warm: one process per code and
size; one warm-up query, then every query twice ("first": the first time the object is asked,
"repeat": asked again); median and p95 over both rounds and per round. --grow K: then K times
a strip of 1 % more Gaussians beyond the map's edge (the field kept, as between two trainings in
the node) and every query asked once after each ("after growth": what the caches keep of a growing map).
Writes OUT/latency.json, OUT/latency.md (tables) and OUT/latency.png.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from _common import add_output_flags, commit_of, finish  # noqa: E402


def p95(xs):
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(round(0.95 * (len(xs) - 1))))] if xs else float("nan")


# ------------------------------------------------------------------------------ children

def child_cold(map_path: str, query: str, mode: str) -> dict:
    """Runs in a fresh process: stage times from interpreter start (imports, map, each stage)."""
    t0 = time.perf_counter()
    import torch  # noqa: F401

    t1 = time.perf_counter()
    from rg_core.config import RGConfig
    from rg_core.grounding.pipeline import Grounder
    from rg_core.map.store import load_map

    t2 = time.perf_counter()
    m = load_map(map_path)
    t3 = time.perf_counter()
    r = Grounder(m, m.field, RGConfig()).ground(query, mode=mode)
    t4 = time.perf_counter()
    heavy = sorted({k.split(".")[0] for k in sys.modules} & {"sklearn", "open3d", "cv2", "matplotlib", "scipy",
                                                           "sentence_transformers", "transformers", "rclpy"})
    return {"import_torch": t1 - t0, "import_rg": t2 - t1, "load_map": t3 - t2, "ground": t4 - t3,
            "stages": r.timings, "success": r.success, "target": r.target, "modules": heavy}


def grow_map(m, frac: float = 0.01, step: float = 0.3) -> int:
    """A new strip of room beyond the map's +x edge: copies of the `frac` of Gaussians that lie
    furthest along x, `step` m further on (what a robot driving on adds). Returns how many."""
    import torch

    g = m.gaussians
    k = max(1, int(frac * len(g)))
    sel = g.means.detach()[:, 0].topk(k).indices
    g.append(g.means.detach()[sel] + torch.tensor([step, 0.0, 0.0]), g.scales.detach()[sel],
             g.colors.detach()[sel], 0.9)
    m.optim.sync()
    return k


def child_warm(map_path: str, queries: list, cache: bool | None, grow: int = 0) -> dict:
    import torch  # noqa: F401

    from rg_core.config import RGConfig
    from rg_core.grounding.pipeline import Grounder
    from rg_core.map.store import load_map

    m = load_map(map_path)
    kw = {} if cache is None else {"cache": cache}
    g = Grounder(m, m.field, RGConfig(), **kw)
    if hasattr(g, "load_models"):   # as the node does once its field answers (older baselines load on first use)
        g.load_models()
    g.ground(queries[0][0], mode=queries[0][1])  # warm-up: vocabulary
    rows = []

    def ask(rnd: str, q: str, mode: str, expect: str, **extra) -> None:
        t = time.perf_counter()
        r = g.ground(q, mode=mode)
        rows.append({"round": rnd, "query": q, "mode": mode, "seconds": time.perf_counter() - t,
                     "stages": r.timings, "target": r.target, "right": r.target == expect,
                     "success": r.success, "ids": int(sum(len(o.gaussian_ids) for o in r.objects)), **extra})

    for rnd in ("first", "repeat"):
        for q, mode, expect in queries:
            ask(rnd, q, mode, expect)
    for step in range(grow):   # the map grows between asks, the field stays: "grown" asks
        added = grow_map(m)
        for q, mode, expect in queries:
            ask("grown", q, mode, expect, added=added, gaussians=len(m.gaussians))
    return {"rows": rows}


def run_child(code: Path, kind: str, payload: dict) -> dict:
    env = {**os.environ, "PYTHONPATH": str(code), "HF_HUB_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1"}
    r = subprocess.run([sys.executable, __file__, "--child", kind, json.dumps(payload)], cwd=code, env=env,
                       capture_output=True, text=True, timeout=1800)
    if r.returncode != 0:
        raise RuntimeError(f"{kind} child in {code} failed:\n{r.stderr[-3000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def cli_wall(code: Path, map_path: str, query: str, mode: str) -> dict:
    env = {**os.environ, "PYTHONPATH": str(code), "HF_HUB_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1"}
    t = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "rg_core.cli", "ground", map_path, query, "--mode", mode, "--json"],
                       cwd=code, env=env, capture_output=True, text=True, timeout=900)
    wall = time.perf_counter() - t
    out = json.loads(r.stdout) if r.stdout.strip() else {"error": r.stderr[-500:]}
    return {"wall": wall, "rc": r.returncode, "target": out.get("target"), "success": out.get("success")}


# ------------------------------------------------------------------------------ driver

def make_maps(map_path: Path, sizes: list[int], out: Path, tile: bool = False) -> dict[int, str]:
    sys.path.insert(0, str(ROOT))
    from rg_core.config import RGConfig
    from rg_core.grounding.pipeline import Grounder
    from rg_core.map.store import load_map, save_map
    from rg_core.report.inputs import resized_map

    m = load_map(map_path)
    if m.field is None:
        raise ValueError(f"{map_path}: the map has no feature field (rg map --supervise --train-field S)")
    paths = {}
    for n in sizes:
        mm, f = resized_map(m, m.field, n, tile=tile)
        mm.frames_seen = m.frames_seen
        Grounder(mm, f, RGConfig()).store_texts()
        paths[n] = str(save_map(mm, out / f"map_{n}.rgmap"))
        print(f"map of {n} Gaussians: {paths[n]}", file=sys.stderr)
    return paths


def _med(xs) -> float:
    """Median, NaN for none (--cold-repeats 0)."""
    xs = list(xs)
    return statistics.median(xs) if xs else float("nan")


def summarise(rows: list[dict]) -> dict:
    out = {}
    for sel, name in ((lambda r: r["round"] != "grown", "all"), (lambda r: r["round"] == "first", "first"),
                      (lambda r: r["round"] == "repeat", "repeat"), (lambda r: r["round"] == "grown", "grown")):
        for mode in ("explicit", "implicit", "any"):
            xs = [r["seconds"] for r in rows if sel(r) and (mode == "any" or r["mode"] == mode)]
            if xs:
                out[f"{name}_{mode}"] = {"median": statistics.median(xs), "p95": p95(xs), "n": len(xs)}
    stages = {}
    for r in rows:
        for k, v in r["stages"].items():
            stages.setdefault(k, []).append(v)
    out["stage_median"] = {k: statistics.median(v) for k, v in stages.items()}
    out["right"] = sum(r["right"] for r in rows if r["round"] != "grown")
    out["n"] = sum(r["round"] != "grown" for r in rows)
    return out


def plot(res: dict, out_png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sizes = sorted(int(n) for n in res["warm"])
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    for code, style in (("baseline", "s--"), ("new", "o-")):
        for mode in ("explicit", "implicit"):
            axes[0].plot(sizes, [res["warm"][str(n)][code]["summary"][f"all_{mode}"]["median"] for n in sizes], style,
                         label=f"{code} {mode} median")
            cold = [_med(c["wall"] for c in (res["cold"][str(n)][code] or {}).get(mode, [])) for n in sizes]
            if any(np.isfinite(cold)):                  # none with --cold-repeats 0 or no baseline code
                axes[1].plot(sizes, cold, style, label=f"{code} {mode}")
        first = [res["warm"][str(n)][code]["summary"]["first_any"]["p95"] for n in sizes]
        axes[0].plot(sizes, first, style[0] + "-.", label=f"{code} first-ask p95")
        grown = [res["warm"][str(n)][code]["summary"].get("grown_any", {}).get("p95", np.nan) for n in sizes]
        if any(np.isfinite(grown)):
            axes[0].plot(sizes, grown, style[0] + ":", label=f"{code} p95 after growth")
    axes[0].axhline(0.3, color="grey", lw=0.8, ls=":")      # median target
    axes[0].axhline(0.5, color="red", lw=0.8, ls=":")       # first-ask p95 target at 1M (issue 28)
    axes[1].axhline(3.0, color="grey", lw=0.8, ls=":")
    for ax, title in ((axes[0], "warm query (Grounder kept), s"), (axes[1], "cold `rg ground` wall, s")):
        ax.set_xscale("log"), ax.set_xlabel("Gaussians"), ax.set_title(title), ax.legend(fontsize=7)
        if len(ax.lines) > 2:
            ax.set_yscale("log")
    fig.tight_layout()
    fig.savefig(out_png, dpi=120)
    plt.close(fig)


def to_rows(res: dict) -> tuple[list[dict], str]:
    """Shared-schema rows: per map size and code, warm median / p95 and cold wall (medians)."""
    rows = []
    for n in sorted(int(k) for k in res["warm"]):
        for code in ("new", "baseline"):
            s, cold = res["warm"][str(n)][code]["summary"], res["cold"][str(n)][code] or {}
            row = {"gaussians": n, "code": code}
            for m in ("explicit", "implicit"):
                row[f"warm_{m}_median_s"] = round(s[f"all_{m}"]["median"], 3)
                row[f"warm_{m}_p95_s"] = round(s[f"all_{m}"]["p95"], 2)
            row["warm_first_ask_p95_s"] = round(s["first_any"]["p95"], 2)
            if "grown_any" in s:
                row["warm_grown_median_s"] = round(s["grown_any"]["median"], 3)
                row["warm_grown_p95_s"] = round(s["grown_any"]["p95"], 2)
            for m in ("explicit", "implicit"):
                v = _med(c["wall"] for c in cold.get(m, []))
                row[f"cold_{m}_s"] = round(v, 2) if np.isfinite(v) else "-"
            row["right_targets"] = f"{s['right']}/{s['n']}"
            rows.append(row)
    return rows, (f"baseline: {res['baseline']}; warm: one Grounder kept, each query asked twice; cold: `rg ground` "
                  "as a new process; targets median 0.3 s, p95 0.6 s warm, 3 s cold at 20k, first-ask p95 0.5 s at 1M "
                  "(issue 28)" + ("; maps tiled" if res.get("tile") else "") + (
                      f"; grown: {res['grow']} x 1 % more Gaussians beyond the map's edge, field kept, every query "
                      "asked after each" if res.get("grow") else ""))


def table(res: dict) -> str:
    lines = ["| Gaussians | code | warm median / p95 explicit (s) | warm median / p95 implicit (s) | first ask median (s) | repeat median (s) | right targets | cold wall explicit / implicit (s) | cold stages (import, load, ground) explicit |",
             "|---|---|---|---|---|---|---|---|---|"]
    for n in sorted(int(k) for k in res["warm"]):
        for code in ("baseline", "new"):
            s = res["warm"][str(n)][code]["summary"]
            cold = res["cold"][str(n)][code] or {}
            cw = [_med(c["wall"] for c in cold.get(m, [])) for m in ("explicit", "implicit")]
            st = cold.get("stages_explicit")
            stages = f"{st['import_torch'] + st['import_rg']:.2f}, {st['load_map']:.2f}, {st['ground']:.2f}" if st else "-"
            lines.append(f"| {n} | {code} | {s['all_explicit']['median']:.3f} / {s['all_explicit']['p95']:.3f} | "
                         f"{s['all_implicit']['median']:.3f} / {s['all_implicit']['p95']:.3f} | "
                         f"{s['first_any']['median']:.3f} | {s['repeat_any']['median']:.3f} | {s['right']}/{s['n']} | "
                         f"{cw[0]:.2f} / {cw[1]:.2f} | {stages} |")
    lines.append("")
    lines.append("| Gaussians | warm median ratio new/baseline (explicit, implicit) | cold wall ratio (explicit, implicit) |")
    lines.append("|---|---|---|")
    for n in sorted(int(k) for k in res["warm"]):
        w = res["warm"][str(n)]
        c = res["cold"][str(n)]
        wr = [w["new"]["summary"][f"all_{m}"]["median"] / w["baseline"]["summary"][f"all_{m}"]["median"] for m in ("explicit", "implicit")]
        cr = [_med(x["wall"] for x in (c["new"] or {}).get(m, [])) / _med(x["wall"] for x in (c["baseline"] or {}).get(m, []))
              for m in ("explicit", "implicit")]
        lines.append(f"| {n} | {wr[0]:.2f}, {wr[1]:.2f} | {cr[0]:.2f}, {cr[1]:.2f} |")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    ap.add_argument("--map", help="map with a trained field (e.g. rg_demo/scene.rgmap)")
    ap.add_argument("--scene", help="its scene folder (queries.json)")
    ap.add_argument("--baseline-code", help="checkout of the code to compare with (default: this code, cache off)")
    ap.add_argument("--sizes", type=int, nargs="+", default=[2000, 20000, 100000])
    ap.add_argument("--cold-repeats", type=int, default=2)
    ap.add_argument("--tile", action="store_true", help="grow a map by copies side by side (a larger area at the "
                                                        "same density) instead of jittered copies in place")
    ap.add_argument("--queries", type=int, default=0, help="use only the first N objects' queries (0: all)")
    ap.add_argument("--grow", type=int, default=0, help="after the warm rounds, grow the map this many times by a "
                                                        "strip of 1 %% more Gaussians and ask every query once after each")
    ap.add_argument("--out", default="bench_out/latency")
    add_output_flags(ap)
    a = ap.parse_args()
    if a.child:
        kind, payload = a.child[0], json.loads(a.child[1])
        res = child_cold(**payload) if kind == "cold" else child_warm(**payload)
        print(json.dumps(res))
        return 0
    if not a.map or not a.scene:
        ap.error("--map and --scene are required")
    qs = json.loads((Path(a.scene) / "queries.json").read_text())
    objs = {o["id"]: o["name"] for o in json.loads((Path(a.scene) / "objects.json").read_text())["objects"]}
    qs = qs[: a.queries] if a.queries else qs
    queries = [(q["explicit"], "explicit", objs.get(q["object_id"], "")) for q in qs] + \
              [(q["implicit"][0], "implicit", objs.get(q["object_id"], "")) for q in qs if q["implicit"]]
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    new_code = ROOT
    base_code = Path(a.baseline_code).resolve() if a.baseline_code else ROOT
    res = {"date": time.strftime("%Y-%m-%d %H:%M"), "cpus": os.cpu_count(), "load_avg_start": os.getloadavg(),
           "baseline": f"the code at {commit_of(base_code)}" if a.baseline_code else "this code with cache=False",
           "queries": [q[:2] for q in queries], "warm": {}, "cold": {}, "tile": a.tile, "grow": a.grow}
    with tempfile.TemporaryDirectory() as tmp:
        maps = make_maps(Path(a.map), a.sizes, Path(tmp), a.tile)
        for n, path in maps.items():
            res["warm"][str(n)], res["cold"][str(n)] = {}, {}
            for code_name, code in (("baseline", base_code), ("new", new_code)):
                cache = None if (code_name == "new" or a.baseline_code) else False
                w = run_child(code, "warm", {"map_path": path, "queries": queries, "cache": cache, "grow": a.grow})
                res["warm"][str(n)][code_name] = {"rows": w["rows"], "summary": summarise(w["rows"])}
                print(f"{n} {code_name} warm: {json.dumps(res['warm'][str(n)][code_name]['summary'])}", file=sys.stderr)
            for code_name, code in (("baseline", base_code), ("new", new_code)):
                if code_name == "baseline" and not a.baseline_code:
                    res["cold"][str(n)][code_name] = None
                    continue
                c = {"explicit": [], "implicit": []}
                for _ in range(a.cold_repeats):
                    for mode in ("explicit", "implicit"):
                        q = next(x for x in queries if x[1] == mode)
                        c[mode].append(cli_wall(code, path, q[0], mode))
                c["stages_explicit"] = run_child(code, "cold", {"map_path": path, "query": queries[0][0], "mode": "explicit"})
                q = next(x for x in queries if x[1] == "implicit")
                c["stages_implicit"] = run_child(code, "cold", {"map_path": path, "query": q[0], "mode": "implicit"})
                res["cold"][str(n)][code_name] = c
                print(f"{n} {code_name} cold: {json.dumps(c)}", file=sys.stderr)
            if not a.baseline_code:  # cold baseline = this code (its caches do not persist across processes)
                res["cold"][str(n)]["baseline"] = res["cold"][str(n)]["new"]
    res["load_avg_end"] = os.getloadavg()
    (out / "latency.json").write_text(json.dumps(res, indent=1))
    md = table(res)
    (out / "latency.md").write_text(md + "\n")
    plot(res, out / "latency.png")
    if a.json:
        print(json.dumps({k: v for k, v in res.items() if k not in ("warm", "cold")} | {"table": md}))
    else:
        print(md)
    a.json = False   # its JSON (the summary, not the raw rows) is printed above
    return finish(a, res, "bench_latency", to_rows, plots=[out / "latency.png"])


if __name__ == "__main__":
    sys.exit(main())
