"""``rig synthesize``: multi-objective, multi-case synthesis of controller gains, as the
paper's MOPS did it — tunables with bounds, cases (plant corners, speeds of both signs,
seeds), criteria with demands from the analysis and from lockstep runs, min-max over the
cases — with pymoo's NSGA-II/III asking for candidates and Dask running them exactly like a
campaign (docs/synthesis.md).

Modules, one job each: :mod:`.spec` (the spec, validated), :mod:`.linear` (the analysis'
criteria), :mod:`.task` (one case of one candidate on a worker), :mod:`.criteria` (min-max
over the cases, the optimizer's objectives and constraints), :mod:`.store` (the synthesis'
tables beside the campaign table), :mod:`.optimize` (pymoo's ask and tell, replayed on
``--resume``), :mod:`.progress` (the bar), :mod:`.report` (Pareto front, chosen point,
``--write``), :mod:`.command` (CLI). What campaigns already do — a run's files, its Dask
task, the table, the dispatch window — is theirs (:mod:`rig_runtime.app.campaign`)."""
