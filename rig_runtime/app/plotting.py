"""matplotlib for the application's figures (reports, identification plots): the
non-interactive backend, and one clear error where the optional extra is not installed."""

from __future__ import annotations


def pyplot():
    """``matplotlib.pyplot`` on the Agg backend; RuntimeError naming the extra if missing."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as e:  # pragma: no cover - depends on the install
        raise RuntimeError("plots need matplotlib: pip install 'rig-runtime[plot]'") from e
    return plt
