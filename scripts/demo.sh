#!/usr/bin/env bash
# Command 1 of the README: install what is missing, then run the main job (`rg demo`).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
export RG_PROFILE="${RG_PROFILE:-demo}"  # install only what rg demo uses
source "$ROOT/scripts/bootstrap.sh"
exec rg demo "$@"
