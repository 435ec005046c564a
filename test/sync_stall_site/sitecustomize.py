"""A node process whose bus owner blocks with the GIL held, for test_vector_step_sync (never
installed): with STEPPER_TEST_GIL_STALL=<seconds>,<every_s> in its environment, a publish of a
drive's status holds the GIL for <seconds>, at most once every <every_s>. rclpy's publish calls
rcl_publish with the GIL held, and on a loaded two-core machine one waited 120-330 ms inside
Fast DDS; here it is made longer than the drives' 0x1006 time. ctypes.PyDLL calls usleep without
releasing the GIL. Each stall prints a line ('GIL stall') to the node's log. Python imports this
module at start-up when its folder leads PYTHONPATH."""

import os

_STALL = os.environ.get('STEPPER_TEST_GIL_STALL')
if _STALL:
    import ctypes
    import sys
    import time

    import rclpy.publisher

    _seconds, _every_s = (float(x) for x in _STALL.split(','))
    _publish = rclpy.publisher.Publisher.publish
    _usleep = ctypes.PyDLL(None).usleep
    _last = [-1e9]

    def _stalling_publish(self, msg):
        now = time.monotonic()
        if self.topic_name.endswith('/status') and now - _last[0] >= _every_s:
            _last[0] = now
            print(f'GIL stall {_seconds:g} s in a publish of {self.topic_name}',
                  file=sys.stderr, flush=True)
            _usleep(int(_seconds * 1e6))
        return _publish(self, msg)

    rclpy.publisher.Publisher.publish = _stalling_publish
