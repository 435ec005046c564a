#!/usr/bin/env python3
"""Benchmark: what vector_step_node publishes when the drives send their TxPDOs at 1 kHz.

For 1 and 4 simulated drives on one CAN bus (the loopback socketcand broker as its own process),
vector_step_node runs with publish_rate_hz 1000, tpdo_event_timer_ms 1 (TxPDO2 = statusword
+ position actual value, at least every 1 ms) and tpdo_inhibit_ms 0 (not its default), the
drives move during the window, and the script measures per second: the TxPDOs the node's CAN
stack received (its link counters), the joint_states and status messages the node published and
how many of them carried a new position, the CPU share of the node process (and of the
simulator), and compares with the frame rate a real 1 Mbit/s bus allows for the same PDO (6 data
bytes).

Run: source scripts/env.sh && python scripts/bench_vector_step.py [--window 4] [--nodes 1 4]
"""

from __future__ import annotations

import argparse
import os
import pathlib
import sys
import tempfile
import time

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')

from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64
from std_srvs.srv import SetBool
from stepper_drivers.cli.ros_client import RosClient
from stepper_drivers_msgs.msg import DriveStatus
from stepper_sim.harness import Proc, executable, free_port
import yaml

NODE = '/vector_step_node'
CLK_TCK = os.sysconf('SC_CLK_TCK')
PDO_DATA_BYTES = 6                      # TxPDO2: statusword (2) + position actual value (4)
BITRATE = 1_000_000


def can_frame_bits(data_bytes: int) -> tuple[int, int]:
    """Bits of a standard (11-bit) data frame incl. 3 bits interframe space: (no stuffing,
    worst-case stuffing). 47 = SOF 1 + ID 11 + RTR 1 + IDE 1 + r0 1 + DLC 4 + CRC 15 + CRC
    delimiter 1 + ACK 2 + EOF 7 + IFS 3; stuff bits over the 34 + 8n bits from SOF to CRC."""
    nominal = 47 + 8 * data_bytes
    return nominal, nominal + (34 + 8 * data_bytes - 1) // 4


def cpu_s(pid: int) -> float:
    fields = pathlib.Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK      # utime + stime


def write_params(path: pathlib.Path, n: int, port: int) -> tuple[pathlib.Path, pathlib.Path]:
    drives = [f'axis{i}' for i in range(1, n + 1)]
    node = {'can': {'interface': 'socketcand', 'channel': 'can0', 'host': '127.0.0.1',
                    'port': port},
            'publish_rate_hz': 1000.0, 'command_timeout_s': 5.0, 'diagnostics_rate_hz': 2.0,
            'drives': drives}
    sim = {'can': {'interface': 'socketcand', 'channel': 'can0', 'host': '127.0.0.1',
                   'port': port}, 'cycle_s': 0.001, 'drives': drives}
    for i, d in enumerate(drives, 1):
        node[f'drives.{d}'] = {'node_id': i, 'joint_name': f'joint{i}', 'steps_per_rev': 3200.0,
                               'max_velocity': 40.0, 'profile_velocity': 6.0,
                               'tpdo_event_timer_ms': 1, 'tpdo_inhibit_ms': 0.0,
                               'heartbeat_timeout_s': 2.0}
        sim[f'drives.{d}'] = {'node_id': i}
    node_file, sim_file = path / f'node{n}.yaml', path / f'sim{n}.yaml'
    node_file.write_text(yaml.safe_dump({'vector_step_node': {'ros__parameters': node}}))
    sim_file.write_text(yaml.safe_dump({'vector_step_sim': {'ros__parameters': sim}}))
    return node_file, sim_file


def link_counters(ros: RosClient) -> dict[str, int]:
    diag = ros.wait_msg('/diagnostics', lambda a: any(s.name.endswith('link') for s in a.status))
    link = next(s for s in diag.status if s.name.endswith('link'))
    return {kv.key: int(kv.value) for kv in link.values if kv.value.isdigit()}


def run(n: int, window_s: float, log_dir: pathlib.Path) -> dict:
    port = free_port()
    node_file, sim_file = write_params(log_dir, n, port)
    procs: list[Proc] = []
    ros = RosClient(f'bench_vector_step_{n}')
    try:
        broker = Proc([executable('stepper_sim', 'socketcand_broker'), '--port', str(port)],
                      log_dir, f'broker{n}')
        procs.append(broker)
        broker.wait_line('listening', 10.0)
        sim = Proc([executable('stepper_sim', 'vector_step_sim'), '--ros-args',
                    '--params-file', str(sim_file)], log_dir, f'sim{n}')
        procs.append(sim)
        sim.wait_line('ready', 30.0)
        node = Proc([executable('stepper_drivers', 'vector_step_node'), '--ros-args',
                     '--params-file', str(node_file)], log_dir, f'node{n}')
        procs.append(node)
        drives = [f'axis{i}' for i in range(1, n + 1)]
        ros.subscribe(JointState, '/joint_states', keep=True)
        ros.subscribe(DiagnosticArray, '/diagnostics')
        for d in drives:
            ros.subscribe(DriveStatus, f'{NODE}/{d}/status', keep=True)
            ros.wait_msg(f'{NODE}/{d}/status', lambda m: m.connected, 60.0, f'{d} connected')
            r = ros.call(SetBool, f'{NODE}/{d}/enable', SetBool.Request(data=True), 10.0)
            assert r.success, r.message
        for d in drives:                       # long moves: positions change during the window
            ros.publish(Float64, f'{NODE}/{d}/position_command', Float64(data=50.0))
        ros.wait_msg(f'{NODE}/{drives[-1]}/status', lambda m: m.moving, 10.0, 'moving')
        time.sleep(0.5)                         # past the acceleration
        with ros.lock:
            js0 = len(ros.history['/joint_states'])
            st0 = {d: len(ros.history[f'{NODE}/{d}/status']) for d in drives}
        pids = (node.pid, sim.pid, broker.pid)
        c0, cpu0, t0 = link_counters(ros), [cpu_s(p) for p in pids], time.monotonic()
        time.sleep(window_s)
        c1, cpu1, t1 = link_counters(ros), [cpu_s(p) for p in pids], time.monotonic()
        with ros.lock:
            js = ros.history['/joint_states'][js0:]
            st = {d: ros.history[f'{NODE}/{d}/status'][st0[d]:] for d in drives}
        elapsed = t1 - t0
        fresh = []
        for i in range(n):                      # joint_states with a new position per joint
            positions = [m.position[i] for m in js]
            fresh.append(sum(1 for a, b in zip(positions, positions[1:]) if a != b))
        assert all(m.moving for m in (st[d][-1] for d in drives)), 'a drive stopped early'
        return {
            'nodes': n, 'window_s': elapsed,
            'tpdo_rx_s': (c1['tpdo_rx'] - c0['tpdo_rx']) / elapsed,
            'joint_states_s': len(js) / elapsed,
            'status_s_per_node': sum(len(v) for v in st.values()) / n / elapsed,
            'fresh_positions_s_per_node': sum(fresh) / n / elapsed,
            'cpu_node': (cpu1[0] - cpu0[0]) / elapsed,
            'cpu_sim': (cpu1[1] - cpu0[1]) / elapsed,
            'cpu_broker': (cpu1[2] - cpu0[2]) / elapsed,
        }
    finally:
        for p in reversed(procs):
            try:
                p.stop()
            except AssertionError:
                p.kill()
        ros.close()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--window', type=float, default=4.0, help='measurement window [s]')
    ap.add_argument('--nodes', type=int, nargs='+', default=[1, 4])
    args = ap.parse_args()
    log_dir = pathlib.Path(tempfile.mkdtemp(prefix='bench_vector_step_'))
    nominal, stuffed = can_frame_bits(PDO_DATA_BYTES)
    bus_max = (BITRATE / stuffed, BITRATE / nominal)
    print(f'1 Mbit/s bus, {PDO_DATA_BYTES}-byte PDO: {nominal}..{stuffed} bits per frame = '
          f'{bus_max[0]:.0f}..{bus_max[1]:.0f} frames/s in total (bus 100 % busy)')
    rows = []
    for n in args.nodes:
        r = run(n, args.window, log_dir)
        rows.append(r)
        per_node_bus = (bus_max[0] / n, bus_max[1] / n)
        print(f'\n{n} node(s), {r["window_s"]:.1f} s window:')
        print(f'  TxPDOs received by the node      {r["tpdo_rx_s"]:8.0f} /s  '
              f'({r["tpdo_rx_s"] / n:.0f} per drive; the drives send 1000 TxPDO2/s each)')
        print(f'  joint_states published            {r["joint_states_s"]:8.0f} /s  '
              f'(publish_rate_hz 1000; all {n} joint(s) in each message)')
        print(f'  status per drive                  {r["status_s_per_node"]:8.0f} /s')
        print(f'  new position per drive           {r["fresh_positions_s_per_node"]:8.0f} /s  '
              f'= {r["fresh_positions_s_per_node"] / 1000.0:.0%} of the 1 kHz TxPDO rate')
        print(f'  CPU: node {r["cpu_node"]:.0%} of one core, simulator {r["cpu_sim"]:.0%}, '
              f'broker {r["cpu_broker"]:.0%}')
        print(f'  a 1 Mbit/s bus allows {per_node_bus[0]:.0f}..{per_node_bus[1]:.0f} such PDOs/s '
              f'per drive: the node publishes '
              f'{r["fresh_positions_s_per_node"] / per_node_bus[0]:.0%} of the worst-case bus '
              f'limit; 1 kHz per drive uses {1000.0 * n / bus_max[0]:.0%} of the bus')
    print(f'\nprocess logs: {log_dir}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
