"""The drives' EDS is parsed once per process and file version, and the shared object
dictionary is left as it was by a start-up of the driver against the simulated drives, which
share it too (rig_runtime.eds.object_dictionary)."""

from __future__ import annotations

import os
import pickle
import shutil
import uuid

import can
import canopen

from drivers import canopen402
from drivers.canopen402 import DriveBus
from rig_runtime import eds
from rig_runtime.eds import object_dictionary
from sim_backend import virtual_drive
from rig_runtime.config import WHEELS, CanBus, Drive, resolve_config_path
from sim_backend.virtual_drive import VirtualDriveSet

EDS = resolve_config_path("irdw-drive.eds")


def snapshot(od) -> bytes:
    """Everything the dictionary holds, as bytes (objects, defaults, values, node id)."""
    return pickle.dumps(od)


def test_same_file_and_node_id_is_parsed_once():
    a = object_dictionary(EDS, 3)
    hits = eds._parse.cache_info().hits
    assert object_dictionary(str(EDS), 3) is a
    assert eds._parse.cache_info().hits == hits + 1


def test_the_cached_dictionary_is_the_parse_of_that_node_id():
    for node_id in (1, 4):
        od = object_dictionary(EDS, node_id)
        fresh = canopen.import_od(str(EDS), node_id)
        assert snapshot(od) == snapshot(fresh)
        # $NODEID entries resolved for this node (TPDO1's COB-ID is 0x180 + node id)
        assert od.get_variable(0x1800, 1).default == 0x180 + node_id
    assert object_dictionary(EDS, 1) is not object_dictionary(EDS, 4)


def test_an_edited_file_is_parsed_again(tmp_path):
    p = tmp_path / "drive.eds"
    shutil.copy(EDS, p)
    first = object_dictionary(p, 2)
    text = p.read_text().replace("ProductName=", "ProductName=edited ", 1)
    assert "edited" in text
    p.write_text(text)
    st = os.stat(p)
    os.utime(p, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))      # a new version even on a coarse clock
    second = object_dictionary(p, 2)
    assert second is not first
    assert second.device_information.product_name.startswith("edited")


def test_a_missing_file_raises_and_nothing_is_cached(tmp_path):
    p = tmp_path / "none.eds"
    size = eds._parse.cache_info().currsize
    try:
        object_dictionary(p, 1)
    except OSError:
        pass
    else:
        raise AssertionError("no error for a missing EDS")
    assert eds._parse.cache_info().currsize == size


def test_a_start_up_leaves_the_shared_dictionaries_unchanged(monkeypatch):
    """Two configures of the drive bus against the simulated drives (two runs of one process):
    the driver and the simulated drives use the same dictionaries, in both runs, and neither
    changes them."""
    channel = f"test-{uuid.uuid4().hex}"
    drives = tuple(Drive(wheel=w, node_id=n, rated_current_A=8.0, velocity_factor=1e-4)
                   for w, n in zip(WHEELS, (1, 2, 3, 4)))
    cfg = CanBus(interface="virtual", channel=channel, drives=drives)
    before = {d.node_id: snapshot(object_dictionary(EDS, d.node_id)) for d in drives}
    used = {"driver": [], "simulated": []}
    for module, key in ((canopen402, "driver"), (virtual_drive, "simulated")):
        def spy(path, node_id, key=key):
            od = object_dictionary(path, node_id)
            used[key].append((node_id, od))
            return od
        monkeypatch.setattr(module, "object_dictionary", spy)
    for _ in range(2):
        a = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        b = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        try:
            vds = VirtualDriveSet(cfg, b)
            drv = DriveBus(cfg, a, period_s=0.005, eds_path=EDS, sdo_timeout_s=2.0)
            try:
                with vds.serving(0.0):
                    drv.configure()
            finally:
                drv.close()
        finally:
            a.shutdown()
            b.shutdown()
    assert len(used["driver"]) == len(used["simulated"]) == 2 * len(drives)
    ods = {n: od for n, od in used["driver"][:len(drives)]}
    assert all(od is ods[n] for n, od in used["driver"] + used["simulated"])      # one object per node id
    after = {d.node_id: snapshot(object_dictionary(EDS, d.node_id)) for d in drives}
    assert after == before
