"""Pure functions of a configuration, computed once per process per configuration.

The stability gate, the coupled analysis (``app/preflight.py``) and the drive-outage table
(``loop.py``) depend on the config alone and cost tens to hundreds of milliseconds for a
vehicle config; a run asks for the gate twice (``rig check``'s checks and the runner's
own), and a warm worker (a campaign's, a test session's) runs the same config again and again. The key is the arguments' ``repr``:
a config is a tree of frozen dataclasses whose repr shows every field (none is hidden), so
two configs share a result only if every value is the same. A call that raises is not kept
(it raises again the next time). Callers treat a result as read-only (the analyses return
frozen dataclasses and tuples).
"""

from __future__ import annotations

import functools
import threading
from collections import OrderedDict
from typing import Any, Callable

MAX_KEPT = 32           # configs kept per function, the least recently used dropped


def by_config(fn: Callable[..., Any], maxsize: int = MAX_KEPT) -> Callable[..., Any]:
    """``fn`` remembered by the ``repr`` of its positional arguments."""
    kept: OrderedDict[str, Any] = OrderedDict()
    lock = threading.Lock()

    @functools.wraps(fn)
    def call(*args: Any) -> Any:
        key = repr(args)
        with lock:
            if key in kept:
                kept.move_to_end(key)
                return kept[key]
        value = fn(*args)
        with lock:
            kept[key] = value
            while len(kept) > maxsize:
                kept.popitem(last=False)
        return value

    call.cache_clear = kept.clear       # type: ignore[attr-defined]
    return call
