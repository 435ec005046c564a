"""How a drive runs one move, as a function of time: the symmetric trapezoid of a rest-to-rest
move (`along`, `along_velocity`) and the general profile of a move taken from any speed
(`motion_state`: the drives' profile generator, as the simulators', stepper_sim.core.motion).

Plain arithmetic on floats: no trajectory types and no planning (trajectory.py plans the
segments, continuous.py the velocity-continuous moves; both evaluate their moves here).
"""

from __future__ import annotations

import math


def _pieces(x0: float, u0: float, target: float, vmax: float, a: float, dec: float
            ) -> list[tuple[float, float, float]]:
    """(duration, velocity at its start, acceleration) of each piece of a drive's move from x0
    at velocity u0 to `target` with cruise vmax and ramps a (inf: start-stop): a profile
    generator's, as the simulators' (stepper_sim.core.motion): too fast to stop in time, or moving
    away, it stops first; then it ramps to vmax (or less: a triangle), cruises, and brakes to
    rest on the target; speeding up at a, slowing down at dec."""
    d = target - x0
    if d == 0.0 and u0 == 0.0:
        return []
    s = (d > 0) - (d < 0) or -((u0 > 0) - (u0 < 0))
    u = u0 * s
    ia = 0.0 if math.isinf(a) else 0.5 / a
    idc = 0.0 if math.isinf(dec) else 0.5 / dec
    distance = abs(d)
    if u < 0.0 or u * u * idc > distance * (1.0 + 1e-12) + 1e-9:
        back = (u0 > 0) - (u0 < 0)
        stop = [] if math.isinf(dec) else [(abs(u0) / dec, u0, -back * dec)]
        return stop + _pieces(x0 + back * u0 * u0 * idc, 0.0, target, vmax, a, dec)
    out = []
    if u > vmax:
        if not math.isinf(dec):
            out.append(((u - vmax) / dec, s * u, -s * dec))
        distance -= (u * u - vmax * vmax) * idc
        u = vp = vmax
    elif ia + idc == 0.0:
        vp = vmax
    else:
        vp = max(u, min(vmax, math.sqrt(max((distance + u * u * ia) / (ia + idc), 0.0))))
        if vp > u and not math.isinf(a):
            out.append(((vp - u) / a, s * u, s * a))
        distance -= (vp * vp - u * u) * ia
    cruise = max(distance - vp * vp * idc, 0.0)
    if cruise > 0.0 and vp > 0.0:
        out.append((cruise / vp, s * vp, 0.0))
    if not math.isinf(dec) and vp > 0.0:
        out.append((vp / dec, s * vp, -s * dec))
    return out


def motion_state(x0: float, u0: float, target: float, vmax: float, a: float, tau_s: float,
                 dec: float | None = None) -> tuple[float, float]:
    """(position, velocity) tau_s after a drive at x0 moving at u0 (signed) took a move to
    `target` with cruise vmax, acceleration a and deceleration dec (None: a) (_pieces); at rest
    on the target after the end."""
    x, t = x0, 0.0
    if tau_s <= 0:
        return x0, u0
    for dur, v, acc in _pieces(x0, u0, target, vmax, a, a if dec is None else dec):
        if tau_s < t + dur:
            tau = tau_s - t
            return x + v * tau + 0.5 * acc * tau * tau, v + acc * tau
        x += v * dur + 0.5 * acc * dur * dur
        t += dur
    return target, 0.0


def ramps(a: float, v: float, start_stop_steps_s: float) -> float:
    """The acceleration a drive runs a move at cruise v with: inf (start-stop, no ramps) at or
    below its start-stop velocity (X-PLUS MT §13 "Motion Profiles"), else a."""
    return math.inf if v <= start_stop_steps_s else a


def along(p0: float, p1: float, v: float, a: float, tau: float) -> float:
    """Position tau into a symmetric trapezoid from p0 to p1 with cruise v and ramps a (inf:
    start-stop); p1 once it has arrived."""
    d = abs(p1 - p0)
    if d == 0 or v <= 0 or a <= 0:
        return p1
    sign = 1.0 if p1 > p0 else -1.0
    t_ramp = 0.0 if math.isinf(a) else v / a
    total = d / v + t_ramp
    if tau <= 0:
        return p0
    if tau >= total:
        return p1
    if t_ramp == 0.0:
        s = v * tau
    elif tau < t_ramp:
        s = 0.5 * a * tau * tau
    elif tau < total - t_ramp:
        s = 0.5 * a * t_ramp * t_ramp + v * (tau - t_ramp)
    else:
        s = d - 0.5 * a * (total - tau) ** 2
    return p0 + sign * min(s, d)


def along_velocity(p0: float, p1: float, v: float, a: float, tau: float) -> float:
    """Velocity tau into the trapezoid of `along` (signed, steps/s)."""
    d = abs(p1 - p0)
    if d == 0 or v <= 0 or a <= 0 or tau <= 0:
        return 0.0
    sign = 1.0 if p1 > p0 else -1.0
    t_ramp = 0.0 if math.isinf(a) else v / a
    total = d / v + t_ramp
    if tau >= total:
        return 0.0
    if t_ramp == 0.0:
        return sign * v
    if tau < t_ramp:
        return sign * a * tau
    if tau < total - t_ramp:
        return sign * v
    return sign * a * (total - tau)
