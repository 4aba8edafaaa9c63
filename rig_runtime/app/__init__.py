"""The application floor: the `rig` command and its wiring (run / dry-run / identify / design)."""
