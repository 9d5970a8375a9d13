"""Learning agents run by the harness (``window_bench.harness.run``).

* ``qcfql.py`` - QC-FQL: flow teacher, one-step student, chunk critic ensemble (paper Sec. 3.5).
* ``hilserl.py`` - the HIL-SERL-style RLPD learner (step-wise, tanh-Gaussian, LayerNorm critics).
* ``sac.py`` - Stable-Baselines3 SAC as is, with its replay buffer pre-filled with D_demo.
* ``act.py`` - ACT (Action Chunking with Transformers) in plain torch, trained on D_demo only.
"""
