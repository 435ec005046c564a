#!/usr/bin/env python3
"""Record what goes on the wire for each command run through a BusOwner, per vendor, and
compare two recordings: a check that a change of the bus owner (bus owner) changes nothing
the drives see. No ROS.

    python scripts/trace_owner.py --out /tmp/trace.json [--vendor xplus_mt rd4 ...]
    python scripts/trace_owner.py --compare /tmp/trace_before.json /tmp/trace.json

For each vendor it starts the simulator in this process (as the drive tests do: X-PLUS MT's
Modbus TCP server, RD4's Modbus RTU line and X-MIND K's ASCII line on a pty with parity N, the
Vector Step nodes behind a socketcand broker), builds one bus with two drives and one
BusOwner (publish_rate_hz 1.0: few polls), then runs a fixed scenario, one command after
the other, each awaited, with a bounded wait for the drive's state in between: connect (the
owner's own), both drives enabled at once, a move, a velocity run and its stop, a homing, a
disable, a fault reset, a save, a register read and write, the second drive's disable and the
owner's shutdown.

A TOOL, NOT A TEST: it monkeypatches, in this process only, the drives' methods (a
thread-local label is set while a call, or each step of a step-wise call, runs) and the
narrowest transport functions (ModbusTcpBus._send/_reply, ModbusRtuBus._exchange,
AsciiLine._write/_read_answer, the driver's CheckedNetwork.send_message and canopen's
SdoClient.read_response), which record (label, direction, frame).

Output: JSON {vendor: {label: [...]}} ('_meta' says which code ran; --compare ignores it).
A command label ('NN drive what') keeps its full ordered list of frames, ending with its
outcome ('= ok' or '= <exception type>'); a poll label ('drive poll') and frames sent outside
any labelled call hold the set of distinct frame sequences (their number depends on timing).
Made deterministic: sent frames are kept whole except the Modbus TCP transaction id; replies
keep their framing (function code, byte count, SDO command and index, an answer's code) but
not their values (positions and counters depend on when the poll landed); frames the simulator
sends by itself (CAN SYNC, heartbeats, TxPDOs, EMCY) are not recorded; a run of identical
consecutive transactions (a request and its reply) is kept once (a wait that polls the drive
until it is ready asks as often as timing makes it).
"""

from __future__ import annotations

import argparse
import concurrent.futures
import contextlib
import difflib
import itertools
import json
import logging
import os
import pathlib
import re
import sys
import tempfile
import threading
import time
from typing import Any, Callable

VENDORS = ('xplus_mt', 'rd4', 'xmind_k', 'vector_step')
DRIVE_METHODS = ('connect', 'read_state', 'enable', 'disable', 'move_to', 'set_velocity', 'stop',
                 'start_homing', 'fault_reset', 'save_params', 'read_register',
                 'write_register', 'until_ready_for_move', 'close')
SETTINGS = {'publish_rate_hz': 1.0, 'command_timeout_s': 5.0, 'reconnect_period_s': 0.5}
WAIT_S = 20.0

_ctx = threading.local()


# ------------------------------------------------------------------------------- the recorder
class Recorder:
    """(label, call number, direction, frame) in the order they happened, all threads."""

    def __init__(self) -> None:
        self.events: list[tuple[str, int, str, str]] = []
        self.kinds: dict[str, str] = {}          # label -> 'command' or 'set'
        self.outcomes: dict[str, str] = {}
        self.lock = threading.Lock()
        self.calls = itertools.count(1)
        self.phase = 'owner'                     # prefix of labels the owner makes itself
        self.pending_connect: dict[str, str] = {}

    def record(self, direction: str, frame: str) -> None:
        label = getattr(_ctx, 'label', None)
        call = getattr(_ctx, 'call', 0)
        if label is None:
            owner = threading.current_thread().name.startswith('owner ')
            label = 'unlabelled (owner thread)' if owner else 'unlabelled (other thread)'
            self.kinds.setdefault(label, 'set')
        with self.lock:
            self.events.append((label, call, direction, frame))

    def result(self) -> dict[str, Any]:
        by_call: dict[tuple[str, int], list[str]] = {}
        for label, call, direction, frame in self.events:
            by_call.setdefault((label, call), []).append(f'{direction} {frame}')
        out: dict[str, Any] = {}
        for (label, _call), frames in by_call.items():
            frames = _collapse(frames)
            if self.kinds.get(label) == 'command':
                out.setdefault(label, []).extend(frames)
            else:
                out.setdefault(label, set()).add(tuple(frames))
        for label, outcome in self.outcomes.items():
            out.setdefault(label, []).append(f'= {outcome}')
        return {label: sorted(list(s) for s in v) if isinstance(v, set) else v
                for label, v in sorted(out.items())}


REC = Recorder()


def _collapse(frames: list[str]) -> list[str]:
    """A run of identical consecutive transactions (a 'tx' and the replies after it) once."""
    transactions: list[list[str]] = []
    for frame in frames:
        if frame.startswith('tx') or not transactions:
            transactions.append([frame])
        else:
            transactions[-1].append(frame)
    out: list[str] = []
    last = None
    for t in transactions:
        if t != last:
            out.extend(t)
        last = t
    return out


@contextlib.contextmanager
def _labelled(label: str, call: int):
    _ctx.label, _ctx.call = label, call
    try:
        yield
    finally:
        _ctx.label, _ctx.call = None, 0


def _labelled_steps(label: str, call: int, gen):
    """A step-wise call (a drive.Operation) whose every step runs under the label."""
    value, exc = None, None
    while True:
        with _labelled(label, call):
            try:
                delay = gen.throw(exc) if exc is not None else gen.send(value)
            except StopIteration as stop:
                return stop.value
        value, exc = None, None
        try:
            value = yield delay
        except GeneratorExit:
            with _labelled(label, call):
                gen.close()
            raise
        except BaseException as e:  # noqa: BLE001 - handed on to the drive's generator
            exc = e


def labelled_call(label_of: Callable[[], tuple[str, str]], fn: Callable) -> Callable:
    """fn with a label set around it (and around each step of a step-wise result); a call made
    while a label is set (a drive method calling another) keeps the outer label."""
    from stepper_drivers.contract.drive import is_operation

    def call(*args, **kwargs):
        if getattr(_ctx, 'label', None) is not None:
            return fn(*args, **kwargs)
        label, kind = label_of()
        REC.kinds.setdefault(label, kind)
        number = next(REC.calls)
        with _labelled(label, number):
            result = fn(*args, **kwargs)
        if is_operation(result):
            return _labelled_steps(label, number, result)
        return result
    return call


def instrument_drive(name: str, drive) -> None:
    """Label what the owner calls by itself: polls, connects, the shutdown's stop."""
    for method in DRIVE_METHODS:
        fn = getattr(drive, method, None)
        if fn is None:
            continue
        if method == 'read_state':
            def label_of(name=name):
                connect = REC.pending_connect.pop(name, None)   # the connect job's own read
                return (connect, 'command') if connect else (f'{name} poll', 'set')
        elif method == 'connect':
            def label_of(name=name):
                label = f'00 {name} connect ({REC.phase})'
                REC.pending_connect[name] = label
                return label, 'command'
        else:
            def label_of(name=name, method=method):
                return f'99 {name} {method} ({REC.phase})', 'command'
        setattr(drive, method, labelled_call(label_of, fn))


# --------------------------------------------------------------------------- the transports
def _hex(data: bytes) -> str:
    return bytes(data).hex(' ')


def _mask_modbus_pdu(pdu: bytes) -> str:
    """A reply PDU without its register values (fc 3/4: function code, byte count)."""
    pdu = bytes(pdu)
    if len(pdu) >= 2 and pdu[0] in (3, 4):
        return f'{pdu[0]:02x} {pdu[1]:02x}' + ' ..' * (len(pdu) - 2)
    return _hex(pdu)


def _mask_ascii(answer: bytes | None) -> str:
    if answer is None:
        return 'silence'
    text = answer.decode('ascii', errors='replace')
    return repr(text[:4] + re.sub(r'[+-]?\d+', '#', text[4:]))


def _mask_sdo(data: bytes) -> str:
    data = bytes(data)
    if not data:
        return ''
    command = data[0] & 0xE0
    if command == 0x40:              # initiate upload response: the value
        return _hex(data[:4]) + ' ..' * (len(data) - 4)
    if command == 0x00:              # upload segment: the data
        return _hex(data[:1]) + ' ..' * (len(data) - 1)
    return _hex(data)


def install_transport_probes() -> None:
    from stepper_drivers.protocol import ascii_line, canopen_link, modbus_rtu, modbus_tcp

    tcp = modbus_tcp.ModbusTcpBus
    send, reply, finish = tcp._send, tcp._reply, tcp._finish_pending

    def tcp_send(self, sock, request):
        pdu = request.pdu()
        mbap = modbus_tcp.MBAP.pack(0, 0, len(pdu) + 1, request.unit & 0xFF)
        REC.record('tx', 'tid ' + _hex(mbap[2:]) + ' | ' + _hex(pdu))   # the id left out
        return send(self, sock, request)

    def tcp_reply(self, sock, request):
        try:
            pdu = reply(self, sock, request)
        except Exception as exc:
            REC.record('rx', f'! {type(exc).__name__}')
            raise
        REC.record('rx', _mask_modbus_pdu(pdu))
        return pdu

    def tcp_finish(self, sock):
        REC.record('rx', '(a stale reply dropped)')
        return finish(self, sock)
    tcp._send, tcp._reply, tcp._finish_pending = tcp_send, tcp_reply, tcp_finish

    rtu = modbus_rtu.ModbusRtuBus
    exchange = rtu._exchange

    def rtu_exchange(self, port, frame, request):
        REC.record('tx', _hex(frame))
        try:
            answer = exchange(self, port, frame, request)
        except Exception as exc:
            REC.record('rx', f'! {type(exc).__name__}')
            raise
        REC.record('rx', _hex(answer[:1]) + ' ' + _mask_modbus_pdu(answer[1:-2]) + ' crc')
        return answer
    rtu._exchange = rtu_exchange

    line = ascii_line.AsciiLine
    write, read_answer = line._write, line._read_answer

    def line_write(self, request):
        REC.record('tx', repr(bytes(request).decode('ascii', errors='replace')))
        return write(self, request)

    def line_read_answer(self, *args, **kwargs):
        answer = read_answer(self, *args, **kwargs)
        REC.record('rx', _mask_ascii(answer))
        return answer
    line._write, line._read_answer = line_write, line_read_answer

    network = canopen_link.CheckedNetwork
    send_message = network.send_message

    def can_send(self, can_id, data, *args, **kwargs):
        REC.record('tx', f'{can_id:03x} [{len(data)}] {_hex(data)}')
        return send_message(self, can_id, data, *args, **kwargs)
    network.send_message = can_send

    from canopen.sdo import client as sdo_client
    read_response = sdo_client.SdoClient.read_response

    def sdo_read_response(self, *args, **kwargs):
        try:
            data = read_response(self, *args, **kwargs)
        except Exception as exc:
            REC.record('rx', f'{self.tx_cobid:03x} ! {type(exc).__name__}')
            raise
        REC.record('rx', f'{self.tx_cobid:03x} [{len(data)}] {_mask_sdo(data)}')
        return data
    sdo_client.SdoClient.read_response = sdo_read_response


# ------------------------------------------------------------------------------ the benches
class Bench:
    """A simulator, a bus with two drives, their scenario values (drive units)."""

    vendor: Any = None
    target = 0
    velocity = 0.0
    motion = None
    homing = None
    register_read: tuple[str, str] = ('', '')
    register_write: tuple[str, str, int] = ('', '', 0)

    def __init__(self, tmp: pathlib.Path):
        self.tmp = tmp

    def params(self, name: str) -> dict[str, Any]:
        raise NotImplementedError

    def build(self):
        bus_params = self.vendor.with_defaults(self.params('axis1'))
        bus = self.vendor.make_bus(bus_params)
        drives = {n: self.vendor.make_drive(bus, n, self.vendor.with_defaults(self.params(n)))
                  for n in ('axis1', 'axis2')}
        return bus, drives

    def stop(self) -> None:
        raise NotImplementedError


class XplusMtBench(Bench):
    def __init__(self, tmp):
        super().__init__(tmp)
        from stepper_drivers.contract.drive import Homing, Motion
        from stepper_drivers.vendors import xplus_mt
        from stepper_sim.xplus_mt.sim import XplusMtDriveConfig, XplusMtSim
        self.vendor = xplus_mt.VENDOR
        self.sim = XplusMtSim(port=0, storage_dir=str(tmp), drives=[
            XplusMtDriveConfig('axis1', unit_id=1, home_switch_steps=20_000.0,
                               home_switch_width_steps=6_400.0, limit_neg_steps=-2_000_000.0,
                               limit_pos_steps=2_000_000.0),
            XplusMtDriveConfig('axis2', unit_id=2)])
        self.sim.start()
        self.target, self.velocity = 12_800, -12_800.0
        self.motion = Motion(64_000.0, 640_000.0, 640_000.0)
        self.homing = Homing(19, 0, 20_000.0, 1_000.0, 640_000.0)
        self.register_read = ('1158', 'u32')
        self.register_write = ('1080', 'u16', 50)

    def params(self, name):
        return {'host': '127.0.0.1', 'port': self.sim.port, 'timeout_s': 0.5,
                'unit_id': 1 if name == 'axis1' else 2, 'word_order': 'little',
                'steps_per_rev': 12800.0, 'joint_name': name, 'input_config': 14,
                'homing.method': 19}

    def stop(self):
        self.sim.stop()


class Rd4Bench(Bench):
    def __init__(self, tmp):
        super().__init__(tmp)
        from stepper_drivers.contract.drive import Homing, Motion
        from stepper_drivers.vendors import rd4
        from stepper_sim.rd4.sim import Rd4DriveSim, RtuLine
        self.vendor = rd4.VENDOR
        self.port = str(tmp / 'rd4.pty')
        self.line = RtuLine([Rd4DriveSim('axis1', 1), Rd4DriveSim('axis2', 2, 'T48')],
                            self.port, baud_switch=0x03)
        self.line.start()
        self.target, self.velocity = 1024, -400.0
        self.motion = Motion(800.0, 1000.0, 1000.0)
        self.homing = Homing(35, 0, 0.0, 0.0, 0.0)
        self.register_read = ('ACCELERATION', 'u16')
        self.register_write = ('ACCELERATION', 'u16', 1000)

    def params(self, name):
        return {'port': self.port, 'baudrate': 19200, 'parity': 'N', 'timeout_s': 0.1,
                'node_id': 1 if name == 'axis1' else 2, 'steps_per_rev': 1024.0,
                'homing.method': 35}

    def stop(self):
        self.line.stop()


class XmindKBench(Bench):
    def __init__(self, tmp):
        super().__init__(tmp)
        from stepper_drivers.contract.drive import Homing, Motion
        from stepper_drivers.vendors import xmind_k
        from stepper_sim.xmind_k.sim import build_line
        self.vendor = xmind_k.VENDOR
        self.line = build_line({'port': str(tmp / 'tty')},
                               {'axis1': {'address': 1, 'px_edge_steps': 3000.0},
                                'axis2': {'address': 2}})
        self.line.start()
        self.target, self.velocity = 2000, -1000.0
        self.motion = Motion(10_000.0, 200_000.0, 200_000.0)
        self.homing = Homing(3, 0, 3820.0, 318.0, 127_324.0)
        self.register_read = ('QE', 'u16')
        self.register_write = ('SA', 'i32', 0)

    def params(self, name):
        return {'port': self.line.link_path, 'baudrate': 9600, 'parity': 'N', 'stopbits': 1,
                'timeout_s': 0.1, 'retries': 1, 'local_echo': False,
                'address': 1 if name == 'axis1' else 2, 'resolution': '',
                'current_preset': -1, 'answer_delay_ms': -1, 'equalization': -1,
                'power_cycle_flag': 'F7', 'busy_poll_period_s': 0.02,
                'status_poll_period_s': 0.2, 'steps_per_rev': 2000.0, 'homing.method': 3}

    def build(self):
        bus, drives = super().build()
        bus.line.margin_s = 0.0        # a pty needs no §3 margin (as the drive tests)
        return bus, drives

    def stop(self):
        self.line.stop()


class VectorStepBench(Bench):
    def __init__(self, tmp):
        super().__init__(tmp)
        from stepper_drivers.contract.drive import Homing, Motion
        from stepper_drivers.vendors import vector_step
        from stepper_sim.core.socketcand_broker import SocketcandBroker
        from stepper_sim.vector_step.sim import NodeConfig, VectorStepSim
        logging.getLogger('can.interfaces.socketcand.socketcand').setLevel(logging.ERROR)
        self.vendor = vector_step.VENDOR
        self.broker = SocketcandBroker(port=0, ready_delay_s=0.01)
        self.broker.start()
        self.sim = VectorStepSim([NodeConfig('axis1', 1, limit_neg_steps=-32_000.0),
                                  NodeConfig('axis2', 2)], port=self.broker.port,
                                 reboot_delay_s=0.02, storage_dir=str(tmp))
        self.sim.start()
        deadline = time.monotonic() + WAIT_S
        while any(n.nmt_state != 0x7F for n in self.sim.nodes.values()):
            if time.monotonic() > deadline:
                raise TimeoutError('vector_step_sim: nodes not booted')
            time.sleep(0.01)
        self.target, self.velocity = 3200, -3200.0
        self.motion = Motion(32_000.0, 160_000.0, 160_000.0)
        self.homing = Homing(35, 0, 3200.0, 320.0, 160_000.0)
        self.register_read = ('0x2020:1', 'u32')
        self.register_write = ('0x2020:1', 'u32', 800)

    def params(self, name):
        return {'can.port': self.broker.port, 'timeout_s': 0.5, 'steps_per_rev': 3200.0,
                'homing.method': 35, 'heartbeat_timeout_s': 0.5,
                'node_id': 1 if name == 'axis1' else 2}

    def stop(self):
        self.sim.stop()
        self.broker.stop()


BENCHES = {'xplus_mt': XplusMtBench, 'rd4': Rd4Bench, 'xmind_k': XmindKBench,
           'vector_step': VectorStepBench}


# ----------------------------------------------------------------------------- the scenario
class Scenario:
    def __init__(self, bus_owner, bench: Bench):
        self.bus_owner = bus_owner
        self.bench = bench
        self.n = 0
        self.notes: list[str] = []

    def label(self, drive: str, what: str) -> str:
        return f'{self.n:02d} {drive} {what}'

    def submit(self, drive: str, what: str, make: Callable, fn: Callable
               ) -> tuple[str, concurrent.futures.Future]:
        from stepper_drivers.owner.commands import Command
        label = self.label(drive, what)
        REC.kinds[label] = 'command'
        command = make(Command, labelled_call(lambda: (label, 'command'), fn), what)
        return label, self.bus_owner.submit(drive, command)

    def settle(self, label: str, fut: concurrent.futures.Future) -> Any:
        try:
            value = fut.result(WAIT_S)
        except concurrent.futures.TimeoutError:
            REC.outcomes[label] = 'no result within the wait'
            self.notes.append(f'{label}: no result within {WAIT_S:g} s')
            return None
        except Exception as exc:  # noqa: BLE001 - the outcome is part of the record
            REC.outcomes[label] = type(exc).__name__
            self.notes.append(f'{label}: {type(exc).__name__}: {exc}')
            return None
        REC.outcomes[label] = 'ok'
        return value

    def run(self, drive: str, what: str, make: Callable, fn: Callable) -> Any:
        self.n += 1
        return self.settle(*self.submit(drive, what, make, fn))

    def wait(self, drive: str, what: str, cond: Callable, timeout_s: float = WAIT_S) -> bool:
        """Poll `drive` (poll_soon, wait_poll: a snapshot read after every write so far) until
        cond(its state) or the time-out."""
        deadline = time.monotonic() + timeout_s
        while True:
            polled = threading.Event()
            self.bus_owner.wait_poll(drive, 2.0, lambda _ok, event=polled: event.set())
            self.bus_owner.poll_soon(drive)
            polled.wait(3.0)
            state = self.bus_owner.slots[drive].state
            if cond(state):
                return True
            if time.monotonic() > deadline:
                self.notes.append(f'{drive}: no {what} within {timeout_s:g} s (last state '
                                  f'{state.state.value}, moving {state.moving}, homing '
                                  f'{state.homing.value})')
                return False
            time.sleep(0.01)

    def play(self) -> None:
        from stepper_drivers.contract.drive import HomingState
        b, bus_owner = self.bench, self.bus_owner
        d1, d2 = (bus_owner.slots[n].drive for n in ('axis1', 'axis2'))
        deadline = time.monotonic() + WAIT_S
        while not all(s.connected for s in bus_owner.slots.values()):
            if time.monotonic() > deadline:
                self.notes.append('not every drive connected: ' + ', '.join(
                    f'{s.name}: {s.last_error}' for s in bus_owner.slots.values()
                    if not s.connected))
                return
            time.sleep(0.01)
        self.n += 1       # both at once, recorded per drive
        both = [self.submit(n, 'enable (both at once)', lambda C, fn, w: C.enable(fn, w),
                            bus_owner.slots[n].drive.enable) for n in ('axis1', 'axis2')]
        for label, fut in both:
            self.settle(label, fut)
        for n in ('axis1', 'axis2'):
            self.wait(n, 'enabled state', lambda s: s.enabled)
        self.run('axis1', f'move_to {b.target}', lambda C, fn, w: C.move(fn, w),
                 lambda: d1.move_to(b.target, b.motion))
        self.wait('axis1', 'standstill at the target', lambda s: not s.moving
                  and s.target_reached and s.position_steps == b.target)
        bus_owner.arm_watchdog('axis1')
        self.run('axis1', f'set_velocity {b.velocity:g}',
                 lambda C, fn, w: C.velocity_stream(fn, w, b.velocity),
                 lambda: d1.set_velocity(b.velocity, b.motion))
        self.wait('axis1', 'motion', lambda s: s.moving)
        self.run('axis1', 'stop', lambda C, fn, w: C.stop(fn, w), d1.stop)
        self.wait('axis1', 'standstill', lambda s: not s.moving)
        self.run('axis1', 'home', lambda C, fn, w: C.homing(fn, w),
                 lambda: d1.start_homing(b.homing))
        self.wait('axis1', 'end of the homing', lambda s: not s.moving and s.homing in (
            HomingState.ATTAINED, HomingState.ERROR))
        self.run('axis1', 'disable', lambda C, fn, w: C.disable(fn, w), d1.disable)
        self.wait('axis1', 'disabled state', lambda s: not s.enabled)
        self.run('axis1', 'fault_reset', lambda C, fn, w: C.fault_reset(fn, w), d1.fault_reset)
        self.run('axis1', 'save_params', lambda C, fn, w: C.maintenance(fn, w), d1.save_params)
        address, data_type = b.register_read
        self.run('axis1', f'read_register {address}', lambda C, fn, w: C.maintenance(fn, w),
                 lambda: d1.read_register(address, data_type))
        address, data_type, value = b.register_write
        self.run('axis1', f'write_register {address}', lambda C, fn, w: C.raw_write(fn, w),
                 lambda: d1.write_register(address, data_type, value))
        self.run('axis2', 'disable', lambda C, fn, w: C.disable(fn, w), d2.disable)
        self.wait('axis2', 'disabled state', lambda s: not s.enabled)


def trace_vendor(key: str) -> tuple[dict[str, Any], list[str]]:
    from stepper_drivers.owner import BusOwner
    global REC
    REC = Recorder()
    with tempfile.TemporaryDirectory(prefix=f'trace_owner_{key}_') as tmp:
        bench = BENCHES[key](pathlib.Path(tmp))
        try:
            bus, drives = bench.build()
            for name, drive in drives.items():
                instrument_drive(name, drive)
            events: list[str] = []
            bus_owner = BusOwner(bus, drives, dict(SETTINGS), name=f'trace {key}',
                                on_event=lambda level, drive, text: events.append(
                                    f'{level} {drive}: {text}'))
            bus_owner.start()
            scenario = Scenario(bus_owner, bench)
            try:
                scenario.play()
            finally:
                REC.phase = 'shutdown'
                if not bus_owner.shutdown(2.0, disable=()):
                    scenario.notes.append('the owner did not end at the shutdown')
        finally:
            bench.stop()
    notes = scenario.notes + [e for e in events if not e.startswith('info')]
    return REC.result(), notes


# ------------------------------------------------------------------------------ comparison
def compare(path_a: str, path_b: str) -> int:
    a = json.loads(pathlib.Path(path_a).read_text())
    b = json.loads(pathlib.Path(path_b).read_text())
    differences = 0
    for vendor in sorted((set(a) | set(b)) - {'_meta'}):
        va, vb = a.get(vendor), b.get(vendor)
        if va is None or vb is None:
            print(f'{vendor}: only in {path_a if vb is None else path_b}')
            differences += 1
            continue
        for label in sorted(set(va) | set(vb)):
            fa, fb = va.get(label), vb.get(label)
            if fa == fb:
                continue
            differences += 1
            if fa is None or fb is None:
                print(f'{vendor} / {label}: only in {path_a if fb is None else path_b}')
                continue
            print(f'{vendor} / {label}:')
            lines_a = [json.dumps(x) if not isinstance(x, str) else x for x in fa]
            lines_b = [json.dumps(x) if not isinstance(x, str) else x for x in fb]
            for line in difflib.unified_diff(lines_a, lines_b, path_a, path_b, lineterm='',
                                             n=2):
                print('    ' + line)
    if differences:
        print(f'{differences} label(s) differ')
        return 1
    print('identical (every vendor, every label)')
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--out', help='write the recording to this JSON file')
    parser.add_argument('--vendor', nargs='+', choices=VENDORS, default=list(VENDORS))
    parser.add_argument('--compare', nargs=2, metavar=('A', 'B'),
                        help='compare two recordings; exit 1 on any difference')
    args = parser.parse_args()
    if args.compare:
        return compare(*args.compare)
    if not args.out:
        parser.error('--out FILE or --compare A B')
    logging.basicConfig(level=logging.ERROR, format='%(name)s: %(message)s')
    import stepper_drivers
    import stepper_drivers.owner
    meta = {'stepper_drivers': os.path.realpath(stepper_drivers.__file__),
            'bus owner': os.path.realpath(stepper_drivers.owner.__file__)}
    print(f'stepper_drivers from {meta["stepper_drivers"]}')
    print(f'bus owner from {meta["bus owner"]}')
    install_transport_probes()
    out: dict[str, Any] = {'_meta': meta}
    for key in args.vendor:
        t0 = time.monotonic()
        out[key], notes = trace_vendor(key)
        counts = ', '.join(f'{label}: {len(v)}' for label, v in out[key].items())
        print(f'{key} ({time.monotonic() - t0:.1f} s): {counts}')
        for note in notes:
            print(f'  note: {note}')
        meta[f'{key} notes'] = notes
    pathlib.Path(args.out).write_text(json.dumps(out, indent=1, sort_keys=True) + '\n')
    print(f'wrote {args.out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
