"""``rig synthesize run|report`` (registered with the CLI on import; docs/synthesis.md).

``run``: the spec validated, every case's config at the tunables' bounds loaded, before
anything is written (one line, exit 2, on a bad spec); the optimizer's candidates evaluated
on Dask, a row per (candidate, case) into ``DIR/campaign.sqlite`` as it arrives;
SIGINT/SIGTERM: the runs under way finish, nothing new starts, exit 128 + signal
(``--resume`` continues, evaluating nothing twice). ``report``: the Pareto front, the chosen
point and why, every criterion against its demand per case; ``--write`` the chosen gains as
a controller fragment."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ...errors import ConfigError
from ..campaign.command import _workers, run_spec
from ..command import Actions, command

ACTIONS = Actions("synthesize")
_action, _a = ACTIONS.action, ACTIONS.arg


@command("synthesize", "multi-objective, multi-case gain synthesis (MOPS-like) on Dask: run a spec, report on it",
         stops=True)
def cmd_synthesize(args: argparse.Namespace) -> int:
    return ACTIONS.dispatch(args)


ACTIONS.install()


def _requirements() -> None:
    try:
        import distributed  # noqa: F401
        import pymoo  # noqa: F401
    except ImportError as e:
        raise ConfigError(None, "synthesize", f"Dask distributed and pymoo installed (pip install -e '.[campaign]'; "
                          f"{e})") from None


@_action("run", "synthesize gains: the optimizer's candidates over every case, evaluated on Dask",
         _a("spec", metavar="SPEC", help="synthesis spec (YAML; configs/synthesis/ has examples)"),
         _a("--out", metavar="DIR", help="synthesis directory (default: synthesis/NAME)"),
         _a("--workers", type=_workers, metavar="N", help="local worker processes (default: the machine's cores)"),
         _a("--scheduler", metavar="ADDRESS", help="a running Dask scheduler (tcp://HOST:PORT) instead of a local cluster"),
         _a("--resume", action="store_true", help="continue the synthesis in DIR: evaluate only what has no row yet"))
def synthesize_run(args: argparse.Namespace) -> int:
    from . import store as sstore
    from .spec import load_spec
    _requirements()
    return run_spec(args, "synthesis", load_spec, lambda spec: Path("synthesis") / spec.name,
                    sstore.reopen, sstore.create, _execute)


def _execute(args, spec, out: Path, store) -> int:
    import time
    from ..campaign import dispatch
    from . import optimize
    from .progress import SynthesisProgress
    stops = args.stops
    opt = spec.optimizer
    total = opt.population * opt.generations * len(spec.cases)
    done = len(store.done_ids())
    print(f"rig synthesize: {spec.name}: {len(spec.tunables)} tunables, {len(spec.cases)} cases, "
          f"{len(spec.criteria)} criteria ({len(spec.objectives)} objectives); {opt.method} "
          f"{opt.population} x {opt.generations} generations: about {total} runs, {done} done; table {store.path}",
          file=sys.stderr)
    t0 = time.monotonic()
    with dispatch.connect(args.workers, args.scheduler) as client:
        with SynthesisProgress(total, done) as bar:
            try:
                result = optimize.run(spec, out, store, client, stop_requested=lambda: stops.requested,
                                      on_row=lambda row: bar.advance(),
                                      on_candidate=lambda c, best: best and bar.best(_describe(spec, best)))
            except dispatch.LostCluster as e:
                print(f"rig synthesize: lost the Dask cluster ({e}); {len(store.done_ids())} runs written; continue "
                      f"with: rig synthesize run {args.spec} --out {out} --resume", file=sys.stderr)
                return 1
            except optimize.ReplayMismatch as e:
                raise ConfigError(None, "--resume", f"a synthesis the optimizer replays ({e})", str(out)) from None
    wall = time.monotonic() - t0
    n = len(store.done_ids())
    if not result.finished:
        print(f"rig synthesize: stopped by {stops.name}: {n} runs written; the runs under way were finished; "
              f"continue with: rig synthesize run {args.spec} --out {out} --resume", file=sys.stderr)
        return 128 + (stops.signum or 0)
    best = result.best
    print(f"rig synthesize: {spec.name}: {len(result.candidates)} candidates, {n} runs ({result.evaluated} in "
          f"{wall:.1f} s now, {result.skipped} skipped on a linear constraint); best feasible: {_describe(spec, best) if best else 'none'}; "
          f"report: rig synthesize report {out}")
    return 0


def _describe(spec, c: dict) -> str:
    x = ", ".join(f"{k.split('.')[-1]} {v:.4g}" for k, v in c["x"].items())
    f = ", ".join(f"{o.name} {v:.4g}" for o, v in zip(spec.objectives, c["verdict"].objectives))
    return f"#{c['candidate']} ({x}): {f}"


@_action("report", "Pareto front, the chosen point and why, every criterion against its demand per case",
         _a("dir", metavar="DIR", help="synthesis directory (from rig synthesize run)"),
         _a("--out", metavar="DIR", help="report directory (default: DIR/report)"),
         _a("--write", metavar="CONTROLLER.yaml", help="write the chosen point's gains as a controller fragment"))
def synthesize_report(args: argparse.Namespace) -> int:
    from .. import preflight
    from .report import write_report
    out = Path(args.out) if args.out else Path(args.dir) / "report"
    preflight.check_plot_dir(out, "--out")
    md, answer = write_report(Path(args.dir), out, Path(args.write) if args.write else None)
    print(answer)
    print(f"report: {md}")
    return 0
