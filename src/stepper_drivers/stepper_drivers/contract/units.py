"""Unit conversion between the ROS side (rad or m, REP-103) and the drive side (steps).

The one place where steps meet SI units. Parameters (from the params file, per drive):
  steps_per_rev  motor steps (micro-steps) per motor revolution
  gear_ratio     motor revolutions per output revolution (1.0: direct drive)
  unit           'rad' for a rotary joint, 'm' for a linear axis
  lead_m         linear travel per output revolution (screw lead), only for unit 'm'
"""

from __future__ import annotations

import dataclasses
import math

UNITS = ('rad', 'm')


@dataclasses.dataclass(frozen=True)
class UnitConversion:
    steps_per_rev: float
    gear_ratio: float = 1.0
    unit: str = 'rad'
    lead_m: float = 0.0

    def __post_init__(self):
        if self.unit not in UNITS:
            raise ValueError(f"unit: {self.unit!r} is not allowed (allowed: 'rad', 'm')")
        if not self.steps_per_rev > 0:
            raise ValueError(f'steps_per_rev: {self.steps_per_rev} must be > 0')
        if not self.gear_ratio > 0:
            raise ValueError(f'gear_ratio: {self.gear_ratio} must be > 0')
        if self.unit == 'm' and not self.lead_m > 0:
            raise ValueError(f'lead_m: {self.lead_m} must be > 0 for a linear axis (unit: m)')

    @property
    def steps_per_unit(self) -> float:
        """Motor steps per rad (rotary) or per m (linear) at the joint."""
        steps_per_output_rev = self.steps_per_rev * self.gear_ratio
        if self.unit == 'rad':
            return steps_per_output_rev / (2.0 * math.pi)
        return steps_per_output_rev / self.lead_m

    def to_steps(self, value: float) -> float:
        """Joint units (rad, m, or their rates) to steps (or steps/s, steps/s^2)."""
        return value * self.steps_per_unit

    def to_steps_int(self, value: float) -> int:
        return int(round(self.to_steps(value)))

    def from_steps(self, steps: float) -> float:
        return steps / self.steps_per_unit
