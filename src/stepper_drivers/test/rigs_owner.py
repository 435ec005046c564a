"""The bus owner's scripted rig (owner/test_bus_owner.py, owner/test_identity_recheck.py): a
scripted implementation of the Drive interface (`ScriptDrive`) on a shared `Line`. Each call
takes one "transaction" of TX_S on the line and is recorded with its time, so a test sees the
order in which calls reached the wire."""

from __future__ import annotations

import threading
import time

from stepper_drivers.contract.capabilities import ChangeCounting
from stepper_drivers.contract.drive import Bus, Drive, DriveState, State

TX_S = 0.01            # one transaction on the scripted line
RATE_HZ = 20.0         # poll rate: a 50 ms period, much longer than a transaction


class Line(Bus, ChangeCounting):
    description = 'scripted line'

    def __init__(self):
        self.open_ = False
        self.wire: list[tuple[float, str, str, tuple]] = []   # (t, drive, call, args)
        self.lock = threading.Lock()

    def open(self):
        self.open_ = True

    def close(self):
        self.open_ = False

    @property
    def is_open(self):
        return self.open_

    def transact(self, drive: str, call: str, *args):
        """One transaction: it takes TX_S and is on the wire when it starts."""
        with self.lock:
            self.wire.append((time.monotonic(), drive, call, args))
        time.sleep(TX_S)

    def calls(self, drive=None, call=None):
        with self.lock:
            return [w for w in self.wire if (drive is None or w[1] == drive)
                    and (call is None or w[2] == call)]


class ScriptDrive(Drive):
    def __init__(self, bus: Line, name: str, params=None):
        super().__init__(bus, name, params or {})
        self.line = bus
        self.fail: dict[str, Exception] = {}     # call name -> exception to raise once
        self.fail_always: dict[str, Exception] = {}
        self.velocity = 0.0
        self.enabled = True
        self.measured_at_s = None              # DriveState.measured_at_s of the next polls
        self.on_read = None          # called once, inside the next read_state()

    def _tx(self, call, *args):
        exc = self.fail.pop(call, None) or self.fail_always.get(call)
        self.line.transact(self.name, call, *args)
        if exc is not None:
            raise exc

    def connect(self):
        self._tx('connect')
        return {'serial_number': '7'}

    def read_state(self):
        self._tx('read_state')
        if self.on_read is not None:
            on_read, self.on_read = self.on_read, None
            on_read()
        return DriveState(state=State.OPERATION_ENABLED, enabled=self.enabled,
                          moving=self.velocity != 0.0, velocity_steps_s=self.velocity,
                          measured_at_s=self.measured_at_s)

    def enable(self):
        for _ in range(5):               # a state-machine walk: five transactions
            self._tx('enable step')
            yield TX_S
        self.enabled = True

    def disable(self):
        self._tx('disable')
        self.enabled = False
        self.velocity = 0.0

    def move_to(self, target_steps, motion):
        self._tx('move_to', target_steps)

    def set_velocity(self, velocity_steps_s, motion):
        self.velocity = velocity_steps_s    # the write reaches the drive, even if its reply
        self._tx('set_velocity', velocity_steps_s)   # is then lost

    def stop(self, quick=False):
        self._tx('stop')
        self.velocity = 0.0

    def start_homing(self, homing):
        for i in range(20):              # a long homing start: 20 steps of 50 ms
            self._tx('homing step', i)
            yield 0.05
        return ''

    def fault_reset(self):
        self._tx('fault_reset')
        return ''

    def save_params(self):
        for i in range(10):
            self._tx('save step', i)
            yield 0.05
        return 'saved'

    def read_register(self, address, data_type):
        self._tx('read_register', address)
        return 1

    def write_register(self, address, data_type, value):
        self._tx('write_register', address, value)


# The settings of an owner of scripted drives (and of the vendors' rigs, rigs_owner_vendors.py)
SETTINGS = {'publish_rate_hz': RATE_HZ, 'command_timeout_s': 0.3, 'reconnect_period_s': 0.05}


def counted(drive):
    """Record the time of every connect() call of `drive`."""
    calls = []
    connect = drive.connect

    def wrapper():
        calls.append(time.monotonic())
        return connect()
    drive.connect = wrapper
    return calls
