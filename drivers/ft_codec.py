"""FT 300 register codec: holding registers 180–185 <-> :class:`Wrench`.

Fx, Fy, Fz are INT16 in 0.01 N per count, Mx, My, Mz INT16 in 0.001 N·m per count;
Modbus delivers them as unsigned 0..65535. A register at an INT16 limit (+32767, −32768) is
a saturated sensor, not a measurement: :attr:`Wrench.saturation` says which axes (the one
rule; the driver's health turns INVALID on it). Written once for both ends of the wire: the
driver decodes (:func:`wrench_from_registers`), the simulated sensors
(``sim_backend.virtual_ft``) encode (:func:`registers_from_wrench`). No I/O here, and no
import of the driver: the simulator imports this module, not the driver.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from typing import NamedTuple

__all__ = [
    "REG_START", "REG_COUNT", "DEFAULT_UNIT_ID", "FORCE_COUNTS_PER_N", "TORQUE_COUNTS_PER_NM",
    "INT16_MIN", "INT16_MAX", "AXES", "Wrench", "wrench_from_registers", "registers_from_wrench",
]

REG_START = 180                 # holding register of Fx (0-based protocol address)
REG_COUNT = 6                   # Fx, Fy, Fz, Mx, My, Mz
DEFAULT_UNIT_ID = 9
FORCE_COUNTS_PER_N = 100.0      # 1 count = 0.01 N
TORQUE_COUNTS_PER_NM = 1000.0   # 1 count = 0.001 N·m
INT16_MIN, INT16_MAX = -32768, 32767
_SCALES = (FORCE_COUNTS_PER_N,) * 3 + (TORQUE_COUNTS_PER_NM,) * 3
AXES = ("Fx", "Fy", "Fz", "Mx", "My", "Mz")
# per axis: its name, the values an INT16 limit decodes to (lowest, highest), how a value is shown
_AXIS_LIMITS = tuple((a, INT16_MIN / s, INT16_MAX / s, show) for a, s, show in
                     zip(AXES, _SCALES, ("{:+.2f} N",) * 3 + ("{:+.3f} N·m",) * 3))
_U16x6, _I16x6 = struct.Struct("=6H"), struct.Struct("=6h")   # two's complement by reinterpretation


class Wrench(NamedTuple):
    """Forces (N) and moments (N·m) in the sensor frame. Immutable; a named tuple rather
    than a frozen dataclass because one is made per sample at both ends of the wire (a
    third of the cost to build)."""

    fx: float = 0.0
    fy: float = 0.0
    fz: float = 0.0
    mx: float = 0.0
    my: float = 0.0
    mz: float = 0.0

    def as_tuple(self) -> tuple[float, float, float, float, float, float]:
        return (self.fx, self.fy, self.fz, self.mx, self.my, self.mz)

    @property
    def saturation(self) -> str:
        """'' while every axis is inside the register format's range; else which axes sit
        at an INT16 limit (what a register of +32767 or −32768 decodes to, or beyond), e.g.
        ``"Fz saturated at +327.67 N (int16 limit)"``. Computed from the values, so it
        survives any hand-off that carries the six floats (the poll process's shared memory)."""
        out = None                      # a loop, not a comprehension: no frame per call (one per sample)
        for v, (a, lo, hi, fmt) in zip(self, _AXIS_LIMITS):      # fx, fy, fz, mx, my, mz
            if v >= hi or v <= lo:
                if out is None:
                    out = []
                out.append(f"{a} saturated at {fmt.format(v)}")
        return ", ".join(out) + " (int16 limit)" if out else ""


def wrench_from_registers(regs: Sequence[int]) -> Wrench:
    """Decode holding registers 180..185 (unsigned integers 0..65535) into a :class:`Wrench`;
    ValueError for another count or a value that is not such an integer. A register at an
    INT16 limit decodes to the limit value, flagged by the result's :attr:`Wrench.saturation`."""
    if len(regs) != REG_COUNT:
        raise ValueError(f"expected {REG_COUNT} registers, got {len(regs)}")
    try:
        fx, fy, fz, mx, my, mz = _I16x6.unpack(_U16x6.pack(*regs))
    except struct.error as exc:
        raise ValueError(f"registers must be integers 0..65535, got {list(regs)}") from exc
    return Wrench(fx / FORCE_COUNTS_PER_N, fy / FORCE_COUNTS_PER_N, fz / FORCE_COUNTS_PER_N,
                  mx / TORQUE_COUNTS_PER_NM, my / TORQUE_COUNTS_PER_NM, mz / TORQUE_COUNTS_PER_NM)


def registers_from_wrench(w: Wrench) -> list[int]:
    """Encode a :class:`Wrench` as the six registers a sensor would hold (rounded to the
    nearest count, saturated at the INT16 range; NaN is refused)."""
    out = []
    for value, counts_per_unit in zip(w, _SCALES):       # fx, fy, fz, mx, my, mz
        counts = value * counts_per_unit
        if counts >= INT16_MAX:
            n = INT16_MAX
        elif counts <= INT16_MIN:
            n = INT16_MIN
        elif counts != counts:
            raise ValueError("NaN cannot be encoded as a register")
        else:
            n = round(counts)
        out.append(n & 0xFFFF)        # unsigned 16-bit register: two's complement
    return out
