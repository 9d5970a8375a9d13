"""Data formats: what an episode is on disk and in memory, and how learners sample it.

* ``steplog.py`` - the per-step log (observation, action, provenance, stage flags);
* ``chunks.py`` - chunk transitions of horizon h (paper Eq. 4);
* ``dataset.py`` - Minari storage of episodes;
* ``replay.py`` - chunk replay on TorchRL and the 1:1 demo/online batches;
* ``effort.py`` - takeover minutes, counts and the intervention rate.
"""
