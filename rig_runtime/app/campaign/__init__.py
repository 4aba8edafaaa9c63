"""``rig campaign``: many lockstep dry runs — the same path as ``rig dry-run`` — over sampled
conditions, on Dask distributed, into one table; and the report that answers "do these gains
hold for every sampled condition, and where do they fail" (docs/campaigns.md).

Modules, one job each: :mod:`.distributions` (a parameter's distribution), :mod:`.spec` (the
campaign spec, validated), :mod:`.design` (the samples), :mod:`.materialize` (a sample as a
config and scenario file), :mod:`.outcome` (a run's metrics and pass/fail), :mod:`.task` (one
run on a worker), :mod:`.store` (the SQLite table), :mod:`.dispatch` (Dask), :mod:`.progress`
(the bar), :mod:`.stats`/:mod:`.discovery`/:mod:`.report` (the report), :mod:`.command` (CLI)."""
