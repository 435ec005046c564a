#!/usr/bin/env bash
# The repository's linter (ruff.toml): every Python file git tracks. Bootstraps first if needed.
#   scripts/lint.sh            check
#   scripts/lint.sh --fix      ruff's safe fixes
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$ROOT"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST   # the bootstrap may build with colcon
bash scripts/bootstrap.sh
# shellcheck source=env.sh
set +u; source scripts/env.sh; set -u
exec python -m ruff check "$@" .
