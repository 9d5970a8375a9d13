"""QC-FQL: Q-chunking with a flow teacher distilled into a one-step student (paper Sec. 3.5).

Read top to bottom: the config, the three networks, the losses (paper Eqs. 6-9), one
update, acting, and the state dict. Everything runs in PyTorch on one CPU thread; TorchRL
supplies the teacher/student MLPs (``torchrl.modules.MLP``) and the replay
(:mod:`window_bench.data.replay`). The critic ensemble, the flow teacher, the distillation and the
Polyak average are written here: TorchRL's MLP puts the norm before the activation (the
reference critic has it after), its ``EnsembleModule`` vmaps one module (slower here than
plain per-member calls, see ``benchmarks/update_speed.py``) and its ``SoftUpdate`` needs a
``LossModule``.

The agent acts in chunks: from state ``s_kh`` the student ``mu(s, z)``, ``z ~ N(0, I)``,
outputs a whole chunk ``u_k`` of ``h`` actions (h x 7 values in [-1, 1]) that runs
open-loop. Per update, on a batch of fixed-grid chunk transitions
(:func:`window_bench.data.chunks.chunk_transitions`):

* critic (Eqs. 6-7): ``y = R_k + gamma^h (1 - terminal) mean_i Qbar_i(s', clip(mu(s', z')))``,
  loss ``mean_i,b valid_b (Q_i(s, u) - y)^2``; windows cut short by truncation
  (``valid = False``) contribute nothing;
* teacher (Eq. 8, rectified flow): ``x_t = (1 - t) x0 + t u``, loss
  ``|v(s, x_t, t) - (u - x0)|^2`` masked per step by ``action_mask``;
* student (Eq. 9): ``alpha |mu(s, z) - a_xi(s, z)|^2 - mean_i Q_i(s, clip(mu(s, z)))`` with
  the SAME ``z`` for student and teacher, ``a_xi`` = ``flow_steps`` Euler steps of the
  teacher from ``z`` (clipped at the end only), and the critic frozen; by default ``a_xi``
  is the Polyak-averaged teacher and the agent acts with the averaged student
  (``policy_ema``, ``distill_from_ema``: our addition, see ``docs/qcfql.md``);
* one Adam step over all three networks on the summed loss (stop-gradients decide who learns
  what, as in the reference, so this equals three separate Adams), then Polyak averaging of
  the target critic.

See ``docs/qcfql.md`` for the equations mapped to the code, paper-vs-reference choices and
the measured update speed.
"""

from __future__ import annotations

import copy
import numbers
from dataclasses import asdict, dataclass
from typing import Mapping

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn
from torchrl.modules import MLP

from window_bench.envs.env import VACUUM_THRESHOLD
from window_bench.data.replay import PROVENANCE_CODES
from window_bench.installer.supervisor import check_fine_pose, extra_features, extra_inputs
from window_bench.harness.agent import (Agent, arm_power, config_from_plain,
                                        load_optimizer_state, module_state, optimizer_state,
                                        plain, with_overrides)

#: Bound on normalised observations (in demo standard deviations).
OBS_CLIP = 10.0

# ---------------------------------------------------------------------------- config

#: Choices of ``QCFQLConfig.prior_data`` (the flow teacher's training chunks).
PRIOR_DATA = ("replay", "accepted", "accepted_no_takeover", "autonomous", "demo",
              "demo_and_takeover")

#: Choices of ``QCFQLConfig.distill_data`` (where, and toward what, the student is distilled).
DISTILL_DATA = ("batch", "prior", "prior_else_self")

#: ``provenance_code`` of a demonstration and of a takeover step in replay batches.
DEMO_CODE, TAKEOVER_CODE = PROVENANCE_CODES["demo"], PROVENANCE_CODES["takeover"]


@dataclass
class QCFQLConfig:
    """Hyperparameters of QC-FQL. Defaults: the paper's Table 8 where it gives a value; our
    departures (``act_noise_scale``, ``td_noise_scale``, ``distill_noise_scale``,
    ``policy_ema``, ``distill_from_ema``, ``prior_data``) are marked and measured in
    ``docs/qcfql.md``. ``PAPER_AGENT`` lists the overrides that restore the paper's agent."""

    h: int = 10
    """Chunk horizon in 10 Hz steps; ``h = 1`` gives the step-wise variants."""
    hidden: tuple[int, ...] = (512, 512, 512, 512)
    """Hidden widths of every MLP (critic, teacher, student)."""
    student_hidden: tuple[int, ...] | None = None
    """Hidden widths of the one-step student alone (``None``: ``hidden``). The student must
    reproduce the teacher's chunk in one pass; on WindowInstall-B the ``cpu`` size (2 x 256)
    stops short of the grasp where a 4 x 512 student distilled from the same teacher does not
    (``docs/results/discussion.md#setting-b-the-grasp``)."""
    num_critics: int = 2
    """Critic ensemble size."""
    alpha: float = 300.0
    """Distillation weight (paper Eq. 9; the reference's default is 100 on a per-entry mean)."""
    flow_steps: int = 10
    """K, the Euler steps of the teacher when it produces distillation targets."""
    lr: float = 3e-4
    """Adam learning rate (one Adam over all networks)."""
    tau: float = 0.005
    """Polyak rate of the target critic, applied every update."""
    gamma: float = 0.99
    """Per-step discount; the chunk discount ``gamma ** h`` comes with each batch."""
    batch_size: int = 256
    """Chunks per update (used by the harness when sampling; ``update`` takes any size)."""
    q_agg: str = "mean"
    """Aggregation over the ensemble in the TD target: ``"mean"`` (paper, reference) or
    ``"min"`` (clipped double Q)."""
    distill_reduction: str = "sum"
    """``"sum"``: squared l2 over the whole h x 7 chunk, averaged over the batch (paper
    Eq. 9: "not a step-wise average"); ``"mean"``: mean over all entries as the reference
    code does (equivalent to ``alpha / (7 h)`` with ``"sum"``)."""
    normalize_q_loss: bool = False
    """Divide the student's Q term by the detached batch mean of ``|Q|`` (FQL's option; off in
    the QC-FQL reference and here)."""
    gelu_approximate: str = "tanh"
    """GELU variant of every hidden layer: ``"tanh"`` (the reference, flax's default) or
    ``"none"`` (exact erf GELU; differs by at most 5e-4 and runs faster on CPU, see
    ``docs/qcfql.md``)."""
    critic_layer_norm: bool = True
    """LayerNorm (eps 1e-6) after each hidden activation of the critic (reference)."""
    obs_std_floor: float = 1e-3
    """Lower bound applied to the observation std given at construction."""
    act_noise_scale: float = 0.0
    """Scale of the student's noise ``z`` when acting stochastically (``act`` with
    ``deterministic=False``: exploration). 1 is the paper and the reference; not in Table 8.
    Default 0 (our choice): on WindowInstall-A no training episode at 1.0 was accepted
    (0 %, the installer took over 63 % of the steps; ``docs/harness.md``)."""

    td_noise_scale: float = 0.0
    """Scale of the noise ``z'`` of the student's next chunk in the TD target (Eq. 6): the
    critic learns the value of ``mu(s, z')`` with ``z' ~ N(0, td_noise_scale^2 I)``. 1 is the
    paper and the reference. ``0`` (default, our choice) makes the critic value the
    deterministic student that evaluation runs (``z = 0``) and, with ``act_noise_scale =
    0``, that collects the online data. At 1.0 the critic's argmax over 16 candidate chunks
    took a policy from 83 % to 6 % (``docs/harness.md``). Not in Table 8."""

    distill_noise_scale: float = 0.0
    """Scale of the noise ``z`` at which the student is trained (Eq. 9: distillation toward
    the teacher from the same ``z``, and the Q term): ``z ~ N(0, distill_noise_scale^2 I)``.
    1 is the paper and the reference. With deterministic acting (``act_noise_scale = 0``)
    only ``mu(s, 0)`` is ever executed; ``0`` (default, our choice) spends the student's
    capacity there. Not in Table 8: on WindowInstall-A the averaged teacher at ``z = 0``
    scored 92 % (M = 100) where the student distilled over ``N(0, I)`` scored 83 %; with the
    three scales at 0 complete runs ended at 86-88 % against 70-76 % after Stage I, over
    three seeds (``docs/harness.md``)."""

    policy_ema: float = 0.001
    """Polyak rate of the averaged copies of the student and the teacher that act and are
    evaluated (``0``: act with the raw networks, as the paper and the reference do). The
    flow loss, the critic and the TD bootstrap use the raw networks; the distillation target
    is the averaged teacher (``distill_from_ema``). Not in the paper: added because
    the closed-loop success of the raw networks swings between 5 % and 70 % from one
    10k-update checkpoint to the next on WindowInstall-A (``docs/qcfql.md``)."""

    online_lr: float | None = None
    """Adam's learning rate from Stage II on (online fine-tuning); ``None``: ``lr`` throughout
    (paper, reference). Stage I never reads it, so runs that differ only here share a Stage I
    (``ONLINE_FIELDS``). Not in the paper: more updates at ``lr`` on the 50 demonstrations
    past Stage I's 20,000 take both networks past their peak (WindowInstall-A, seed 1: the
    averaged student 20 -> 15 -> 11 -> 9 -> 9 of 20 dev seeds over 24,000 further demo-only
    updates, the averaged teacher 18 -> 17 -> 13 over 12,000), and the online phase's
    updates do the same more slowly (``docs/results/diagnoses/online-decline-a.md``)."""

    distill_from_ema: bool = True
    """Distil the student toward the averaged teacher (``ema_teacher``, rate ``policy_ema``)
    instead of the raw one (paper, reference). A stable target: over 10k updates on the
    demos the averaged student went 65 -> 80 % with it and 65 -> 45 % without
    (``docs/harness.md``). With ``policy_ema = 0`` both are the same network."""

    prior_data: str = "accepted_no_takeover"
    """Which replayed chunks the flow teacher (the behaviour prior, Eq. 8) learns from:
    ``"replay"``, every chunk of the batch (paper: "trained ... on replay data"; reference);
    ``"accepted"``, the chunks of episodes that ended in acceptance (all of D_demo, and the
    online episodes the acceptance check passed, their takeover segments included);
    ``"accepted_no_takeover"`` (default), the same without the takeover steps: the
    installer's takeovers still turn failing episodes into accepted ones, and the critic
    still learns from them, but the prior imitates only the demonstrations and the policy's
    own steps; ``"autonomous"``, the accepted episodes that had no takeover at all (D_demo
    and the policy's own successes: an episode the installer rescued also holds the policy's
    steps that needed rescuing); ``"demo"``, the chunks of D_demo only;
    ``"demo_and_takeover"``, D_demo and the installer's takeover steps whatever the episode's
    outcome (DAgger's data: the corrections at the states the policy reaches). The critic
    and the student use every chunk in all of them. Not in the paper: on WindowInstall-A,
    flow BC on all online chunks took the averaged student from 80 % to 5 % in 4k updates,
    and on the takeover steps alone to 0 %; complete runs ended at 20 % (``"replay"``), 40-80 % (``"accepted"``) and
    80-85 % (``"accepted_no_takeover"``) (``docs/harness.md``)."""

    distill_data: str = "batch"
    """Where the student is distilled toward the teacher (Eq. 9): ``"batch"`` (paper,
    reference), every row of the batch; ``"prior"`` (not in the paper), only the rows the
    flow teacher learns from (``prior_data``): the demonstrations and the accepted online
    episodes, not the states where the teacher extrapolates; ``"prior_else_self"`` (not in
    the paper), toward the teacher on those rows and toward the averaged student's own chunk
    ``mu_ema(s, z)`` on the others (a trust region: there the Q term alone moves the
    student, against the same ``alpha`` pull). The Q term acts on every row. On
    WindowInstall-B the teacher seats fewer episodes than its student, and 3,000
    distillation updates at the student's own states take the student down to the
    teacher's level (``docs/results/diagnoses/b-online.md``)."""

    fine_pose_mm: float = 0.0
    """Fine pose features (not in the paper; state track): ``0`` off; else the networks see,
    beside the z-scored observation, ``tanh(window_pos_rel / fine_pose_mm)`` and
    ``tanh(window_rot_rel / fine_pose_deg)``, which resolve the panel's millimetres and
    tenths of a degree around the seat where the z-score of a whole episode does not (on
    WindowInstall-B the vertical std of ``window_pos_rel`` over the demonstrations is 0.24 m:
    a 3 mm error is 0.01 standard deviations)."""
    fine_pose_deg: float = 1.0
    """Angle scale of the fine rotation features (used when ``fine_pose_mm > 0``)."""

    grasp_mm: float = 0.0
    """Grasp features (not in the paper; state track): ``0`` off; else the networks also see
    ``tanh`` of the TCP's offset from the panel's centre in the panel's face plane at this
    scale (:func:`window_bench.installer.supervisor.grasp_features`): where the cup holds
    the panel, which the z-scored state carries only as a millimetre difference of two
    positions spread over tenths of a metre."""

    tool_in_panel_m: float = 0.0
    """Tool features (not in the paper; state track): ``0`` off; else the networks also see
    ``tanh`` of the TCP's offset from the panel's centre in the panel's frame over this many
    metres (:func:`window_bench.installer.supervisor.tool_features`, 3 values): where the
    tool is relative to the panel, which with ``observed_keys`` leaving out the absolute
    positions is all a policy has to steer the pick by."""

    observed_keys: tuple[str, ...] | None = None
    """A diagnostic of what the privileged state gives the learner (state track, not in the
    paper): ``None``, every key of the flat state; else only these keys of
    :data:`~window_bench.envs.env.STATE_KEYS` reach the networks, the others enter as zeros
    (e.g. ``["robot0_proprio"]`` with ``fine_pose_mm`` is what a pixel agent with an exact
    pose read-out observes, less its view embeddings). The fine pose features are computed
    from the whole state."""

    takeover_value: float | None = None
    """The critic's target for a chunk of the policy's at whose end the installer takes over
    on a safety cue (``takeover_onset``, :func:`window_bench.data.chunks.chunk_transitions`).
    ``None`` (paper, HIL-SERL): such a chunk bootstraps through the takeover like any other,
    so a state the installer rescues from keeps the value of the rescue. A number (not in the
    paper; RLIF, Luo et al. 2023, treats a takeover as a failure signal): the policy's
    segment ends there, a terminal chunk with this reward, so the policy learns to stay out
    of the states that make the installer take over. The installer's own chunks are learnt
    from as before. Needs batches with ``takeover_onset`` (ChunkReplay's)."""

    demo_chunk_stride: int | None = None
    """Where D_demo's chunk windows start (:func:`window_bench.data.chunks.chunk_transitions`):
    ``None`` (paper, Eq. 4), on the fixed grid ``t = k*h``; ``1`` (the reference's sampling,
    not the paper's), at every step, ``h`` times as many distinct windows of the same 50
    demonstrations; any stride in ``1..h``. The online replay stays on the grid."""

    flow_trains_encoder: bool = False
    """Pixel track only (``window_bench.pixels.agent.PixelQCFQL``): the flow teacher's loss
    also trains the trainable aggregation of the camera features, beside the critic's
    (``False``: the critic's alone, as HIL-SERL and DrQ train their encoders). No effect on
    the state track, which has no encoder."""

    view_embeddings: bool = True
    """Pixel track only, a diagnostic: ``False`` zeroes both views' 32-value embeddings, so
    the networks see the proprioception and the track's pose read-out alone."""

    action_power: float = 1.0
    """Action companding (not in the paper): ``1`` (paper), the networks learn and output the
    env's actions; ``p > 1``, they learn and output ``c = sign(a) |a|^(1/p)`` for the arm's
    entries (not the vacuum) and the env receives ``sign(c) |c|^p``: a 1 mm step (0.04 action
    units) becomes 0.2 internal units at ``p = 2``, spreading the small corrections near
    contact over more of the regression's range."""

    offline_steps: int | None = None
    """Stage I's gradient steps: ``None``, the profile's (``cpu``: 20,000); a number (a
    diagnostic, not in the paper), this many. A short Stage I starts the online phase from a
    weak policy, as the paper's does (offline-only 78 / 75 %), to test whether the
    installer's takeovers fall as the policy improves."""

    binary_gripper: bool = False
    """Feed the critic the vacuum command as the env executes it (``+1`` where the last
    action entry of each step is > 0.5, else ``-1``) so that ``Q`` values realized chunks and
    the student's Q gradient never moves the vacuum entry (it is left to distillation)."""

    def __post_init__(self):
        self.hidden = tuple(self.hidden)
        if self.student_hidden is not None:
            self.student_hidden = tuple(self.student_hidden)
        for name in ("h", "num_critics", "flow_steps", "batch_size"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
                raise ValueError(f"QCFQLConfig.{name} = {value!r} is not allowed: it must be "
                                 f"an integer >= 1")
        def widths_ok(widths) -> bool:
            return bool(widths) and all(not isinstance(w, bool) and isinstance(w, numbers.Integral)
                                        and w >= 1 for w in widths)

        if not widths_ok(self.hidden):
            raise ValueError(f"QCFQLConfig.hidden = {self.hidden!r} is not allowed: it must be "
                             f"a non-empty tuple of integers >= 1")
        if self.student_hidden is not None and not widths_ok(self.student_hidden):
            raise ValueError(f"QCFQLConfig.student_hidden = {self.student_hidden!r} is not "
                             f"allowed: it must be null or a non-empty tuple of integers >= 1")
        # Finite bounds only: Infinity or 1e30 would pass an open range and crash later.
        checks = (("alpha", 0.0, 1e6, True), ("lr", 0.0, 1.0, False),
                  ("tau", 0.0, 1.0, False), ("gamma", 0.0, 1.0, True),
                  ("obs_std_floor", 0.0, 1.0, False),
                  ("act_noise_scale", 0.0, 10.0, True), ("td_noise_scale", 0.0, 10.0, True),
                  ("distill_noise_scale", 0.0, 10.0, True),
                  ("policy_ema", 0.0, 1.0, True)) + (
                      (("online_lr", 0.0, 1.0, False),) if self.online_lr is not None else ())
        for name, lo, hi, lo_ok in checks:
            value = getattr(self, name)
            ok = (isinstance(value, numbers.Real) and not isinstance(value, bool)
                  and (lo <= value if lo_ok else lo < value) and value <= hi)
            if not ok:
                interval = f"{'[' if lo_ok else '('}{lo}, {hi}]"
                raise ValueError(f"QCFQLConfig.{name} = {value!r} is not allowed: it must be "
                                 f"a real number in {interval}")
        for name in ("normalize_q_loss", "critic_layer_norm", "distill_from_ema",
                     "binary_gripper", "flow_trains_encoder", "view_embeddings"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"QCFQLConfig.{name} = {getattr(self, name)!r} is not "
                                 f"allowed: it must be true or false")
        check_fine_pose("QCFQLConfig", self.fine_pose_mm, self.fine_pose_deg)
        o = self.offline_steps
        if o is not None and (isinstance(o, bool) or not isinstance(o, numbers.Integral)
                              or not 0 <= o <= 10_000_000):
            raise ValueError(f"QCFQLConfig.offline_steps = {o!r} is not allowed: it must be "
                             f"null (the profile's) or an integer in [0, 10000000]")
        p = self.action_power
        if isinstance(p, bool) or not isinstance(p, numbers.Real) or not 1.0 <= p <= 4.0:
            raise ValueError(f"QCFQLConfig.action_power = {p!r} is not allowed: it must lie "
                             f"in [1.0, 4.0] (1: the env's actions)")
        g = self.grasp_mm
        if isinstance(g, bool) or not isinstance(g, numbers.Real) or not 0 <= g <= 1000:
            raise ValueError(f"QCFQLConfig.grasp_mm = {g!r} is not allowed: it must lie in "
                             f"[0.0, 1000.0] (0: off)")
        t = self.tool_in_panel_m
        if isinstance(t, bool) or not isinstance(t, numbers.Real) or not 0 <= t <= 10:
            raise ValueError(f"QCFQLConfig.tool_in_panel_m = {t!r} is not allowed: it must lie "
                             f"in [0.0, 10.0] (0: off)")
        if self.observed_keys is not None:
            from window_bench.envs.env import STATE_KEYS

            bad = [k for k in self.observed_keys if k not in STATE_KEYS]
            if bad or not self.observed_keys:
                raise ValueError(f"QCFQLConfig.observed_keys = {self.observed_keys!r} is not "
                                 f"allowed: a non-empty list of {', '.join(STATE_KEYS)}")
        if self.q_agg not in ("mean", "min"):
            raise ValueError(f"QCFQLConfig.q_agg = {self.q_agg!r} is not allowed: use 'mean' "
                             f"or 'min'")
        if self.gelu_approximate not in ("tanh", "none"):
            raise ValueError(f"QCFQLConfig.gelu_approximate = {self.gelu_approximate!r} is "
                             f"not allowed: use 'tanh' or 'none'")
        if self.prior_data not in PRIOR_DATA:
            raise ValueError(f"QCFQLConfig.prior_data = {self.prior_data!r} is not allowed: "
                             f"use one of {', '.join(map(repr, PRIOR_DATA))}")
        value = self.takeover_value
        if value is not None and (isinstance(value, bool) or not isinstance(value, numbers.Real)
                                  or not -1.0 <= value <= 1.0):
            raise ValueError(f"QCFQLConfig.takeover_value = {value!r} is not allowed: it must "
                             f"be null or a real number in [-1.0, 1.0]")
        if self.distill_data not in DISTILL_DATA:
            raise ValueError(f"QCFQLConfig.distill_data = {self.distill_data!r} is not "
                             f"allowed: use one of {', '.join(map(repr, DISTILL_DATA))}")
        if self.distill_data == "prior_else_self" and self.prior_data == "replay":
            raise ValueError("QCFQLConfig.distill_data = 'prior_else_self' needs prior_data "
                             "other than 'replay' (every row is a prior row there)")
        stride = self.demo_chunk_stride
        if stride is not None and (isinstance(stride, bool) or not isinstance(
                stride, numbers.Integral) or not 1 <= stride <= self.h):
            raise ValueError(f"QCFQLConfig.demo_chunk_stride = {stride!r} is not allowed: it "
                             f"must be null or an integer in 1..h = {self.h}")
        if self.distill_reduction not in ("sum", "mean"):
            raise ValueError(f"QCFQLConfig.distill_reduction = {self.distill_reduction!r} is "
                             f"not allowed: use 'sum' or 'mean'")


#: ``--agent-config`` overrides that give the paper's and the reference's agent back.
PAPER_AGENT = {"act_noise_scale": 1.0, "td_noise_scale": 1.0, "distill_noise_scale": 1.0,
               "policy_ema": 0.0, "distill_from_ema": False, "prior_data": "replay",
               "fine_pose_mm": 0.0, "grasp_mm": 0.0, "action_power": 1.0, "online_lr": None}

#: Named configurations: ``paper`` (Table 8's sizes, 4 x 512, with our defaults) and ``cpu`` (2 x 256 networks, about 6x
#: faster updates on one CPU thread; ``benchmarks/update_speed.py`` measures both).
PROFILES = {"paper": QCFQLConfig(), "cpu": QCFQLConfig(hidden=(256, 256))}

# ---------------------------------------------------------------------------- networks


def _xavier_(weight: torch.Tensor, fan_in: int, fan_out: int, gen: torch.Generator) -> None:
    """Xavier-uniform init of ``weight`` with explicit fans (a stacked ensemble weight has
    the fans of one member)."""
    bound = float(np.sqrt(6.0 / (fan_in + fan_out)))
    with torch.no_grad():
        weight.uniform_(-bound, bound, generator=gen)


class EnsembleCritic(nn.Module):
    """``num`` critics ``Q_i(s, u)`` with their own parameters, evaluated in one call.

    Member ``i``: hidden blocks Linear -> GELU(tanh) -> LayerNorm(eps 1e-6), output
    Linear(1) (``members[i].linears`` / ``members[i].norms``). The members run one after the
    other with plain ``F.linear``: on one CPU thread this measured faster than stacking the
    members' weights for ``torch.baddbmm`` or ``torch.vmap`` (``docs/qcfql.md``).
    """

    def __init__(self, in_dim: int, hidden: tuple[int, ...], num: int, layer_norm: bool,
                 gen: torch.Generator, gelu_approximate: str = "tanh"):
        super().__init__()
        self.num, self.layer_norm, self.gelu_approximate = num, layer_norm, gelu_approximate
        dims = (in_dim, *hidden, 1)
        self.members = nn.ModuleList()
        for _ in range(num):
            member = nn.Module()
            member.linears = nn.ModuleList([nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:])])
            member.norms = nn.ModuleList(
                [nn.LayerNorm(d, eps=1e-6) for d in hidden] if layer_norm else [])
            for lin in member.linears:
                _xavier_(lin.weight, lin.in_features, lin.out_features, gen)
                nn.init.zeros_(lin.bias)
            self.members.append(member)

    def forward(self, x: torch.Tensor, frozen: bool = False) -> torch.Tensor:
        """``x`` (B, in) -> Q values (num, B). ``frozen=True`` detaches the parameters, so a
        backward pass reaches the input (the student's chunk) but not the critic."""
        p = (lambda t: t.detach()) if frozen else (lambda t: t)
        out = []
        for member in self.members:
            y = x
            last = len(member.linears) - 1
            for i, lin in enumerate(member.linears):
                y = F.linear(y, p(lin.weight), p(lin.bias))
                if i == last:
                    break
                y = F.gelu(y, approximate=self.gelu_approximate)
                if self.layer_norm:
                    norm = member.norms[i]
                    y = F.layer_norm(y, y.shape[-1:], p(norm.weight), p(norm.bias), norm.eps)
            out.append(y.squeeze(-1))
        return torch.stack(out)


def _mlp(in_dim: int, out_dim: int, hidden: tuple[int, ...], gen: torch.Generator,
         gelu_approximate: str) -> MLP:
    """Linear -> GELU hidden blocks, linear output; Xavier-uniform weights, zero biases."""
    net = MLP(in_features=in_dim, out_features=out_dim, num_cells=list(hidden),
              activation_class=nn.GELU, activation_kwargs={"approximate": gelu_approximate})
    for module in net.modules():
        if isinstance(module, nn.Linear):
            _xavier_(module.weight, module.in_features, module.out_features, gen)
            nn.init.zeros_(module.bias)
    return net


class VectorField(nn.Module):
    """The flow teacher ``v(s, x_t, t)``: input ``concat(s, x_t, t)``, t a raw scalar in [0, 1).

    The observation part of the first layer is the same at every Euler step, so
    :meth:`integrate` computes it once.
    """

    def __init__(self, obs_dim: int, chunk_dim: int, hidden: tuple[int, ...],
                 gen: torch.Generator, gelu_approximate: str = "tanh"):
        super().__init__()
        self.obs_dim, self.chunk_dim = obs_dim, chunk_dim
        self.net = _mlp(obs_dim + chunk_dim + 1, chunk_dim, hidden, gen, gelu_approximate)

    def forward(self, obs: torch.Tensor, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([obs, x, t], dim=-1))

    def integrate(self, obs: torch.Tensor, z: torch.Tensor, steps: int) -> torch.Tensor:
        """Euler from ``x = z`` over ``steps`` steps, ``x += v(s, x, k/steps) / steps``;
        clipped to [-1, 1] at the end only (reference ``compute_flow_actions``)."""
        first, rest = self.net[0], list(self.net)[1:]
        w_obs = first.weight[:, :self.obs_dim]
        w_x = first.weight[:, self.obs_dim:self.obs_dim + self.chunk_dim]
        w_t = first.weight[:, -1]
        obs_part = torch.addmm(first.bias, obs, w_obs.t())
        x = z
        for k in range(steps):
            pre = torch.addmm(obs_part + (k / steps) * w_t, x, w_x.t())
            for layer in rest:
                pre = layer(pre)
            x = x + pre / steps
        return x.clamp(-1.0, 1.0)


class OneStepPolicy(nn.Module):
    """The student ``mu(s, z)``: input ``concat(s, z)``, output an unclipped chunk."""

    def __init__(self, obs_dim: int, chunk_dim: int, hidden: tuple[int, ...],
                 gen: torch.Generator, gelu_approximate: str = "tanh"):
        super().__init__()
        self.net = _mlp(obs_dim + chunk_dim, chunk_dim, hidden, gen, gelu_approximate)

    def forward(self, obs: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([obs, z], dim=-1))


# ---------------------------------------------------------------------------- agent

#: Keys :meth:`QCFQLAgent.update` reads from a batch (as made by ``chunk_transitions``).
BATCH_KEYS = ("obs", "actions", "action_mask", "reward", "next_obs", "discount", "terminal",
              "valid")


def _config_from(saved: dict) -> QCFQLConfig:
    """A config from a saved dict; fields added since it was saved take their defaults."""
    return config_from_plain(QCFQLConfig, saved)


class QCFQLAgent(Agent):
    """QC-FQL agent: critic ensemble, flow teacher, one-step student.

    Parameters
    ----------
    obs_dim : int
        Size of the flat observation.
    action_dim : int
        Size of one 10 Hz action (7 here); the chunk has ``h * action_dim`` values.
    config : QCFQLConfig
        Hyperparameters (copied).
    seed : int
        Seeds the network initialisation and the agent's two noise generators (one for
        :meth:`act`, one for :meth:`update`); the global torch RNG is neither used nor
        advanced.
    obs_mean, obs_std : np.ndarray, optional
        Fixed observation normaliser ``(obs - mean) / max(std, config.obs_std_floor)``,
        normally computed by the harness from the demonstrations. Default: identity.
    """

    follows_method_h = True   # h is the method's (Table 1) or the run's (Tables 5/6)

    def __init__(self, obs_dim: int, action_dim: int = 7, config: QCFQLConfig | None = None,
                 seed: int = 0, obs_mean: np.ndarray | None = None,
                 obs_std: np.ndarray | None = None):
        config = QCFQLConfig() if config is None else config
        if not isinstance(config, QCFQLConfig):
            raise TypeError(f"config must be a QCFQLConfig, got {type(config).__name__}")
        for name, value in (("obs_dim", obs_dim), ("action_dim", action_dim)):
            if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
                raise ValueError(f"{name} = {value!r} is not allowed: it must be an integer "
                                 f">= 1")
        if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
            raise ValueError(f"seed = {seed!r} is not allowed: it must be an integer >= 0")
        self.config = copy.deepcopy(config)
        self.obs_dim, self.action_dim, self.seed = int(obs_dim), int(action_dim), int(seed)
        self.chunk_dim = self.config.h * self.action_dim
        in_dim = obs_dim + extra_inputs(self.config, self.obs_dim)   # what the networks see
        self.num_updates = 0

        mean = np.zeros(obs_dim) if obs_mean is None else np.asarray(obs_mean, np.float64)
        std = np.ones(obs_dim) if obs_std is None else np.asarray(obs_std, np.float64)
        for name, arr in (("obs_mean", mean), ("obs_std", std)):
            if arr.shape != (obs_dim,) or not np.all(np.isfinite(arr)):
                raise ValueError(f"{name}: expected {obs_dim} finite values, got shape "
                                 f"{arr.shape}")
        self.obs_mean = torch.as_tensor(mean, dtype=torch.float32)
        self.obs_std = torch.as_tensor(np.maximum(std, self.config.obs_std_floor),
                                       dtype=torch.float32)

        cfg = self.config
        init_gen = torch.Generator().manual_seed(self.seed)
        act = cfg.gelu_approximate
        self.critic = EnsembleCritic(in_dim + self.chunk_dim, cfg.hidden, cfg.num_critics,
                                     cfg.critic_layer_norm, init_gen, act)
        self.teacher = VectorField(in_dim, self.chunk_dim, cfg.hidden, init_gen, act)
        self.student = OneStepPolicy(in_dim, self.chunk_dim, cfg.student_hidden or cfg.hidden,
                                     init_gen, act)
        self.target_critic = copy.deepcopy(self.critic).requires_grad_(False)
        self._params = [*self.critic.parameters(), *self.teacher.parameters(),
                        *self.student.parameters()]
        # fused Adam: one kernel for all parameters (the same update rule as Adam)
        self.optimizer = torch.optim.Adam(self._params, lr=cfg.lr, fused=True)
        self._online = list(self.critic.parameters())
        self._target = list(self.target_critic.parameters())
        # the acting policy: Polyak averages of the student and the teacher (policy_ema)
        self.ema_student = copy.deepcopy(self.student).requires_grad_(False)
        self.ema_teacher = copy.deepcopy(self.teacher).requires_grad_(False)
        self._policy = [*self.student.parameters(), *self.teacher.parameters()]
        self._ema = [*self.ema_student.parameters(), *self.ema_teacher.parameters()]
        # separate streams: evaluation rollouts do not shift the training noise
        self.act_generator = torch.Generator().manual_seed(self.seed + 1)
        self.update_generator = torch.Generator().manual_seed(self.seed + 2)

    # ------------------------------------------------------------------ the harness's interface
    #: What ``bench run`` sets beside the config's defaults (not in the paper; ``--agent-config``
    #: entries win): the fine pose and grasp features and action companding, which seat
    #: setting B (revision 2 of the defaults; docs/results/diagnoses/b-resolution.md), and a
    #: 10x lower learning rate online, which keeps Stage I's peak on A (revision 3;
    #: docs/results/diagnoses/online-decline-a.md). ``PAPER_AGENT`` turns them off.
    RUN_DEFAULTS = {"fine_pose_mm": 10.0, "fine_pose_deg": 2.0, "grasp_mm": 10.0,
                    "action_power": 2.0, "online_lr": 3e-5}

    #: Settings Stage I never reads: runs that differ only here share a Stage I. On D_demo alone
    #: every row is accepted and no chunk holds a takeover, so the prior, the distillation and
    #: the takeover target select every row whatever they are set to
    #: (``tests/test_qcfql.py::test_online_fields_leave_stage_i_bit_identical``).
    ONLINE_FIELDS = ("online_lr", "prior_data", "distill_data", "takeover_value")

    @classmethod
    def make_config(cls, h: int, profile, overrides: dict) -> QCFQLConfig:
        return with_overrides(QCFQLConfig(h=h, hidden=tuple(profile.hidden),
                                          batch_size=profile.batch_size),
                              {**cls.RUN_DEFAULTS, **overrides})

    @property
    def h(self) -> int:
        return self.config.h

    @property
    def demo_chunk_stride(self) -> int | None:
        return self.config.demo_chunk_stride

    @property
    def offline_steps(self) -> int | None:
        """Stage I gradient steps for the harness: the config's, None for the profile's."""
        return self.config.offline_steps

    def begin_online(self) -> None:
        """From Stage II on, Adam steps at ``config.online_lr`` (when set)."""
        if self.config.online_lr is not None:
            for group in self.optimizer.param_groups:
                group["lr"] = self.config.online_lr

    def learn(self, sample) -> tuple[dict[str, float], int]:
        """One :meth:`update` on one batch."""
        return self.update(sample()), 1

    # ------------------------------------------------------------------ helpers
    def normalize(self, obs: torch.Tensor) -> torch.Tensor:
        """``(obs - mean) / std`` with the fixed normaliser, clipped to ``+-OBS_CLIP``: a state
        far outside the demonstrations (a dropped panel, a violent contact) stays a large but
        bounded input instead of thousands of standard deviations. With ``fine_pose_mm`` the
        fine pose features follow, then with ``grasp_mm`` the grasp features, then with
        ``tool_in_panel_m`` the tool features
        (:class:`QCFQLConfig`)."""
        z = ((obs - self.obs_mean) / self.obs_std).clamp(-OBS_CLIP, OBS_CLIP)
        if self.config.observed_keys is not None:
            z = z * self._observed_mask(z.shape[-1])
        c = self.config
        extra = extra_features(obs, c.fine_pose_mm, c.fine_pose_deg, c.grasp_mm,
                               c.tool_in_panel_m)
        return torch.cat([z, *[e.to(z.dtype) for e in extra]], dim=-1) if extra else z

    def _observed_mask(self, dim: int) -> torch.Tensor:
        """1 on the flat state's columns of ``config.observed_keys``, 0 elsewhere."""
        from window_bench.installer.supervisor import FLAT_DIM, FLAT_SLICES

        if dim != FLAT_DIM:
            raise ValueError(f"QCFQLConfig.observed_keys needs the flat state observation "
                             f"({FLAT_DIM} values); obs_dim = {dim}")
        mask = torch.zeros(dim)
        for key in self.config.observed_keys:
            mask[FLAT_SLICES[key]] = 1.0
        return mask

    def _power(self, chunks: torch.Tensor, exponent: float) -> torch.Tensor:
        """``sign(x) |x|^exponent`` on the arm's entries of (..., h, A) chunks."""
        return chunks if self.config.action_power == 1.0 else arm_power(chunks, exponent)

    def _noise(self, batch: int) -> torch.Tensor:
        return torch.randn(batch, self.chunk_dim, generator=self.update_generator)

    def prepare(self, batch: Mapping) -> dict[str, torch.Tensor]:
        """Batch (TensorDict or dict of tensors/arrays, keys :data:`BATCH_KEYS`) -> float32
        tensors with normalised observations and flattened chunks. Raises ``ValueError`` on
        a missing key or a shape that does not fit this agent."""
        missing = [k for k in BATCH_KEYS if k not in batch.keys()]
        if missing:
            raise ValueError(f"QCFQLAgent.update: batch lacks keys {missing}; expected "
                             f"{BATCH_KEYS} (chunk_transitions' layout)")
        t = {k: torch.as_tensor(batch[k]) for k in BATCH_KEYS}
        B = t["obs"].shape[0]
        h, A = self.config.h, self.action_dim
        expected = {"obs": (B, self.obs_dim), "next_obs": (B, self.obs_dim),
                    "actions": (B, h, A), "action_mask": (B, h), "reward": (B,),
                    "discount": (B,), "terminal": (B,), "valid": (B,)}
        for key, shape in expected.items():
            if tuple(t[key].shape) != shape:
                raise ValueError(f"QCFQLAgent.update: batch[{key!r}] has shape "
                                 f"{tuple(t[key].shape)}, expected {shape} (h = {h}, "
                                 f"action_dim = {A}, obs_dim = {self.obs_dim})")
        f32 = torch.float32
        if self.config.takeover_value is not None:
            t["terminal"], t["reward"] = self.end_at_takeover(batch, t["terminal"], t["reward"])
        return {"prior_mask": self.prior_mask(batch, B),
                "obs": self.normalize(t["obs"].to(f32)),
                "next_obs": self.normalize(t["next_obs"].to(f32)),
                "actions": self._power(t["actions"].to(f32),
                                       1.0 / self.config.action_power).reshape(B, h * A),
                "action_mask": t["action_mask"].to(f32),
                "reward": t["reward"].to(f32), "discount": t["discount"].to(f32),
                "not_terminal": 1.0 - t["terminal"].to(f32), "valid": t["valid"].to(f32)}

    def end_at_takeover(self, batch: Mapping, terminal: torch.Tensor,
                        reward: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``terminal`` and ``reward`` with every ``takeover_onset`` chunk made terminal with
        reward ``config.takeover_value``; a batch without the key raises ``ValueError``."""
        if "takeover_onset" not in batch.keys():
            raise ValueError(f"QCFQLAgent.update: takeover_value = "
                             f"{self.config.takeover_value!r} needs batch['takeover_onset'] "
                             f"(ChunkReplay batches carry it); use takeover_value=None for "
                             f"batches without it")
        onset = torch.as_tensor(batch["takeover_onset"]).bool()
        if tuple(onset.shape) != tuple(reward.shape):
            raise ValueError(f"QCFQLAgent.update: batch['takeover_onset'] has shape "
                             f"{tuple(onset.shape)}, expected {tuple(reward.shape)}")
        value = torch.full_like(reward, float(self.config.takeover_value), dtype=torch.float32)
        return terminal.bool() | onset, torch.where(onset, value, reward.float())

    def prior_mask(self, batch: Mapping, B: int) -> torch.Tensor | None:
        """(B, h) float 0/1: the steps the flow teacher learns from (``config.prior_data``);
        ``None`` for ``"replay"`` (every step). ``"accepted"`` reads ``episode_accepted``,
        ``"demo"`` reads ``provenance_code``, ``"accepted_no_takeover"`` both; a batch
        without a key needed raises ``ValueError``."""
        mode, h = self.config.prior_data, self.config.h
        if mode == "replay":
            return None
        needs = {"accepted": ("episode_accepted",), "demo": ("provenance_code",),
                 "demo_and_takeover": ("provenance_code",),
                 "accepted_no_takeover": ("episode_accepted", "provenance_code"),
                 "autonomous": ("episode_accepted", "episode_supervised")}[mode]
        shapes = {"episode_accepted": (B,), "episode_supervised": (B,), "provenance_code": (B, h)}
        values = {}
        for key in needs:
            if key not in batch.keys():
                raise ValueError(f"QCFQLAgent.update: prior_data = {mode!r} needs "
                                 f"batch[{key!r}] (ChunkReplay batches carry it); use "
                                 f"prior_data='replay' for batches without it")
            values[key] = torch.as_tensor(batch[key])
            if tuple(values[key].shape) != shapes[key]:
                raise ValueError(f"QCFQLAgent.update: batch[{key!r}] has shape "
                                 f"{tuple(values[key].shape)}, expected {shapes[key]}")
        mask = torch.ones(B, h, dtype=torch.bool)
        if "episode_accepted" in values:
            mask &= values["episode_accepted"].bool().unsqueeze(-1)
        if mode == "demo":
            mask &= (values["provenance_code"] == DEMO_CODE).any(-1, keepdim=True)
        if mode == "demo_and_takeover":
            prov = values["provenance_code"]
            mask &= (prov == DEMO_CODE).any(-1, keepdim=True) | (prov == TAKEOVER_CODE)
        if mode == "accepted_no_takeover":
            mask &= values["provenance_code"] != TAKEOVER_CODE
        if mode == "autonomous":
            mask &= ~values["episode_supervised"].bool().unsqueeze(-1)
        return mask.float()

    # ------------------------------------------------------------------ losses
    def critic_input(self, obs: torch.Tensor, chunk: torch.Tensor) -> torch.Tensor:
        """``concat(s, flat chunk)``; with ``binary_gripper`` the vacuum entries are replaced
        by the command the env executes (``VACUUM_THRESHOLD``, as the env's ``step``)."""
        if self.config.binary_gripper:
            steps = chunk.reshape(chunk.shape[0], self.config.h, self.action_dim)
            vac = torch.where(steps[..., -1:] > VACUUM_THRESHOLD, 1.0, -1.0)
            chunk = torch.cat([steps[..., :-1], vac], dim=-1).reshape(chunk.shape[0], -1)
        return torch.cat([obs, chunk], dim=-1)

    def td_target(self, b: dict[str, torch.Tensor]) -> torch.Tensor:
        """Eq. 6: ``R + gamma^h (1 - terminal) agg_i Qbar_i(s', clip(mu(s', z')))``, with
        ``z' ~ N(0, I)`` scaled by ``config.td_noise_scale``."""
        with torch.no_grad():
            z = self.config.td_noise_scale * self._noise(len(b["reward"]))
            next_u = self.student(b["next_obs"], z).clamp(-1, 1)
            next_q = self.target_critic(self.critic_input(b["next_obs"], next_u))
            next_q = next_q.mean(0) if self.config.q_agg == "mean" else next_q.min(0).values
            return b["reward"] + b["discount"] * b["not_terminal"] * next_q

    def critic_loss(self, b: dict[str, torch.Tensor],
                    y: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Eq. 7 over the members and the batch; invalid (truncated short) windows are
        zeroed, and the mean keeps them in the denominator as the reference does.
        ``y`` defaults to :meth:`td_target`. Returns ``(loss, q)``, ``q`` (num_critics, B)."""
        y = self.td_target(b) if y is None else y
        q = self.critic(self.critic_input(b["obs"], b["actions"]))
        loss = ((q - y).square() * b["valid"]).mean()
        return loss, q.detach()

    def flow_loss(self, b: dict[str, torch.Tensor]) -> torch.Tensor:
        """Eq. 8 (rectified flow BC), one ``t ~ U[0, 1)`` per sample; squared error masked per
        step by ``action_mask``, mean over all B x h x A entries (reference). Steps outside
        ``b["prior_mask"]`` (``config.prior_data``) are masked too, and the mean is then
        over the entries of the rows with a kept step (0 if none is kept)."""
        x1 = b["actions"]
        B = x1.shape[0]
        x0 = self._noise(B)
        t = torch.rand(B, 1, generator=self.update_generator)
        x_t = (1.0 - t) * x0 + t * x1
        err = (self.teacher(b["obs"], x_t, t) - (x1 - x0)).square()
        err = err.view(B, self.config.h, self.action_dim) * b["action_mask"].unsqueeze(-1)
        keep = b.get("prior_mask")
        if keep is None:
            return err.mean()
        rows = (keep > 0).any(-1).sum().clamp_min(1)
        return (err * keep.unsqueeze(-1)).sum() / (rows * err[0].numel())

    def teacher_actions(self, obs: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """``a_xi(s, z)``: the distillation target, the teacher's chunk from noise ``z`` (no
        gradient); the averaged teacher when ``config.distill_from_ema``."""
        teacher = self.ema_teacher if self.config.distill_from_ema else self.teacher
        with torch.no_grad():
            return teacher.integrate(obs, z, self.config.flow_steps)

    def actor_loss(self, b: dict[str, torch.Tensor], z: torch.Tensor | None = None,
                   target: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Eq. 9: ``alpha * distill - mean_i Q_i(s, clip(mu(s, z)))``, critic frozen, teacher
        detached, the SAME ``z`` for both (drawn here unless given, scaled by
        ``config.distill_noise_scale``; ``target`` may pass a
        precomputed ``teacher_actions(obs, z)``)."""
        obs = b["obs"]
        z = self.config.distill_noise_scale * self._noise(obs.shape[0]) if z is None else z
        target = self.teacher_actions(obs, z) if target is None else target
        if self.config.distill_data == "prior_else_self":   # trust region off the prior rows
            prior_rows = (b["prior_mask"] > 0).any(-1, keepdim=True)
            with torch.no_grad():
                target = torch.where(prior_rows, target, self.ema_student(obs, z))
        u = self.student(obs, z)
        sq = (u - target).square()
        per_row = sq.sum(-1) if self.config.distill_reduction == "sum" else sq.mean(-1)
        keep = b.get("prior_mask") if self.config.distill_data == "prior" else None
        if keep is None:
            distill = per_row.mean()
        else:   # only where the teacher learnt: the rows with a step the prior trains on
            rows = (keep > 0).any(-1).to(per_row.dtype)
            distill = (per_row * rows).sum() / rows.sum().clamp_min(1.0)
        q_pi = self.critic(self.critic_input(obs, u.clamp(-1.0, 1.0)), frozen=True).mean(0)
        q_loss = -q_pi.mean()
        if self.config.normalize_q_loss:
            q_loss = q_loss / q_pi.abs().mean().detach().clamp_min(1e-6)
        return {"loss": self.config.alpha * distill + q_loss, "distill": distill,
                "q_loss": q_loss, "q_pi": q_pi.detach()}

    # ------------------------------------------------------------------ update
    def polyak(self) -> None:
        """``target <- target + tau (online - target)`` for every critic parameter, and the
        same with rate ``policy_ema`` for the acting copies of the student and the teacher
        (``policy_ema = 0``: they are kept equal to the raw networks)."""
        with torch.no_grad():
            torch._foreach_lerp_(self._target, self._online, self.config.tau)
            torch._foreach_lerp_(self._ema, self._policy, self.config.policy_ema or 1.0)

    def update(self, batch: Mapping) -> dict[str, float]:
        """One gradient step on all three networks plus the Polyak step; returns metrics.

        ``batch``: keys :data:`BATCH_KEYS` as produced by ``chunk_transitions`` /
        :class:`window_bench.data.replay.ChunkReplay` (``obs`` (B, obs_dim), ``actions`` (B, h, 7),
        ``action_mask`` (B, h), ``reward``, ``discount``, ``terminal``, ``valid`` (B,)).
        """
        b = self.prepare(batch)
        critic_loss, q = self.critic_loss(b)
        flow_loss = self.flow_loss(b)
        actor = self.actor_loss(b)
        loss = critic_loss + flow_loss + actor["loss"]
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        self.polyak()
        self.num_updates += 1
        values = torch.stack([
            loss.detach(), critic_loss.detach(), flow_loss.detach(), actor["distill"].detach(),
            actor["q_loss"].detach(), actor["loss"].detach(), q.mean(), q.max(), q.min(),
            actor["q_pi"].mean(), b["valid"].mean()]).tolist()
        names = ("loss", "critic_loss", "flow_loss", "distill_loss", "q_loss", "actor_loss",
                 "q_mean", "q_max", "q_min", "q_policy", "valid_fraction")
        return dict(zip(names, values))

    # ------------------------------------------------------------------ acting
    def _obs_tensor(self, obs) -> tuple[torch.Tensor, bool]:
        o = torch.as_tensor(np.asarray(obs, dtype=np.float32))
        single = o.ndim == 1
        o = o.unsqueeze(0) if single else o
        if o.ndim != 2 or o.shape[1] != self.obs_dim:
            raise ValueError(f"obs: expected shape ({self.obs_dim},) or (B, {self.obs_dim}), "
                             f"got {tuple(np.shape(obs))}")
        return self.normalize(o), single

    @torch.no_grad()
    def act(self, obs: np.ndarray, deterministic: bool = False,
            policy: str = "student") -> np.ndarray:
        """Action chunk(s) for ``obs`` (obs_dim,) or (B, obs_dim): (h, A) or (B, h, A) float32
        in [-1, 1].

        ``z ~ N(0, I)`` from the agent's act generator (``deterministic=True``: ``z = 0``).
        ``policy="student"`` is the one-step actor ``mu(s, z)``; ``policy="teacher"`` runs the
        flow prior (K Euler steps), for the "flow BC only" ablation. Both act with their
        Polyak-averaged copies (``config.policy_ema``).
        """
        if policy not in ("student", "teacher"):
            raise ValueError(f"policy = {policy!r} is not allowed: use 'student' or 'teacher'")
        o, single = self._obs_tensor(obs)
        B = o.shape[0]
        z = (torch.zeros(B, self.chunk_dim) if deterministic
             else self.config.act_noise_scale
             * torch.randn(B, self.chunk_dim, generator=self.act_generator))
        u = (self.ema_student(o, z).clamp(-1.0, 1.0) if policy == "student"
             else self.ema_teacher.integrate(o, z, self.config.flow_steps))
        u = self._power(u.view(B, self.config.h, self.action_dim),
                        self.config.action_power).numpy()
        return u[0] if single else u

    @torch.no_grad()
    def q_values(self, obs: np.ndarray, chunks: np.ndarray) -> np.ndarray:
        """Critic values (num_critics, B) of chunks (B, h, A) at observations (B, obs_dim)."""
        o, _ = self._obs_tensor(obs)
        u = torch.as_tensor(np.asarray(chunks, dtype=np.float32))
        u = self._power(u, 1.0 / self.config.action_power).reshape(o.shape[0], -1)
        return self.critic(self.critic_input(o, u)).numpy()

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        """Everything for an exact resume (copies): config, dims, seed, the six networks,
        the optimizer, both noise generators, the normaliser and the update count."""
        return copy.deepcopy({
            **self.policy_state_dict(), "num_updates": self.num_updates,
            **{name: module_state(getattr(self, name)) for name in (
                "critic", "target_critic", "teacher", "student", "ema_teacher")},
            "optimizer": optimizer_state(self.optimizer),
            "act_generator": self.act_generator.get_state(),
            "update_generator": self.update_generator.get_state()})

    def policy_state_dict(self) -> dict:
        """The acting policy only: the averaged student, the normaliser, sizes and config."""
        return {"config": plain(asdict(self.config)), "obs_dim": self.obs_dim,
                "action_dim": self.action_dim, "seed": self.seed,
                "obs_mean": self.obs_mean.clone(), "obs_std": self.obs_std.clone(),
                "ema_student": module_state(self.ema_student)}

    @classmethod
    def from_policy_state_dict(cls, sd: dict) -> "QCFQLAgent":
        """An agent that acts like the one :meth:`policy_state_dict` came from (its other
        networks keep their initial weights: for acting only)."""
        agent = cls(sd["obs_dim"], sd["action_dim"], _config_from(sd["config"]), seed=sd["seed"])
        agent.obs_mean, agent.obs_std = sd["obs_mean"].clone(), sd["obs_std"].clone()
        agent.ema_student.load_state_dict(sd["ema_student"])
        return agent

    def load_state_dict(self, sd: dict) -> None:
        """Restore :meth:`state_dict` output. The network structure (obs_dim, action_dim, h,
        hidden, num_critics, critic_layer_norm, gelu_approximate) must match this agent (``ValueError``
        otherwise); the other hyperparameters are taken from ``sd``."""
        saved = _config_from(sd["config"])
        structural = {"obs_dim": (sd["obs_dim"], self.obs_dim),
                      "action_dim": (sd["action_dim"], self.action_dim)}
        for name in ("h", "hidden", "student_hidden", "num_critics", "critic_layer_norm",
                     "gelu_approximate", "fine_pose_mm", "grasp_mm", "tool_in_panel_m"):
            structural[name] = (getattr(saved, name), getattr(self.config, name))
        for name, (theirs, ours) in structural.items():
            if theirs != ours:
                raise ValueError(f"QCFQLAgent.load_state_dict: {name} = {theirs!r} in the "
                                 f"state dict, {ours!r} in this agent")
        sd = copy.deepcopy(sd)
        self.config, self.seed, self.num_updates = saved, sd["seed"], sd["num_updates"]
        self.obs_mean, self.obs_std = sd["obs_mean"], sd["obs_std"]
        for name in ("critic", "target_critic", "teacher", "student"):
            getattr(self, name).load_state_dict(sd[name])
        for name in ("teacher", "student"):   # states saved before policy_ema act raw
            getattr(self, f"ema_{name}").load_state_dict(sd.get(f"ema_{name}", sd[name]))
        load_optimizer_state(self.optimizer, sd["optimizer"])
        self.act_generator.set_state(sd["act_generator"])
        self.update_generator.set_state(sd["update_generator"])

    @classmethod
    def from_state_dict(cls, sd: dict) -> "QCFQLAgent":
        """A new agent restored from :meth:`state_dict` output."""
        config = _config_from(sd["config"])
        agent = cls(sd["obs_dim"], sd["action_dim"], config, seed=sd["seed"])
        agent.load_state_dict(sd)
        return agent
