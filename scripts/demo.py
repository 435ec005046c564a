#!/usr/bin/env python3
"""The embedded default: simulated drives and their driver nodes, driven through ROS only.

For each vendor: start its simulator and its node (the params files in config/, on a free port),
then per drive: enable, home, move to two targets and back, a velocity run that the node's watchdog
stops, disable. Prints joint states as it goes and exits 0 when every step worked, leaving no process.
Run it with scripts/demo.sh (which bootstraps the workspace first).
"""

from __future__ import annotations

import argparse
import math
import os
import pathlib
import sys
import tempfile
import time

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')

from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Float64  # noqa: E402
from std_srvs.srv import SetBool, Trigger  # noqa: E402
from stepper_drivers.tools.client import RosClient  # noqa: E402
from stepper_drivers.tools.processes import CONFIG, Proc, executable, free_port, wait_for  # noqa
from stepper_drivers_msgs.msg import DriveStatus  # noqa: E402

# vendor: simulator, node, params files, the parameter that carries the link address, and the moves
DEMOS = {
    'xplus_mt': dict(sim='xplus_mt_sim', node='xplus_mt_node', link_param='port',
                     targets=(3.0, -2.0, 0.0), velocity=6.0),
    # link='path': the link is a serial port path (the simulator's pty symlink), not a TCP port
    'rd4': dict(sim='rd4_sim', node='rd4_node', link_param='port', link='path',
                targets=(3.0, -2.0, 0.0), velocity=6.0),
}


class Demo:
    def __init__(self, ros: RosClient, log_dir: pathlib.Path, verbose: bool):
        self.ros = ros
        self.log_dir = log_dir
        self.verbose = verbose
        self.procs: list[Proc] = []
        self.failures: list[str] = []

    def say(self, text: str) -> None:
        print(text, flush=True)

    def start(self, vendor: str, spec: dict) -> tuple[str, list[str]]:
        port = str(free_port()) if spec.get('link') != 'path' else str(self.log_dir / vendor)
        sim = Proc([executable('stepper_sim', spec['sim']), '--ros-args', '--params-file',
                    str(CONFIG / f"{vendor}_sim.yaml"), '-p', f"{spec['link_param']}:={port}"],
                   self.log_dir, spec['sim'])
        self.procs.append(sim)
        sim.wait_line('ready', 30.0)
        node = Proc([executable('stepper_drivers', spec['node']), '--ros-args', '--params-file',
                     str(CONFIG / f'{vendor}.yaml'), '-p', f"{spec['link_param']}:={port}"],
                    self.log_dir, spec['node'])
        self.procs.append(node)
        ns = '/' + spec['node']
        self.ros.subscribe(JointState, '/joint_states')
        drives = self._drive_names(vendor)
        for d in drives:
            self.ros.subscribe(DriveStatus, f'{ns}/{d}/status')
            self.ros.wait_msg(f'{ns}/{d}/status', lambda m: m.connected, 30.0,
                              f'{spec["node"]}/{d} to connect')
        where = port if spec.get('link') == 'path' else f'127.0.0.1:{port}'
        self.say(f'[{vendor}] simulator and node up on {where}; drives: {", ".join(drives)}')
        return ns, drives

    @staticmethod
    def _drive_names(vendor: str) -> list[str]:
        import yaml
        params = yaml.safe_load((CONFIG / f'{vendor}.yaml').read_text())
        return list(next(iter(params.values()))['ros__parameters']['drives'])

    def check(self, ok: bool, what: str) -> bool:
        if not ok:
            self.failures.append(what)
            self.say(f'  FAILED: {what}')
        return ok

    def service(self, srv_type, name: str, request=None, timeout_s: float = 30.0):
        resp = self.ros.call(srv_type, name, request, timeout_s)
        self.say(f'  {name.split("/")[-1]}: {resp.message}')
        self.check(resp.success, f'{name}: {resp.message}')
        return resp

    def status(self, ns: str, drive: str) -> DriveStatus:
        return self.ros.latest[f'{ns}/{drive}/status']

    def print_joints(self, ns: str) -> None:
        js = self.ros.latest.get('/joint_states')
        if js is not None:
            joints = '  '.join(f'{n}={p:+8.3f} rad ({v:+7.2f} rad/s)'
                               for n, p, v in zip(js.name, js.position, js.velocity))
            self.say(f'    joint_states t={js.header.stamp.sec % 1000}.{js.header.stamp.nanosec // 1_000_000:03d}  {joints}')

    def wait_still(self, ns: str, drive: str, timeout_s: float, target: float | None = None):
        deadline = time.monotonic() + timeout_s
        last_print = 0.0
        while time.monotonic() < deadline:
            st = self.status(ns, drive)
            if time.monotonic() - last_print > 0.25:
                self.print_joints(ns)
                last_print = time.monotonic()
            if st.fault:
                return st
            if not st.moving and (target is None or abs(st.position - target) < 1e-3):
                return st
            time.sleep(0.02)
        return self.status(ns, drive)

    def run_drive(self, ns: str, drive: str, spec: dict) -> None:
        base = f'{ns}/{drive}'
        self.say(f'[{drive}] enable')
        self.service(SetBool, base + '/enable', SetBool.Request(data=True))
        self.say(f'[{drive}] home')
        self.service(Trigger, base + '/home')
        for target in spec['targets']:
            self.say(f'[{drive}] move to {target:+.3f} rad')
            self.ros.publish(Float64, base + '/position_command', Float64(data=target))
            st = self.wait_still(ns, drive, 20.0, target)
            self.check(abs(st.position - target) < 1e-3 and not st.fault,
                       f'{drive} at {st.position:.4f}, expected {target}')
        v = spec['velocity']
        self.say(f'[{drive}] velocity {v} rad/s for 1 s, then no more commands: the watchdog stops it')
        t_end = time.monotonic() + 1.0
        while time.monotonic() < t_end:
            self.ros.publish(Float64, base + '/velocity_command', Float64(data=v))
            self.print_joints(ns)
            time.sleep(0.1)  # command rate of this demo: 10 Hz
        st = self.wait_still(ns, drive, 10.0)
        self.check(not st.moving and not st.fault, f'{drive} still moving after the watchdog')
        self.say(f'[{drive}] stopped by the watchdog at {st.position:+.3f} rad; disable')
        self.service(SetBool, base + '/enable', SetBool.Request(data=False))

    def stop_all(self) -> None:
        for p in reversed(self.procs):
            code = p.stop()
            self.check(code == 0, f'{p.name} exit code {code}')
        self.procs.clear()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--vendor', action='append', choices=sorted(DEMOS),
                    help='run only this vendor (repeatable); default: all')
    ap.add_argument('--verbose', action='store_true')
    args = ap.parse_args()
    log_dir = pathlib.Path(tempfile.mkdtemp(prefix='stepper_demo_'))
    ros = RosClient('stepper_demo')
    demo = Demo(ros, log_dir, args.verbose)
    try:
        for vendor in args.vendor or DEMOS:
            spec = DEMOS[vendor]
            ns, drives = demo.start(vendor, spec)
            for d in drives:
                demo.run_drive(ns, d, spec)
            demo.stop_all()
    except (AssertionError, FileNotFoundError) as e:
        demo.failures.append(str(e))
        print(f'demo: {e}', file=sys.stderr)
    finally:
        for p in demo.procs:
            p.kill()
        ros.close()
    if demo.failures:
        print(f'demo FAILED ({len(demo.failures)}): ' + '; '.join(demo.failures)
              + f'\nprocess logs: {log_dir}', file=sys.stderr)
        return 1
    print(f'demo OK: every drive enabled, homed, moved and stopped. Process logs: {log_dir}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
