"""The lines ``rig sim`` prints on stdout before ``ready``, written and read here only:
``laser <role> <pty>``, ``can slcan <pty>``, ``ft <name> <host>:<port>``, ``status <path>``,
``config <path>`` (docs/sim-process.md, "Output")."""

from __future__ import annotations

from typing import Any, Mapping


def port_lines(laser_ports: Mapping[str, str], can_port: str,
               ft_endpoints: Mapping[str, tuple[str, int]]) -> list[str]:
    """One machine-readable line per port."""
    lines = [f"laser {r} {p}" for r, p in laser_ports.items()]
    lines.append(f"can slcan {can_port}")
    lines += [f"ft {n} {h}:{p}" for n, (h, p) in ft_endpoints.items()]
    return lines


def parse_port_line(line: str, ports: dict[str, Any]) -> None:
    """Fold one line of ``rig sim``'s output into ``ports``
    (``{"laser": {role: path}, "can": {"interface", "channel"}, "ft": {name: (host, port)}, …}``)."""
    parts = line.split()
    if len(parts) == 3 and parts[0] == "laser":
        ports.setdefault("laser", {})[parts[1]] = parts[2]
    elif len(parts) == 3 and parts[0] == "can":
        ports["can"] = {"interface": parts[1], "channel": parts[2]}
    elif len(parts) == 3 and parts[0] == "ft":
        host, _, port = parts[2].rpartition(":")
        ports.setdefault("ft", {})[parts[1]] = (host, int(port))
    elif len(parts) == 2 and parts[0] in ("config", "status"):
        ports[parts[0]] = parts[1]
