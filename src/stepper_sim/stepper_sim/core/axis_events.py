"""The names of an axis' inputs and events, and `AxisEvent`: what a `SimAxis` (core/axis.py)
hands its listeners and what a homing procedure (core/homing.py) waits for.

Only the contract between the two: no motion, no switch logic, no homing.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

HOME = 'home'
LIMIT_NEG = 'limit_neg'
LIMIT_POS = 'limit_pos'
INDEX = 'index'
TARGET_REACHED = 'target_reached'
LIMITS = (LIMIT_NEG, LIMIT_POS)


@dataclasses.dataclass(frozen=True)
class AxisEvent:
    """Something that happened on the axis during update() (or at set_input()).

    name: an input name ('home', 'limit_neg', 'limit_pos', vendor inputs), 'index', or
    'target_reached' (the motion plan attained its final state: at rest, or at speed).
    raw_position_steps is exact for a crossing: the switch edge or index position itself.
    """

    name: str
    active: bool
    time_s: float
    position_steps: float
    raw_position_steps: float
    direction: int
    forced: bool = False


Listener = Callable[[AxisEvent], None]
