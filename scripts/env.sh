# Source me: the environment of the built workspace (ROS, .venv, install/), loopback-only DDS.
# shellcheck shell=bash
_stepper_root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
# Fast DDS multicasts discovery on every interface by default; keep it on this machine.
# On a robot with several hosts, export ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET (see README).
export ROS_AUTOMATIC_DISCOVERY_RANGE=${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}
if [ -f "${STEPPER_SYSTEM_ROS:-/opt/ros/jazzy}/setup.bash" ] && [ "${STEPPER_FORCE_PIP_ROS:-0}" != 1 ]; then
    source "${STEPPER_SYSTEM_ROS:-/opt/ros/jazzy}/setup.bash"
else
    export AMENT_PREFIX_PATH="$_stepper_root/.venv${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
fi
if [ -d "$_stepper_root/.venv/bin" ]; then
    export VIRTUAL_ENV="$_stepper_root/.venv"
    export PATH="$_stepper_root/.venv/bin:$PATH"
fi
# The minimal control_msgs that scripts/bootstrap.sh builds when the environment has none (pip
# ROS), unless a prefix on AMENT_PREFIX_PATH has one by now (e.g. ros-jazzy-control-msgs installed
# since): it never shadows the released package.
_stepper_cm=$_stepper_root/.venv/control_msgs
if [ -f "$_stepper_cm/local_setup.bash" ]; then
    _stepper_rest=${AMENT_PREFIX_PATH:-}
    while [ -n "$_stepper_rest" ]; do
        _stepper_p=${_stepper_rest%%:*}
        case $_stepper_rest in *:*) _stepper_rest=${_stepper_rest#*:} ;; *) _stepper_rest= ;; esac
        if [ "$_stepper_p" != "$_stepper_cm" ] && \
            [ -e "$_stepper_p/share/ament_index/resource_index/packages/control_msgs" ]; then
            _stepper_cm=
            break
        fi
    done
    [ -z "$_stepper_cm" ] || source "$_stepper_cm/local_setup.bash"
    unset _stepper_rest _stepper_p
fi
unset _stepper_cm
if [ -z "${STEPPER_NO_WORKSPACE:-}" ] && [ -f "$_stepper_root/install/local_setup.bash" ]; then
    source "$_stepper_root/install/local_setup.bash"
    # stepperctl (and the node executables) as plain commands
    export PATH="$_stepper_root/install/stepper_drivers/lib/stepper_drivers:$PATH"
fi
# Fast DDS announces a participant every 3 s and does not answer a newcomer at once, so a
# short-lived client (stepperctl, a test) waits up to 3 s to see a node; this profile makes it 0.3 s.
export FASTRTPS_DEFAULT_PROFILES_FILE=${FASTRTPS_DEFAULT_PROFILES_FILE:-$_stepper_root/config/fastdds_fast_discovery.xml}
export PYTHONUNBUFFERED=1
unset _stepper_root
