"""ros2_control's topic hardware interface as a test sends its commands.

`PluginStream` publishes exactly what `joint_state_topic_hardware_interface/JointStateTopicSystem`
(ros-controls/topic_based_hardware_interfaces 1.1.0) sends on its `joint_commands_topic`: on every
controller_manager update (UPDATE_HZ) one sensor_msgs/JointState stamped now, `name` = every
joint of its `<ros2_control>` block in URDF order, `position[]` for the joints with a position
command interface (or `velocity[]` for velocity ones), NaN before a controller writes; QoS
depth 1, reliable. `quintic` and
RAMP_RAD, RAMP_S make the ramp the tests stream.
"""

from __future__ import annotations

import math
import threading
import time

from rosharness import wait_for

UPDATE_HZ = 100.0             # controller_manager's update_rate
RAMP_RAD, RAMP_S = 1.0, 2.0


def quintic(t: float) -> float:
    """The minimum-jerk ramp 0 -> 1 over 0..1 (rest to rest)."""
    t = min(max(t, 0.0), 1.0)
    return t ** 3 * (10.0 - 15.0 * t + 6.0 * t * t)


class PluginStream:
    """The plugin's command publisher: a thread that publishes `make(now)` (positions or
    velocities for every joint of the block) at UPDATE_HZ on an absolute schedule, and records
    (time.monotonic(), values) of each message sent."""

    def __init__(self, ros, joints: list[str]):
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState
        self.ros, self.joints, self.JointState = ros, joints, JointState
        qos = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                         reliability=ReliabilityPolicy.RELIABLE)      # rclcpp::QoS(1)
        self.pub = ros.node.create_publisher(JointState, '/joint_command', qos)
        wait_for(lambda: self.pub.get_subscription_count() > 0, 10.0, 'the node subscribed')
        self.sent: list[tuple[float, str, list[float]]] = []
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    def run(self, field: str, make, duration_s: float) -> None:
        """Publish `field` (position or velocity) = make(seconds since start) for duration_s."""
        self._stop.clear()
        t0 = time.monotonic()
        n = 0
        while not self._stop.is_set():
            now = time.monotonic()
            if now - t0 > duration_s:
                break
            values = [float(v) for v in make(now - t0)]
            msg = self.JointState(name=list(self.joints))
            msg.header.stamp = self.ros.node.get_clock().now().to_msg()
            setattr(msg, field, values)
            self.pub.publish(msg)
            self.sent.append((now, field, values))
            n += 1
            self._stop.wait(max(0.0, t0 + n / UPDATE_HZ - time.monotonic()))

    def start(self, field: str, make, duration_s: float = math.inf) -> None:
        self._thread = threading.Thread(target=self.run, args=(field, make, duration_s))
        self._thread.start()

    def stop(self) -> float:
        """End a stream started with start(); the time of its last message."""
        self._stop.set()
        self._thread.join()
        return self.sent[-1][0]
