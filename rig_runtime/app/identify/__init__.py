"""System identification of the rear wheel carrier (paper Sec. 4) from recorded experiments.

``rig identify`` runs the paper's procedure in its order, each step the optimisation problem
(1) on its own experiment (docs/identification.md): relation (4), lateral (2b), free response,
steps, sines, then the verification on the held-out open-loop steps.
"""
