"""``rig commission``: the wiring checks before the first closed loop (docs/commissioning.md).

Passive checks with the power stages off (the operator moves things by hand, or the
simulated operator ``sim: {operator: commission}`` does), then bump tests: a short
open-loop current pulse on one carrier through the supervisor's normal ARM path. Each
item is judged from what was observed (``judge``), captured by ``session``, reported and
put on record (``record``); ``command`` is the command line."""

CHECKS = ("lasers", "encoders", "bump-rear", "bump-front")
