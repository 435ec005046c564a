#!/usr/bin/env python3
"""Command-path benchmark: latency, poll rate and CPU of the nodes, against their limits.

Every process is real and separate: simulator, node, a wire probe (scripts/bench_cp_relays.py:
a Modbus TCP relay, a pty relay or a socketcand client) and a tiny rclpy subscriber; the
benchmark publishes through rclpy and reads the probes' CLOCK_MONOTONIC timestamps. The run
takes a private ROS_DOMAIN_ID (test/conftest.py's scheme), so no other node on the machine sees
its commands.

--part latency: `position_command` published -> the command on the wire, p50/p99, while the node
    polls at its configured rate (config/<vendor>.yaml) with the drive enabled; two targets
    alternate, one command at a time, each after the previous one finished plus a random part
    of a poll period (a fresh command, never coalesced). Two points on the wire: the first
    frame of the command (the node's queueing time) and the frame that carries the target
    (X-PLUS MT: FC16 Target Position 1042; RD4: FC16 Target position 0x2B; X-MIND K: WN, the
    move instruction; Vector Step: RxPDO2 with controlword bit 4). In the same run, between two
    commands, the middleware floor: publish -> callback of a Float64 in another process (a
    SingleThreadedExecutor, the node's QoS). Goal: p99 <= floor p99 + one transaction in flight
    (the longest kind of transaction the node makes while polling, its median at the probe)
    + 1 ms; for the target frame also + the command's own transactions before it (first frame
    -> target frame, median).
--part rate: the node's poll loop flat out (publish_rate_hz 1000, the top of its range; its own
    transaction counter from /diagnostics) against a bare library loop on the same simulator
    (X-PLUS MT: pymodbus FC03, the node with 1 and with 4 unit ids, since 1 drive cannot poll
    more than 1000 times a second; RD4: pymodbus async RTU FC04; X-MIND K: pyserial QA).
    Goal: >= 60 % of the bare loop.
--part cpu: CPU (utime + stime of /proc/<pid>/stat over a window) of one node polling 8 drives
    at 50 Hz against a bare library loop polling the same (X-PLUS MT: 8 simulators on 8 ports,
    and 8 unit ids on one port; Vector Step: 8 drives on one CAN bus). Goal: <= 1.3 x the
    floor: the bare loop that also publishes what the node publishes (rclpy). Also shown: the
    node's CPU by thread, the bare loop alone, and (X-PLUS MT) the project's driver polling
    without ROS and the bare loop with a thread per port. `--rounds N` measures the node and
    every loop N times, alternating, and gives the means and each round's ratios.

Run: source scripts/env.sh && python scripts/bench_command_path.py [--vendor xplus_mt ...]
     [--part latency rate cpu] [--commands N] [--window S] [--rounds N] [--owner-priority N]
     [--json out.json]      (--owner-priority: latency with the node's bus owner on SCHED_FIFO)
"Before" figures: run this file from another work tree's environment, e.g.
     git worktree add ../before 4a9d1a6 (built there), then
     cd ../before && source scripts/env.sh && python ../main/scripts/bench_command_path.py
The executables, configs and project modules then come from that tree (the probes are this
tree's scripts/bench_cp_relays.py).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pathlib
import queue
import random
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from typing import Any, Callable

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')

from diagnostic_msgs.msg import DiagnosticArray
from std_msgs.msg import Float64
from std_srvs.srv import SetBool
from stepper_drivers.cli.ros_client import RosClient
from stepper_drivers_msgs.msg import DriveStatus
from stepper_sim.harness import CONFIG, Proc, executable, free_port, wait_for
import yaml

HELPER = str(pathlib.Path(__file__).resolve().parent / 'bench_cp_relays.py')
CLK_TCK = os.sysconf('SC_CLK_TCK')
FLOOR_TOPIC = '/bench_cp_floor/position_command'
MARGIN_S = 0.001                 # the goal's "+ 1 ms"
RATE_GOAL = 0.60
CPU_GOAL = 1.3
POLL_RATE_CPU_HZ = 50.0
DRIVES_CPU = 8
# The figures measured on the node before the bus owner (4a9d1a6, multi-threaded executor).
BEFORE = {
    'latency': {'xplus_mt': 'p99 23 ms', 'vector_step': 'p99 13-22 ms',
                'rd4': 'p99 41-49 ms (19200)', 'xmind_k': 'p99 132-233 ms (9600)'},
    'floor': 'p99 3-12 ms single-threaded, 12-120 ms with 4 executor threads',
    'rate': {'xplus_mt': '0.24-0.28 of bare'},
    'cpu': {'xplus_mt': '8 nodes: 26-28 % of a core vs one process polling 8 unit ids 14-17 %'},
}


def machine() -> str:
    return f'{os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}'


def pct(values: list[float], q: float) -> float:
    """Nearest-rank percentile (q in 0..1) of a non-empty list."""
    s = sorted(values)
    return s[min(len(s) - 1, max(0, int(round(q * len(s) + 0.5)) - 1))]


def ms(x: float | None) -> str:
    return 'n/a' if x is None else f'{1000 * x:.2f}'


def cpu_s(pid: int) -> float:
    fields = pathlib.Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK      # utime + stime


class Helper:
    """A bench_cp_relays.py process: its first line (`ready`/`port N`) is waited for, every
    further line goes to on_line in a reader thread."""

    def __init__(self, args: list[str], log_dir: pathlib.Path, name: str,
                 on_line: Callable[[str], None] | None = None, first_lines: int = 1,
                 timeout_s: float = 20.0):
        self.name = name
        self.log = open(log_dir / f'{name}.log', 'wb')
        self.proc = subprocess.Popen([sys.executable, HELPER, *args], stdout=subprocess.PIPE,
                                     stderr=self.log, text=True, start_new_session=True)
        self.on_line = on_line or (lambda line: None)
        self._first: queue.Queue[str] = queue.Queue()
        self._n_first = first_lines
        threading.Thread(target=self._read, daemon=True).start()
        self.head = []
        for _ in range(first_lines):
            try:
                self.head.append(self._first.get(timeout=timeout_s))
            except queue.Empty:
                self.stop()
                raise RuntimeError(f'{name} did not start within {timeout_s} s (log '
                                   f'{self.log.name})') from None

    @property
    def pid(self) -> int:
        return self.proc.pid

    def _read(self) -> None:
        for i, line in enumerate(self.proc.stdout):
            if i < self._n_first:
                self._first.put(line.strip())
            else:
                self.on_line(line)

    def stop(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGINT)
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(5)
        self.log.close()


# ------------------------------------------------------------------------------ wire records
@dataclasses.dataclass
class Req:
    """One request (or CAN frame) seen by a probe."""
    t: float
    unit: int = 0
    fc: int | str = 0          # Modbus function code, X-MIND K code, CAN: COB-ID
    address: int = 0
    count: int = 0
    data: bytes = b''
    conn: int = 0
    done_t: float | None = None    # last reply byte forwarded (Q/A probes)


class Wire:
    def __init__(self, parse: Callable[[str], Req | None]):
        self.parse = parse
        self.reqs: list[Req] = []
        self.cv = threading.Condition()
        self._last_by_conn: dict[int, Req] = {}

    def on_line(self, line: str) -> None:
        parts = line.split()
        if not parts:
            return
        if parts[0] == 'A':             # A <t> <conn>: reply bytes went back to the node
            with self.cv:
                last = self._last_by_conn.get(int(parts[2]))
                if last is not None:
                    last.done_t = float(parts[1])
            return
        req = self.parse(line)
        if req is None:
            return
        with self.cv:
            self.reqs.append(req)
            self._last_by_conn[req.conn] = req
            self.cv.notify_all()

    def wait(self, since: float, pred: Callable[[Req], bool], timeout_s: float) -> Req | None:
        deadline = time.monotonic() + timeout_s
        i = 0
        with self.cv:
            while True:
                while i < len(self.reqs):
                    r = self.reqs[i]
                    i += 1
                    if r.t >= since and pred(r):
                        return r
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self.cv.wait(left)

    def between(self, t0: float, t1: float) -> list[Req]:
        with self.cv:
            return [r for r in self.reqs if t0 <= r.t <= t1]


def parse_tcp(line: str) -> Req | None:
    p = line.split()        # Q t conn unit fc address count
    if p[0] != 'Q':
        return None
    return Req(float(p[1]), int(p[3]), int(p[4]), int(p[5]), int(p[6]), conn=int(p[2]))


def parse_rtu(line: str) -> Req | None:
    p = line.split()        # Q t hex
    if p[0] != 'Q':
        return None
    b = bytes.fromhex(p[2])
    if len(b) < 6:
        return Req(float(p[1]), data=b)
    return Req(float(p[1]), b[0], b[1], int.from_bytes(b[2:4], 'big'),
               int.from_bytes(b[4:6], 'big'), data=b)


def parse_ascii(line: str) -> Req | None:
    p = line.split()
    if p[0] != 'Q':
        return None
    text = bytes.fromhex(p[2]).decode('ascii', 'replace').strip('\r')
    try:
        unit = int(text[:2])
    except ValueError:
        unit = -1
    return Req(float(p[1]), unit, text[2:4], data=text.encode())


def parse_can(line: str) -> Req | None:
    p = line.split()        # F t cob hex
    if p[0] != 'F':
        return None
    cob = int(p[2], 16)
    return Req(float(p[1]), cob & 0x7F, cob, data=bytes.fromhex(p[3]) if len(p) > 3 else b'')


# ----------------------------------------------------------------------------------- vendors
@dataclasses.dataclass
class Vendor:
    key: str
    title: str
    node: str                     # executable = node name
    sim: str
    line: str                     # what the line is, for the report
    targets: tuple[float, float]
    gap_s: float                  # pause after a command's target frame (its tail ends)
    is_first: Callable[[Req], bool]
    is_target: Callable[[Req], bool]
    first_text: str
    target_text: str
    commands: int
    # silence a transaction leaves on the line before the next may start: Modbus RTU t3.5
    # (RD4 manual §7.3.1: 3.5 characters of 11 bits), the X-MIND K's 4 ms margin (§3)
    silence_s: float = 0.0


VENDORS = {
    'xplus_mt': Vendor(
        'xplus_mt', 'X-PLUS MT', 'xplus_mt_node', 'xplus_mt_sim',
        'Modbus TCP on 127.0.0.1 through a relay (non-strict sim: one FC03 per poll)',
        (0.5, -0.5), 0.06,
        is_first=lambda r: r.unit == 1 and (r.fc, r.address, r.count) != (3, 1001, 21),
        is_target=lambda r: r.unit == 1 and r.fc == 16 and r.address == 1042,
        first_text='first request to unit 1 that is not a poll',
        target_text='FC16 Target Position 1042',
        commands=200),
    'rd4': Vendor(
        'rd4', 'Lika RD4', 'rd4_node', 'rd4_sim',
        'Modbus RTU, 19200 8N2 pty with line timing, through a pty relay',
        (0.5, -0.5), 0.12,
        is_first=lambda r: r.unit == 1 and r.fc == 4 and r.address == 0 and r.count == 2,
        is_target=lambda r: r.unit == 1 and r.fc == 16 and r.address == 0x2B,
        first_text='FC04 0x00 x2 (alarms check)', target_text='FC16 Target position 0x2B',
        commands=150, silence_s=3.5 * 11 / 19200),
    'xmind_k': Vendor(
        'xmind_k', 'X-MIND K', 'xmind_k_node', 'xmind_k_sim',
        'ASCII, 9600 8N1 pty with line timing (§3), through a pty relay',
        (0.1, -0.1), 0.4,
        is_first=lambda r: r.unit == 1 and r.fc != 'QA',
        is_target=lambda r: r.unit == 1 and r.fc == 'WN',
        first_text='first string to 01 that is not QA', target_text='WN (move instruction)',
        commands=100, silence_s=0.004),       # §3: 4 ms after an answer before the next string
    'vector_step': Vendor(
        'vector_step', 'Vector Step', 'vector_step_node', 'vector_step_sim',
        'CANopen through the socketcand broker (frames seen by another broker client)',
        (0.5, -0.5), 0.06,
        is_first=lambda r: r.unit == 1 and (r.fc & ~0x7F) in (0x200, 0x300, 0x400, 0x500, 0x600),
        is_target=lambda r: r.fc == 0x301 and len(r.data) >= 1 and bool(r.data[0] & 0x10),
        first_text='first RxPDO/SDO request to node 1', target_text='RxPDO2 0x301, CW bit 4',
        commands=200),
}


def load_params(name: str, section: str) -> dict[str, Any]:
    return yaml.safe_load((CONFIG / name).read_text())[section]['ros__parameters']


class _NoAliases(yaml.SafeDumper):
    def ignore_aliases(self, data):      # ROS 2 params files refuse YAML aliases
        return True


def write_params(path: pathlib.Path, section: str, params: dict[str, Any]) -> pathlib.Path:
    path.write_text(yaml.dump({section: {'ros__parameters': params}}, Dumper=_NoAliases))
    return path


def running(proc: Proc, cond: Callable[[], Any]) -> Callable[[], Any]:
    """cond for wait_for that fails at once, with the process's last lines, when it ended."""
    def check():
        if proc.proc.poll() is not None:
            raise RuntimeError(f'{proc.name} exited with {proc.proc.returncode}: '
                               + proc.output()[-800:].strip())
        return cond()
    return check


class Setup:
    """Simulator, probe and node of one vendor in one run; stops all of them on close()."""

    def __init__(self, v: Vendor, log_dir: pathlib.Path, tag: str):
        self.v, self.log_dir, self.tag = v, log_dir, tag
        self.procs: list[Any] = []
        self.node: Proc | None = None

    def add(self, p):
        self.procs.append(p)
        return p

    def close(self) -> None:
        for p in reversed(self.procs):
            try:
                p.stop()
            except AssertionError:
                p.kill()
            except Exception:  # noqa: BLE001 - best effort: every process gets its signal
                pass

    def proc(self, args: list[str], name: str) -> Proc:
        return self.add(Proc(args, self.log_dir, f'{self.tag}_{name}'))

    def start_node(self, node_params: pathlib.Path, extra: list[str] = ()) -> Proc:
        self.node = self.proc([executable('stepper_drivers', self.v.node), '--ros-args',
                               '--params-file', str(node_params), *extra], 'node')
        return self.node


def start_sim_line(s: Setup, wire: Wire | None, link: Wire | None = None) -> list[str]:
    """The simulator (and the probe when wire is given; Vector Step: `link`, a relay on the
    node's own connection to the broker as well); returns the node's -p overrides."""
    v, d = s.v, s.log_dir
    if v.key == 'xplus_mt':
        port = free_port()
        sim = s.proc([executable('stepper_sim', v.sim), '--ros-args', '--params-file',
                      str(CONFIG / 'xplus_mt_sim.yaml'), '-p', f'port:={port}',
                      '-p', 'strict:=false'], 'sim')
        sim.wait_line('ready', 30)
        if wire is None:
            return ['-p', f'port:={port}']
        relay = s.add(Helper(['tcp', str(port)], d, f'{s.tag}_relay', wire.on_line))
        return ['-p', f'port:={relay.head[0].split()[1]}']
    if v.key in ('rd4', 'xmind_k'):
        sim_path, node_path = str(d / f'{s.tag}_sim.pty'), str(d / f'{s.tag}_node.pty')
        sim_cfg = 'rd4_sim.yaml' if v.key == 'rd4' else 'xmind_k_sim.yaml'
        sim = s.proc([executable('stepper_sim', v.sim), '--ros-args', '--params-file',
                      str(CONFIG / sim_cfg), '-p', f'port:={sim_path}',
                      '-p', 'line_timing:=true'], 'sim')
        sim.wait_line('ready', 30)
        if wire is None:
            return ['-p', f'port:={sim_path}']
        baud = load_params(f'{v.key}.yaml', v.node)['baudrate']
        s.add(Helper(['pty', node_path, sim_path, str(baud)], d, f'{s.tag}_relay',
                     wire.on_line))
        return ['-p', f'port:={node_path}']
    # vector_step: broker, the probe on it (from the start: it sees the SDOs of the connect)
    port = free_port()
    broker = s.proc([executable('stepper_sim', 'socketcand_broker'), '--port', str(port)],
                    'broker')
    broker.wait_line('listening', 10)
    if wire is not None:
        s.add(Helper(['can', str(port)], d, f'{s.tag}_sniffer', wire.on_line))
    sim = s.proc([executable('stepper_sim', v.sim), '--ros-args', '--params-file',
                  str(CONFIG / 'vector_step_sim.yaml'), '-p', f'can.port:={port}'], 'sim')
    sim.wait_line('ready', 30)
    if link is not None:
        relay = s.add(Helper(['canlink', str(port)], d, f'{s.tag}_link', link.on_line))
        return ['-p', f'can.port:={relay.head[0].split()[1]}']
    return ['-p', f'can.port:={port}']


def kind(r: Req) -> str:
    if isinstance(r.fc, str):
        return r.fc
    if r.fc in (3, 4, 16):
        return f'FC{r.fc:02d} {r.address} x{r.count}'
    return f'FC{r.fc:02d} {r.address}' if r.fc < 0x80 else f'0x{r.fc:03X}'


def transaction_times(v: Vendor, wire: Wire, busy: list[tuple[float, float]]
                      ) -> dict[str, list[float]]:
    """Durations by kind of the transactions the node made outside the `busy` windows (the
    commands), as the probe saw them: request's first byte -> reply forwarded; CANopen: SDO
    request 0x600+n -> answer 0x580+n."""
    with wire.cv:
        reqs = list(wire.reqs)
    out: dict[str, list[float]] = {}

    def idle(t: float) -> bool:
        return not any(a <= t <= b for a, b in busy)
    if v.key != 'vector_step':
        for r in reqs:
            if r.done_t is not None and r.done_t > r.t and idle(r.t):
                out.setdefault(kind(r), []).append(r.done_t - r.t)
        return out
    pending: dict[int, float] = {}
    for r in reqs:
        if 0x601 <= r.fc <= 0x67F:
            pending[r.fc & 0x7F] = r.t
        elif 0x581 <= r.fc <= 0x5FF and (r.fc & 0x7F) in pending:
            out.setdefault('SDO', []).append(r.t - pending.pop(r.fc & 0x7F))
    return out


def in_flight(txn: dict[str, list[float]]) -> tuple[str, float | None]:
    """The longest transaction the node's polling puts on the line: the kind with the
    longest median among the kinds seen at least 5 times."""
    kinds = [(statistics.median(d), k) for k, d in txn.items() if len(d) >= 5]
    if not kinds:
        return '', None
    t, k = max(kinds)
    return k, t


# ----------------------------------------------------------------------------- part: latency
def bench_latency(v: Vendor, ros: RosClient, log_dir: pathlib.Path, n: int,
                  owner_priority: int | None = None, can_link: bool = False) -> dict:
    parse = {'xplus_mt': parse_tcp, 'rd4': parse_rtu, 'xmind_k': parse_ascii,
             'vector_step': parse_can}[v.key]
    wire = Wire(parse)
    link = Wire(parse_can) if can_link and v.key == 'vector_step' else None
    floor_t: dict[int, float] = {}

    def on_floor(line: str) -> None:
        p = line.split()
        if p and p[0] == 'M':
            floor_t[int(p[2])] = float(p[1])
    s = Setup(v, log_dir, f'{v.key}_lat')
    node_cfg = load_params(f'{v.key}.yaml', v.node)
    rate_hz = float(node_cfg['publish_rate_hz'])
    ns = f'/{v.node}/axis1'
    try:
        overrides = start_sim_line(s, wire, link)
        s.add(Helper(['floor', FLOOR_TOPIC], log_dir, f'{v.key}_floor', on_floor))
        priority = ([] if owner_priority is None
                    else ['-p', f'owner_thread_priority:={owner_priority}'])
        s.start_node(CONFIG / f'{v.key}.yaml', overrides + priority)
        ros.subscribe(DriveStatus, f'{ns}/status')
        wait_for(running(s.node, lambda: getattr(ros.latest.get(f'{ns}/status'), 'connected',
                                                 False)), 60, f'{v.title} axis1 connected')
        r = ros.call(SetBool, f'{ns}/enable', SetBool.Request(data=True), 20)
        if not r.success:
            raise RuntimeError(f'enable refused: {r.message}')
        ros.wait_msg(f'{ns}/status', lambda m: m.enabled, 10, f'{v.title} axis1 enabled')
        topic = f'{ns}/position_command'
        # warm-up: publishers matched, the first set point (settling after enable) done
        ros.publish(Float64, FLOOR_TOPIC, Float64(data=-1.0))
        for target in (v.targets[0], v.targets[1]):    # the loop starts at targets[0]
            t = time.monotonic()
            ros.publish(Float64, topic, Float64(data=target))
            if wire.wait(t, v.is_target, 5.0) is None:
                raise RuntimeError(f'no {v.target_text} on the wire within 5 s of a '
                                   f'position_command (log dir {log_dir})')
            time.sleep(max(v.gap_s, 0.3))
        pubs, floor_pub = [], {}
        missed = 0
        t_start = time.monotonic()
        for i in range(n):
            target = v.targets[i % 2]
            t_pub = time.monotonic()
            ros.publish(Float64, topic, Float64(data=target))
            hit = wire.wait(t_pub, v.is_target, 3.0)
            if hit is None:
                missed += 1
            # the floor probe between two commands, at a random phase of the poll cycle
            time.sleep(v.gap_s / 2 + random.uniform(0, 0.5 / rate_hz))
            floor_pub[i] = time.monotonic()
            pubs.append((t_pub, hit, floor_pub[i]))
            ros.publish(Float64, FLOOR_TOPIC, Float64(data=float(i)))
            time.sleep(v.gap_s / 2 + random.uniform(0, 0.5 / rate_hz))
        duration = time.monotonic() - t_start
        time.sleep(0.3)
        ros.call(SetBool, f'{ns}/enable', SetBool.Request(data=False), 20)
        load = os.getloadavg()[0]
    finally:
        s.close()
        with wire.cv:
            (log_dir / f'{v.key}_wire.txt').write_text(''.join(
                f'{r.t:.6f} {r.unit} {r.fc} {r.address} {r.count} {r.data.hex()} '
                f'{"" if r.done_t is None else f"{r.done_t - r.t:.6f}"}\n' for r in wire.reqs))
    target_lat, first_lat, preamble, dump = [], [], [], []
    for t_pub, hit, _ in pubs:
        if hit is None:
            dump.append(f'{t_pub:.6f} - -\n')
            continue
        target_lat.append(hit.t - t_pub)
        first = next((r for r in wire.between(t_pub, hit.t) if v.is_first(r)), None)
        if first is not None:
            first_lat.append(first.t - t_pub)
            preamble.append(hit.t - first.t)
        dump.append(f'{t_pub:.6f} {hit.t - t_pub:.6f} '
                    f'{"-" if first is None else f"{first.t - t_pub:.6f}"}\n')
    (log_dir / f'{v.key}_commands.txt').write_text(''.join(dump))
    link_first = []          # Vector Step: its first frame is its target frame
    if link is not None:
        with link.cv:
            (log_dir / f'{v.key}_link.txt').write_text(''.join(
                f'{r.t:.6f} {r.fc:03X} {r.data.hex()}\n' for r in link.reqs))
        for t_pub, hit, _ in pubs:
            frame = link.wait(t_pub, v.is_target, 0.0) if hit is not None else None
            if frame is not None and frame.t <= hit.t:
                first = next((r for r in link.between(t_pub, frame.t) if v.is_first(r)), frame)
                link_first.append(first.t - t_pub)
    floor = [floor_t[i] - t for i, t in floor_pub.items() if i in floor_t]
    txn = transaction_times(v, wire, [(t, f) for t, _, f in pubs])
    res = {'vendor': v.key, 'commands': n, 'missed': missed, 'rate_hz': rate_hz,
           'owner_priority': owner_priority,
           'duration_s': duration, 'load': load, 'cores': os.cpu_count(),
           'drives': len(node_cfg['drives']),
           'floor': floor, 'target': target_lat, 'first': first_lat, 'preamble': preamble,
           'txn': txn, 'floor_missed': n - len(floor), 'link_first': link_first}
    report_latency(v, res)
    return res


def stats(xs: list[float]) -> tuple[float | None, float | None]:
    return (statistics.median(xs), pct(xs, 0.99)) if xs else (None, None)


def report_latency(v: Vendor, r: dict) -> None:
    f50, f99 = stats(r['floor'])
    t50, t99 = stats(r['target'])
    c50, c99 = stats(r['first'])
    x_kind, x50 = in_flight(r['txn'])
    pre50 = statistics.median(r['preamble']) if r['preamble'] else None
    print(f'\n== command -> wire, {v.title} [{r["cores"]} cores, load {r["load"]:.2f}]')
    print(f'   {v.line}; node at its configured {r["rate_hz"]:g} Hz with {r["drives"]} drives, '
          f'axis1 enabled; {r["commands"]} position_command ({len(r["target"])} seen on the '
          f'wire) in {r["duration_s"]:.0f} s; bus owner '
          + ("at the node's default (SCHED_FIFO 10 where granted)"
             if r.get('owner_priority') is None else
             f'on SCHED_FIFO {r["owner_priority"]}' if r['owner_priority']
             else 'on the normal scheduler'))
    print('   line transactions outside the commands, at the probe (median ms, n): '
          + ', '.join(f'{k} {ms(statistics.median(d))} ({len(d)})'
                      for k, d in sorted(r['txn'].items(), key=lambda kd: -len(kd[1]))[:6]))
    print(f'   one transaction in flight: the longest of them, {x_kind} {ms(x50)} ms')
    print(f'   middleware floor, rclpy publish -> callback in another process: p50 {ms(f50)} ms,'
          f' p99 {ms(f99)} ms (n={len(r["floor"])})')
    if x50 is not None:
        x50 += v.silence_s
        if v.silence_s:
            print(f'   ... plus the line silence after it: {ms(x50)} ms')
    if c99 is not None and f99 is not None and x50 is not None:
        goal = f99 + x50 + MARGIN_S
        r['goal_first'] = goal
        print(f'   -> first frame of the command ({v.first_text}): p50 {ms(c50)} ms, '
              f'p99 {ms(c99)} ms; goal p99 <= {ms(f99)} + {ms(x50)} + 1 = {ms(goal)} ms: '
              f'{"met" if c99 <= goal else "NOT met"}')
    if t99 is not None and f99 is not None and x50 is not None and pre50 is not None:
        goal = f99 + x50 + pre50 + MARGIN_S
        r['goal_target'] = goal
        print(f'   -> {v.target_text}: p50 {ms(t50)} ms, p99 {ms(t99)} ms; its own transactions '
              f'before it take {ms(pre50)} ms (median); goal p99 <= {ms(goal)} ms: '
              f'{"met" if t99 <= goal else "NOT met"}')
    elif t99 is not None:
        print(f'   -> {v.target_text}: p50 {ms(t50)} ms, p99 {ms(t99)} ms')
    l50, l99 = stats(r.get('link_first', []))
    if l99 is not None and 'goal_first' in r:
        print(f"   -> the same first frame on the node's own link (a relay between the node and "
              f'the broker, as the X-PLUS MT\'s; n={len(r["link_first"])}): p50 {ms(l50)} ms, '
              f'p99 {ms(l99)} ms; goal p99 <= {ms(r["goal_first"])} ms: '
              f'{"met" if l99 <= r["goal_first"] else "NOT met"}. The broker\'s figures above '
              "come after this relay's hop and its own fan-out")
    print(f'   before the bus owner thread: {BEFORE["latency"][v.key]}; floor '
          f'{BEFORE["floor"]}')


# --------------------------------------------------------------------------------- part: rate
def diag_transactions(ros: RosClient, after: float) -> tuple[float, int]:
    """(stamp, link transactions) of the first /diagnostics stamped after `after`
    (time.time())."""
    def link():
        m = ros.latest.get('/diagnostics')
        if m is None:
            return None
        stamp = m.header.stamp.sec + m.header.stamp.nanosec * 1e-9
        if stamp < after:
            return None
        for st in m.status:
            if st.name.endswith('link') or ': link' in st.name:
                kv = {x.key: x.value for x in st.values}
                if 'transactions' in kv:
                    return stamp, int(kv['transactions'])
        return None
    return wait_for(link, 10.0, 'a /diagnostics link status')


def bare_rate(v: Vendor, target: str, seconds: float) -> float:
    """Transactions/s of a bare library loop on the simulator (`target`: port or pty path)."""
    n, t0 = 0, time.monotonic()
    if v.key == 'xplus_mt':
        from pymodbus.client import ModbusTcpClient
        c = ModbusTcpClient('127.0.0.1', port=int(target), timeout=1)
        assert c.connect()
        while time.monotonic() - t0 < seconds:
            r = c.read_holding_registers(1001, count=21, device_id=1)
            assert not r.isError(), r
            n += 1
        c.close()
    elif v.key == 'rd4':
        import asyncio

        from pymodbus.client import AsyncModbusSerialClient

        async def run() -> int:
            c = AsyncModbusSerialClient(target, baudrate=19200, parity='N', stopbits=2,
                                        timeout=0.2, retries=0)
            assert await c.connect(), 'pymodbus could not open the pty'
            k = 0
            try:
                while time.monotonic() - t0 < seconds:
                    r = await c.read_input_registers(0, count=8, device_id=1)
                    assert not r.isError(), r
                    k += 1
            finally:
                c.close()
            return k
        t0 = time.monotonic()
        n = asyncio.run(run())
    else:
        import serial
        with serial.Serial(target, 9600, timeout=0.2) as port:
            while time.monotonic() - t0 < seconds:
                port.write(b'01QA\r')
                answer = port.read_until(b'\r')
                assert answer.startswith(b'01QA'), answer
                n += 1
    return n / (time.monotonic() - t0)


def xplus_params(drives: list[tuple[int, int]], rate_hz: float) -> dict[str, Any]:
    """X-PLUS MT node parameters for drives given as (port, unit id); drives on another port
    than the first get their own drives.<name>.port (a link and an owner thread of their own)."""
    base = load_params('xplus_mt.yaml', 'xplus_mt_node')
    params = {k: val for k, val in base.items() if not k.startswith('drives')}
    names = [f'axis{i}' for i in range(1, len(drives) + 1)]
    params.update({'publish_rate_hz': rate_hz, 'diagnostics_rate_hz': 2.0, 'drives': names,
                   'port': drives[0][0]})
    for i, (name, (port, unit)) in enumerate(zip(names, drives)):
        block = dict(base['drives.axis2'], joint_name=f'bench_joint{i + 1}', unit_id=unit)
        if port != drives[0][0]:
            block['port'] = port
        params[f'drives.{name}'] = block
    return params


def node_tps(s: Setup, ros: RosClient, params: pathlib.Path, extra: list[str],
             drives: list[str], seconds: float) -> float:
    """Transactions/s of a node, from its own link counter in /diagnostics."""
    ros.latest.pop('/diagnostics', None)
    ros.subscribe(DiagnosticArray, '/diagnostics')
    node = s.start_node(params, extra)
    wait_drives(ros, node, s.v.node, drives, 60)
    time.sleep(1.0)                                   # warm-up: first cycles, discovery
    a = diag_transactions(ros, time.time())
    time.sleep(seconds)
    b = diag_transactions(ros, a[0] + seconds)
    node.stop()
    s.procs.remove(node)
    return (b[1] - a[1]) / (b[0] - a[0])


def bench_rate(v: Vendor, ros: RosClient, log_dir: pathlib.Path, seconds: float) -> dict:
    s = Setup(v, log_dir, f'{v.key}_rate')
    flat = ['-p', 'publish_rate_hz:=1000.0', '-p', 'diagnostics_rate_hz:=4.0']
    nodes: dict[int, float] = {}
    try:
        if v.key == 'xplus_mt':
            # 4 unit ids on one port: 4 drives per cycle lift the 1000 Hz ceiling of
            # publish_rate_hz above what the line can do
            sims = s.add(Helper(['xsims', '1', '4'], log_dir, f'{s.tag}_sims', first_lines=2))
            port = int(sims.head[0].split()[1])
            target = str(port)
            bares = [bare_rate(v, target, seconds)]
            for n in (1, 4):
                params = write_params(log_dir / f'{s.tag}_{n}.yaml', v.node, xplus_params(
                    [(port, u) for u in range(1, n + 1)], 1000.0))
                nodes[n] = node_tps(s, ros, params, [], [f'axis{i}' for i in range(1, n + 1)],
                                    seconds)
        else:
            overrides = start_sim_line(s, None)
            target = overrides[1].split(':=', 1)[1]
            bares = [bare_rate(v, target, seconds)]
            nodes[1] = node_tps(s, ros, CONFIG / f'{v.key}.yaml',
                                overrides + flat + ['-p', 'drives:=[axis1]'], ['axis1'], seconds)
        bares.append(bare_rate(v, target, seconds))      # before and after: the load drifts
        bare = statistics.mean(bares)
        load = os.getloadavg()[0]
    finally:
        s.close()
    best = nodes[max(nodes)]
    res = {'vendor': v.key, 'bare': bare, 'bares': bares, 'node': nodes, 'ratio': best / bare,
           'load': load, 'cores': os.cpu_count()}
    print(f'\n== poll rate flat out, {v.title} [{res["cores"]} cores, load {load:.2f}]')
    what = {'xplus_mt': 'pymodbus ModbusTcpClient FC03 1001 x21',
            'rd4': 'pymodbus AsyncModbusSerialClient FC04 0x00 x8 (line timing 19200)',
            'xmind_k': 'pyserial 01QA (line timing 9600)'}[v.key]
    print(f'   bare loop ({what}): {bare:8.1f} transactions/s (mean of {bares[0]:.1f} before '
          f'and {bares[1]:.1f} after the node)')
    for n, tps in nodes.items():
        print(f'   node, {n} drive{"s" if n > 1 else ""} on the line, publish_rate_hz 1000: '
              f'{tps:8.1f} transactions/s = {tps / bare:.1%} of bare, {tps / n:.0f} cycles/s '
              '(its own counter, /diagnostics)')
    met = res['ratio'] >= RATE_GOAL
    print(f'   goal >= {RATE_GOAL:.0%} of bare: {"met" if met else "NOT met"}'
          + (f'; before the bus owner (1 drive): {BEFORE["rate"][v.key]}'
             if v.key in BEFORE['rate'] else ''))
    return res


# ---------------------------------------------------------------------------------- part: cpu
def cpu_window(pids: list[int], window_s: float) -> list[float]:
    c0, t0 = [cpu_s(p) for p in pids], time.monotonic()
    time.sleep(window_s)
    c1, t1 = [cpu_s(p) for p in pids], time.monotonic()
    return [(b - a) / (t1 - t0) for a, b in zip(c0, c1)]


def thread_cpu_s(pid: int) -> dict[str, float]:
    """CPU seconds of a process by kind of thread: the main thread (rclpy's executor), the
    other Python threads (bus owners, python-can/pymodbus receivers) and Fast DDS's own
    (named dds.*)."""
    out: dict[str, float] = {}
    for task in pathlib.Path(f'/proc/{pid}/task').iterdir():
        try:
            fields = (task / 'stat').read_text().rsplit(')', 1)[1].split()
            comm = (task / 'comm').read_text().strip()
        except OSError:             # the thread ended meanwhile
            continue
        kind = ('main thread' if task.name == str(pid) else
                'DDS threads' if comm.startswith('dds.') else 'other Python threads')
        out[kind] = out.get(kind, 0.0) + (int(fields[11]) + int(fields[12])) / CLK_TCK
    return out


def wait_drives(ros: RosClient, proc: Proc, node: str, drives: list[str],
                timeout_s: float) -> None:
    def ok():
        m = ros.latest.get('/diagnostics')
        if m is None:
            return False
        seen = {st.name.rsplit(': ', 1)[-1]: st.message for st in m.status
                if st.name.startswith(f'{node}: ')}
        return all(d in seen and seen[d] != 'DISCONNECTED' and not seen[d].startswith('not ')
                   for d in drives)
    wait_for(running(proc, ok), timeout_s,
             f'{len(drives)} drives of {node} connected (diagnostics)')


def cpu_case(case: str, ros: RosClient, log_dir: pathlib.Path, window_s: float,
             rounds: int = 1) -> dict:
    """case: 'xplus_ports' (8 sims, 8 ports), 'xplus_units' (8 unit ids, one port),
    'vector_step' (8 drives on one CAN bus)."""
    drives = [f'axis{i}' for i in range(1, DRIVES_CPU + 1)]
    v = VENDORS['vector_step' if case == 'vector_step' else 'xplus_mt']
    s = Setup(v, log_dir, f'cpu_{case}')
    try:
        if case.startswith('xplus'):
            ports_n, units_n = (DRIVES_CPU, 1) if case == 'xplus_ports' else (1, DRIVES_CPU)
            sims = s.add(Helper(['xsims', str(ports_n), str(units_n)], log_dir,
                                f'cpu_{case}_sims', first_lines=ports_n + 1, timeout_s=60))
            ports = [int(h.split()[1]) for h in sims.head[:ports_n]]
            node_params = xplus_params([(p, 1) for p in ports] if case == 'xplus_ports' else
                                       [(ports[0], u) for u in range(1, DRIVES_CPU + 1)],
                                       POLL_RATE_CPU_HZ)
            loop_args = ([str(POLL_RATE_CPU_HZ), '1', *map(str, ports)]
                         if case == 'xplus_ports' else
                         [str(POLL_RATE_CPU_HZ), str(DRIVES_CPU), str(ports[0])])
            refs = [('bare', ['bare-modbus', *loop_args]),
                    ('bare+ROS', ['bare-modbus-ros', *loop_args]),
                    ('driver', ['driver-xplus', *loop_args])]
            if case == 'xplus_ports':
                refs.append(('bare/link', ['bare-modbus-threads', *loop_args]))
            sim_pid = sims.pid
        else:
            port = free_port()
            broker = s.proc([executable('stepper_sim', 'socketcand_broker'), '--port',
                             str(port)], 'broker')
            broker.wait_line('listening', 10)
            sim_params = load_params('vector_step_sim.yaml', 'vector_step_sim')
            sim_params = {k: val for k, val in sim_params.items() if not k.startswith('drives')}
            sim_params['can'] = dict(sim_params['can'], port=port)
            sim_params['drives'] = drives
            for i, d in enumerate(drives):
                sim_params[f'drives.{d}'] = {'node_id': i + 1}
            sim = s.proc([executable('stepper_sim', 'vector_step_sim'), '--ros-args',
                          '--params-file', str(write_params(
                              log_dir / f'cpu_{case}_sim.yaml', 'vector_step_sim',
                              sim_params))], 'sim')
            sim.wait_line('ready', 30)
            base = load_params('vector_step.yaml', v.node)
            node_params = {k: val for k, val in base.items() if not k.startswith('drives')}
            node_params.update({'publish_rate_hz': POLL_RATE_CPU_HZ, 'drives': drives,
                                'diagnostics_rate_hz': 2.0, 'can': dict(base['can'], port=port)})
            for i, d in enumerate(drives):
                node_params[f'drives.{d}'] = dict(base['drives.axis2'], node_id=i + 1,
                                                  joint_name=f'bench_joint{i + 1}')
            loop_args = [str(POLL_RATE_CPU_HZ), str(port),
                         ','.join(str(i) for i in range(1, DRIVES_CPU + 1))]
            refs = [('bare', ['bare-canopen', *loop_args]),
                    ('bare+ROS', ['bare-canopen-ros', *loop_args])]
            sim_pid = sim.pid
        params_file = write_params(log_dir / f'cpu_{case}_node.yaml', v.node, node_params)
        ros.subscribe(DiagnosticArray, '/diagnostics')
        node_rounds: list[tuple[float, float]] = []            # (node, simulator) per round
        ref_rounds: dict[str, list[tuple[float, float]]] = {}
        split_rounds: list[dict[str, float]] = []
        failed_refs: set[str] = set()
        for r in range(rounds):
            suffix = f'_{r + 1}' if rounds > 1 else ''
            ros.latest.pop('/diagnostics', None)
            node = s.start_node(params_file)
            wait_drives(ros, node, v.node, drives, 90)
            time.sleep(2.0)                                   # past the connects' SDOs/writes
            threads0 = thread_cpu_s(node.pid)
            node_rounds.append(tuple(cpu_window([node.pid, sim_pid], window_s)))
            split_rounds.append({k: (val - threads0.get(k, 0.0)) / window_s
                                 for k, val in thread_cpu_s(node.pid).items()})
            node.stop()
            s.procs.remove(node)
            for name, helper_args in refs:
                if name in failed_refs:
                    continue
                try:
                    ref = s.add(Helper(helper_args, log_dir,
                                       f'cpu_{case}_{helper_args[0]}{suffix}', timeout_s=60))
                except RuntimeError as exc:
                    if name == 'bare':
                        raise
                    print(f'   ({name} reference loop failed: {exc})')
                    failed_refs.add(name)
                    continue
                time.sleep(1.0)
                ref_rounds.setdefault(name, []).append(
                    tuple(cpu_window([ref.pid, sim_pid], window_s)))
                if ref.proc.poll() is not None:
                    raise RuntimeError(f'the {name} loop ended during its window (log '
                                       f'{ref.log.name})')
                ref.stop()
                s.procs.remove(ref)
        load = os.getloadavg()[0]
    finally:
        s.close()

    def mean(values: list[float]) -> float:
        return sum(values) / len(values)
    node_cpu, sim_cpu = mean([n for n, _ in node_rounds]), mean([m for _, m in node_rounds])
    ref_cpu = {name: (mean([c for c, _ in rs]), mean([m for _, m in rs]))
               for name, rs in ref_rounds.items() if len(rs) == rounds}
    split = {k: mean([sp.get(k, 0.0) for sp in split_rounds]) for k in split_rounds[0]}
    bare_cpu = ref_cpu['bare'][0]
    res = {'case': case, 'node': node_cpu, 'sim_node': sim_cpu, 'refs': ref_cpu, 'split': split,
           'ratio': node_cpu / bare_cpu, 'load': load, 'cores': os.cpu_count(),
           'window_s': window_s, 'rounds': {'node': node_rounds, **ref_rounds}}
    title = {'xplus_ports': 'X-PLUS MT, 8 drives on 8 ports (8 simulators, one process)',
             'xplus_units': 'X-PLUS MT, 8 unit ids on one port',
             'vector_step': 'Vector Step, 8 drives on one CAN bus (TxPDO2 every 100 ms)'}[case]
    lib = 'pymodbus FC03 1001 x21' if case != 'vector_step' else \
        "canopen: the node's TxPDO set, SYNC and heartbeat; cached values"
    what = {'bare': f'bare loop ({lib} per drive per period)',
            'bare+ROS': 'the same + rclpy publishing what the node does when nothing '
                        'changes, the cheapest way (JointState per period, DriveStatus 1 Hz, '
                        '/diagnostics 2 Hz): the floor of an rclpy node',
            'driver': "the project's XplusMtDrive.read_state() loop, no ROS",
            'bare/link': 'the bare loop with a thread per link, as the node has'}

    def each(values: list[float], fmt: str) -> str:
        return f' (rounds {" ".join(format(x, fmt) for x in values)})' if rounds > 1 else ''
    print(f'\n== CPU at {POLL_RATE_CPU_HZ:g} Hz, {title} [{res["cores"]} cores, load '
          f'{load:.2f}; {window_s:g} s windows, {rounds} round(s) alternating; % of one core, '
          'means of the rounds]')
    print(f'   node:      {node_cpu:6.1%}{each([n for n, _ in node_rounds], ".1%")}   by '
          'thread: ' + ', '.join(f'{k} {val:.1%}' for k, val in sorted(split.items()))
          + f' (simulator meanwhile {sim_cpu:.1%})')
    for name, (cpu, sim) in ref_cpu.items():
        per = [n / c for (n, _), (c, _) in zip(node_rounds, ref_rounds[name])]
        print(f'   {name + ":":10} {cpu:6.1%}{each([c for c, _ in ref_rounds[name]], ".1%")}   '
              f'node/this {node_cpu / cpu:4.2f}{each(per, ".2f")}; {what[name]} '
              f'(simulator {sim:.1%})')
    goal_ref = 'bare+ROS' if 'bare+ROS' in ref_cpu else 'bare'
    if goal_ref == 'bare+ROS':
        res['floor_ratio'] = ref_cpu['bare+ROS'][0] / bare_cpu
        print(f'   bare+ROS / bare loop {res["floor_ratio"]:.2f}: what publishing the interface '
              'adds to the bare loop, before any driver or bus owner')
    res['goal_ratio'] = node_cpu / ref_cpu[goal_ref][0]
    print(f'   ratio node / {"floor" if goal_ref == "bare+ROS" else "bare loop"} '
          f'{res["goal_ratio"]:.2f}; goal <= {CPU_GOAL:g}: '
          f'{"met" if res["goal_ratio"] <= CPU_GOAL else "NOT met"}'
          + (f'; before the bus owner: {BEFORE["cpu"]["xplus_mt"]}' if case != 'vector_step'
             else ''))
    return res


# ----------------------------------------------------------------------------------------- main
def reserve_domain() -> socket.socket | None:
    """A private ROS_DOMAIN_ID for this run (test/conftest.py's scheme: a bound port per
    domain), so nodes and tests of other runs on this machine never see ours."""
    if os.environ.get('ROS_DOMAIN_ID'):
        return None
    for domain in range(101, 200):
        lock = socket.socket()
        try:
            lock.bind(('127.0.0.1', 23000 + domain))
        except OSError:
            lock.close()
            continue
        os.environ['ROS_DOMAIN_ID'] = str(domain)
        return lock
    return None


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--vendor', nargs='+', choices=list(VENDORS), default=list(VENDORS))
    ap.add_argument('--part', nargs='+', choices=['latency', 'rate', 'cpu'],
                    default=['latency', 'rate', 'cpu'])
    ap.add_argument('--commands', type=int, default=0,
                    help='commands per vendor (default: 200, RD4 150, X-MIND K 100)')
    ap.add_argument('--seconds', type=float, default=5.0, help='rate window [s]')
    ap.add_argument('--window', type=float, default=5.0, help='CPU window [s]')
    ap.add_argument('--rounds', type=int, default=1,
                    help='CPU: the node and each reference loop measured this many times, '
                         'alternating (one run on a shared machine moves by a third)')
    ap.add_argument('--owner-priority', type=int, default=None,
                    help='latency: the node with -p owner_thread_priority:=N (SCHED_FIFO; 0: '
                         "the normal scheduler; default: the node's own, 10)")
    ap.add_argument('--can-link', action='store_true',
                    help="Vector Step latency: a relay on the node's own link to the broker as "
                         "well (the X-PLUS MT's way of timing the frame); the broker's figures "
                         'then include its hop')
    ap.add_argument('--json', type=pathlib.Path, help='write every figure to this file')
    args = ap.parse_args()
    log_dir = pathlib.Path(tempfile.mkdtemp(prefix='bench_cp_'))
    domain_lock = reserve_domain()      # noqa: F841 - held until the end of the run
    print(f'command-path benchmark: {machine()}; workspace {CONFIG.parent}; ROS_DOMAIN_ID '
          f'{os.environ.get("ROS_DOMAIN_ID", "0")}; logs {log_dir}')
    results: dict[str, Any] = {'machine': machine(), 'workspace': str(CONFIG.parent)}
    failed = 0
    ros = RosClient('bench_command_path')
    try:
        jobs: list[tuple[str, str, Callable[[], dict]]] = []
        for part in args.part:
            if part == 'cpu':
                cases = [c for c, vk in (('xplus_ports', 'xplus_mt'), ('xplus_units', 'xplus_mt'),
                                         ('vector_step', 'vector_step')) if vk in args.vendor]
                jobs += [('cpu', c, lambda c=c: cpu_case(c, ros, log_dir, args.window,
                                                         args.rounds))
                         for c in cases]
                continue
            for key in args.vendor:
                v = VENDORS[key]
                if part == 'latency':
                    jobs.append(('latency', key, lambda v=v: bench_latency(
                        v, ros, log_dir, args.commands or v.commands, args.owner_priority,
                        args.can_link)))
                elif key != 'vector_step':
                    jobs.append(('rate', key, lambda v=v: bench_rate(v, ros, log_dir,
                                                                     args.seconds)))
                else:
                    print('\n== poll rate flat out, Vector Step: no poll transactions (read_state '
                          'reads the TxPDO cache); scripts/bench_vector_step.py measures the '
                          'PDO path')
        for part, key, job in jobs:
            try:
                results.setdefault(part, {})[key] = job()
            except Exception as exc:  # noqa: BLE001 - report, go on with the next one
                failed += 1
                print(f'\n== {part} {key}: FAILED: {exc} (logs in {log_dir})', flush=True)
                results.setdefault(part, {})[key] = {'error': str(exc)}
            sys.stdout.flush()
    finally:
        ros.close()
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 1 if failed else 0


if __name__ == '__main__':
    sys.exit(main())
