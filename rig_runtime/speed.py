"""The measured roller speed v̂: a stage of the cycle.

Each carrier on the rollers rolls its two wheels at the roller's surface speed (their
difference Δω is the carrier's yaw work, (3)/(4); their mean is v/r0), so the speed of a
carrier in contact is ``r0 · (ω_left + ω_right)/2`` of that carrier, sign included (the
running direction). Each carrier's speed is low-passed (first order at
``schedule.v_filter_hz``, else ``DEFAULT_FILTER_HZ``); v̂ is the mean of the filtered speeds of
the carriers in contact. The supervisor judges them (``safety.SPEED_RULES``: |v̂| within the
hardware's v_max, the carriers agreeing); the gain schedule uses v̂.

Which carriers are in contact is a config fact, answered in one place: ``Plant.in_contact``.
A wheel value that is not finite (no sample yet, a lost drive: the channel rules judge it)
leaves that carrier's filtered speed where it was. Scalar arithmetic on preallocated lists:
this runs every cycle.
"""

from __future__ import annotations

import math
from operator import itemgetter
from typing import Mapping, Sequence

from .config import Plant, RigConfig
from .lanes import CARRIER_WHEELS

DEFAULT_FILTER_HZ = 2.0      # Hz: the schedule's default v_filter_hz (config.Schedule)


def columns(plant: Plant) -> list[str]:
    """The log's columns of this stage: v̂, then each carrier in contact's speed (m/s)."""
    return ["v_meas"] + [f"{c}_v" for c in plant.in_contact]


def filter_hz(cfg: RigConfig) -> float:
    sch = cfg.controller.schedule
    return sch.v_filter_hz if sch is not None else DEFAULT_FILTER_HZ


class SpeedEstimate:
    """Per cycle ``update(values)`` (the channel values by name: wheel speeds in rad/s);
    afterwards ``v_hat`` (m/s) and ``v[i]`` the filtered speed of ``carriers[i]``."""

    __slots__ = ("carriers", "_wheels", "_r0", "_alpha", "v", "v_hat", "_seeded", "_n")

    def __init__(self, carriers: Sequence[str], r0: Mapping[str, float], h: float, f_hz: float):
        self.carriers = tuple(carriers)
        # each carrier's (left, right) wheel speeds by name, resolved into one getter each here
        self._wheels = [itemgetter(*CARRIER_WHEELS[c]) for c in self.carriers]
        self._r0 = [0.5 * r0[c] for c in self.carriers]     # r0/2: (ω_l + ω_r) · r0/2
        self._alpha = 1.0 - math.exp(-2.0 * math.pi * f_hz * h)
        self._n = len(self.carriers)
        self.v = [math.nan] * self._n
        self._seeded = [False] * self._n
        self.v_hat = math.nan

    @classmethod
    def from_config(cls, cfg: RigConfig) -> "SpeedEstimate":
        carriers = cfg.plant.in_contact
        return cls(carriers, {c: cfg.plant.carrier(c).r0 for c in carriers}, cfg.controller.h, filter_hz(cfg))

    def update(self, values: Mapping[str, float]) -> float:
        """This cycle's wheel speeds -> v̂ (m/s; NaN until every carrier in contact had a
        finite speed)."""
        a = self._alpha
        v, seeded = self.v, self._seeded
        total = 0.0
        wheels, r0 = self._wheels, self._r0
        for i in range(self._n):
            left, right = wheels[i](values)
            raw = (left + right) * r0[i]
            if raw - raw == 0.0:            # finite
                if seeded[i]:
                    v[i] += a * (raw - v[i])
                else:
                    v[i] = raw
                    seeded[i] = True
            total += v[i]
        self.v_hat = total / self._n if self._n else math.nan
        return self.v_hat

    def log_values(self) -> list[float]:
        """The values of :func:`columns`."""
        return [self.v_hat, *self.v]
