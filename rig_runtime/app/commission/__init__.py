"""``rig commission``: the wiring checks before the first closed loop (docs/commissioning.md).

Passive checks with the power stages off (the operator moves things by hand, or the
simulated operator ``sim: {operator: commission}`` does), then bump tests: a short
open-loop current pulse on one carrier through the supervisor's normal ARM path — first
(after the lasers) with the carriers lifted (each wheel spins freely: which encoder answers, each drive's
current polarity), then on the rollers (the encoders at roller speed, the yaw sign,
relation (4)). Each
item is judged from what was observed (``judge``), captured by ``session``, reported and
put on record (``record``); ``command`` is the command line."""

CHECKS = ("lasers", "lifted-rear", "lifted-front", "encoders", "bump-rear", "bump-front")
