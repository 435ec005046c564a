"""The Vector Step driver's parameters for a test without the node (vendors/vector_step/
test_vector_step_drive.py and the tests that put a Vector Step on a CAN bus: owner/,
vendors/test_malformed_answers.py)."""

from stepper_drivers.vendors import vector_step as vs


def params(**over):
    p = {spec.name: spec.default for spec in vs.PARAMS}
    p.update({'timeout_s': 0.5, 'steps_per_rev': 3200.0, 'homing.method': 35,
              'heartbeat_timeout_s': 0.5})
    p.update(over)
    return p
