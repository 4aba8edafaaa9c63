"""A campaign directory: created once from the spec (samples drawn, every run's config and
scenario written and loaded — refused before any run if one is not valid), or opened again
for ``--resume`` (the same spec, else refused)."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

from rig_runtime import config as rig_config
from rig_runtime.errors import ConfigError
from rig_runtime.memo import without_disk
from rig_runtime.scenario import load_scenario

from . import design, materialize
from .spec import Spec
from .store import DB_NAME, Store

SPEC_COPY = "spec.yaml"


def spec_hash(spec: Spec) -> str:
    return hashlib.sha256(Path(spec.source).read_bytes()).hexdigest()


def create(spec: Spec, out: Path) -> Store:
    """Draw the samples, write ``out/configs``, ``out/scenarios``, the table's samples.
    Every run's config is loaded as ``rig dry-run`` loads it (a value the config's rules
    or the hardware ceilings refuse ends here, before any run)."""
    base = materialize.read_base(spec)
    materialize.check_extremes(spec, base)
    samples = design.draw(spec)
    existed = out.exists()
    out.mkdir(parents=True, exist_ok=True)
    try:
        return _fill(spec, out, base, samples)
    except BaseException:
        if not existed:                 # refused (or interrupted) before any run: leave nothing half-made
            shutil.rmtree(out, ignore_errors=True)
        raise


def _fill(spec: Spec, out: Path, base, samples) -> Store:
    shutil.copyfile(spec.source, out / SPEC_COPY)
    base_sc = out / "scenarios" / "base.yaml"
    base_sc.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(spec.scenario, base_sc)
    store = Store(out / DB_NAME)
    store.create({"spec": spec.to_json(), "spec_sha256": spec_hash(spec), "names": list(samples.names),
                  "n_runs": len(samples.values), "complete": False}, samples.names)
    rows = []
    for i in range(len(samples.values)):
        values = samples.row(i)
        cfg, sc = materialize.write_run_files(out.resolve(), base, values, i, base_sc.resolve())
        try:
            with without_disk():        # each sample's file is read once here: not kept for another process
                rig_config.load(cfg)
                if sc != base_sc.resolve():
                    load_scenario(sc)
        except ConfigError as e:
            store.close()
            raise ConfigError(spec.source, "parameters", f"samples the config accepts (run {i}: {e})") from None
        rows.append((i, samples.seeds[i], *values.values(), str(cfg), str(sc),
                     materialize.reproduce_command(cfg, sc, samples.seeds[i], spec.duration_s)))
    store.add_samples(rows)
    store.set_meta("complete", True)
    return store


def reopen(spec: Spec, out: Path) -> Store:
    """An existing campaign of the same spec (``--resume``)."""
    db = out / DB_NAME
    if not db.is_file():
        raise ConfigError(None, "--resume", f"a campaign directory (no {DB_NAME} in {out})", str(out))
    store = Store(db)
    meta = store.meta()
    if not meta.get("complete"):
        store.close()
        raise ConfigError(None, "--resume", "a campaign whose samples were all written (remove the directory and "
                          "start again)", str(out))
    if meta.get("spec_sha256") != spec_hash(spec):
        store.close()
        raise ConfigError(spec.source, "", f"the spec the campaign in {out} was started with (it differs; "
                          f"its copy is {out / SPEC_COPY})")
    return store
