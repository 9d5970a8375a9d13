"""The matched-budget harness: methods and profiles, one training run, evaluation and the
leaderboard.

* ``methods.py`` - the paper's Table 1 as a registry of methods, the agents registry, the
  published agent presets and the run profiles;
* ``tracks.py`` - the observation tracks (the state track here; others registered above);
* ``agent.py`` - the interface every learner implements, and building one for a run;
* ``run.py`` - :class:`Run`, stages I-III with checkpoint evaluation and resume;
* ``evaluation.py`` - seeded rollouts of frozen policies and controllers, Wilson intervals,
  provenance, atomic files;
* ``stage1.py`` - the Stage I cache; ``files.py`` - run directories; ``results.py`` - the
  results files; ``sweep.py``, ``leaderboard.py``, ``tables.py`` - grids and their pages.

The harness imports no learner and no track: :mod:`window_bench.catalog` registers them.
Names are imported lazily so that ``import window_bench.harness.methods`` does not load torch.
"""

from importlib import import_module

_NAMES = {"Run": "run", "AgentPolicy": "evaluation", "Evaluator": "evaluation",
          "evaluate_policy_file": "evaluation", "summarize_eval": "evaluation",
          "time_to_threshold": "evaluation", "make_agent": "agent", "parse_overrides": "agent",
          "obs_normalizer": "agent"}


def __getattr__(name):
    if name in _NAMES:
        return getattr(import_module(f"window_bench.harness.{_NAMES[name]}"), name)
    raise AttributeError(f"module 'window_bench.harness' has no attribute {name!r}")


__all__ = list(_NAMES)
