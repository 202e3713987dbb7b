"""A scene task for tests/test_many_scenes_ray.py that the Ray workers import (the test's cluster has
tests/ on its PYTHONPATH): `rg eval`'s own task, except that a scene folder holding a KILL_MY_WORKER
file first removes the file, then kills the worker process running it (SIGKILL, as the kernel's OOM
killer does). Deterministic: which scene dies is fixed before the run, and it dies at once."""
import os
import signal
from pathlib import Path

from rg_core.cli.evaluation import eval_task

MARKER = "KILL_MY_WORKER"


def eval_or_die(payload: dict) -> dict:
    marker = Path(payload["args"]["scene"]) / MARKER
    if marker.exists():
        marker.unlink()
        os.kill(os.getpid(), signal.SIGKILL)
    return eval_task(payload)
