"""A bug injected into a node process for test_safety_ros (never installed): with
STEPPER_TEST_OWNER_FAULT=<path> in its environment, every bus owner of the process raises from
its work loop once <path> exists, as an internal error of the owner would. Python imports this
module at start-up when its folder leads PYTHONPATH."""

import os

_TRIGGER = os.environ.get('STEPPER_TEST_OWNER_FAULT')
if _TRIGGER:
    from stepper_drivers import supervisor

    _work_once = supervisor.BusSupervisor._work_once

    def _failing_work_once(self):
        if os.path.exists(_TRIGGER):
            raise RuntimeError(f'injected owner fault ({_TRIGGER} exists)')
        return _work_once(self)

    supervisor.BusSupervisor._work_once = _failing_work_once
