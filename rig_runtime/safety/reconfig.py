"""Reconfiguration keyed by device: isolate a device the run can do without, let the
carriers it serves go on without it (absorb), readmit it when it is fit again.

One :class:`Reconfiguration` per kind of device loss: lateral lasers (the carriers they
feed run DEGRADED on the observer's ŷ) and drives (the carrier runs RECONFIGURED on its
remaining wheels). It keeps only the bookkeeping — which device is isolated since when,
whether it may come back, which carriers are absorbing a loss since when, and the intervals
for the summary; what may be isolated and when a device is fit again are the supervisor's
rules."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Mapping, Sequence


@dataclass(slots=True)
class Isolation:
    """One isolated device: since when, the consecutive cycles it has been fit and agreeing
    (for readmission), and whether it may be readmitted at all (a device found lying is not)."""
    since: float
    agreeing: int
    readmit: bool


class Reconfiguration:
    """``feeds``: device -> the carriers whose loop it serves. ``mode``: the state name the
    carriers run in while absorbing (DEGRADED, RECONFIGURED); ``device_key``: the summary's
    key for the device (``laser`` for DEGRADED, as the summary has always said, ``device``
    for RECONFIGURED)."""

    def __init__(self, mode: str, feeds: Mapping[str, Sequence[str]], device_key: str = "device"):
        self.mode = mode
        self.feeds = {d: tuple(cs) for d, cs in feeds.items()}
        self.device_key = device_key
        self.isolated: dict[str, Isolation] = {}
        self.since: dict[str, float] = {}         # carrier -> absorbing a loss since t
        self.log: list[dict] = []                 # the intervals, for the summary

    def carriers_of(self, devices: Sequence[str]) -> list[str]:
        """The carriers any of ``devices`` serves, in the order the feeds were given."""
        out: list[str] = []
        for d in devices:
            for c in self.feeds.get(d, ()):
                if c not in out:
                    out.append(c)
        return out

    def isolate(self, t: float, devices: Sequence[str], check: str, readmit: bool,
                extra: Mapping | None = None) -> list[str]:
        """Isolate ``devices``; every carrier they serve absorbs the loss (an interval opens
        for each not already absorbing one). Returns those carriers (empty: nothing here
        serves them, nothing is isolated)."""
        carriers = self.carriers_of(devices)
        if not carriers:
            return []
        for d in devices:
            self.isolated[d] = Isolation(t, 0, readmit)
        name = "/".join(devices)
        for car in carriers:
            if car not in self.since:
                self.since[car] = t
                self.log.append({"carrier": car, self.device_key: name, "check": check, "t_start": t,
                                 "t_end": None, "end": "", **(extra or {})})
            else:                   # a further loss in the carrier's open interval: named there too
                for e in self.log:
                    if e["carrier"] == car and e["t_end"] is None:
                        named = e[self.device_key].split("/")
                        e[self.device_key] = "/".join(named + [d for d in devices if d not in named])
        return carriers

    def isolated_any(self, devices: Sequence[str]) -> bool:
        iso = self.isolated
        return bool(iso) and any(d in iso for d in devices)

    def readmit(self, t: float, need: int, fit: Callable[[str], bool]) -> list[tuple[str, list[str]]]:
        """Count each readmittable isolated device's consecutive fit cycles (``fit(device)``);
        readmit those fit for ``need`` cycles. Returns (device, the carriers whose absorption
        ended with it) per device readmitted."""
        out = []
        for d, iso in list(self.isolated.items()):
            if not iso.readmit:
                continue
            iso.agreeing = iso.agreeing + 1 if fit(d) else 0
            if iso.agreeing < need:
                continue
            del self.isolated[d]
            ended = []
            for car in list(self.since):
                if not any(x in self.isolated for x, cs in self.feeds.items() if car in cs):
                    del self.since[car]
                    self._end(car, t, f"{d} readmitted")
                    ended.append(car)
            out.append((d, ended))
        return out

    def _end(self, carrier: str, t: float, how: str) -> None:
        for e in self.log:
            if e["carrier"] == carrier and e["t_end"] is None:
                e["t_end"], e["end"] = t, how

    def close(self, t: float, how: str) -> None:
        """The run ends while absorbing: close every open interval and forget the isolation."""
        for e in self.log:
            if e["t_end"] is None:
                e["t_end"], e["end"] = t, how
        self.since.clear()
        self.isolated.clear()
