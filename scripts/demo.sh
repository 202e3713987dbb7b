#!/usr/bin/env bash
# Command 1 of the README: install what is missing, then run the main job (`rg demo`).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
source "$ROOT/scripts/bootstrap.sh"
exec rg demo "$@"
