"""What test_safety_ros injects into a node process (never installed). Python imports this
module at start-up when its folder leads PYTHONPATH; the environment says what to inject:
- STEPPER_TEST_OWNER_FAULT=<path>: every bus owner of the process raises from its work loop once
  <path> exists, as an internal error of the owner would.
- STEPPER_TEST_JOB_TIMEOUT_S=<s>: the services' JOB_TIMEOUT_S (node_services.py).
- STEPPER_TEST_HELD_SAVE=<dir>: every save_params job, once it ran, creates <dir>/started and
  goes on (step-wise: the bus owner is not held) until <dir>/release exists, as a save that
  takes long.
"""

import os

_TRIGGER = os.environ.get('STEPPER_TEST_OWNER_FAULT')
if _TRIGGER:
    from stepper_drivers import owner

    _work_once = owner.BusOwner._work_once

    def _failing_work_once(self):
        if os.path.exists(_TRIGGER):
            raise RuntimeError(f'injected owner fault ({_TRIGGER} exists)')
        return _work_once(self)

    owner.BusOwner._work_once = _failing_work_once

_JOB_TIMEOUT_S = os.environ.get('STEPPER_TEST_JOB_TIMEOUT_S')
if _JOB_TIMEOUT_S:
    from stepper_drivers.ros import services as node_services

    node_services.JOB_TIMEOUT_S = float(_JOB_TIMEOUT_S)

_HELD_SAVE = os.environ.get('STEPPER_TEST_HELD_SAVE')
if _HELD_SAVE:
    from stepper_drivers import owner
    from stepper_drivers.owner.commands import Command

    _maintenance = Command.maintenance.__func__

    def _held(fn):
        def steps():
            result = yield from owner._steps(fn())
            open(os.path.join(_HELD_SAVE, 'started'), 'w').close()
            while not os.path.exists(os.path.join(_HELD_SAVE, 'release')):
                yield 0.05
            return result
        return steps

    def _maintenance_held(cls, fn, label):
        return _maintenance(cls, _held(fn) if label == 'save_params' else fn, label)

    Command.maintenance = classmethod(_maintenance_held)
