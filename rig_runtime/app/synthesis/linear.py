"""The linear criteria of a synthesis: numbers of the analysis ``rig tune`` and the stability
gate make of a config, through their public functions only (:func:`rig_runtime.analysis.tune`,
:func:`~rig_runtime.analysis.tune_failures`, :func:`rig_runtime.coupled.analyse`), so a law
described once there is judged here the same way. Every criterion is an upper bound."""

from __future__ import annotations

from typing import Optional

import numpy as np

LINEAR: dict[str, str] = {
    "spectral_radius": "largest |z| of the sampled closed loop as implemented, over the analysed speeds and every "
                       "D_min/D_max combination (< 1: stable)",
    "max_pole_real_every_D_1_s": "largest real part of the continuous coupled loop's poles over the analysed speeds "
                                 "and every D_min/D_max combination, 1/s (a vehicle config)",
    "max_pole_real_1_s": "largest real part of the continuous closed loop's poles, 1/s (the coupled loop over the "
                         "analysed speeds on a vehicle config; (19) on the paper's set-up)",
    "worst_case_input_per_term_A": "Sec. 5.2.3: the larger of K_P,psi psi_design and K_D,psi psi_rate_design, A",
    "worst_case_input_sum_A": "Sec. 5.2.3: their sum (against the saturation), A",
    "worst_case_psi_ref_rad": "Sec. 5.2.3: K_P,y y_design, rad",
    "slowest_outer_eigenvalue": "Sec. 5.2.3: the slowest eigenvalue of the outer loop (17), 1/s",
    "design_checks_failed": "how many of rig tune's checks fail (0: rig tune exits 0 for this case's plant)",
}
_CHECKS = {"worst_case_input_per_term_A": "worst_case_input_per_term_A",
           "worst_case_input_sum_A": "input_within_saturation",
           "worst_case_psi_ref_rad": "worst_case_psi_ref_rad",
           "slowest_outer_eigenvalue": "slowest_outer_eigenvalue"}


def linear_criteria(cfg, names) -> dict[str, Optional[float]]:
    """The named linear criteria of ``cfg`` (None where the analysis cannot compute one)."""
    from rig_runtime import analysis, coupled
    out: dict[str, Optional[float]] = dict.fromkeys(names)
    try:
        with np.errstate(all="ignore"):
            r = analysis.tune(cfg)
            vehicle = coupled.applies(cfg)
            co = (coupled.analyse(cfg) if {"spectral_radius", "max_pole_real_1_s", "max_pole_real_every_D_1_s"} & set(names)
                  else None)
            for n in names:
                if n in _CHECKS:
                    out[n] = float(r.checks[_CHECKS[n]]["value"])
                elif n == "design_checks_failed":
                    out[n] = float(len(analysis.tune_failures(cfg, r)))
                elif n == "spectral_radius":
                    out[n] = max(max(p.spectral_radius, p.ungated_radius or 0.0) for p in co.points)
                elif n == "max_pole_real_every_D_1_s":
                    out[n] = max(p.rightmost.real for p in co.points) if vehicle else None
                elif n == "max_pole_real_1_s":
                    out[n] = (max(p.least_damped.real for p in co.points) if vehicle
                              else float(np.max(np.real(r.closed_loop))))
    except (ArithmeticError, ValueError):       # numbers so extreme the matrices overflow: undefined
        pass
    return {k: (v if v is None or np.isfinite(v) else None) for k, v in out.items()}
