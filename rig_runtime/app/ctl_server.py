"""The control socket of a run (``rig ctl``): an output of the recording sidecar.

``CtlServer(info, path, mailbox, config_json=None)`` listens on a Unix-domain stream socket
(never a network listener) in a directory only its owner can enter (0700; the socket 0600),
answers newline-delimited JSON requests in its own thread and passes commands to the control
loop through the shared-memory :class:`~rig_runtime.mailbox.Mailbox`:

    {"cmd": "status"}                          -> {"ok": true, "status": {...}, "row": {...}, "events": [...]}
    {"cmd": "stop"}                            -> {"ok": true, "message": "stop requested in RUNNING"}
    {"cmd": "set", "name": N, "value": V}      -> {"ok": true, "message": "K_P_y 3 -> 4"}
    {"cmd": "reset-fault"}                     -> {"ok": false, "message": "no latched fault (state RUNNING)"}

``set`` is checked here, before it reaches the loop, by :func:`rig_runtime.tuning.check`
with the run's config (``info.attrs["config"]``) and the gains in force; a refusal is the
check's one-line reason. The loop applies an accepted change at its next cycle boundary
and answers; no answer within ``timeout_s`` is an error saying so.

As an output it keeps the latest status snapshot, log row and a few recent events for
``status`` (``rows``/``event``/``status`` only store references: they return at once).

A path where a live server answers is refused (two runs cannot share a socket); a stale
socket file (nobody answers) is removed.
"""

from __future__ import annotations

import collections
import json
import math
import os
import socket
import stat
import struct
import sys
import threading
import time
from pathlib import Path
from typing import Any

from ..errors import RigError

MAX_REQUEST_BYTES = 4096
REQUEST_READ_S = 1.0        # a local client writes its one line at once
SOCKET_PATH_MAX = 107           # sun_path, less its terminating NUL
REQUESTS = ("status", "stop", "set", "reset-fault")


class CtlError(RigError):
    """The control socket cannot be used (no run listening, refused command, bad path)."""


def default_ctl_path() -> Path:
    """``$XDG_RUNTIME_DIR/rig-runtime/ctl.sock``, else ``/tmp/rig-runtime-$UID/ctl.sock``."""
    xdg = os.environ.get("XDG_RUNTIME_DIR")
    base = Path(xdg) / "rig-runtime" if xdg else Path(f"/tmp/rig-runtime-{os.getuid()}")
    return base / "ctl.sock"


def _plain(x: Any) -> Any:
    """A value JSON does not know (a numpy scalar, ...): its Python value, else its text."""
    item = getattr(x, "item", None)
    from .metrics import clean      # numpy: the server's side only, not the `rig ctl` client's
    return clean(item()) if callable(item) else str(x)


def _private_dir(d: Path) -> None:
    """Create ``d`` 0700, or accept it only if it is ours and nobody else can enter it."""
    try:
        d.mkdir(mode=0o700, parents=True, exist_ok=True)
        st = d.lstat()
    except OSError as e:
        raise CtlError(f"control socket directory {d}: {e.strerror}") from None
    if not stat.S_ISDIR(st.st_mode):
        raise CtlError(f"control socket directory {d} is not a directory")
    if st.st_uid != os.getuid():
        raise CtlError(f"control socket directory {d} belongs to another user (uid {st.st_uid})")
    if st.st_mode & 0o077:
        raise CtlError(f"control socket directory {d} is open to other users (mode {stat.S_IMODE(st.st_mode):o}; "
                       "it must be 0700)")


def _connect(path: Path, timeout_s: float) -> socket.socket:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout_s)
    try:
        s.connect(str(path))
    except BaseException:
        s.close()
        raise
    return s


def request(path: str | Path, req: dict, timeout_s: float = 10.0) -> dict:
    """Send one request to the run listening at ``path``; its JSON answer. ``CtlError``
    "no run is listening at PATH" if there is none."""
    path = Path(path)
    try:
        s = _connect(path, timeout_s)
    except (FileNotFoundError, ConnectionRefusedError, NotADirectoryError):
        raise CtlError(f"no run is listening at {path}") from None
    except OSError as e:
        raise CtlError(f"no run is listening at {path} ({e.strerror or e})") from None
    with s:
        try:
            s.sendall(json.dumps(req).encode() + b"\n")
            f = s.makefile("rb")
            line = f.readline(1 << 20)
        except socket.timeout:
            raise CtlError(f"the run at {path} did not answer within {timeout_s:g} s") from None
        except OSError as e:
            raise CtlError(f"the connection to {path} failed: {e.strerror or e}") from None
    if not line:
        raise CtlError(f"the run at {path} closed the connection without an answer")
    try:
        ans = json.loads(line)
    except ValueError:
        raise CtlError(f"the run at {path} sent an answer that is not JSON") from None
    if not isinstance(ans, dict):
        raise CtlError(f"the run at {path} sent an answer that is not a JSON object")
    return ans


class CtlServer:
    """The control socket as a sidecar output (see the module docstring)."""

    TAKES_MAILBOX = True        # the sidecar hands the loop's mailbox to this output only

    def __init__(self, info, path: str | os.PathLike | None = None, mailbox=None, config_json: str | None = None,
                 timeout_s: float = 2.0, poll_s: float = 0.002):
        from .. import tuning          # numpy/scipy: only where a server runs, not in `rig ctl`
        self._tuning = tuning
        self.cfg = tuning.config_from_json(config_json if config_json is not None else info.attrs["config"])
        # the gains in force, for the stability check of the next set: the config's, then each
        # change the loop confirmed (its answer, or its operator event); never a status
        # snapshot, which may predate the last change
        self.gains = tuning.gains_of(self.cfg)
        self._unconfirmed: str | None = None    # a set that timed out: its outcome is not known yet
        self.columns = tuple(info.columns)
        self.mailbox = mailbox
        self.timeout_s = timeout_s
        self.poll_s = poll_s
        self.path = Path(path) if path is not None else default_ctl_path()
        self._status: dict | None = None
        self._row: tuple | None = None
        self._events: collections.deque = collections.deque(maxlen=20)
        self._lock = threading.Lock()           # one command in flight through the mailbox
        self._closed = threading.Event()
        self._sock = self._listen(self.path)
        st = os.stat(self.path)
        self._ident = (st.st_dev, st.st_ino)      # close() removes the socket only if it is still this one
        self._thread = threading.Thread(target=self._serve, name="rig-ctl", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ the socket
    @staticmethod
    def _listen(path: Path) -> socket.socket:
        if len(os.fsencode(str(path))) > SOCKET_PATH_MAX:
            raise CtlError(f"control socket path too long for a Unix socket ({SOCKET_PATH_MAX} bytes): {path}")
        _private_dir(path.parent)
        if path.exists() or path.is_symlink():
            if not stat.S_ISSOCK(path.lstat().st_mode):
                raise CtlError(f"{path} exists and is not a socket: not replacing it")
            try:
                _connect(path, 0.5).close()
            except OSError:
                path.unlink()                   # stale: nobody answers there
            else:
                raise CtlError(f"another run is listening at {path} (give this one --ctl-socket PATH, or --no-ctl)")
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            s.bind(str(path))
            os.chmod(path, 0o600)               # (no umask games: the umask is the whole process's; the
        except OSError as e:                    # 0700 directory keeps others out until this chmod)
            s.close()
            raise CtlError(f"cannot listen at {path}: {e.strerror}") from None
        s.listen(4)
        s.settimeout(0.2)                       # the accept loop looks at close() this often
        return s

    def _serve(self) -> None:
        while not self._closed.is_set():
            try:
                conn, _ = self._sock.accept()
            except socket.timeout:
                continue
            except OSError:
                return                          # closed
            with conn:
                try:
                    if self._peer_uid(conn) not in (os.getuid(), 0):
                        continue                # another user (the 0700 directory should already stop them)
                    self._session(conn)
                except OSError:
                    pass                        # the client went away
                except Exception as e:  # noqa: BLE001 - a bug in one request must not end the server
                    print(f"rig ctl server: request failed: {type(e).__name__}: {e}", file=sys.stderr)

    @staticmethod
    def _peer_uid(conn: socket.socket) -> int:
        """The connecting process's user id (SO_PEERCRED); ours where the OS does not tell."""
        try:
            _, uid, _ = struct.unpack("3i", conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i")))
            return uid
        except (AttributeError, OSError):
            return os.getuid()

    def _session(self, conn: socket.socket) -> None:
        """One request per connection, read within REQUEST_READ_S: the server serves one
        client at a time, and an idle or chatty one must not hold off another's ``stop``."""
        conn.settimeout(REQUEST_READ_S)
        line = conn.makefile("rb").readline(MAX_REQUEST_BYTES + 1)
        if not line:
            return
        if len(line) > MAX_REQUEST_BYTES:
            conn.sendall(self._encode({"ok": False, "message": f"request longer than {MAX_REQUEST_BYTES} bytes"}))
            return
        conn.settimeout(self.timeout_s + 5.0)
        conn.sendall(self._encode(self.handle(line)))

    @staticmethod
    def _encode(ans: dict) -> bytes:
        from .metrics import clean      # numpy: the server's side only, not the `rig ctl` client's
        return json.dumps(clean(ans), default=_plain).encode() + b"\n"

    # ------------------------------------------------------------------ requests
    def handle(self, line: bytes | str) -> dict:
        """One request (a JSON object) -> its answer."""
        try:
            req = json.loads(line)
        except ValueError:
            return {"ok": False, "message": "request is not JSON"}
        if not isinstance(req, dict):
            return {"ok": False, "message": "request is not a JSON object"}
        cmd = req.get("cmd")
        if cmd == "status":
            return self._status_answer()
        if cmd not in REQUESTS:
            return {"ok": False, "message": f"unknown command {str(cmd)[:40]!r} (known: {', '.join(REQUESTS)})"}
        if cmd == "set":
            name, value = req.get("name"), req.get("value")
            if not isinstance(name, str):
                return {"ok": False, "message": "set needs a gain name"}
            if self._unconfirmed is not None:
                return {"ok": False, "message": f"an earlier change ({self._unconfirmed}) got no answer from the "
                                                "control loop, so the gains in force are not known: no further set"}
            try:
                change = self._tuning.check(self.cfg, name, value, self.gains)
            except RigError as e:
                return {"ok": False, "message": str(e)}
            ans = self._command("set", change.name, change.new)
            if ans["ok"]:
                self.gains[change.name] = change.new
            elif ans.get("timeout"):
                self._unconfirmed = f"{change.name} {change.old:g} -> {change.new:g}"
            return ans
        return self._command(cmd)

    def _command(self, kind: str, name: str = "", value: float = math.nan) -> dict:
        mb = self.mailbox
        if mb is None:
            return {"ok": False, "message": "this run takes no commands (no mailbox to the control loop)"}
        with self._lock:
            seq = mb.submit(kind, name, value)
            deadline = time.monotonic() + self.timeout_s
            while True:
                r = mb.result(seq)
                if r is not None:
                    return {"ok": r[0], "message": r[1]}
                if time.monotonic() >= deadline or self._closed.is_set():
                    return {"ok": False, "timeout": True,
                            "message": f"the control loop did not answer within {self.timeout_s:g} s "
                                       "(has the run ended? the command may still take effect: see rig ctl status)"}
                time.sleep(self.poll_s)

    def _status_answer(self) -> dict:
        row = self._row
        return {"ok": True, "status": self._status or {},
                "row": dict(zip(self.columns, row)) if row is not None else {},
                "events": list(self._events), "gains": dict(self.gains), "socket": str(self.path)}

    # ------------------------------------------------------------------ the output interface
    def rows(self, block) -> None:
        if len(block):
            self._row = tuple(float(x) for x in block[-1])

    def event(self, ev: tuple) -> None:
        ev = tuple(ev)
        self._events.append(ev)
        if len(ev) == 7 and ev[1] == "operator" and ev[2] == "controller" and ev[3] in self.gains:
            self.gains[ev[3]] = float(ev[4])     # the loop applied it (the record of a set, answered or not)
            if self._unconfirmed is not None and self._unconfirmed.startswith(ev[3] + " "):
                self._unconfirmed = None

    def status(self, st: dict) -> None:
        self._status = st

    def close(self) -> None:
        """Stop answering and remove the socket (if it is still ours)."""
        if self._closed.is_set():
            return
        self._closed.set()
        try:
            st = os.stat(self.path)
            mine = (st.st_dev, st.st_ino) == self._ident
        except OSError:
            mine = False
        self._sock.close()
        self._thread.join(timeout=self.timeout_s + 6.0)
        if mine:
            try:
                self.path.unlink()
            except OSError:
                pass
