"""``rig campaign run|report`` (registered with the CLI on import; docs/campaigns.md).

``run``: the spec validated and every sample's config written and loaded before any run
(one line, exit 2, on a bad spec); runs on Dask; rows into ``DIR/campaign.sqlite`` as they
arrive; SIGINT/SIGTERM: the runs under way finish, nothing new starts, exit 128 + signal
(``--resume`` continues). ``report``: Markdown and PNG figures from a campaign directory."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Callable

from ...errors import ConfigError
from ..command import Actions, command

ACTIONS = Actions("campaign")
_action, _a = ACTIONS.action, ACTIONS.arg


@command("campaign", "Monte Carlo and sweeps of lockstep dry runs on Dask: run a spec, report on it", stops=True)
def cmd_campaign(args: argparse.Namespace) -> int:
    return ACTIONS.dispatch(args)


ACTIONS.install()


def _workers(value: str) -> int:
    try:
        n = int(value)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"an integer >= 1, got {value!r}")
    return n


@_action("run", "run every sample of a campaign spec as a lockstep dry run on Dask",
         _a("spec", metavar="SPEC", help="campaign spec (YAML; configs/campaigns/ has examples)"),
         _a("--out", metavar="DIR", help="campaign directory (default: campaigns/NAME)"),
         _a("--workers", type=_workers, metavar="N", help="local worker processes (default: the machine's cores)"),
         _a("--scheduler", metavar="ADDRESS", help="a running Dask scheduler (tcp://HOST:PORT) instead of a local cluster"),
         _a("--resume", action="store_true", help="continue the campaign in DIR: run only what has no row yet"))
def campaign_run(args: argparse.Namespace) -> int:
    from . import prepare
    from .spec import load_spec
    try:
        import distributed  # noqa: F401
        import SALib  # noqa: F401
    except ImportError as e:
        raise ConfigError(None, "campaign", f"Dask distributed and SALib installed (pip install -e '.[campaign]'; {e})") \
            from None
    return run_spec(args, "campaign", load_spec, lambda spec: Path("campaigns") / spec.name,
                    prepare.reopen, prepare.create, _execute)


def run_spec(args: argparse.Namespace, what: str, load_spec: Callable, default_out: Callable,
             reopen: Callable, create: Callable, execute: Callable) -> int:
    """What ``rig campaign run`` and ``rig synthesize run`` share: --workers or --scheduler (not
    both), the spec loaded, the output directory new or empty — or, with --resume, the
    store reopened — and the store closed however ``execute(args, spec, out, store)`` ends."""
    if args.workers and args.scheduler:
        raise ConfigError(None, "--workers", "either --workers (local cluster) or --scheduler, not both")
    spec = load_spec(args.spec)
    out = Path(args.out) if args.out else default_out(spec)
    if args.resume:
        store = reopen(spec, out)
    else:
        if out.exists() and any(out.iterdir()):
            raise ConfigError(None, "--out", "a new or empty directory (it holds files; --resume continues a "
                              f"{what})", str(out))
        store = create(spec, out)
    try:
        return execute(args, spec, out.resolve(), store)
    finally:
        store.close()


def _execute(args, spec, out: Path, store) -> int:
    from . import dispatch
    from .progress import CampaignProgress
    from .task import Job
    stops = args.stops
    done = store.done_ids()
    ids = [i for i in store.sample_ids() if i not in done]
    hardware = (out / "configs" / "hardware.yaml").read_text()
    texts: dict[str, str] = {}

    def job(i: int) -> Job:
        s = store.sample(i)
        sc = s["scenario"]
        if sc not in texts:
            texts.clear() if len(texts) > 64 else None
            texts[sc] = Path(sc).read_text()
        return Job(run_id=i, config_text=Path(s["config"]).read_text(), hardware_text=hardware,
                   scenario_text=texts[sc], seed=s["seed"], duration_s=spec.duration_s, settle_s=spec.settle_s, criteria=spec.criteria,
                   no_fault=spec.no_fault, keep_logs=spec.keep_logs, audit_path=str(out / "started.log"))

    counts = store.counts()
    total = len(store.sample_ids())
    judged = sum(v for k, v in counts.items() if k != "error")
    print(f"rig campaign: {spec.name}: {total} runs, {len(done)} done, {len(ids)} to run; table {store.path}",
          file=sys.stderr)
    (out / "logs").mkdir(exist_ok=True)

    def on_row(j: Job, row: dict) -> None:
        log = None
        data = row.pop("log_bytes", None)
        if data is not None:
            log = out / "logs" / f"run-{j.run_id:05d}.h5"
            log.write_bytes(data)
        store.add_result(row, str(log) if log else None)
        bar.advance(row.get("status", "error"))

    with dispatch.connect(args.workers, args.scheduler) as client:
        with CampaignProgress(total, len(done), counts.get("pass", 0), judged) as bar:
            try:
                finished = dispatch.run_all(client, (job(i) for i in ids), on_dispatch=store.note_dispatch,
                                            on_row=on_row, stop_requested=lambda: stops.requested)
            except dispatch.LostCluster as e:
                print(f"rig campaign: lost the Dask cluster ({e}); {len(store.done_ids())} of {total} rows "
                      f"written; continue with: rig campaign run {args.spec} --out {out} --resume", file=sys.stderr)
                return 1
    c = store.counts()
    line = ", ".join(f"{c.get(k, 0)} {k}" for k in ("pass", "fail", "refused", "error"))
    if not finished:
        print(f"rig campaign: stopped by {stops.name}: {sum(c.values())} of {total} rows ({line}); the runs under way "
              f"were finished; continue with: rig campaign run {args.spec} --out {out} --resume", file=sys.stderr)
        return 128 + (stops.signum or 0)
    print(f"rig campaign: {spec.name}: {sum(c.values())} of {total} rows ({line}); table {store.path}; "
          f"report: rig campaign report {out}")
    return 0


@_action("report", "pass rate with its interval, the one-line answer, figures, Sobol indices (Markdown + PNG)",
         _a("dir", metavar="DIR", help="campaign directory (from rig campaign run)"),
         _a("--out", metavar="DIR", help="report directory (default: DIR/report)"))
def campaign_report(args: argparse.Namespace) -> int:
    from .. import preflight
    from .report import write_report
    out = Path(args.out) if args.out else Path(args.dir) / "report"
    preflight.check_plot_dir(out, "--out")
    md, answer = write_report(Path(args.dir), out)
    print(answer)
    print(f"report: {md}")
    return 0
