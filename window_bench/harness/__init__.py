"""The matched-budget harness: methods and profiles, one training run, evaluation and the
leaderboard.

* ``methods.py`` - the paper's Table 1 as a registry of methods, and the run profiles;
* ``run.py`` - :class:`Run`, stages I-III with checkpoint evaluation and resume;
* ``evaluation.py`` - seeded rollouts, Wilson intervals, provenance, atomic files;
* ``leaderboard.py`` - ``bench leaderboard``.

Names are imported lazily so that ``import window_bench.harness.methods`` does not load torch.
"""

from importlib import import_module

_RUN_NAMES = ("Run", "Evaluator", "AgentPolicy", "evaluate_policy_file", "make_agent",
              "parse_overrides", "summarize_eval", "time_to_threshold", "obs_normalizer")


def __getattr__(name):
    if name in _RUN_NAMES:
        return getattr(import_module("window_bench.harness.run"), name)
    raise AttributeError(f"module 'window_bench.harness' has no attribute {name!r}")


__all__ = list(_RUN_NAMES)
