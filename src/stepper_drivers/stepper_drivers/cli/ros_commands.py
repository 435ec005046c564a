"""stepperctl commands that work through the ROS interface of running driver nodes.

Each `cmd_*` takes the Graph and the parsed arguments and returns an exit code, or raises
CliError (one line, an exit code). The node answers services with success/message; a failure is
reported as EXIT_FAULT when the drive's status shows a fault, else EXIT_FAILED.
"""

from __future__ import annotations

import json
import logging
import os
import sys
import threading
import time
from typing import Any

from .errors import (
    EXIT_FAILED,
    EXIT_FAULT,
    EXIT_INTERRUPTED,
    EXIT_NOT_FOUND,
    EXIT_OK,
    EXIT_TIMEOUT,
    EXIT_USAGE,
    CliError,
)
from .graph import DriveRef, Graph
from .view import CLEAR_SCREEN, Live, progress_bar, row, table

logger = logging.getLogger(__name__)

STOP_WAIT_S = 10.0           # after a stop, how long the drive may take to stand still
JOG_MAX_PERIOD_S = 0.1       # velocity_command at least at 10 Hz ...
JOG_WATCHDOG_SHARE = 3       # ... and at least 3 times per command_timeout_s of the node


def out(text: str) -> None:
    print(text, flush=True)


def one_line(text: str) -> str:
    return ' '.join(str(text).split())


def strip_drive(ref: DriveRef, message: str) -> str:
    """The node prefixes its messages with the drive name; we print node/drive instead."""
    prefix = ref.drive + ': '
    return message[len(prefix):] if message.startswith(prefix) else message


def failed(g: Graph, ref: DriveRef, message: str) -> CliError:
    """A refusal/failure, as EXIT_FAULT when the drive is in fault."""
    message = f'{ref.label}: {one_line(strip_drive(ref, message))}'
    try:
        st = g.status(ref, timeout_s=1.0)
    except CliError:
        st = None
    if st is not None and st.fault:
        extra = '' if f'0x{st.fault_code:04X}' in message else \
            f' (FAULT 0x{st.fault_code:04X} {st.fault_text})'
        return CliError(EXIT_FAULT, message + extra)
    return CliError(EXIT_FAILED, message)


def finish(g: Graph, ref: DriveRef, resp) -> int:
    if not resp.success:
        raise failed(g, ref, resp.message)
    out(f'{ref.label}: {one_line(strip_drive(ref, resp.message))}')
    return EXIT_OK


def require_ready(g: Graph, ref: DriveRef, what: str, spec: str) -> Any:
    """Status of a drive that may take a motion command; CliError otherwise."""
    st = g.status(ref)
    if not st.connected:
        raise CliError(EXIT_FAILED, f'{ref.label}: {what}: drive is DISCONNECTED (the node is '
                       'reconnecting; see stepperctl status)')
    if st.fault:
        raise CliError(EXIT_FAULT, f'{ref.label}: {what}: drive is in FAULT 0x{st.fault_code:04X}'
                       f' {st.fault_text}; run: stepperctl fault-reset {spec}')
    if not st.enabled:
        raise CliError(EXIT_FAILED, f'{ref.label}: {what}: drive is not enabled (state '
                       f'{st.state}); run: stepperctl enable {spec}')
    return st


def stop_quietly(g: Graph, ref: DriveRef) -> None:
    from std_srvs.srv import Trigger
    try:
        g.call(ref, 'stop', Trigger, timeout_s=5.0)
    except CliError as e:
        print(f'stepperctl: {e.message}', file=sys.stderr)


def wait_standstill(g: Graph, ref: DriveRef, timeout_s: float) -> Any:
    first = g.latest(ref)[0]
    return g.status(ref, lambda m: not m.moving, timeout_s, newer_than=first,
                    what='standstill')


def _wait_future(future, timeout_s: float) -> bool:
    done = threading.Event()
    future.add_done_callback(lambda _f: done.set())
    return done.wait(timeout_s)


# ---------------------------------------------------------------------------------- commands
def cmd_list(g: Graph, args) -> int:
    refs = g.discover()
    if not refs:
        raise CliError(EXIT_NOT_FOUND, 'no drives found on the ROS graph (ROS_DOMAIN_ID='
                       f'{os.environ.get("ROS_DOMAIN_ID", "0")}, ROS_AUTOMATIC_DISCOVERY_RANGE='
                       f'{os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "SUBNET")}); '
                       'is a driver node running?')
    g.subscribe_status(refs)
    deadline = time.monotonic() + 3.0
    while time.monotonic() < deadline and any(g.latest(r)[0] is None for r in refs):
        time.sleep(0.02)   # poll the subscriptions' first messages
    rows = []
    for r in refs:
        m = g.latest(r)[0]
        rows.append({'drive': r.label, 'vendor': m.vendor if m else '',
                     'address': m.address if m else '', 'joint': m.joint_name if m else '',
                     'state': m.state if m else 'NO STATUS',
                     'position': round(m.position, 6) if m else None,
                     'fault': f'0x{m.fault_code:04X} {m.fault_text}'.strip()
                     if m and m.fault else ''})
    if args.json:
        out(json.dumps(rows, indent=1))
        return EXIT_OK
    fmt = '{:<24} {:<15} {:>4}  {:<10} {:<22} {:>10}  {}'
    out(fmt.format('DRIVE', 'VENDOR', 'ADDR', 'JOINT', 'STATE', 'POSITION', 'FAULT'))
    for d in rows:
        pos = '' if d['position'] is None else f"{d['position']:+.4f}"
        out(fmt.format(d['drive'], d['vendor'], d['address'], d['joint'], d['state'], pos,
                       d['fault']).rstrip())
    return EXIT_OK


def cmd_status(g: Graph, args) -> int:
    named = bool(args.drives)
    refs = [g.find(s) for s in args.drives] if named else g.discover()
    if not refs:
        raise CliError(EXIT_NOT_FOUND, 'no drives found on the ROS graph (ROS_DOMAIN_ID='
                       f'{os.environ.get("ROS_DOMAIN_ID", "0")}); is a driver node running?')
    g.subscribe_status(refs)
    deadline = time.monotonic() + 3.0
    while time.monotonic() < deadline and any(g.latest(r)[0] is None for r in refs):
        time.sleep(0.02)   # poll the subscriptions' first messages

    def render() -> str:
        return table(row(r.label, *g.latest(r)) for r in refs)

    if args.once:
        out(render())
        missing = [r.label for r in refs if g.latest(r)[0] is None]
        if missing:
            raise CliError(EXIT_TIMEOUT, 'no status from ' + ', '.join(missing))
        faults = [r.label for r in refs if g.latest(r)[0].fault]
        if faults:
            raise CliError(EXIT_FAULT, 'in FAULT: ' + ', '.join(faults))
        return EXIT_OK
    tty = sys.stdout.isatty()
    end = time.monotonic() + args.duration if args.duration else float('inf')
    next_discovery = time.monotonic() + 2.0
    try:
        while True:
            now = time.monotonic()
            if not named and now >= next_discovery:     # drives that came up meanwhile
                refs = sorted(set(refs) | set(g.drive_refs()))
                g.subscribe_status(refs)
                next_discovery = now + 2.0
            stamp = time.strftime('%H:%M:%S')
            text = f'stepperctl status  {stamp}  (Ctrl-C to end)\n' + render()
            sys.stdout.write((CLEAR_SCREEN + text + '\n') if tty else text + '\n\n')
            sys.stdout.flush()
            if now >= end:
                return EXIT_OK
            time.sleep(min(args.period, max(end - now, 0.0)))  # the refresh period
    except KeyboardInterrupt:
        return EXIT_OK


def cmd_enable(g: Graph, args, on: bool = True) -> int:
    from std_srvs.srv import SetBool
    ref = g.find(args.drive)
    resp = g.call(ref, 'enable', SetBool, SetBool.Request(data=on), args.timeout)
    return finish(g, ref, resp)


def cmd_disable(g: Graph, args) -> int:
    return cmd_enable(g, args, on=False)


def _trigger(g: Graph, args, name: str) -> int:
    from std_srvs.srv import Trigger
    ref = g.find(args.drive)
    return finish(g, ref, g.call(ref, name, Trigger, timeout_s=args.timeout))


def cmd_stop(g: Graph, args) -> int:
    return _trigger(g, args, 'stop')


def cmd_save(g: Graph, args) -> int:
    return _trigger(g, args, 'save_params')


def cmd_fault_reset(g: Graph, args) -> int:
    from std_srvs.srv import Trigger
    ref = g.find(args.drive)
    resp = g.call(ref, 'fault_reset', Trigger, timeout_s=args.timeout)
    if not resp.success and 'fault remains' in resp.message:
        raise CliError(EXIT_FAULT, f'{ref.label}: {one_line(strip_drive(ref, resp.message))}')
    return finish(g, ref, resp)


def cmd_home(g: Graph, args) -> int:
    from std_srvs.srv import Trigger
    ref = g.find(args.drive)
    st = g.status(ref)
    if st.fault:
        raise CliError(EXIT_FAULT, f'{ref.label}: home: drive is in FAULT 0x{st.fault_code:04X}'
                       f' {st.fault_text}; run: stepperctl fault-reset {args.drive}')
    live = Live(period_s=1.0)
    t0 = time.monotonic()

    def progress() -> None:
        m = g.latest(ref)[0]
        if m is not None:
            live.line(f'{ref.label}: homing {m.homing_state:<8} position {m.position:+.4f} '
                      f'({time.monotonic() - t0:4.1f} s)', time.monotonic())
    try:
        resp = g.call(ref, 'home', Trigger, timeout_s=args.timeout, while_waiting=progress)
    except CliError as e:
        live.end()
        if e.code == EXIT_TIMEOUT:
            stop_quietly(g, ref)
            raise CliError(EXIT_TIMEOUT, f'{ref.label}: homing not finished within '
                           f'{args.timeout:g} s (--timeout); drive stopped') from None
        raise
    except KeyboardInterrupt:
        live.end()
        stop_quietly(g, ref)
        raise CliError(EXIT_INTERRUPTED, f'{ref.label}: interrupted; drive stopped') from None
    live.end()
    return finish(g, ref, resp)


def cmd_move(g: Graph, args) -> int:
    from stepper_drivers_msgs.action import MoveTo
    ref = g.find(args.drive)
    st = require_ready(g, ref, f'move to {args.position:g}', args.drive)
    client = g.action_client(ref, 'move_to', MoveTo)
    target, start = args.position, st.position
    span = abs(target - start) or 1.0
    goal_future = g.ros.in_spin(client.send_goal_async, MoveTo.Goal(position=target))
    if not _wait_future(goal_future, 5.0):
        raise CliError(EXIT_TIMEOUT, f'{ref.label}: move_to goal not answered within 5 s')
    handle = goal_future.result()
    if not handle.accepted:
        raise failed(g, ref, f'move to {target:g}: goal rejected')
    result_future = g.ros.in_spin(handle.get_result_async)
    done = threading.Event()
    result_future.add_done_callback(lambda _f: done.set())
    live = Live(period_s=1.0)
    deadline = time.monotonic() + args.timeout
    try:
        while not done.wait(0.1):
            m = g.latest(ref)[0]
            now = time.monotonic()
            if m is not None:
                live.line(f'{ref.label}: {progress_bar(1.0 - abs(target - m.position) / span)} '
                          f'at {m.position:+.4f} -> {target:+.4f}  {m.state}', now)
            if now >= deadline:
                live.end()
                cancel = g.ros.in_spin(handle.cancel_goal_async)   # the node stops the drive
                _wait_future(cancel, 5.0)
                pos = m.position if m is not None else float('nan')
                raise CliError(EXIT_TIMEOUT, f'{ref.label}: target {target:g} not reached within '
                               f'{args.timeout:g} s (--timeout), at {pos:.4f}; drive stopped')
    except KeyboardInterrupt:
        live.end()
        _wait_future(g.ros.in_spin(handle.cancel_goal_async), 5.0)
        stop_quietly(g, ref)
        raise CliError(EXIT_INTERRUPTED, f'{ref.label}: interrupted; drive stopped') from None
    result = result_future.result().result
    if result.success:
        live.line(f'{ref.label}: {progress_bar(1.0)} at {result.final_position:+.4f}',
                  time.monotonic(), force=True)
        live.end()
        out(f'{ref.label}: at {result.final_position:.6g} (target {target:g})')
        return EXIT_OK
    live.end()
    raise failed(g, ref, result.message)


def cmd_jog(g: Graph, args) -> int:
    from std_msgs.msg import Float64
    ref = g.find(args.drive)
    st = require_ready(g, ref, f'jog at {args.velocity:g}', args.drive)
    watchdog_s = g.param(ref.node, 'command_timeout_s')
    period_s = JOG_MAX_PERIOD_S
    if isinstance(watchdog_s, float) and watchdog_s > 0:
        period_s = min(period_s, watchdog_s / JOG_WATCHDOG_SHARE)
    pub = g.publisher(Float64, ref.interface('velocity_command'))
    refused = st.commands_refused
    start = st.position
    live = Live(period_s=1.0)
    t0 = time.monotonic()
    end = t0 + args.duration
    try:
        while True:
            now = time.monotonic()
            if now >= end:
                break
            pub.publish(Float64(data=float(args.velocity)))
            m = g.latest(ref)[0]
            if m.fault:
                live.end()
                stop_quietly(g, ref)
                raise CliError(EXIT_FAULT, f'{ref.label}: FAULT 0x{m.fault_code:04X} '
                               f'{m.fault_text} during the jog')
            if m.commands_refused > refused:
                live.end()
                stop_quietly(g, ref)
                raise CliError(EXIT_FAILED, f'{ref.label}: velocity_command refused: '
                               f'{m.last_refusal}')
            live.line(f'{ref.label}: jog {args.velocity:+g}  {now - t0:4.1f}/{args.duration:g} s'
                      f'  at {m.position:+.4f}  velocity {m.velocity:+.3f}', now)
            time.sleep(period_s)  # the command rate: faster than the node's watchdog
    except KeyboardInterrupt:
        live.end()
        stop_quietly(g, ref)
        raise CliError(EXIT_INTERRUPTED, f'{ref.label}: interrupted; drive stopped') from None
    live.end()
    if args.no_stop:
        how = f'by the node watchdog (command_timeout_s {watchdog_s})'
    else:
        stop_quietly(g, ref)
        how = 'by stop'
    wait_s = STOP_WAIT_S + (watchdog_s if isinstance(watchdog_s, float) else 1.0)
    m = wait_standstill(g, ref, wait_s)
    if m.fault:
        raise CliError(EXIT_FAULT, f'{ref.label}: FAULT 0x{m.fault_code:04X} {m.fault_text}')
    out(f'{ref.label}: jogged at {args.velocity:+g} for {args.duration:g} s from {start:+.4f} '
        f'to {m.position:+.4f}; stopped {how}')
    return EXIT_OK


def cmd_read(g: Graph, args) -> int:
    from stepper_drivers_msgs.srv import ReadRegister
    ref = g.find(args.drive)
    resp = g.call(ref, 'read_register', ReadRegister,
                  ReadRegister.Request(address=args.address, data_type=args.type), args.timeout)
    if not resp.success:
        raise failed(g, ref, resp.message)
    if args.type.lower() == 'string':
        out(f'{ref.label}: {args.address} ({args.type}) = {resp.text!r}')
    else:
        out(f'{ref.label}: {args.address} ({args.type}) = {resp.value} '
            f'(0x{resp.value & 0xFFFFFFFFFFFFFFFF:X})')
    return EXIT_OK


def cmd_write(g: Graph, args) -> int:
    from stepper_drivers_msgs.srv import WriteRegister
    req = WriteRegister.Request(address=args.address, data_type=args.type)
    if args.type.lower() == 'string':
        req.text = args.value
    else:
        try:
            req.value = int(args.value, 0)
        except ValueError:
            raise CliError(EXIT_USAGE, f'write: value {args.value!r} is not an integer '
                           '(decimal or 0x hex)') from None
    ref = g.find(args.drive)
    return finish(g, ref, g.call(ref, 'write_register', WriteRegister, req, args.timeout))


COMMANDS = {
    'list': cmd_list, 'status': cmd_status, 'enable': cmd_enable, 'disable': cmd_disable,
    'stop': cmd_stop, 'home': cmd_home, 'move': cmd_move, 'jog': cmd_jog,
    'fault-reset': cmd_fault_reset, 'save': cmd_save, 'read': cmd_read, 'write': cmd_write,
}


def run(args) -> int:
    g = Graph(discovery_timeout_s=args.discovery_timeout)
    try:
        return COMMANDS[args.command](g, args)
    finally:
        g.close()
