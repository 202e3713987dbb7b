"""Small process-level helpers shared by the CLI and the benchmark scripts."""
from __future__ import annotations

import contextlib
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
