#!/usr/bin/env bash
# The main command: simulated drives and their ROS nodes, enabled, homed, moved, stopped.
# Bootstraps the workspace first if needed. Arguments pass to scripts/demo.py (--vendor NAME).
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$ROOT"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
bash scripts/bootstrap.sh
# shellcheck source=env.sh
set +u; source scripts/env.sh; set -u
exec python scripts/demo.py "$@"
