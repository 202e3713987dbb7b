"""Where the tasks run: "local" (one after another, in this process) or "ray" (one Ray task per
scene, on local workers or a cluster). Ray is imported only here and only when asked for, so
rg_core runs without it. The task function is named "package.module:attr" (as registries name their
backends): the driver never imports it, so a Ray driver loads no torch.

A task never takes the run down: an exception inside it, a worker killed (by a person, the kernel's
OOM killer or Ray's memory monitor) or a node lost is that task's record, status "failed", with the
error; the other tasks go on. Ray tasks run with max_retries=0, so a crash is reported, not hidden
by a silent rerun (`--retry-failed` reruns on purpose)."""
from __future__ import annotations

import importlib
import os
import platform
import socket
import sys
import time
import traceback
from collections.abc import Callable

RAY_INSTALL = "pip install .[ray]  (from the checkout; or pip install -r requirements-ray.txt)"


class EngineError(RuntimeError):
    """The engine cannot start (Ray missing, no cluster at the address)."""


def import_ray():
    """The ray module, or an EngineError that says how to install it."""
    try:
        import ray
    except ImportError as exc:
        raise EngineError(f"--ray needs Ray, which is not installed in this Python ({sys.executable}): "
                          f"{RAY_INSTALL}") from exc
    return ray


def engine_info(name: str) -> dict:
    """{"name": "local" | "ray", "version"}: Ray's version, or this Python's for the in-process loop."""
    if name == "ray":
        return {"name": "ray", "version": import_ray().__version__}
    return {"name": "local", "version": f"python {platform.python_version()}"}


def cores() -> int:
    """CPU cores this process may use (its affinity, not the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:   # not Linux
        return os.cpu_count() or 1


def execute(fn_ref: str, name: str, payload: dict, threads: int = 0, node: str = "local") -> dict:
    """Run one task -> its record. `threads` > 0: torch's thread count while it runs (restored after):
    the same count wherever a task runs keeps its figures the same, since a thread count changes
    how torch splits its reductions and so their float rounding."""
    t0 = time.perf_counter()
    rec = {"scene": name, "node": node, "host": socket.gethostname(), "pid": os.getpid(), "threads": threads}
    old = None
    try:
        if threads > 0:
            import torch

            old = torch.get_num_threads()
            torch.set_num_threads(threads)
        module, _, attr = fn_ref.partition(":")
        result = getattr(importlib.import_module(module), attr)(payload)
        rec.update(status="ok", error=None, result=result)
    except (Exception, MemoryError) as exc:   # noqa: BLE001 - every failure is the task's record
        rec.update(status="failed", error=f"{type(exc).__name__}: {exc}", result=None,
                   traceback="".join(traceback.format_exception(exc))[-4000:])
    finally:
        if old is not None:
            import torch

            torch.set_num_threads(old)
    rec["seconds"] = round(time.perf_counter() - t0, 3)
    return rec


def _ray_execute(fn_ref: str, name: str, payload: dict, threads: int) -> dict:
    """execute() inside a Ray worker, with the node's id in the record."""
    import ray

    return execute(fn_ref, name, payload, threads, ray.get_runtime_context().get_node_id())


def _crash_record(name: str, exc: BaseException) -> dict:
    """The record of a task whose worker died (killed, out of memory, node lost) before it could answer."""
    text = " ".join(str(exc).split())
    return {"scene": name, "status": "failed", "error": f"{type(exc).__name__}: {text[:1500]}", "result": None,
            "node": None, "host": None, "pid": None, "threads": None, "seconds": None}


def run_tasks(fn_ref: str, tasks: list, on_record: Callable[[object, dict], None], engine: str = "local",
              workers: int = 1, address: str | None = None, progress: bool = True, threads: int = 0,
              ray_init: dict | None = None) -> None:
    """Run each task (`.name`, `.payload`) with `fn_ref`; call on_record(task, record) in this process
    as each finishes (in finishing order). `threads` > 0: each task's torch threads, and on Ray the
    CPUs it asks for (so a node runs at most its CPUs / threads tasks at once: never more threads
    than cores). engine "ray": `address` None starts Ray here for `workers` tasks at once; "auto" or
    "host:port" joins a running cluster."""
    from tqdm import tqdm

    bar = tqdm(total=len(tasks), desc="scenes", unit="scene", disable=not progress, file=sys.stderr)
    try:
        if engine == "local":
            for t in tasks:
                bar.set_postfix_str(t.name, refresh=False)
                on_record(t, execute(fn_ref, t.name, t.payload, threads))
                bar.update()
        elif engine == "ray":
            _run_ray(fn_ref, tasks, on_record, workers, address, bar, threads, ray_init or {})
        else:
            raise ValueError(f"engine must be 'local' or 'ray', got {engine!r}")
    finally:
        bar.close()


def _run_ray(fn_ref: str, tasks: list, on_record, workers: int, address: str | None, bar, threads: int,
             ray_init: dict) -> None:
    ray = import_ray()
    started_here = not ray.is_initialized()
    if started_here:
        kw = dict(include_dashboard=False, log_to_driver=False, configure_logging=False, **ray_init)
        try:
            if address is None:
                # Ray runs task workers at nice 15; here the scenes are the job, and on a shared machine
                # they would lose the CPU to anything else (a cluster's nodes keep their own setting)
                ray.init(num_cpus=workers * max(1, threads), _system_config={"worker_niceness": 0}, **kw)
            else:
                ray.init(address=address, **kw)
        except ConnectionError as exc:
            raise EngineError(f"--ray {address}: cannot join a Ray cluster there ({exc}); start one with "
                              "`ray start --head` (with the cluster's RAY_AUTH_TOKEN where it uses tokens), or give "
                              "--ray without an address for local workers") from exc
    try:
        # SPREAD: a cluster's nodes share the scenes, rather than the driver's node taking them first
        cpus = max(1, threads)
        remote = ray.remote(num_cpus=cpus, max_retries=0, scheduling_strategy="SPREAD")(_ray_execute)
        window = max(2, 2 * int(ray.cluster_resources().get("CPU", workers)) // cpus)   # tasks in flight at once
        pending = iter(tasks)
        inflight: dict = {}

        def submit(n: int) -> None:
            while len(inflight) < n:
                t = next(pending, None)
                if t is None:
                    return
                inflight[remote.remote(fn_ref, t.name, t.payload, threads)] = t

        submit(window)
        while inflight:
            done, _ = ray.wait(list(inflight), num_returns=1)
            for ref in done:
                t = inflight.pop(ref)
                try:
                    rec = ray.get(ref)
                except ray.exceptions.RayError as exc:   # worker killed, out of memory, node died
                    rec = _crash_record(t.name, exc)
                del ref
                on_record(t, rec)
                bar.update()
            submit(window)
    finally:
        if started_here:
            ray.shutdown()
