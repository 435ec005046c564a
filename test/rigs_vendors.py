"""The vendors' benches: each vendor's simulator and node as separate processes
(rosharness.DriveBench), with the settings the end-to-end tests run them at.

`XplusBench`, `Rd4Bench` (and `Rd4LineTimingBench`), `XmindBench` take the test's procs, ros
client and tmp_path; `VectorRig` brings its own (the CAN broker, processes and a ROS client) and
is ended by close(). `make_bench(vendor, ...)` starts any of them by vendor key, and the tables
below give what a bound computed from a bench's settings needs.
"""

import math

from rosharness import DriveBench, Procs, RosClient, free_port, wait_for
from stepper_drivers_msgs.srv import ReadRegister, WriteRegister
from stepper_sim.core.socketcand_broker import SocketcandBroker

# steps per rad of the shipped configs
STEPS_PER_RAD = {'xplus_mt': 12800 / (2 * math.pi), 'rd4': 1024 / (2 * math.pi),
                 'xmind_k': 2000 / (2 * math.pi), 'vector_step': 3200 / (2 * math.pi)}
# The benches' settings (config/<vendor>.yaml unless the bench overrides it).
DECEL_RAD_S2 = {'xplus_mt': 200.0, 'rd4': 12.0, 'xmind_k': 400.0, 'vector_step': 200.0}
RATE_HZ = {'xplus_mt': 50.0, 'rd4': 20.0, 'xmind_k': 20.0, 'vector_step': 50.0}
# One line transaction: what may be in flight when the watchdog fires (X-MIND K at 9600 baud
# is the slowest: about 30 ms; a Python simulator on a shared machine answers later).
TRANSACTION_S = {'xplus_mt': 0.01, 'rd4': 0.05, 'xmind_k': 0.06, 'vector_step': 0.02}
# The simulators move their axes in ticks: a stop acts at the next one.
SIM_TICK_S = {'xplus_mt': 0.02, 'rd4': 0.01, 'xmind_k': 0.05, 'vector_step': 0.02}


# ------------------------------------------------------------------------------- X-PLUS MT
class XplusBench(DriveBench):
    """A simulator and a node on a free port, plus helpers to reach them through ROS."""

    vendor = 'xplus_mt'
    node_extra_args = ('-p', 'drives.axis1.allow_raw_write:=true')   # shipped: refused

    def __init__(self, procs, ros, tmp_path, node_args=()):
        self.port = free_port()
        self.storage = tmp_path / 'eeprom'
        self.storage.mkdir()
        super().__init__(procs, ros, node_args)

    def link_args(self):
        return ['-p', f'port:={self.port}']

    def sim_args(self):
        return ['-p', f'storage_dir:={self.storage}']


# ------------------------------------------------------------------------------------- RD4
class Rd4Bench(DriveBench):
    """The simulator on a fresh pty and the node on its symlink, plus ROS helpers."""

    vendor = 'rd4'
    node_extra_args = (
        '-p', 'publish_rate_hz:=20.0',
        # the simulator is a Python process on a shared 2-core machine: a reply can be later
        # than the 0.1 s a real line needs (config/rd4.yaml), and no test is about that
        '-p', 'timeout_s:=0.3',
        '-p', 'drives.axis1.allow_raw_write:=true')   # the shipped params refuse raw writes

    def __init__(self, procs, ros, tmp_path, node_args=()):
        self.port = str(tmp_path / 'rd4.pty')
        self.storage = tmp_path / 'flash'
        super().__init__(procs, ros, node_args)

    def link_args(self):
        return ['-p', f'port:={self.port}']

    def sim_args(self):
        return ['-p', f'storage_dir:={self.storage}']

    def true_steps(self, drive, steps=None):
        """The simulated unit's position counter (rounded as Current position reports it);
        with `steps`: wait until it reads that (the topic lags the status by up to 50 ms)."""
        cond = (lambda m: True) if steps is None else (lambda m: round(m.data) == steps)
        return round(self.ros.wait_msg(self.true_topic(drive), cond,
                                       what=f'{drive} true position {steps}').data)

    def link_values(self):
        diag = self.ros.wait_msg('/diagnostics', lambda a: any(
            s.name.endswith('link') for s in a.status))
        link = next(s for s in diag.status if s.name.endswith('link'))
        return {kv.key: kv.value for kv in link.values}

    def settled(self, drive, period_s=0.3):
        """Wait until the true position stops changing (bounded)."""
        last = [None]

        def still():
            self.ros.latest.pop(self.true_topic(drive), None)   # a fresh sample each time
            now = self.ros.wait_msg(self.true_topic(drive)).data
            same, last[0] = now == last[0], now
            return same
        wait_for(still, 10.0, f'{drive} at rest', period_s)
        return round(last[0])


class Rd4LineTimingBench(Rd4Bench):
    """The simulator's line timing: replies come as late as on a real 19200-baud line."""

    def sim_args(self):
        return super().sim_args() + ['-p', 'line_timing:=true']


# -------------------------------------------------------------------------------- X-MIND K
XMIND_DRIVES = ('axis1', 'axis2', 'axis3')


class XmindBench(DriveBench):
    """A simulator and a node on a private pty symlink, plus helpers to reach them via ROS."""

    vendor = 'xmind_k'
    drives = XMIND_DRIVES
    node_extra_args = (
        '-p', 'publish_rate_hz:=20.0',
        '-p', 'timeout_s:=0.25',        # generous: the simulator shares 2 busy cores
        *[a for d in XMIND_DRIVES for a in ('-p', f'drives.{d}.busy_poll_period_s:=0.05')],
        '-p', 'drives.axis1.allow_raw_write:=true')   # the shipped params refuse raw writes
    keep_status = True

    def __init__(self, procs, ros, tmp_path, line_timing=False, node_args=()):
        self.link = str(tmp_path / 'xmind_k.tty')
        self.line_timing = line_timing
        super().__init__(procs, ros, node_args)

    def link_args(self):
        return ['-p', f'port:={self.link}']

    def sim_args(self):
        return ['-p', f'line_timing:={str(self.line_timing).lower()}']

    def set_param(self, name, value):
        (r,) = self.set_params((name, float(value)))
        assert r.successful, r.reason


# ----------------------------------------------------------------------------- Vector Step
class VectorRig(DriveBench):
    """Broker, simulator and node, plus helpers to reach them through ROS."""

    vendor = 'vector_step'
    first_sim_args = ('-p', 'drives.axis2.power_stage_blocked:=true')
    # The simulator is a Python process on a shared 2-core machine: an SDO answer can come later
    # than the 0.5 s of config/vector_step.yaml, and no test here is about that.
    node_extra_args = ('-p', 'timeout_s:=1.5',
                       '-p', 'drives.axis1.allow_raw_write:=true')   # shipped: refused

    def __init__(self, log_dir, node_args=()):
        self.storage = log_dir / 'eeprom'
        self.storage.mkdir()
        self.broker = SocketcandBroker(port=0)
        self.broker.start()
        self.procs, self.ros = Procs(log_dir), RosClient('vector_step_test')
        try:
            super().__init__(self.procs, self.ros, node_args)
        except BaseException:
            self.close()            # a failed start leaves no process, client or broker behind
            raise

    def link_args(self):
        return ['-p', f'can.port:={self.broker.port}']

    def sim_args(self):
        return ['-p', f'storage_dir:={self.storage}']

    def close(self):
        self.procs.kill_all()
        self.ros.close()
        self.broker.stop()

    def read(self, drive, address, data_type):
        return self.call(drive, 'read_register',
                         ReadRegister.Request(address=address, data_type=data_type),
                         ReadRegister)

    def write(self, drive, address, data_type, value=0, text=''):
        return self.call(drive, 'write_register',
                         WriteRegister.Request(address=address, data_type=data_type,
                                               value=value, text=text), WriteRegister)

    def idle(self, drive):
        """Leave a drive disabled and without fault for the next test."""
        st = self.status(drive)
        if st.fault:
            self.inject(drive, 'clear_fault')
            assert self.call(drive, 'fault_reset').success
        self.enable(drive, False)
        self.status(drive, lambda m: not m.enabled and not m.moving, what=f'{drive} idle')


# ----------------------------------------------------------------------------- any vendor
def make_bench(vendor, procs, ros, tmp_path, node_args=(), node_env=None):
    """The bench of `vendor` (a vendor key), its processes ended with the `procs` fixture's;
    node_env: the node process's further environment."""
    if vendor == 'vector_step':
        assert node_env is None, 'the Vector Step rig starts its node by itself'
        rig = VectorRig(tmp_path, node_args=node_args)
        procs.append(_Closer(rig))
        return rig
    bench = {'xplus_mt': XplusBench, 'rd4': Rd4Bench, 'xmind_k': XmindBench}[vendor]
    if node_env:
        bench = type(bench.__name__, (bench,), {'node_env': node_env})
    return bench(procs, ros, tmp_path, node_args=node_args)


class _Closer:
    """Lets the procs fixture end a Vector Step rig (broker, processes, its ROS client)."""

    def __init__(self, rig):
        self.rig = rig

    def kill(self):
        self.rig.close()
