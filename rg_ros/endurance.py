"""A long run of the node on loopback: `rg-node` fed a looped scene by `rg-replay --loop`, a /ground
call every few seconds, the node's memory, queue, drops and query latency sampled over time.

Used by benchmarks/bench_endurance.py (>= 20,000 frames) and, short, by the test suite (1,000 frames).
Both processes are started with this interpreter and environment; the caller sets ROS_DOMAIN_ID and
ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


@dataclass
class EnduranceConfig:
    frames: int = 20000            # frames rg-replay publishes (the scene looped)
    rate: float = 20.0             # frames per second
    ground_period: float = 2.0     # seconds between /ground calls
    ground_timeout: float = 60.0   # a call without a reply after this counts as unanswered
    sample_period: float = 0.5     # seconds between memory samples
    warmup_timeout: float = 300.0  # before the run: one slow pass of the scene, then wait (up to this many
                                   # seconds) for the node to settle: frames mapped, the field's first stop
    queries: tuple[str, ...] = ("orange", "the biggest object", "something to eat")
    faults_every: int = 0          # rg-replay --faults: a bad pose, a pose/TF gap, a 100-frame burst in turn (rg_ros.replay.Faults)
    save_every: int = 0            # every Nth /ground call goes out together with a ~/save_map call
    save_period: float = 0.0       # > 0: a second client calls ~/save_map every this many seconds (issue 62)
    code_dir: str = ""             # run the node from this checkout (a baseline), put first on PYTHONPATH
    params: dict = field(default_factory=lambda: dict(
        pose_source="topic", map_width=80, iters_per_keyframe=2, torch_threads=1, frame_queue_size=4,
        features=True, train_slice=0.5, train_seconds_max=2.0, status_period=0.5, mask_rate=0.0,
        map_cloud_period=0.0, min_confidence=0.0, scene_graph_period=0.0))


def _rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def write_params(path: Path, params: dict, name: str = "rg_node") -> Path:
    """A ros__parameters file for node `name` (rcl's parser refuses YAML aliases: repeated values are
    written out)."""
    import yaml

    class NoAliases(yaml.SafeDumper):
        def ignore_aliases(self, data):
            return True

    path.write_text(yaml.dump({name: {"ros__parameters": params}}, Dumper=NoAliases))
    return path


def status_values(msg) -> dict[str, dict]:
    """A /diagnostics message -> {node name: {key: value}}: values JSON-decoded where they are JSON,
    plus '_t' (when it arrived, monotonic) and '_message'."""
    out = {}
    for s in msg.status:
        vals = {}
        for kv in s.values:
            try:
                vals[kv.key] = json.loads(kv.value)
            except ValueError:
                vals[kv.key] = kv.value
        vals["_t"], vals["_message"] = time.monotonic(), s.message
        out[s.name.split(":")[0]] = vals
    return out


def stop_process(proc: subprocess.Popen, timeout: float = 30.0) -> int | None:
    """SIGINT, wait, then kill (SIGTERM right after a reply can hang a server); the exit code, None
    when it had to be killed."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)
            return None
    return proc.returncode


def run(scene: Path, work: Path, cfg: EnduranceConfig, progress: bool = True) -> dict:
    """Run the node against `scene` (a scene folder) for cfg.frames frames; -> samples and summary."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rg_interfaces.srv import Ground, MapFile
    from tqdm import tqdm

    from .run import NodeExecutor

    work.mkdir(parents=True, exist_ok=True)
    params = write_params(work / "endurance.yaml", {"save_path": str(work / "endurance_map.pt"), **cfg.params})
    env = dict(os.environ, RCUTILS_LOGGING_BUFFERED_STREAM="0")
    node_env = dict(env)
    if cfg.code_dir:
        node_env["PYTHONPATH"] = os.pathsep.join([cfg.code_dir, env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    from .params import INPUTS

    remap = [a for name, target in INPUTS.items() for a in ("-r", f"{name}:={target}")]   # where rg-replay publishes
    node = subprocess.Popen([sys.executable, "-m", "rg_ros.tools", "node", "--params", str(params), "--ros-args",
                             *remap], env=node_env,
                            stdout=(work / "node.log").open("w"), stderr=subprocess.STDOUT)
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    probe = rclpy.create_node("rg_endurance_probe", context=ctx)
    status: dict = {}

    def on_status(msg):
        vals = status_values(msg).get("/rg_node")
        if vals is not None:
            status.clear()
            status.update(vals)

    probe.create_subscription(DiagnosticArray, "/diagnostics", on_status, 10)
    client = probe.create_client(Ground, "/ground")
    save_type = MapFile
    saver = None
    executor = NodeExecutor(context=ctx)
    executor.add_node(probe)
    spin = threading.Thread(target=executor.spin, daemon=True)
    spin.start()
    samples, calls, saves, save_log = [], [], [], []
    replay, warm = None, {}
    stop = threading.Event()
    t0 = time.monotonic()
    try:
        end = time.monotonic() + 180
        while not status and node.poll() is None and time.monotonic() < end:
            time.sleep(0.2)
        if node.poll() is not None or not status:
            raise RuntimeError(f"rg-node did not come up: {(work / 'node.log').read_text()[-2000:]}")
        # ~/save_map is rg_interfaces/srv/MapFile since issue 62, std_srvs/srv/Trigger before (a baseline)
        types = dict(probe.get_service_names_and_types())
        if "std_srvs/srv/Trigger" in types.get("/rg_node/save_map", []):
            from std_srvs.srv import Trigger as save_type
        saver = probe.create_client(save_type, "/rg_node/save_map")
        # Warm-up, not measured: models load, the first keyframes are supervised and the field trains
        # once. The run then measures the steady state a robot lives in for hours.
        subprocess.run([sys.executable, "-m", "rg_ros.tools", "replay", str(scene), "--rate", "4", "--wait", "60"],
                       env=env, stdout=(work / "warmup.log").open("w"), stderr=subprocess.STDOUT,
                       timeout=cfg.warmup_timeout)
        end = time.monotonic() + cfg.warmup_timeout
        while time.monotonic() < end and node.poll() is None and not (
                status.get("field_stop") and status.get("queue") == 0 and status.get("received", 0) > 0
                and status.get("grounding_models", "loaded") == "loaded"):   # older nodes do not say
            time.sleep(0.5)
        warm = dict(status)
        t0 = time.monotonic()
        replay = subprocess.Popen([sys.executable, "-m", "rg_ros.tools", "replay", str(scene), "--loop", "--count",
                                   str(cfg.frames), "--rate", str(cfg.rate), "--wait", "60",
                                   "--faults", str(cfg.faults_every)], env=env,
                                  stdout=(work / "replay.log").open("w"), stderr=subprocess.STDOUT)

        def caller():
            i = 0
            if not client.wait_for_service(timeout_sec=60):
                calls.append({"t": time.monotonic() - t0, "seconds": None, "success": False, "message": "no service"})
                return
            while not stop.is_set():
                q = cfg.queries[i % len(cfg.queries)]
                t = time.monotonic()
                save = saver.call_async(save_type.Request()) if cfg.save_every and i % cfg.save_every == 0 else None
                res = client.call(Ground.Request(query=q), timeout_sec=cfg.ground_timeout)
                dt = time.monotonic() - t
                if save is not None:
                    end = time.monotonic() + cfg.ground_timeout
                    while not save.done() and time.monotonic() < end:
                        time.sleep(0.05)
                    saves.append(bool(save.done() and save.result() is not None and save.result().success))
                calls.append({"t": t - t0, "query": q, "seconds": dt if res is not None else None,
                              "success": bool(res is not None and res.success),
                              "message": (res.message if res is not None else "no reply")[:100]})
                i += 1
                stop.wait(max(0.0, cfg.ground_period - dt))

        def periodic_saver():
            saver.wait_for_service(timeout_sec=60)
            while not stop.wait(cfg.save_period):
                t = time.monotonic()
                fut = saver.call_async(save_type.Request())
                end = t + cfg.ground_timeout
                while not fut.done() and time.monotonic() < end:
                    time.sleep(0.02)
                r = fut.result() if fut.done() else None
                save_log.append({"t": t - t0, "seconds": time.monotonic() - t if r is not None else None,
                                 "success": bool(r is not None and r.success),
                                 "message": (r.message if r is not None else "no reply")[:100]})

        ground = threading.Thread(target=caller, daemon=True)
        if cfg.ground_period > 0:
            ground.start()
        if cfg.save_period > 0:
            threading.Thread(target=periodic_saver, daemon=True).start()
        bar = tqdm(total=cfg.frames, desc="endurance", unit="frame", disable=not progress, file=sys.stderr)
        while replay.poll() is None and node.poll() is None:
            st = dict(status)
            since = {k: (st.get(k) or 0) - (warm.get(k) or 0) for k in ("received", "mapped", "dropped", "rejected")}
            samples.append({"t": time.monotonic() - t0, "rss_mb": _rss_mb(node.pid), **since,   # counts: after warm-up
                            **{k: st.get(k) for k in ("queue", "gaussians", "keyframes", "evicted", "keyframes_dropped", "keyframes_replaced", "revisits")},
                            "input_errors": sum((st.get("input_errors") or {}).values()),
                            # frames refused for what they held (pose, images, TF), not dropped for want of time
                            "bad_input": sum(v for k, v in (st.get("input_errors") or {}).items() if k != "queue_drop"),
                            "sync_dropped": st.get("sync_dropped"), "sync_mixed": st.get("sync_mixed"),
                            "tf_dropped": st.get("tf_dropped")})
            if int(st.get("received") or 0) != bar.n:
                bar.n = int(st.get("received") or 0)
                bar.refresh()
            time.sleep(cfg.sample_period)
        bar.close()
        time.sleep(3 * cfg.sample_period)   # the last frames in flight
        stop.set()
        if ground.is_alive():
            ground.join(cfg.ground_timeout + 5)
        crashed = node.poll() is not None
    finally:
        stop.set()
        if replay is not None:
            stop_process(replay, 10)
        stop_process(node)
        executor.shutdown(timeout_sec=5)
        probe.destroy_node()
        ctx.try_shutdown()
    summary = summarise(samples, calls, crashed)
    warmup = {k: warm.get(k) for k in ("received", "mapped", "keyframes", "gaussians", "field_stop")}
    lat = np.array([c["seconds"] for c in calls if c["seconds"] is not None], float)
    during_save = [c["seconds"] for c in calls if c["seconds"] is not None and any(
        x["seconds"] is not None and x["t"] <= c["t"] <= x["t"] + x["seconds"] for x in save_log)]
    summary.update(latency_p50_s=float(np.percentile(lat, 50)) if len(lat) else float("nan"),
                   latency_p95_s=float(np.percentile(lat, 95)) if len(lat) else float("nan"),
                   latency_max_s=float(lat.max()) if len(lat) else float("nan"),
                   calls_during_save=len(during_save),
                   latency_max_during_save_s=float(max(during_save)) if during_save else float("nan"),
                   mapped_per_s=(summary["frames_mapped"] or 0) / summary["seconds"] if summary["seconds"] else 0.0,
                   periodic_saves=len(save_log), periodic_saves_ok=sum(x["success"] for x in save_log),
                   save_seconds_max=max((x["seconds"] or 0.0 for x in save_log), default=0.0))
    summary.update(faults_injected=_faults_logged(work / "replay.log"), saves=len(saves), saves_ok=sum(saves),
                   keyframes_min_after_warmup=min((x["keyframes"] or 0 for x in samples), default=0),
                   keyframes_at_warmup=warmup["keyframes"])
    return {"samples": samples, "calls": calls, "saves": save_log, "crashed": crashed, "node_exit": node.returncode,
            "warmup": warmup, "summary": summary}


def _faults_logged(log: Path) -> dict:
    """The fault counts rg-replay logs at its end ({} when none were injected or it did not finish)."""
    text = log.read_text() if log.is_file() else ""
    i = text.rfind("faults injected: ")
    if i < 0:
        return {}
    try:
        return json.JSONDecoder().raw_decode(text[i + len("faults injected: "):])[0]
    except ValueError:
        return {}


def summarise(samples: list[dict], calls: list[dict], crashed: bool) -> dict:
    """Growth of the peak RSS over the run's last half, query latency p95 of the first and last 10 %
    of the calls, unanswered calls, frames received / dropped."""
    rss = np.array([s["rss_mb"] for s in samples if s["rss_mb"] is not None], np.float64)
    half = len(rss) // 2
    peak_mid = float(rss[:max(half, 1)].max()) if len(rss) else float("nan")
    peak_end = float(rss.max()) if len(rss) else float("nan")
    lat = [c["seconds"] for c in calls if c["seconds"] is not None]
    k = max(1, len(lat) // 10)
    last = samples[-1] if samples else {}
    # Keyframes ever added: those held, dropped, and replaced (a replacement removes the old one and
    # adds a new one, with its own supervision and field caches, at an unchanged count).
    kf = [(x["keyframes"] or 0) + (x.get("keyframes_dropped") or 0) + (x.get("keyframes_replaced") or 0)
          for x in samples if x["rss_mb"] is not None]
    kf_added = int(kf[-1] - kf[max(half - 1, 0)]) if kf else 0
    return {"frames_received": last.get("received"), "frames_mapped": last.get("mapped"),
            "frames_dropped": last.get("dropped"), "queue_max": max((s["queue"] or 0) for s in samples) if samples else 0,
            "gaussians": last.get("gaussians"), "keyframes": last.get("keyframes"),
            "rss_mid_mb": peak_mid, "rss_peak_mb": peak_end,
            "rss_growth_last_half_pct": 100.0 * (peak_end - peak_mid) / peak_mid if peak_mid > 0 else float("nan"),
            "keyframes_added_last_half": kf_added,
            "calls": len(calls), "calls_unanswered": sum(c["seconds"] is None for c in calls),
            "calls_answered_success": sum(c["success"] for c in calls),
            "latency_p95_first_s": float(np.percentile(lat[:k], 95)) if lat else float("nan"),
            "latency_p95_last_s": float(np.percentile(lat[-k:], 95)) if lat else float("nan"),
            "crashed": crashed, "seconds": samples[-1]["t"] if samples else 0.0,
            **{k: last.get(k) for k in ("input_errors", "bad_input", "sync_dropped", "sync_mixed", "tf_dropped", "rejected", "keyframes_dropped", "keyframes_replaced", "revisits")}}


def plot(result: dict, png: Path, title: str) -> Path:
    """RSS, queue and drops, and query latency over time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s, c = result["samples"], result["calls"]
    t = [x["t"] for x in s]
    fig, ax = plt.subplots(1, 3, figsize=(13, 3.2))
    ax[0].plot(t, [x["rss_mb"] for x in s])
    ax[0].set_ylabel("node RSS (MB)")
    ax[1].plot(t, [x["queue"] or 0 for x in s], label="queue")
    ax[1].plot(t, [x["dropped"] or 0 for x in s], label="dropped (total)")
    ax[1].legend(fontsize=7)
    ax[2].plot([x["t"] for x in c if x["seconds"] is not None], [x["seconds"] for x in c if x["seconds"] is not None],
               ".", ms=3)
    ax[2].set_ylabel("/ground latency (s)")
    for a in ax:
        a.set_xlabel("time (s)")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=100)
    plt.close(fig)
    return png
