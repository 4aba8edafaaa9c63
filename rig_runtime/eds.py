"""The drives' object dictionary from the config's EDS file (``devices.can.eds``), parsed once
per process and file version: the runtime's drive driver (``drivers.canopen402``) and the
simulated drives (``sim_backend.virtual_drive``) of every run of a process share it instead
of parsing the file per drive and run (a parse is ~3–10 ms; a run had eight).

Shared read-only: the driver only looks objects up to encode and decode SDO values,
canopen's ``RemoteNode`` and ``LocalNode`` keep the dictionary as given (a ``LocalNode``
stores what is written to it in a store of its own); tests/test_canopen_eds.py checks that
two start-ups leave it bit-identical.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path


def object_dictionary(path: str | Path, node_id: int):
    """The object dictionary of the EDS at ``path`` for node ``node_id`` (its ``$NODEID``
    entries resolved), cached by the resolved path, its modification time and size (an
    edited file is parsed again) and the node id. OSError or a parse error: raised, nothing
    cached."""
    p = Path(path).resolve()
    st = os.stat(p)
    return _parse(str(p), st.st_mtime_ns, st.st_size, node_id)


@functools.lru_cache(maxsize=64)
def _parse(path: str, mtime_ns: int, size: int, node_id: int):
    import canopen  # heavy; only a blocking start-up needs it
    return canopen.import_od(path, node_id)
