#!/usr/bin/env python3
"""ros2_control benchmark: a node driven as the topic hardware interface drives it, per vendor.

What is streamed is what `joint_state_topic_hardware_interface/JointStateTopicSystem`
(ros-controls/topic_based_hardware_interfaces 1.1.0, src/joint_state_topic_hardware_interface.cpp,
write()) publishes on its `joint_commands_topic` on every controller_manager update: one
sensor_msgs/JointState, `name` = every joint of its `<ros2_control>` block in URDF order (here
the vendor's joints of config/<vendor>.yaml and one joint of another node, `foreign_joint`),
`position[]` one value per name, `header.stamp` now, QoS depth 1 reliable (rclcpp::QoS(1)). The
node runs as docs/ros2_control.md starts it: in a namespace of its own (`-r __ns:=/<vendor>`,
its params file keyed `/<vendor>/<vendor>_node`), with `-p joint_command_shared:=true`, so the
stream goes to `/<vendor>/joint_command`. Every process is real and separate (stepper_sim.harness):
the simulator with its line timing on (as scripts/bench_trajectory.py starts it: RD4 and X-MIND K
the baud rate's character times, X-PLUS MT 2 ms reply latency, Vector Step the socketcand broker)
and its true positions (`~/<drive>/true_position_steps`) at `--sample-rate` (200 Hz), the node,
and this script as the controller_manager.

Phases, every drive of the node enabled first:
  idle   --idle-s without a message;
  NaN    0.5 s of NaN positions (1.1.0 before a controller writes): nothing may move or be refused;
  hold   --hold-s of the positions /<vendor>/joint_states shows (read with SensorDataQoS, as the
         plugin reads; a JointTrajectoryController holds there when it activates);
  ramp   axis1 and axis2 +1 rad along a quintic over 2 s (the block's other joints held), then
         the end held until both stand there (at most --settle-s).

Figures:
- tracking: each true-position sample (stamped when it arrives here, one DDS hop after the
  simulator read it; samples that came in a burst, after a stall, are left out as
  bench_trajectory.on_time does) against the set point streamed last before that moment: the
  largest distance behind it during the 2 s of the ramp and its 95th percentile, and the lag in
  s (the sample's time minus the time the stream passed its position), max and median over the
  samples between 5 % and 95 % of the distance; whether and when each axis stood at its end
  (within one step). Goal on the X-PLUS MT and the Vector Step: the distance behind at most one
  poll period (1 / publish_rate_hz of config/<vendor>.yaml) of travel at the ramp's top speed
  (1.875 x distance / duration).
- bus use: the node's own transaction counter (DriveStatus.link_transactions; the node runs with
  status_rate_hz 10 so that the counter is seen often) per second, idle, during the hold and
  during the ramp, beside the line's limit: Modbus RTU and the X-MIND K's ASCII computed from the
  baud rate (characters x bits per character / baud + the silences the protocol needs) and a bare
  library loop measured on the same simulator before the node opens the line; Modbus TCP the bare
  round trip on the simulator; CAN the frame times at can.bitrate, and every frame on the bus (a
  socketcand client of the broker) beside the node's count.
- new targets on the wire per second, per phase: a probe on the node's line counts the frames
  that carry one (bench_cp_relays.py between node and simulator: X-PLUS MT FC16 Target Position
  1042 through a Modbus TCP relay, RD4 FC16 Target position 0x2B and X-MIND K WN through a pty
  relay; Vector Step RxPDO2 with the controlword's new set point, seen on the broker). A hold
  should cost none: a target the drive already took is not sent again.
- joint_states per second per phase (what the plugin's state interfaces get), refusals
  (status.commands_refused) per phase, the foreign joint told once in the node's log.

Run: source scripts/env.sh && python scripts/bench_ros2_control.py [--vendor rd4 ...]
     [--rate HZ] [--sample-rate HZ] [--sim-arg NAME:=VALUE] [--node-arg NAME:=VALUE]
     [--json out.json]                                    (about 30 s per vendor)
     --rate 10: the stream of a block with rw_rate="10" (docs/ros2_control.md)
"""

from __future__ import annotations

import argparse
import bisect
import dataclasses
import json
import math
import os
import pathlib
import statistics
import sys
import tempfile
import threading
import time
from typing import Any

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')

from bench_command_path import Helper, machine, parse_ascii, parse_rtu, parse_tcp, reserve_domain
from bench_trajectory import VENDORS as TRAJ_VENDORS
from bench_trajectory import Recorder, enable_all, on_time, quintic, transaction_s
from stepper_drivers.cli.ros_client import RosClient
from stepper_drivers.contract.units import UnitConversion
from stepper_sim.core.line_timing import char_time_s, t35_s
from stepper_sim.harness import CONFIG, Proc, executable, fifo_allowed, free_port, wait_for
import yaml

FOREIGN_JOINT = 'foreign_joint'       # a joint of another node in the same block
RAMP_RAD, RAMP_S = 1.0, 2.0
NAN_S = 0.5
TOP_SPEED_FACTOR = 1.875              # the quintic's peak velocity: 1.875 x distance / duration
FAST = ('xplus_mt', 'vector_step')
STATUS_RATE_HZ = 10.0


@dataclasses.dataclass
class Limit:
    """The line's limit in transactions (or frames) per second, and how it was found."""
    low: float
    high: float
    how: str


# ------------------------------------------------------------------------------ line limits
def line_limit(key: str, params: dict[str, Any], bare_s: float, bare_what: str) -> Limit:
    bare = 1.0 / bare_s if bare_s > 0 else math.nan
    if key == 'rd4':
        baud = int(params['baudrate'])
        bits = 11                      # RD4 §7.3.1: 1 start, 8 data, parity or a 2nd stop, 1 stop
        char, gap = char_time_s(baud, bits), t35_s(baud, bits)
        # request + reply bytes, each frame followed by its t3.5 silence
        poll = (8 + 21) * char + 2 * gap        # FC04 0x00 x8: 8-byte request, 21-byte reply
        write = (8 + 8) * char + 2 * gap        # FC06: 8 bytes each way
        return Limit(1 / poll, 1 / write,
                     f'{baud} baud, {bits}-bit characters ({1000 * char:.3f} ms), t3.5 '
                     f'{1000 * gap:.2f} ms: a state poll FC04 x8 (8 + 21 bytes + 2 t3.5) '
                     f'{1000 * poll:.1f} ms, a register write FC06 (8 + 8 bytes + 2 t3.5) '
                     f'{1000 * write:.1f} ms; bare pymodbus FC04 x8 loop on the simulator '
                     f'{bare:.1f}/s')
    if key == 'xmind_k':
        from stepper_drivers.protocol import xmind_k as xk
        rd = 0.010                     # the factory answer delay RD (the simulator's default)
        # QA and its answer with an 8-digit value: '01QA' + CR, '01QA,+10854000' + CR (§3)
        qa = (5 + 15) * xk.CHAR_TIME_S + xk.TURNAROUND_S + rd + xk.MARGIN_S
        qa0 = (5 + 15) * xk.CHAR_TIME_S + xk.TURNAROUND_S + xk.MARGIN_S
        return Limit(1 / qa, 1 / qa0,
                     f'9600 baud, 10-bit characters ({1000 * xk.CHAR_TIME_S:.3f} ms): a QA of 5 '
                     f'+ 15 characters, {1000 * xk.TURNAROUND_S:.1f} ms turnaround, RD 10 ms '
                     f'(factory) or 0, {1000 * xk.MARGIN_S:.0f} ms margin (§3) = '
                     f'{1000 * qa:.1f} / {1000 * qa0:.1f} ms; a WN waits 12 ms, not 1.5; bare '
                     f'pyserial 01QA loop on the simulator {bare:.1f}/s')
    if key == 'vector_step':
        bitrate = int(params['can']['bitrate'])
        # a base frame of n data bytes: 47 + 8 n bits, up to (34 + 8 n - 1) / 4 stuff bits
        rpdo = 47 + 8 * 6                       # RxPDO2: controlword + target position
        sdo = 47 + 8 * 8
        worst = sdo + (34 + 8 * 8 - 1) // 4
        return Limit(bitrate / worst, bitrate / rpdo,
                     f'{bitrate // 1000} kbit/s: an 8-byte SDO frame {sdo}-{worst} bits, a '
                     f'6-byte RxPDO {rpdo} bits (frames/s; an SDO transaction is 2 frames)')
    return Limit(bare, bare, f'{bare_what}: the simulator with its 2 ms reply latency serves '
                             'one transaction at a time on a connection (a real drive: its own '
                             'reply time; the Ethernet itself is no limit)')


# ---------------------------------------------------------------------------------- the run
class Stream:
    """The plugin's publisher on /<ns>/joint_command: depth 1, reliable; every message sent is
    recorded as (time.monotonic(), positions)."""

    def __init__(self, ros: RosClient, topic: str, names: list[str]):
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState
        self.ros, self.names, self.JointState = ros, names, JointState
        qos = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                         reliability=ReliabilityPolicy.RELIABLE)         # rclcpp::QoS(1)
        self.pub = ros.node.create_publisher(JointState, topic, qos)
        wait_for(lambda: self.pub.get_subscription_count() > 0, 10.0, f'{topic} matched')
        self.sent: list[tuple[float, list[float]]] = []

    def run(self, make, duration_s: float, rate_hz: float, until=None) -> None:
        """Publish make(seconds since start) at rate_hz on an absolute schedule, for
        duration_s or until `until()` is true."""
        t0 = time.monotonic()
        n = 0
        while True:
            now = time.monotonic()
            if now - t0 > duration_s or (until is not None and until()):
                return
            values = [float(v) for v in make(now - t0)]
            msg = self.JointState(name=list(self.names), position=values)
            msg.header.stamp = self.ros.node.get_clock().now().to_msg()
            self.pub.publish(msg)
            self.sent.append((now, values))
            n += 1
            time.sleep(max(0.0, t0 + n / rate_hz - time.monotonic()))


def rate_between(rec: Recorder, t0: float, t1: float) -> tuple[float | None, float, int]:
    """(transactions/s, over how many s, statuses inside t0..t1) from the last status that
    arrived before t0 and the first after t1: a node that publishes nothing while its line is
    full still shows what it did in between."""
    with rec.lock:
        samples = list(rec.samples)
    before = [(t, m) for t, m in samples if t <= t0]
    after = [(t, m) for t, m in samples if t >= t1]
    inside = sum(1 for t, _m in samples if t0 < t < t1)
    if not before or not after:
        return None, math.nan, inside
    (ta, ma), (tb, mb) = before[-1], after[0]
    return (((mb.link_transactions - ma.link_transactions) & 0xFFFFFFFF) / (tb - ta), tb - ta,
            inside)


def refused(rec: Recorder, t: float) -> tuple[int, str]:
    m = rec.last_before(t)
    return (m.commands_refused, m.last_refusal) if m is not None else (0, '')


class SetPoints:
    """Times of the frames that carry a new target, seen by a probe on the node's line:
    X-PLUS MT FC16 Target Position (1042) through a Modbus TCP relay, RD4 FC16 Target position
    (0x2B) and X-MIND K WN through a pty relay (bench_cp_relays.py), Vector Step RxPDO2 with
    the controlword's new set point (Frames)."""

    def __init__(self, is_target):
        self.is_target = is_target
        self.times: list[float] = []
        self.lock = threading.Lock()

    def on_line(self, line: str) -> None:
        if self.is_target(line):
            self.add(float(line.split()[1]))

    def add(self, t: float) -> None:
        with self.lock:
            self.times.append(t)

    def rate(self, t0: float, t1: float) -> float:
        with self.lock:
            n = bisect.bisect_right(self.times, t1) - bisect.bisect_left(self.times, t0)
        return n / (t1 - t0)


def target_frame(key: str):
    """is_target(line) of the probe's output lines for the vendor."""
    def tcp(line: str) -> bool:
        r = parse_tcp(line) if line.startswith('Q ') else None
        return r is not None and r.fc == 16 and r.address == 1042

    def rtu(line: str) -> bool:
        r = parse_rtu(line) if line.startswith('Q ') else None
        return r is not None and r.fc == 16 and r.address == 0x2B

    def ascii_(line: str) -> bool:
        r = parse_ascii(line) if line.startswith('Q ') else None
        return r is not None and r.fc == 'WN'
    return {'xplus_mt': tcp, 'rd4': rtu, 'xmind_k': ascii_}[key]


class Frames:
    """Every CAN frame on the broker (a socketcand client of bench_cp_relays.py), by kind."""

    def __init__(self):
        self.frames: list[tuple[float, int]] = []
        self.setpoints = SetPoints(lambda line: None)
        self.lock = threading.Lock()

    def on_line(self, line: str) -> None:
        p = line.split()
        if p and p[0] == 'F':
            t, cob = float(p[1]), int(p[2], 16)
            with self.lock:
                self.frames.append((t, cob))
            # RxPDO2 (0x300 + node-ID): controlword + target; bit 4 = new set point
            if cob & ~0x7F == 0x300 and len(p) > 3 and int(p[3][:2], 16) & 0x10:
                self.setpoints.add(t)

    @staticmethod
    def kind(cob: int) -> str:
        if cob == 0x080:
            return 'SYNC'
        fn = cob & ~0x7F
        return {0x080: 'EMCY', 0x180: 'TxPDO', 0x280: 'TxPDO', 0x380: 'TxPDO', 0x480: 'TxPDO',
                0x200: 'RxPDO', 0x300: 'RxPDO', 0x400: 'RxPDO', 0x500: 'RxPDO',
                0x580: 'SDO', 0x600: 'SDO', 0x700: 'heartbeat'}.get(fn, 'other')

    def rate(self, t0: float, t1: float) -> dict[str, float]:
        with self.lock:
            inside = [cob for t, cob in self.frames if t0 <= t <= t1]
        out: dict[str, float] = {'all': len(inside) / (t1 - t0)}
        for cob in inside:
            k = self.kind(cob)
            out[k] = out.get(k, 0.0) + 1.0 / (t1 - t0)
        return out


def namespaced_params(key: str, ns: str, log_dir: pathlib.Path) -> pathlib.Path:
    """config/<key>.yaml with its node key made the node's name in the namespace (the line
    `<key>_node:` -> `/<ns>/<key>_node:`, the rest as it is): rcl applies a params-file block
    `<key>_node:` to /<key>_node only, not to /<ns>/<key>_node."""
    text = (CONFIG / f'{key}.yaml').read_text()
    head = f'\n{key}_node:\n'
    if head not in text:
        raise RuntimeError(f'config/{key}.yaml has no line {head.strip()!r}')
    path = log_dir / f'{key}_ns.yaml'
    path.write_text(text.replace(head, f'\n/{ns}/{key}_node:\n', 1))
    return path


def probe(key: str, link: str, params: dict[str, Any], log_dir: pathlib.Path,
          frames: Any, procs: list[Any]) -> tuple[str, Any]:
    """(the link the node opens, what counts the new targets on the wire): the CAN broker's
    frames, or a relay between node and simulator (a Modbus TCP relay, a pty relay), started
    and added to `procs`."""
    if frames is not None:
        return link, frames.setpoints
    setpoints = SetPoints(target_frame(key))
    if key == 'xplus_mt':
        relay = Helper(['tcp', link], log_dir, f'{key}_relay', setpoints.on_line)
        node_link = relay.head[0].split()[1]
    else:
        node_link = str(log_dir / f'{key}_node.tty')
        relay = Helper(['pty', node_link, link, str(params['baudrate'])], log_dir,
                       f'{key}_relay', setpoints.on_line)
    procs.append(relay)
    return node_link, setpoints


def run_vendor(key: str, ros: RosClient, log_dir: pathlib.Path, args) -> dict:
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64
    from std_srvs.srv import SetBool
    from stepper_drivers_msgs.msg import DriveStatus
    spec = TRAJ_VENDORS[key]
    ns, node_name = key, f'{key}_node'
    params = yaml.safe_load((CONFIG / f'{key}.yaml').read_text())[node_name]['ros__parameters']
    drives = list(params['drives'])
    ramped = drives[:2]
    convs, joints = {}, {}
    for d in drives:
        p = params[f'drives.{d}']
        convs[d] = UnitConversion(float(p['steps_per_rev']), float(p.get('gear_ratio', 1.0)),
                                  p.get('unit', 'rad'), float(p.get('lead_m', 0.0)))
        joints[d] = p['joint_name']
    poll_hz = float(params['publish_rate_hz'])
    procs: list[Any] = []
    subs = []
    frames = Frames() if key == 'vector_step' else None
    res: dict[str, Any] = {'vendor': key, 'title': spec.title, 'line': spec.line,
                           'poll_hz': poll_hz, 'rate_hz': args.rate, 'joints': joints}
    try:
        link = str(free_port()) if spec.link != 'path' else str(log_dir / f'{key}.tty')
        if spec.link == 'broker':
            broker = Proc([executable('stepper_sim', 'socketcand_broker'), '--port', link],
                          log_dir, f'{key}_broker')
            procs.append(broker)
            broker.wait_line('listening', 10)
            procs.append(Helper(['can', link], log_dir, f'{key}_frames', frames.on_line))
        sim = Proc([executable('stepper_sim', f'{key}_sim'), '--ros-args', '--params-file',
                    str(CONFIG / f'{key}_sim.yaml'), '-p', f'{spec.link_param}:={link}',
                    '-p', f'publish_rate_hz:={args.sample_rate}',
                    *[x for a in (*spec.sim_args, *args.sim_arg) for x in ('-p', a)]],
                   log_dir, f'{key}_sim')
        procs.append(sim)
        sim.wait_line('ready', 30)
        bare_s, bare_what = transaction_s(spec, link)
        res['limit'] = dataclasses.asdict(line_limit(key, params, bare_s, bare_what))
        # the probe between node and simulator (after the bare loop: a pty takes one master)
        node_link, setpoints = probe(key, link, params, log_dir, frames, procs)
        node = Proc([executable('stepper_drivers', node_name), '--ros-args',
                     '--params-file', str(namespaced_params(key, ns, log_dir)),
                     '-r', f'__ns:=/{ns}', '-p', f'{spec.link_param}:={node_link}',
                     '-p', 'joint_command_shared:=true',
                     '-p', f'status_rate_hz:={STATUS_RATE_HZ}',
                     *[x for a in args.node_arg for x in ('-p', a)]], log_dir, f'{key}_node')
        procs.append(node)
        true = {d: Recorder(ros, Float64, f'/{key}_sim/{d}/true_position_steps',
                            lambda m: m.data) for d in drives}
        status = {d: Recorder(ros, DriveStatus, f'/{ns}/{node_name}/{d}/status')
                  for d in drives}
        subs = [*true.values(), *status.values()]
        js: list[tuple[float, Any]] = []
        js_sub = ros.in_spin(ros.node.create_subscription, JointState, f'/{ns}/joint_states',
                             lambda m: js.append((time.monotonic(), m)),
                             qos_profile_sensor_data)
        js_reliable = Recorder(ros, JointState, f'/{ns}/joint_states', lambda m: None)
        subs.append(js_reliable)
        enable_all(ros, node, status, f'/{ns}/{node_name}', drives, spec.title)
        wait_for(lambda: all(true[d].last_before(time.monotonic()) is not None
                             for d in drives) and js, 10, 'true positions and joint_states')
        names = [joints[d] for d in drives] + [FOREIGN_JOINT]
        stream = Stream(ros, f'/{ns}/joint_command', names)
        time.sleep(1.0)                       # the enables' own transactions are over

        def now_true(d: str) -> float:
            return convs[d].from_steps(true[d].last_before(time.monotonic()))

        def count(t: float) -> dict[str, int]:
            return {d: refused(status[d], t)[0] for d in drives}
        a = res['phases'] = {}
        # idle
        t = time.monotonic()
        time.sleep(args.idle_s)
        a['idle'] = (t, time.monotonic())
        # NaN: before a controller writes
        start_true = {d: now_true(d) for d in drives}
        t = time.monotonic()
        stream.run(lambda _t: [math.nan] * len(names), NAN_S, args.rate)
        a['nan'] = (t, time.monotonic())
        time.sleep(0.3)
        res['nan_moved_steps'] = {d: abs(convs[d].to_steps(now_true(d) - start_true[d]))
                                  for d in drives}
        # hold: what the plugin's state interfaces read (joint_states, best effort)
        last_js = js[-1][1]
        by_name = dict(zip(last_js.name, last_js.position))
        res['joint_states_velocity'] = dict(zip(last_js.name, last_js.velocity))
        hold = [by_name[joints[d]] for d in drives] + [0.0]
        t = time.monotonic()
        stream.run(lambda _t: hold, args.hold_s, args.rate)
        a['hold'] = (t, time.monotonic())
        # the ramp, then the end held until every ramped axis stands there
        start = dict(zip(drives, hold))
        end = {d: start[d] + (RAMP_RAD if d in ramped else 0.0) for d in drives}

        def ramp(s: float) -> list[float]:
            f = quintic(min(s / RAMP_S, 1.0))[0]
            return [start[d] + (RAMP_RAD * f if d in ramped else 0.0) for d in drives] + [0.0]
        t_ramp = time.monotonic()
        sent_from = len(stream.sent)
        stream.run(ramp, RAMP_S, args.rate)
        a['ramp'] = (t_ramp, time.monotonic())

        def arrived() -> bool:
            for d in ramped:
                samples = true[d].between(time.monotonic() - 0.3, time.monotonic())
                target = convs[d].to_steps(end[d])
                if len(samples) < 2 or any(abs(x - target) > 1.0 for _t, x in samples):
                    return False
            return True
        t = time.monotonic()
        stream.run(lambda _t: ramp(RAMP_S), args.settle_s, args.rate, until=arrived)
        a['settle'] = (t, time.monotonic())
        time.sleep(0.3)
        res['sent'] = stream.sent[sent_from:]
        res['messages'] = len(stream.sent)
        res['stream_hz'] = (len(stream.sent) - sent_from - 1) / (
            stream.sent[-1][0] - stream.sent[sent_from][0])
        # samples that came in a burst (this process or DDS stalled: stamped late) are left out
        raw = {d: true[d].between(t_ramp - 0.5, time.monotonic()) for d in drives}
        kept = {d: on_time(raw[d], 1.0 / args.sample_rate) for d in drives}
        res['true_dropped'] = sum(len(raw[d]) - len(kept[d]) for d in drives)
        res['true_n'] = sum(len(raw[d]) for d in drives)
        res['true'] = {d: [(t, convs[d].from_steps(x)) for t, x in kept[d]] for d in drives}
        res['start'], res['end'], res['ramped'] = start, end, ramped
        res['step_rad'] = {d: 1.0 / convs[d].steps_per_unit for d in drives}
        res['tps'] = {name: rate_between(status[drives[0]], t0 + (0.5 if name == 'hold'
                                                                           else 0.0), t1)
                      for name, (t0, t1) in a.items() if name != 'settle'}
        res['tps_ramp_settle'] = rate_between(status[drives[0]], a['ramp'][0], a['settle'][1])
        if frames is not None:
            res['frames'] = {name: frames.rate(t0 + (0.5 if name == 'hold' else 0.0), t1)
                             for name, (t0, t1) in a.items() if name != 'settle'}
        res['setpoints'] = {name: setpoints.rate(t0 + (0.5 if name == 'hold' else 0.0), t1)
                            for name, (t0, t1) in a.items()}
        res['refused'] = {}
        marks = [('NaN', a['nan']), ('hold', a['hold']),
                 ('ramp', (a['ramp'][0], a['settle'][1]))]
        for name, (t0, t1) in marks:
            c0, c1 = count(t0), count(t1 + 0.2)
            res['refused'][name] = {d: c1[d] - c0[d] for d in drives}
        res['last_refusal'] = {d: refused(status[d], time.monotonic())[1]
                               for d in drives}
        js_n = [m for tt, m in js if a['hold'][0] + 0.5 <= tt <= a['hold'][1]]
        res['joint_states_hz'] = len(js_n) / (a['hold'][1] - a['hold'][0] - 0.5)
        res['joint_states_phase_hz'] = {
            name: len(js_reliable.between(t0 + (0.5 if name == 'hold' else 0.0), t1))
            / (t1 - t0 - (0.5 if name == 'hold' else 0.0))
            for name, (t0, t1) in a.items() if name != 'settle'}
        for d in drives:
            ros.call(SetBool, f'/{ns}/{node_name}/{d}/enable', SetBool.Request(data=False), 30)
        res['load'], res['cores'] = os.getloadavg()[0], os.cpu_count()
        ros.in_spin(ros.node.destroy_publisher, stream.pub)
        ros.in_spin(ros.node.destroy_subscription, js_sub)
    finally:
        for p in reversed(procs):
            try:
                p.stop()
            except AssertionError as exc:
                print(f'   ({str(exc).splitlines()[0]})')
        for rec in subs:
            ros.in_spin(ros.node.destroy_subscription, rec.sub)
    out = (log_dir / f'{key}_node.log').read_text(errors='replace')
    res['foreign_told'] = out.count(f"joint {FOREIGN_JOINT!r} is not one of this node's")
    res['foreign_warned'] = out.count(f'unknown joint {FOREIGN_JOINT!r}')
    analyse(res)
    report(res)
    return res


# ---------------------------------------------------------------------------------- analysis
def axis_figures(sent: list[tuple[float, list[float]]], i: int, samples: list[tuple[float, float]],
                 t0: float, start: float, end: float, step: float) -> dict:
    """One ramped axis: `sent` the stream's (time, positions), i its column, samples its true
    positions (time, rad), t0 the ramp's start."""
    sent_t = [t for t, _ in sent]

    def set_point(t: float) -> float:
        k = bisect.bisect_right(sent_t, t) - 1
        return start if k < 0 else sent[k][1][i]

    def passed(x: float) -> float | None:
        """When the stream first set a point at or beyond x (linear between two sends)."""
        prev = None
        for t, v in sent:
            if v[i] >= x:
                if prev is None or prev[1] == v[i]:
                    return t
                return prev[0] + (t - prev[0]) * (x - prev[1]) / (v[i] - prev[1])
            prev = (t, v[i])
        return None
    behind = [(set_point(t) - x, t) for t, x in samples if t0 <= t <= t0 + RAMP_S]
    worst, worst_t = max(behind, default=(math.nan, None))
    lags = []
    for t, x in samples:
        if t >= t0 and start + 0.05 * RAMP_RAD <= x <= start + 0.95 * RAMP_RAD:
            tp = passed(x)
            if tp is not None:
                lags.append(t - tp)
    at_end = next((t for k, (t, _x) in enumerate(samples)
                   if t >= t0 and all(abs(x2 - end) <= step * 1.01 for _t2, x2 in samples[k:])),
                  None)
    final = samples[-1][1] if samples else math.nan
    ranked = sorted(b for b, _t in behind)
    p95 = ranked[min(len(ranked) - 1, int(0.95 * len(ranked)))] if ranked else math.nan
    return {'behind_max_rad': worst, 'behind_at_s': None if worst_t is None else worst_t - t0,
            'behind_p95_rad': p95,
            'lag_max_s': max(lags, default=math.nan),
            'lag_median_s': statistics.median(lags) if lags else math.nan,
            'lag_samples': len(lags), 'samples': len(behind),
            'at_end_s': None if at_end is None else at_end - t0,
            'final_rad': final, 'short_rad': end - final}


def analyse(r: dict) -> None:
    t0 = r['phases']['ramp'][0]
    r['axes'] = {d: axis_figures(r['sent'], i, r['true'][d], t0, r['start'][d], r['end'][d],
                                 r['step_rad'][d])
                 for i, d in enumerate(r['joints']) if d in r['ramped']}
    r['goal_rad'] = TOP_SPEED_FACTOR * RAMP_RAD / RAMP_S / r['poll_hz']
    del r['sent'], r['true']


def fmt(x: float | None, spec: str = '.1f', none: str = '-') -> str:
    return none if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, spec)


def report(r: dict) -> None:
    lim = Limit(**r['limit'])
    print(f'\n== {r["title"]} [{r["cores"]} cores, load {r["load"]:.2f}]: {r["line"]}; node '
          f'polls at {r["poll_hz"]:g} Hz; stream {r["stream_hz"]:.1f} Hz (asked {r["rate_hz"]:g})'
          f', {len(r["joints"]) + 1} names per message')
    unit = 'frames' if r['vendor'] == 'vector_step' else 'transactions'
    span = (f'{lim.low:.0f}' if abs(lim.high - lim.low) < 0.5
            else f'{lim.low:.0f}-{lim.high:.0f}')
    print(f'   line limit: {span} {unit}/s ({lim.how})')
    def tx(ph: str) -> str:
        rate, over, inside = r['tps'][ph]
        return f'{ph} {fmt(rate)} (over {fmt(over, ".2f")} s, {inside} statuses inside)'
    print('   node transactions/s (status.link_transactions, between the statuses around the '
          'phase): ' + ', '.join(tx(ph) for ph in ('idle', 'nan', 'hold', 'ramp')))
    if 'frames' in r:
        f = r['frames']
        print('   every frame on the bus/s: ' + ', '.join(
            f'{ph} {f[ph]["all"]:.0f} (' + ' '.join(
                f'{k} {v:.0f}' for k, v in sorted(f[ph].items()) if k != 'all') + ')'
            for ph in ('idle', 'hold', 'ramp')))
    sp = r['setpoints']
    print('   new targets on the wire/s (the probe): ' + ', '.join(
        f'{ph} {sp[ph]:.1f}' for ph in ('idle', 'nan', 'hold', 'ramp', 'settle'))
          + f' (the stream: {r["rate_hz"]:g}/s per joint)')
    moved = ', '.join(f'{d} {v:.0f}' for d, v in r['nan_moved_steps'].items())
    print(f'   NaN phase: moved (steps) {moved}; refused ' + '; '.join(
        f'{ph}: ' + ' '.join(str(n) for n in c.values()) for ph, c in r['refused'].items()))
    for d, why in r['last_refusal'].items():
        if why and any(c[d] for c in r['refused'].values()):
            print(f'     {d} last refusal: {why}')
    print(f'   true-position samples: {r["true_n"]}, {r["true_dropped"]} left out (arrived in a '
          'burst)')
    js = r['joint_states_phase_hz']
    print(f'   joint_states/s: idle {js["idle"]:.1f}, NaN {js["nan"]:.1f}, hold {js["hold"]:.1f}, '
          f'ramp {js["ramp"]:.1f}; on a SensorDataQoS reader during the hold '
          f'{r["joint_states_hz"]:.1f}; velocity '
          + ', '.join(f'{j} {fmt(v, ".3f", "?")}' for j, v in r['joint_states_velocity'].items()))
    print(f'   foreign joint {FOREIGN_JOINT!r}: told {r["foreign_told"]} time(s), warned '
          f'{r["foreign_warned"]} time(s)')
    goal = r['goal_rad']
    for d, x in r['axes'].items():
        ok = x['behind_max_rad'] <= goal
        print(f'   {d} ({r["joints"][d]}): behind the set point at most '
              f'{1000 * x["behind_max_rad"]:.1f} mrad (at {fmt(x["behind_at_s"], ".2f")} s of '
              f'the ramp), 95 % of the samples {1000 * x["behind_p95_rad"]:.1f} mrad; lag max '
              f'{fmt(x["lag_max_s"], ".3f")} s, median '
              f'{fmt(x["lag_median_s"], ".3f")} s; '
              + (f'at its end {x["at_end_s"] - RAMP_S:+.2f} s after the ramp ended'
                 if x['at_end_s'] is not None else
                 f'NOT at its end ({1000 * x["short_rad"]:.0f} mrad short)')
              + (f'; goal <= {1000 * goal:.2f} mrad (one poll period at '
                 f'{TOP_SPEED_FACTOR * RAMP_RAD / RAMP_S:.4f} rad/s): '
                 f'{"met" if ok else "NOT met"}' if r['vendor'] in FAST else ''))


# --------------------------------------------------------------------------------------- main
def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--vendor', nargs='+', choices=list(TRAJ_VENDORS),
                    default=['xplus_mt', 'vector_step', 'rd4', 'xmind_k'])
    ap.add_argument('--rate', type=float, default=100.0,
                    help="messages/s (the controller_manager's update_rate or the block's "
                         'rw_rate; default 100)')
    ap.add_argument('--sample-rate', type=float, default=200.0,
                    help="the simulators' true-position rate [Hz] (default 200)")
    ap.add_argument('--idle-s', type=float, default=3.0)
    ap.add_argument('--hold-s', type=float, default=3.0)
    ap.add_argument('--settle-s', type=float, default=8.0,
                    help='the end held at most this long after the ramp (default 8)')
    ap.add_argument('--sim-arg', action='append', default=[], metavar='NAME:=VALUE',
                    help='a further simulator parameter (e.g. strict:=false), repeatable')
    ap.add_argument('--node-arg', action='append', default=[], metavar='NAME:=VALUE',
                    help='a further node parameter (e.g. publish_rate_hz:=100), repeatable')
    ap.add_argument('--json', type=pathlib.Path, help='write every figure to this file')
    args = ap.parse_args()
    log_dir = pathlib.Path(tempfile.mkdtemp(prefix='bench_r2c_'))
    domain_lock = reserve_domain()      # noqa: F841 - held until the end of the run
    print(f'ros2_control topic-interface benchmark: {machine()}; ROS_DOMAIN_ID '
          f'{os.environ.get("ROS_DOMAIN_ID", "0")}; stream {args.rate:g} Hz; true positions at '
          f'{args.sample_rate:g} Hz; simulator {args.sim_arg or "as config/"}, node '
          f'{args.node_arg or "as config/"}; '
          f"the nodes' bus owners on SCHED_FIFO 10: "
          f'{"yes" if fifo_allowed(10) else "no (refused here: the normal scheduler)"}; logs '
          f'{log_dir}')
    results: dict[str, Any] = {'machine': machine(), 'runs': []}
    failed = 0
    ros = RosClient('bench_ros2_control')
    try:
        for key in args.vendor:
            try:
                results['runs'].append(run_vendor(key, ros, log_dir, args))
            except Exception as exc:  # noqa: BLE001 - report, go on with the next one
                failed += 1
                print(f'\n== {key}: FAILED: {exc} (logs in {log_dir})', flush=True)
                results['runs'].append({'vendor': key, 'error': str(exc)})
            sys.stdout.flush()
    finally:
        ros.close()
    if args.json:
        args.json.write_text(json.dumps(results, indent=1, default=str))
    return 1 if failed else 0


if __name__ == '__main__':
    sys.exit(main())
