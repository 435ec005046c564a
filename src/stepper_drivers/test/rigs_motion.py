"""Plans for the trajectory follower's tests (motion/test_trajectory.py, motion/test_follow.py),
no bus."""

from stepper_drivers.motion.trajectory import Trajectory, build


def quintic_line(joints, travel_steps, duration_s, dt_s) -> Trajectory:
    """MoveIt-like: a straight line from 0 with quintic timing, each joint `travel_steps` of
    it, positions, velocities and accelerations every dt_s, the start at t=0."""
    n = int(round(duration_s / dt_s))
    times, pos, vel, acc = [], [], [], []
    for k in range(n + 1):
        s = k / n
        f = 10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5
        df = (30 * s ** 2 - 60 * s ** 3 + 30 * s ** 4) / duration_s
        ddf = (60 * s - 180 * s ** 2 + 120 * s ** 3) / duration_s ** 2
        times.append(k * dt_s)
        pos.append([f * d for d in travel_steps])
        vel.append([df * d for d in travel_steps])
        acc.append([ddf * d for d in travel_steps])
    return build(list(joints), times, pos, list(joints), vel, acc)
