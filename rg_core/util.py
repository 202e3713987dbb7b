"""Small process-level helpers shared by the CLI, the registries and the benchmark scripts."""
from __future__ import annotations

import contextlib
import importlib
import os
import sys


@contextlib.contextmanager
def stdout_to_stderr():
    """Send fd 1 to fd 2 while the block runs (pybullet and other C code print to stdout) and yield
    a file object on the real stdout, for the one JSON line a `--json` command prints."""
    sys.stdout.flush()
    saved = os.dup(1)
    os.dup2(2, 1)
    real = os.fdopen(os.dup(saved), "w")
    try:
        yield real
    finally:
        sys.stdout.flush()
        real.flush()
        real.close()
        os.dup2(saved, 1)
        os.close(saved)


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far (MB)."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_json_script(main) -> None:
    """Run a benchmark's `main()` with C-level stdout sent to stderr, so that the one JSON line it
    prints with --json is all that reaches stdout; exit with its return code."""
    with stdout_to_stderr() as real_stdout:
        sys.stdout = real_stdout
        try:
            code = main()
        finally:
            sys.stdout = sys.__stdout__
    sys.exit(code)


def make_registered(kind: str, registry: dict, name: str, **kwargs):
    """Build backend `name` of a registry {name: factory or "package.module:attr"}: a string entry
    is imported on first use, so a registry never imports its backends (nor their dependencies)."""
    if name not in registry:
        raise ValueError(f"unknown {kind} {name!r}; known: {sorted(registry)}")
    factory = registry[name]
    if isinstance(factory, str):
        module, _, attr = factory.partition(":")
        factory = getattr(importlib.import_module(module), attr)
    return factory(**kwargs)


@contextlib.contextmanager
def torch_threads(n: int):
    """torch.set_num_threads(n) inside the block (n <= 0: leave it), the old count restored after."""
    import torch

    old = torch.get_num_threads()
    if n > 0 and n != old:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        if torch.get_num_threads() != old:
            torch.set_num_threads(old)


_PREFETCHING: list = []   # the threads prefetch started (join_prefetches waits for them)


def prefetch(module: str) -> None:
    """Import a module in a background thread (a later import of it waits for this one)."""
    import threading

    if module not in sys.modules:
        t = threading.Thread(target=importlib.import_module, args=(module,), daemon=True)
        t.start()
        _PREFETCHING.append(t)


def join_prefetches() -> None:
    """Wait for every prefetch import to finish: a process must not exit while one is loading a
    native library (a daemon thread stopped inside C++ initialisation aborts the process:
    "terminate called without an active exception", exit -6, after the work was done)."""
    while _PREFETCHING:
        _PREFETCHING.pop().join()
