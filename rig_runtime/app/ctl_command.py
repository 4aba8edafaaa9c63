"""``rig ctl``: operator commands to a running ``rig run`` / ``rig dry-run --realtime``
over its control socket (rig_runtime.app.ctl_server; docs/ctl.md)."""

from __future__ import annotations

import json
import math
import sys

from .command import arg, command
from .ctl_server import CtlError, default_ctl_path, request

ACTIONS = ("status", "stop", "set", "reset-fault")


def _num(x, scale: float = 1.0, fmt: str = "+.3f") -> str:
    return format(x * scale, fmt) if isinstance(x, (int, float)) and math.isfinite(x) else "-"


def format_status(ans: dict) -> str:
    """The status answer as a few lines for a terminal (a missing value shows as '-')."""
    st, row = ans.get("status") or {}, ans.get("row") or {}
    t_run, dur = st.get("t_run"), st.get("duration_s")
    lines = [f"state {st.get('state', '-')}   t_run {_num(t_run, fmt='.1f')} s"
             + (f" of {_num(dur, fmt='.1f')} s" if isinstance(dur, (int, float)) else "")
             + f"   socket {ans.get('socket', '-')}"]
    for c in st.get("controlled") or []:
        lines.append(f"{c}: y_ref {_num(row.get(c + '_y_ref', row.get('y_ref')), 1e3)} mm  y {_num(row.get('y_' + c[0]), 1e3)} mm  "
                     f"psi {_num(row.get('psi_a' + c[0]), 1e3)} mrad  u {_num(row.get(c + '_u_lim'))} A")
    gains = ans.get("gains") or st.get("gains") or {}
    if gains:
        lines.append("gains " + "  ".join(f"{k} {v:g}" for k, v in gains.items()))
    for f in st.get("faults") or []:
        lines.append(f"fault at t_run {_num(f.get('t_run'), fmt='.3f')} s: {f.get('device', '-')} "
                     f"{f.get('check', '-')}: {f.get('message', '')}")
    tm = st.get("timing") or {}
    if tm:
        lat, work = tm.get("lateness_us") or {}, tm.get("work_us") or {}
        lines.append(f"timing: cycles {tm.get('cycles', '-')}  lateness p99 {_num(lat.get('p99'), fmt='.0f')} us  "
                     f"work p99 {_num(work.get('p99'), fmt='.0f')} us  misses {tm.get('deadline_misses', '-')}")
    return "\n".join(lines)


@command("ctl", "operator commands to a running `rig run` / `rig dry-run --realtime`: "
                "status, stop, set NAME VALUE (a controller gain), reset-fault")
@arg("--socket", metavar="PATH", default=None,
     help=f"the run's control socket (default {default_ctl_path()})")
@arg("--json", action="store_true", help="print the answer as JSON")
@arg("--timeout", type=float, default=10.0, metavar="S", help="how long to wait for the run's answer (default 10 s)")
@arg("action", choices=ACTIONS, help="status | stop | set NAME VALUE | reset-fault")
@arg("operands", nargs="*", metavar="NAME VALUE", help="for set: the gain's name and its new value")
def ctl(args) -> int:
    if not 0 < args.timeout < math.inf:
        raise CtlError(f"--timeout: a number of seconds > 0, got {args.timeout!r}")
    path = args.socket or default_ctl_path()
    req: dict = {"cmd": args.action}
    if args.action == "set":
        if len(args.operands) != 2:
            raise CtlError("set needs NAME VALUE (e.g. rig ctl set K_P_y 3.5)")
        name, text = args.operands
        try:
            value = float(text)
        except ValueError:
            raise CtlError(f"set {name}: {text!r} is not a number") from None
        req.update(name=name, value=value)
    elif args.operands:
        raise CtlError(f"{args.action} takes no operands (got {' '.join(args.operands)})")
    ans = request(path, req, timeout_s=args.timeout)
    if args.json:
        print(json.dumps(ans, indent=1))
    elif args.action == "status" and ans.get("ok"):
        print(format_status(ans))
    if not ans.get("ok"):
        raise CtlError(str(ans.get("message") or "refused"))
    if not args.json and args.action != "status":
        print(ans.get("message", "ok"))
    sys.stdout.flush()
    return 0
