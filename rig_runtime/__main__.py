"""``python -m rig_runtime`` = the ``rig`` command."""
import sys

from rig_runtime.app.entry import main

sys.exit(main())
