"""The `ros2` command line as a user types it, for the tests that call it (test_ros2_cli, test_ros_teach).

Fast-DDS can crash a CLI process with SIGSEGV while it tears its participant down at exit, after the
command's work is done and printed (eProsima/Fast-DDS#1906, ros2/rosbag2#1311: the participant
factory's static teardown); CI saw it on `ros2 service call /ground` with the whole response on
stdout (2026-12-05). Such a run counts as the success it was when its complete result is on
stdout (a warning says so); a crash before that, or any other exit status, is still a failure.
"""
from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import warnings
from pathlib import Path

PREFIX = Path(sys.prefix)   # the venv: where the set-up installs rg_ros's ROS layout and the vendored CLI
_BESIDE = Path(sys.executable).with_name("ros2")
ROS2 = shutil.which("ros2") or (str(_BESIDE) if _BESIDE.exists() else None)

# What each command prints once its work is done, before it shuts down (the verb's own output format).
_COMPLETE = {
    ("service", "call"): re.compile(r"^response:\n\S+_Response\(.*\)\s*\Z", re.S | re.M),
    ("topic", "pub"): re.compile(r"^publishing #1: ", re.M),
    ("topic", "echo"): re.compile(r"^---\s*\Z", re.M),
}


def ros_env() -> dict:
    """os.environ with the venv on AMENT_PREFIX_PATH and PATH, logging unbuffered."""
    env = dict(os.environ)
    paths = [p for p in env.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    env["AMENT_PREFIX_PATH"] = os.pathsep.join(dict.fromkeys([str(PREFIX), *paths]))
    env["PATH"] = os.pathsep.join([str(PREFIX / "bin"), env.get("PATH", "")])
    env["RCUTILS_LOGGING_BUFFERED_STREAM"] = "0"
    return env


def completed_before_crash(args: tuple[str, ...], returncode: int, stdout: str) -> bool:
    """True when a run killed by SIGSEGV had already printed its verb's complete result."""
    rule = _COMPLETE.get(tuple(args[:2]))
    return returncode == -signal.SIGSEGV and rule is not None and rule.search(stdout) is not None


def ros2(*args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    """One `ros2` command; its CompletedProcess. Not finishing in `timeout` s is a failure."""
    try:
        r = subprocess.run([ROS2, *args], env=ros_env(), capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired as exc:
        raise AssertionError(f"`ros2 {' '.join(args)}` did not finish in {timeout:.0f} s: "
                             f"{(exc.stdout or b'')[-2000:]!r} {(exc.stderr or b'')[-2000:]!r}") from exc
    if completed_before_crash(args, r.returncode, r.stdout):
        warnings.warn(f"`ros2 {' '.join(args[:2])}` crashed (SIGSEGV) in DDS teardown after its complete result")
        r = subprocess.CompletedProcess(r.args, 0, r.stdout, r.stderr)
    return r
