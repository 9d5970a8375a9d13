"""What a run writes besides its state: ``results.json``'s schema version and time scale,
``checkpoints.csv``, ``learning_curve.png`` and the TensorBoard scalars under ``tb/``.

Progress is reported in simulated hours: environment steps at 10 Hz, :data:`STEPS_PER_HOUR`.
"""

from __future__ import annotations

import csv
import io
import json
import os
from pathlib import Path

import numpy as np

from window_bench.data.steplog import DEFAULT_DEMO_ACTIONS
from window_bench.installer.operators import DEFAULT_OPERATOR

RESULTS_SCHEMA = 1
STEPS_PER_HOUR = 36_000            # 10 Hz
LOSS_LOG_EVERY = 500    # learner calls averaged into one TensorBoard point (loss/...)
#: Which checkpoint's policy the final evaluation runs: ``last`` (the tables' protocol) or
#: ``best-dev``, the one with the highest success on the development seeds (ties: the later),
#: as an operator picks a checkpoint to evaluate in HIL-SERL (``--eval_checkpoint_step``).
FINAL_CHECKPOINTS = ("last", "best-dev")


def check_final_checkpoint(choice) -> str:
    if choice not in FINAL_CHECKPOINTS:
        raise ValueError(f"--final-checkpoint {choice!r}; allowed: {', '.join(FINAL_CHECKPOINTS)}")
    return choice


def chosen_checkpoint(checkpoints: list[dict], choice: str) -> dict:
    """The checkpoint row whose policy the final evaluation runs (see FINAL_CHECKPOINTS).
    ``best-dev`` reads only the development-seed evaluations, never the test seeds."""
    if check_final_checkpoint(choice) == "last":
        return checkpoints[-1]
    best = max(range(len(checkpoints)), key=lambda i: (checkpoints[i]["success_rate"], i))
    return checkpoints[best]


def checkpoints_csv(checkpoints: list[dict]) -> str:
    cols = ["env_steps", "sim_hours", "wall_clock_s", "episodes", "successes", "success_rate",
            "wilson_lo", "wilson_hi", "cycle_time_s", "pr_S", "pr_I_given_S", "pr_T_given_I",
            "takeover_minutes", "train_success_rate", "train_intervention_rate",
            "failure_modes"]
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(cols)
    for c in checkpoints:
        row = {**c, "wilson_lo": c["wilson95"][0], "wilson_hi": c["wilson95"][1],
               "failure_modes": json.dumps(c["failure_modes"])}
        w.writerow(["" if row.get(k) is None else row.get(k) for k in cols])
    return buf.getvalue()


def plot_learning_curve(results: dict) -> bytes:
    """Success with its Wilson band and the training intervention rate vs simulated hours
    (the layout of the paper's Figs. 10 and 11), as PNG bytes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cps = results["checkpoints"]
    x = [c["sim_hours"] for c in cps]
    y = [100 * c["success_rate"] for c in cps]
    lo = [100 * c["wilson95"][0] for c in cps]
    hi = [100 * c["wilson95"][1] for c in cps]
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(6.4, 5.6), sharex=True)
    a1.fill_between(x, lo, hi, alpha=0.25, label="95 % Wilson")
    a1.plot(x, y, "o-", label=f"{results['method']['label']}")
    a1.axhline(95, ls=":", c="gray")
    a1.set_ylabel("success (%)")
    a1.set_ylim(-2, 102)
    a1.legend(loc="lower right")
    a1.set_title(f"{results['method']['name']} on {results['env_id']} "
                 f"({results['profile']['name']} profile, seed {results['seed']})")
    ir = [100 * (c["train_intervention_rate"] or 0) for c in cps]
    a2.plot(x, ir, "s-", c="C3")
    a2.set_ylabel("intervention rate,\nlast 20 episodes (%)")
    a2.set_xlabel("online interaction (simulated hours, warm start included)")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return buf.getvalue()


class Scalars:
    """TensorBoard scalars under ``out/tb/``, or none where tensorboard is not installed (the
    checkpoints are in the CSV and JSON files too); nothing is kept in the resume state."""

    def __init__(self, out: str | os.PathLike, loss_log_every: int = LOSS_LOG_EVERY):
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError:
            self.writer = None
        else:
            self.writer = SummaryWriter(str(Path(out) / "tb"))
        self.loss_log_every, self._losses = loss_log_every, []

    def losses(self, metrics: dict, grad_steps: int) -> None:
        """One learner call's metrics; every ``loss_log_every`` calls their means go in as
        ``loss/<name>`` at ``grad_steps`` (the gradient steps after that call)."""
        self._losses.append(metrics)
        if len(self._losses) < self.loss_log_every:
            return
        if self.writer is not None:
            for key in self._losses[0]:
                vals = [m[key] for m in self._losses if isinstance(m.get(key), (int, float))]
                if vals:
                    self.writer.add_scalar(f"loss/{key}", float(np.mean(vals)), grad_steps)
        self._losses = []

    def checkpoint(self, cp: dict) -> None:
        """A checkpoint row's success (``eval/``) and training rates (``train/``)."""
        if self.writer is None:
            return
        for key in ("success_rate", "takeover_minutes", "train_intervention_rate",
                    "train_success_rate", "wall_clock_s"):
            if cp.get(key) is not None:
                self.writer.add_scalar(f"eval/{key}" if key == "success_rate" else
                                       f"train/{key}", cp[key], cp["env_steps"])
        self.writer.flush()

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()


# ---------------------------------------------------------------------------- defaults revisions
#: The revision of the shipped defaults a run was made under (``results.json``'s ``defaults``;
#: a file without it is revision 1). What a revision sets beside the agents' own configs: the
#: operator profile of D_demo and the takeovers, and which of D_demo's actions learners train
#: on. Revision 2 also changed QC-FQL's run config (``QCFQLAgent.RUN_DEFAULTS``); revision 3
#: only that (``online_lr``). A row of the tables departs from its own revision's defaults,
#: never from another's.
DEFAULTS_REVISION = 3
REVISION_DEFAULTS = {1: {"operator": "average", "demo_actions": "executed"},
                     2: {"operator": DEFAULT_OPERATOR, "demo_actions": DEFAULT_DEMO_ACTIONS},
                     DEFAULTS_REVISION: {"operator": DEFAULT_OPERATOR,
                                         "demo_actions": DEFAULT_DEMO_ACTIONS}}


def revision_of(results: dict) -> int:
    """The defaults revision a results file was made under (1 for files without one)."""
    return results.get("defaults", 1)


def departures(results: dict) -> dict:
    """The run's operator profile and D_demo labels where they depart from the defaults of
    the revision it was made under (bench tables and bench leaderboard name them)."""
    defaults = REVISION_DEFAULTS.get(revision_of(results), {})
    return {k: results.get(k, v) for k, v in defaults.items() if results.get(k, v) != v}
