"""The CLI's start imports only what every command needs: scipy comes with a run's set-up
(the stability gate, the observer design), not with ``rig`` itself (``rig log``, ``rig ctl``...)."""

import subprocess
import sys


def test_importing_the_cli_imports_no_scipy():
    code = "import sys, rig_runtime.app.cli; print(sorted(m for m in sys.modules if m.split('.')[0] == 'scipy'))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
