"""XmindKDrive against xmind_k_sim over a real pty, in one process (vendors/xmind_k/
test_xmind_k_drive.py and the tests that put an X-MIND K on a line: owner/, vendors/
test_malformed_answers.py). The simulator's tap records every host string in `Rig.wire`."""

import time

from stepper_drivers.contract.drive import complete
from stepper_drivers.vendors import xmind_k as v
from stepper_sim.xmind_k.sim import XmindKDriveSim, XmindKLine, build_line

BUS = {'baudrate': 9600, 'parity': 'N', 'stopbits': 1, 'timeout_s': 0.1, 'retries': 1,
       'local_echo': False}
DRIVE = {'resolution': '', 'current_preset': -1, 'answer_delay_ms': -1, 'equalization': -1,
         'power_cycle_flag': 'F7', 'busy_poll_period_s': 0.02, 'status_poll_period_s': 0.2,
         'steps_per_rev': 2000.0, 'homing.method': 3}


def wait_until(cond, timeout_s=10.0, what='condition'):
    deadline = time.monotonic() + timeout_s
    while not (value := cond()):
        assert time.monotonic() < deadline, f'timed out waiting for {what}'
        time.sleep(0.002)      # poll period of this wait; the driver polls the drive itself
    return value


class Rig:
    def __init__(self, tmp_path, sims=None, devices=None, connect=True, **drive_params):
        """`sims`: simulator parameters per drive; `devices`: ready-made device models (a
        device that is not an X-MIND K); `connect`: connect every drive."""
        self.tmp_path = tmp_path
        self.wire: list[str] = []
        if devices:
            self.line = XmindKLine(devices, str(tmp_path / 'tty'))
        else:
            self.line = build_line({'port': str(tmp_path / 'tty')},
                                   sims or {'a1': {'address': 1, 'px_edge_steps': 3000.0},
                                            'a2': {'address': 2}})
        self.line.tap = self._tap
        self.line.start()
        self.bus = v.make_bus({**BUS, 'port': self.line.link_path})
        self.bus.line.margin_s = 0.0     # a pty needs no §3 margin: keeps the test fast
        self.drives = {name: v.make_drive(self.bus, name, {**BUS, **DRIVE, **drive_params,
                                                           'address': d.address})
                       for name, d in self.line.by_name.items()}
        self.bus.open()
        if connect:
            for d in self.drives.values():
                complete(d.connect())
        self.wire.clear()

    def _tap(self, direction, data, _t):
        if direction == 'rx':
            self.wire.append(data.decode('ascii', errors='replace').rstrip('\r'))

    def sim(self, name='a1'):
        return self.line.by_name[name]

    def true(self, name='a1'):
        with self.line.lock:
            return self.sim(name).true_position_steps()

    def settle(self, drive):
        return wait_until(lambda: (s := complete(drive.read_state())) and not s.moving and s, 20.0,
                          f'{drive.name} at rest')

    def close(self):
        self.bus.close()
        self.line.stop()


class OtherDevice(XmindKDriveSim):
    """A device on the line that answers some strings otherwise than an X-MIND K."""

    def __init__(self, name, address, replies):
        super().__init__(name, address)
        self.replies = replies

    def receive(self, text, tolerant=True, now=None):
        raw = text.decode('ascii', errors='replace') if isinstance(text, bytes) else text
        reply = self.replies.get(raw.rstrip('\r'))
        return reply if reply is not None else super().receive(text, tolerant, now)
