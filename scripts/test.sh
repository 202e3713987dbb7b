#!/usr/bin/env bash
# Command 2 of the README: install what is missing (Ray too: its tests start real clusters), then run
# the test suite on RG_TEST_WORKERS pytest-xdist workers (default 2, one a core; tests/conftest.py
# gives each one thread and its own ROS domain), a whole test file per worker so that module
# fixtures are built once. The 25 slowest tests are listed at the end. Extra arguments go to pytest (`-n 0`: one process).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
source "$ROOT/scripts/bootstrap.sh"
cd "$ROOT"
exec python -m pytest -q -n "${RG_TEST_WORKERS:-2}" --dist loadfile --durations=25 tests "$@"
