#!/usr/bin/env bash
# Run every test (unit, simulator, integration through ROS). Bootstraps first if needed.
#   scripts/test.sh               all tests
#   scripts/test.sh -k xplus      pytest arguments pass through
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$ROOT"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
bash scripts/bootstrap.sh
# shellcheck source=env.sh
set +u; source scripts/env.sh; set -u
exec python -m pytest "$@"
