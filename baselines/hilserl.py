"""HIL-SERL: the SAC/RLPD learner with binary takeovers, step-wise (``h = 1``), on TorchRL parts.

This is the ``hil-serl`` baseline of the paper's Table 1 (Section 4.3): a unimodal
tanh-Gaussian actor and a LayerNorm critic ensemble trained by soft actor-critic on
symmetric batches (half demonstrations, half online experience, as in RLPD), with offline
pretraining, a non-updating warm start and installer takeovers. ``offline_steps=0`` drops
the offline pretraining (HIL-SERL's and RLPD's own protocol); ``suction_loss_terminal``
values a lost panel at 0 in the TD targets (an experiment of this benchmark, off by
default; docs/baselines.md). The harness
(``window_bench.harness.run``) owns the stages, the buffers and the takeovers; this module owns
the learner and two rules the harness applies:

* :func:`hilserl_buffers_for` - where a step of a given provenance is stored. As in HIL-SERL,
  every online transition goes to the online buffer and transitions executed by a takeover
  ALSO go to the demo buffer (the harness cuts them out of an episode log with
  :func:`~window_bench.harness.agent.takeover_segments`, as ``takeovers_to_demo`` asks).
* :func:`symmetric_sampler` - a ``sample() -> TensorDict`` that draws exactly half of every
  batch from the demo buffer (``window_bench.data.replay.mixed_batch`` does the same for two
  :class:`~window_bench.data.replay.ChunkReplay` buffers).

Defaults follow HIL-SERL's learner for a single arm with a learnt gripper
(``serl_launcher`` ``SACAgentHybridSingleArm`` as configured by
``make_sac_pixel_agent_hybrid_single_arm``): 2 critics with LayerNorm and tanh activations,
256x256, target = min over both, no entropy backup, temperature initialised at 0.01, target
entropy ``-|A|/2``, critic-to-actor ratio 2; the actor and the critics cover the 6 pose
dimensions and a separate grasp critic (a DQN head over the three vacuum commands
{release, stay, engage}, double-DQN target, Polyak target network, trained with every
critic step on the task reward plus the toggle penalty ``grasp_penalty``) chooses the
vacuum by argmax. ``vacuum_head="gaussian"`` keeps the vacuum as a 7th Gaussian dimension;
``vacuum_head="held"`` is HIL-SERL's fixed-gripper setup for tasks that start grasped
(every action commands "hold"); ``vacuum_head="binary"`` is the earlier two-way grasp
critic over {release, hold}, kept so that policies saved with it still act. Normalised
observations are clipped to +-10 (QC-FQL). RLPD's variant (10 critics, target = min over 2
members drawn without replacement, ReLU, entropy backup, temperature 1.0) is a
configuration: :data:`RLPD_CONFIG`; HIL-SERL's own protocol (no offline pretraining, its
discount and std bounds) is the preset :data:`HILSERL_OWN`. Deviations from HIL-SERL, all
disclosed in ``docs/baselines.md``: the discount is the paper's 0.99 (HIL-SERL's examples use
0.97-0.98), the log-std is clipped to [-20, 2] (RLPD; HIL-SERL clips the std to [1e-5, 5]),
the temperature loss uses the actor's samples on ``obs`` (HIL-SERL's uses samples on
``next_obs``), observations are z-scored with demo statistics, and there is no image encoder
(the flat 52-float state is the input).

Why the losses are written here instead of ``torchrl.objectives.SACLoss`` (0.14): SACLoss
always subtracts the entropy term in the TD target (HIL-SERL turns the backup off), takes
the target min over every member (RLPD draws 2 of 10), trains the actor on the min over
members (RLPD and HIL-SERL use the mean), and samples with the global torch RNG (an exact
resume needs the agent's own generators). The networks are TorchRL :class:`~torchrl.modules.MLP`
stacks; batches are :class:`~tensordict.TensorDict` (keys of
:func:`window_bench.data.chunks.chunk_transitions` with ``h = 1``).
"""

from __future__ import annotations

import copy
import dataclasses
import math
import numbers
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F
from tensordict import TensorDict
from torch import nn
from torchrl.modules import MLP

from window_bench.data.steplog import PROVENANCES, EpisodeLog
from window_bench.harness.agent import (Agent, config_from_plain, load_optimizer_state,
                                        module_state, optimizer_state, plain, with_overrides)
from window_bench.envs.env import (POS_SCALE, ROT_SCALE, VACUUM_THRESHOLD, mat_to_rotvec,
                                   rotvec_to_mat)
from window_bench.installer.supervisor import (FLAT_DIM, FLAT_SLICES, check_fine_pose,
                                              fine_pose_features, extra_inputs)

_ACTIVATIONS = {"tanh": nn.Tanh, "relu": nn.ReLU}
#: Batch keys the learner reads (``valid`` is optional and defaults to all True; the
#: optional ``vacuum_flag`` gives the vacuum flag of ``obs`` where ``obs`` is not the flat
#: state, see :meth:`HILSERLAgent.act`).
BATCH_KEYS = ("obs", "actions", "reward", "next_obs", "discount", "terminal")
_HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)
#: How the last action dimension (the vacuum) is learnt; see :class:`HILSERLConfig`.
VACUUM_HEADS = ("discrete", "gaussian", "held", "binary")
#: The executed vacuum values: the environment engages the vacuum iff ``action[6]`` exceeds
#: ``VACUUM_THRESHOLD`` and releases it otherwise.
VACUUM_OFF, VACUUM_ON = -1.0, 1.0
#: The grasp critic's commands (HIL-SERL's gripper actions -1, 0, +1, its outputs 0, 1, 2):
#: release, stay (keep the current vacuum state), engage.
VACUUM_COMMANDS = ("release", "stay", "engage")
RELEASE, STAY, ENGAGE = range(len(VACUUM_COMMANDS))
#: The ``"binary"`` head's commands, executed as ``VACUUM_OFF`` and ``VACUUM_ON``.
BINARY_COMMANDS = ("release", "hold")
#: Index of the vacuum flag (``robot0_vacuum``: 1 while the panel is held) in the flat state
#: observation, which concatenates ``STATE_KEYS`` in order; and that observation's size.
VACUUM_OBS_INDEX = FLAT_SLICES["robot0_vacuum"].start
FLAT_OBS_DIM = FLAT_DIM


# --------------------------------------------------------------------------- configuration
def _check_int(name: str, value, minimum: int) -> None:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
        raise ValueError(f"{name} = {value!r} is not allowed: it must be an integer "
                         f">= {minimum}")


@dataclass(frozen=True)
class HILSERLConfig:
    """Hyperparameters of the HIL-SERL learner (defaults: HIL-SERL; see :data:`RLPD_CONFIG`).

    Attributes
    ----------
    hidden : tuple of int
        Hidden widths of the actor and of every critic member.
    activation : {"tanh", "relu"}
        Hidden activation (HIL-SERL: tanh; RLPD: ReLU). Each hidden layer is
        Linear -> LayerNorm (if enabled) -> activation.
    critic_layernorm, actor_layernorm : bool
        LayerNorm after every hidden Linear of the critics / the actor (HIL-SERL: both).
    num_critics : int
        Critic ensemble size (HIL-SERL 2, RLPD 10).
    num_min : int
        The TD target takes the min over this many members drawn without replacement
        (``num_min == num_critics``: the min over all; RLPD: 2 of 10).
    log_std_min, log_std_max : float
        Clip of the actor's log standard deviation.
    init_temperature : float
        Initial entropy temperature alpha (HIL-SERL 0.01, RLPD 1.0).
    target_entropy : float or None
        Target policy entropy; None means ``-action_dim / 2``.
    backup_entropy : bool
        Subtract ``alpha * log pi(a'|s')`` in the TD target (HIL-SERL False, RLPD True).
    gamma : float
        Per-step discount; batches must carry ``discount == gamma`` (``h = 1``).
    tau : float
        Polyak rate of the target critics, applied after every critic step.
    actor_lr, critic_lr, temperature_lr : float
        Adam learning rates.
    batch_size : int
        Rows per gradient step (even: half demo, half online).
    critic_actor_ratio : int
        Critic steps per :meth:`HILSERLAgent.update` call; the actor and temperature step
        once per call, on the last critic step's batch.
    obs_std_floor : float
        Floor on the observation standard deviation used for z-scoring (constant features,
        e.g. the vacuum flag in demonstrations from the rack, would divide by zero).
    obs_clip : float or None
        Normalised observations are clipped to ``+-obs_clip`` (QC-FQL's 10): a state never
        seen in the demonstrations cannot drive the networks arbitrarily far. None: no clip.
    vacuum_head : {"discrete", "gaussian", "held", "binary"}
        How the vacuum command (the last action dimension) is learnt. ``"discrete"``
        (HIL-SERL's ``SACAgentHybridSingleArm``): the tanh-Gaussian actor and the critic
        ensemble cover the pose dimensions only, and a separate grasp critic ``Q_g(s, .)``
        over the commands :data:`VACUUM_COMMANDS` {release, stay, engage} is trained by
        double DQN and acts by argmax; "stay" executes the current state, read from the
        observation's vacuum flag. A stored action is labelled by what it did to that state
        (:func:`grasp_command_labels`). ``"gaussian"``: the vacuum is one more dimension of
        the tanh-Gaussian, engaged iff it exceeds :data:`VACUUM_THRESHOLD` (plain SAC for
        tasks without a vacuum). ``"held"`` (HIL-SERL's ``single-arm-fixed-gripper``
        setup, its ``GripperCloseEnv``, for insertion tasks that start with the part
        grasped): nothing learns the vacuum; the actor and the critic ensemble cover the
        pose dimensions and every action commands "hold". For setting A, whose panel starts
        held and is accepted while held; in B it would engage the cup wherever it comes
        within reach. ``"binary"``: this baseline's earlier grasp critic over
        {release, hold}, without the toggle penalty; policies saved with it load as it.
    grasp_penalty : float
        Added to the grasp critic's reward (and only there: the critics learn the task
        reward) on every step whose command changes the vacuum state, a release while held
        or an engage while not, as HIL-SERL's ``GripperPenaltyWrapper`` marks a gripper
        toggle. -0.02, its value for a single-arm learnt gripper. ``"discrete"`` only; <= 0.
    vacuum_epsilon : float
        Probability of a uniformly drawn vacuum command when acting stochastically
        (``act(..., deterministic=False)``); HIL-SERL's agent explores the gripper only
        through interventions (0).
    suction_loss_terminal : bool
        A transition whose observation has the panel held (vacuum flag 1) and whose next
        observation has it lost (flag 0) ends the TD targets of the critics and the grasp
        critic (terminal, no bootstrap): a lost panel counts as a failure with value 0.
        Neither the paper nor HIL-SERL has it (they bootstrap through it, as the sparse
        acceptance reward defines no failure); state track only (the flat 52-float
        observation). Default False.
    target_range : (float, float) or None
        Clip every TD target (the critics' and the grasp critic's) to ``[lo, hi]``. This
        task's reward is 1 on acceptance, which terminates, and 0 otherwise, so no return
        lies outside ``[0, 1]``: ``target_range=[0,1]`` stops the bootstrap from carrying
        values the task cannot produce. Neither RLPD nor HIL-SERL clips (a named departure,
        measured in docs/baselines.md). None (default): no clip.
    action_scale : (float, float)
        HIL-SERL's per-task ``ACTION_SCALE``: the policy's unit action moves the TCP by
        ``action_scale[0]`` times the env's 25 mm and rotates it by ``action_scale[1]`` times
        its 5 deg per step. Executed actions (demonstrations, takeovers, the policy's own) are
        stored in env units and divided by the scale (clipped to [-1, 1]) for learning.
        HIL-SERL's insertion tasks use 10-15 mm and 0.06-0.1 rad
        (``examples/experiments/ram_insertion/config.py:47``,
        ``usb_pickup_insertion/config.py:51``): about ``(0.4, 0.7)`` here. ``(1, 1)``
        (default): the env's own scale.
    safety_box : (float, float) or None
        HIL-SERL's safety box (``clip_safety_box`` in ``franka_env/envs/franka_env.py``,
        bounds ``ABS_POSE_LIMIT_LOW/HIGH`` per task, e.g. ``ram_insertion/config.py``: a few
        centimetres and 0.01-0.4 rad around the target): every pose the policy commands is
        clipped into a box. Here the box is the demonstrations' TCP envelope (position, and
        orientation as a rotation vector from the first demonstration's final TCP pose)
        widened by ``(metres, degrees)``; the policy's action is replaced by the one that
        commands the clipped pose (flat state only). Takeovers are not clipped. None
        (default): no box.
    offline_steps : int or None
        Stage I gradient steps (offline pretraining on D_demo only). None: the profile's
        ``offline_steps`` (the paper's protocol); 0: no Stage I, the learner starts with the
        online phase on 1:1 demo/online batches (HIL-SERL's and RLPD's own protocol).
    fine_pose_mm, fine_pose_deg : float
        Fine pose features (not in HIL-SERL; state track; QC-FQL's and ACT's option of the
        same name): ``fine_pose_mm = 0`` (default) off; else the actor and the critics also
        read ``tanh(window_pos_rel / fine_pose_mm)`` and ``tanh(window_rot_rel /
        fine_pose_deg)`` (:func:`window_bench.installer.supervisor.fine_pose_features`), the
        panel's millimetres around the seat that the z-score of whole episodes flattens.
    """

    hidden: tuple[int, ...] = (256, 256)
    activation: str = "tanh"
    critic_layernorm: bool = True
    actor_layernorm: bool = True
    num_critics: int = 2
    num_min: int = 2
    log_std_min: float = -20.0
    log_std_max: float = 2.0
    init_temperature: float = 0.01
    target_entropy: float | None = None
    backup_entropy: bool = False
    gamma: float = 0.99
    tau: float = 0.005
    actor_lr: float = 3e-4
    critic_lr: float = 3e-4
    temperature_lr: float = 3e-4
    batch_size: int = 256
    critic_actor_ratio: int = 2
    obs_std_floor: float = 1e-2
    obs_clip: float | None = 10.0
    vacuum_head: str = "discrete"
    vacuum_epsilon: float = 0.0
    grasp_penalty: float = -0.02
    suction_loss_terminal: bool = False
    target_range: tuple[float, float] | None = None
    action_scale: tuple[float, float] = (1.0, 1.0)
    safety_box: tuple[float, float] | None = None
    offline_steps: int | None = None
    fine_pose_mm: float = 0.0
    fine_pose_deg: float = 1.0

    @property
    def h(self) -> int:
        """Chunk horizon: always 1 (step-wise control), as the harness reads ``config.h``."""
        return 1

    def __post_init__(self):
        object.__setattr__(self, "hidden", tuple(self.hidden))
        if not self.hidden or any(isinstance(w, bool) or not isinstance(w, numbers.Integral)
                                  or w < 1 for w in self.hidden):
            raise ValueError(f"hidden = {self.hidden!r} is not allowed: it must be a non-empty "
                             f"sequence of integers >= 1")
        if self.activation not in _ACTIVATIONS:
            raise ValueError(f"activation = {self.activation!r} is not allowed: choose from "
                             f"{tuple(_ACTIVATIONS)}")
        _check_int("num_critics", self.num_critics, 1)
        _check_int("critic_actor_ratio", self.critic_actor_ratio, 1)
        _check_int("batch_size", self.batch_size, 2)
        if self.batch_size % 2:
            raise ValueError(f"batch_size = {self.batch_size} is not allowed: it must be even "
                             f"(half demo, half online)")
        _check_int("num_min", self.num_min, 1)
        if self.num_min > self.num_critics:
            raise ValueError(f"num_min = {self.num_min} is not allowed: it must lie in "
                             f"[1, num_critics = {self.num_critics}]")
        real = lambda v: (isinstance(v, numbers.Real) and not isinstance(v, bool)  # noqa: E731
                          and math.isfinite(v))
        for name in ("log_std_min", "log_std_max"):
            if not real(getattr(self, name)):
                raise ValueError(f"{name} = {getattr(self, name)!r} is not allowed: it must be "
                                 f"a finite number")
        if not (self.log_std_min < self.log_std_max):
            raise ValueError(f"log_std_min = {self.log_std_min} must be < log_std_max = "
                             f"{self.log_std_max}")
        for name in ("critic_layernorm", "actor_layernorm", "backup_entropy",
                     "suction_loss_terminal"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} = {getattr(self, name)!r} is not allowed: it must be "
                                 f"true or false")
        for name in ("init_temperature", "obs_std_floor"):
            value = getattr(self, name)
            if not (real(value) and value > 0):
                raise ValueError(f"{name} = {value!r} is not allowed: it must be a finite "
                                 f"number > 0")
        for name in ("actor_lr", "critic_lr", "temperature_lr"):
            value = getattr(self, name)
            if not (real(value) and 0 < value <= 1):
                raise ValueError(f"{name} = {value!r} is not allowed: it must lie in (0, 1]")
        if not (real(self.gamma) and 0.0 <= self.gamma <= 1.0):
            raise ValueError(f"gamma = {self.gamma!r} is not allowed: it must lie in [0, 1]")
        if not (real(self.tau) and 0.0 < self.tau <= 1.0):
            raise ValueError(f"tau = {self.tau!r} is not allowed: it must lie in (0, 1]")
        if self.target_entropy is not None and not real(self.target_entropy):
            raise ValueError(f"target_entropy = {self.target_entropy!r} is not allowed: it "
                             f"must be finite or None")
        if self.obs_clip is not None and not (isinstance(self.obs_clip, numbers.Real)
                                              and math.isfinite(self.obs_clip)
                                              and self.obs_clip > 0):
            raise ValueError(f"obs_clip = {self.obs_clip!r} is not allowed: it must be a "
                             f"finite number > 0 or None")
        if self.vacuum_head not in VACUUM_HEADS:
            raise ValueError(f"vacuum_head = {self.vacuum_head!r} is not allowed: choose from "
                             f"{VACUUM_HEADS}")
        if self.offline_steps is not None:
            _check_int("offline_steps", self.offline_steps, 0)
        if self.target_range is not None:
            bounds = (tuple(self.target_range) if isinstance(self.target_range, (list, tuple))
                      else ())
            if not (len(bounds) == 2 and all(real(v) for v in bounds)
                    and bounds[0] < bounds[1]):
                raise ValueError(f"target_range = {self.target_range!r} is not allowed: it "
                                 f"must be two finite numbers [lo, hi] with lo < hi, or None")
            object.__setattr__(self, "target_range", tuple(float(v) for v in bounds))
        if not (isinstance(self.vacuum_epsilon, numbers.Real)
                and 0.0 <= self.vacuum_epsilon <= 1.0):
            raise ValueError(f"vacuum_epsilon = {self.vacuum_epsilon!r} is not allowed: it "
                             f"must lie in [0, 1]")
        scale = tuple(self.action_scale) if isinstance(self.action_scale, (list, tuple)) else ()
        if not (len(scale) == 2 and all(real(v) and 0 < v <= 1 for v in scale)):
            raise ValueError(f"action_scale = {self.action_scale!r} is not allowed: it must be "
                             f"two numbers in (0, 1] (translation, rotation)")
        object.__setattr__(self, "action_scale", tuple(float(v) for v in scale))
        if self.safety_box is not None:
            box = tuple(self.safety_box) if isinstance(self.safety_box, (list, tuple)) else ()
            if not (len(box) == 2 and all(real(v) for v in box)
                    and 0 <= box[0] <= 1 and 0 <= box[1] <= 180):
                raise ValueError(f"safety_box = {self.safety_box!r} is not allowed: it must be "
                                 f"[metres in [0, 1], degrees in [0, 180]] or None")
            object.__setattr__(self, "safety_box", tuple(float(v) for v in box))
        check_fine_pose("HILSERLConfig", self.fine_pose_mm, self.fine_pose_deg)
        if not (real(self.grasp_penalty) and self.grasp_penalty <= 0):
            raise ValueError(f"grasp_penalty = {self.grasp_penalty!r} is not allowed: it must "
                             f"be a finite number <= 0")


#: RLPD's learner (Ball et al. 2023) in this module's terms.
RLPD_CONFIG = HILSERLConfig(activation="relu", actor_layernorm=False, num_critics=10,
                            num_min=2, init_temperature=1.0, backup_entropy=True,
                            critic_actor_ratio=1, vacuum_head="gaussian")

#: ``--agent-config`` overrides that run HIL-SERL as its authors run a single-arm task with a
#: learnt gripper (the preset ``hilserl-own``; docs/baselines.md): no offline pretraining
#: (the learner trains from the first online transitions on 1:1 batches), the discount of
#: its pick-and-insert example (``usb_pickup_insertion``), its 256 x 256 networks (the
#: ``paper`` profile's are 4 x 512) and its std clip [1e-5, 5] as log-std bounds.
HILSERL_OWN = {"offline_steps": 0, "gamma": 0.98, "hidden": (256, 256),
               "log_std_min": math.log(1e-5), "log_std_max": math.log(5.0)}


# --------------------------------------------------------------------------- networks
def _mlp(in_features: int, out_features: int, cfg: HILSERLConfig, layernorm: bool) -> MLP:
    norm = dict(norm_class=nn.LayerNorm,
                norm_kwargs=[{"normalized_shape": w} for w in cfg.hidden]) if layernorm else {}
    net = MLP(in_features=in_features, out_features=out_features, num_cells=list(cfg.hidden),
              activation_class=_ACTIVATIONS[cfg.activation], **norm)
    # The references initialise Dense layers Xavier-uniform with zero biases.
    for layer in net.modules():
        if isinstance(layer, nn.Linear):
            nn.init.xavier_uniform_(layer.weight)
            nn.init.zeros_(layer.bias)
    return net


class TanhGaussianActor(nn.Module):
    """``pi(a|s)``: an MLP giving the mean and the (clipped) log-std of a Gaussian over
    pre-squash actions ``u``; the action is ``tanh(u)``, in [-1, 1]^A."""

    def __init__(self, obs_dim: int, action_dim: int, cfg: HILSERLConfig):
        super().__init__()
        self.net = _mlp(obs_dim, 2 * action_dim, cfg, cfg.actor_layernorm)
        self.log_std_min, self.log_std_max = cfg.log_std_min, cfg.log_std_max

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mean, log_std = self.net(obs).chunk(2, dim=-1)
        return mean, log_std.clamp(self.log_std_min, self.log_std_max)

    def sample(self, obs: torch.Tensor, generator: torch.Generator
               ) -> tuple[torch.Tensor, torch.Tensor]:
        """Reparameterised sample ``a = tanh(mean + std * eps)`` and its log-density."""
        mean, log_std = self(obs)
        eps = torch.randn(mean.shape, generator=generator, dtype=mean.dtype)
        u = mean + log_std.exp() * eps
        # log N(u; mean, std) - log|d tanh(u)/du|, with log(1 - tanh(u)^2) written stably.
        log_prob = (-0.5 * eps.pow(2) - log_std - _HALF_LOG_2PI).sum(-1)
        log_prob = log_prob - (2.0 * (math.log(2.0) - u - F.softplus(-2.0 * u))).sum(-1)
        return torch.tanh(u), log_prob

    def mode(self, obs: torch.Tensor) -> torch.Tensor:
        """The deterministic action ``tanh(mean)`` used for evaluation."""
        return torch.tanh(self(obs)[0])


class CriticEnsemble(nn.Module):
    """``num_critics`` independent Q-networks ``Q_k(s, a)``; forward returns (E, B)."""

    def __init__(self, obs_dim: int, action_dim: int, cfg: HILSERLConfig):
        super().__init__()
        self.members = nn.ModuleList(_mlp(obs_dim + action_dim, 1, cfg, cfg.critic_layernorm)
                                     for _ in range(cfg.num_critics))

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        x = torch.cat([obs, action], dim=-1)
        # A loop over members measured as fast as a batched (bmm) ensemble at E = 2 and 10.
        return torch.stack([m(x).squeeze(-1) for m in self.members])


class GraspCritic(nn.Module):
    """HIL-SERL's grasp critic: ``Q_g(s, c)`` for every vacuum command ``c`` at once, one
    MLP with the critics' hidden layers (HIL-SERL: 256 x 256, tanh, LayerNorm) and one
    output per command; forward returns (B, num_commands)."""

    def __init__(self, obs_dim: int, cfg: HILSERLConfig, num_commands: int):
        super().__init__()
        self.net = _mlp(obs_dim, num_commands, cfg, cfg.critic_layernorm)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.net(obs)


def grasp_command_labels(vacuum: torch.Tensor, held: torch.Tensor) -> torch.Tensor:
    """The :data:`VACUUM_COMMANDS` index of executed vacuum values ``vacuum`` (B,), taken in
    states whose vacuum was on where ``held`` (B,) is True: a value that changes the state is
    the command that does so (engage above ``VACUUM_THRESHOLD``, release otherwise), one that
    keeps it is "stay". HIL-SERL stores gripper commands -1, 0, +1 and labels them
    ``round(a) + 1``; here the executed vacuum value is a level, so a command is a change."""
    on = vacuum > VACUUM_THRESHOLD
    labels = torch.full(on.shape, STAY, dtype=torch.long)
    labels[on & ~held] = ENGAGE
    labels[~on & held] = RELEASE
    return labels


def vacuum_values(commands: torch.Tensor, held: torch.Tensor) -> torch.Tensor:
    """The executed vacuum values of :data:`VACUUM_COMMANDS` indices in states whose vacuum
    is on where ``held``: release -> ``VACUUM_OFF``, engage -> ``VACUUM_ON``, stay -> the
    value that keeps the state."""
    on = (commands == ENGAGE) | ((commands == STAY) & held)
    return torch.where(on, VACUUM_ON, VACUUM_OFF)


# --------------------------------------------------------------------------- storage rules
def hilserl_buffers_for(step_provenance: str) -> tuple[str, ...]:
    """The buffers a step of this provenance goes to, as HIL-SERL stores them.

    ``"policy"`` -> ``("online",)``; ``"takeover"`` -> ``("online", "demo")`` (intervened
    transitions are also demonstrations); ``"demo"`` -> ``("demo",)`` (the offline dataset).
    Raises ``ValueError`` for any other value.
    """
    routes = {"demo": ("demo",), "policy": ("online",), "takeover": ("online", "demo")}
    if step_provenance not in routes:
        raise ValueError(f"step_provenance = {step_provenance!r} is not allowed: choose from "
                         f"{PROVENANCES}")
    return routes[step_provenance]


def symmetric_sampler(sample_demo: Callable[[int], TensorDict],
                      sample_online: Callable[[int], TensorDict],
                      batch_size: int) -> Callable[[], TensorDict]:
    """``sample() -> TensorDict`` with exactly ``batch_size / 2`` demo rows, then as many
    online rows (RLPD's symmetric sampling), marked by a boolean ``from_demo`` key.

    ``sample_demo(n)`` / ``sample_online(n)`` draw ``n`` rows from each buffer (e.g.
    ``ChunkReplay.sample``). Only :data:`BATCH_KEYS` and ``valid`` (where both parts have
    it) are kept. Raises ``ValueError`` for an odd or non-positive ``batch_size``.
    """
    _check_int("batch_size", batch_size, 2)
    if batch_size % 2:
        raise ValueError(f"batch_size = {batch_size} is not allowed: it must be even "
                         f"(half demo, half online)")
    half = batch_size // 2

    def sample() -> TensorDict:
        demo, online = sample_demo(half), sample_online(half)
        keys = [k for k in (*BATCH_KEYS, "valid") if k in demo.keys() and k in online.keys()]
        batch = torch.cat([demo.select(*keys), online.select(*keys)], dim=0)
        batch["from_demo"] = torch.arange(batch_size) < half
        return batch

    return sample


def _tcp_pose(obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """TCP position and rotation matrix of one flat observation."""
    import mujoco

    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, np.asarray(obs[FLAT_SLICES["robot0_eef_quat"]], np.float64))
    return np.asarray(obs[FLAT_SLICES["robot0_eef_pos"]], np.float64), mat.reshape(3, 3)


@dataclass(frozen=True)
class SafetyBox:
    """HIL-SERL's safety box on commanded TCP poses (``HILSERLConfig.safety_box``):
    positions in ``[pos_low, pos_high]`` (m, world) and orientations whose rotation vector
    from ``rot_ref`` lies in ``[rot_low, rot_high]`` (rad, per component)."""

    pos_low: np.ndarray
    pos_high: np.ndarray
    rot_low: np.ndarray
    rot_high: np.ndarray
    rot_ref: np.ndarray

    @classmethod
    def from_demos(cls, episodes: list[EpisodeLog], margin_m: float,
                   margin_deg: float) -> "SafetyBox":
        """The TCP envelope of every observation of ``episodes`` (flat state), widened by
        the margins; the reference orientation is the first episode's final TCP pose."""
        if not episodes:
            raise ValueError("SafetyBox.from_demos: got no episodes; need at least one")
        obs = np.concatenate([np.asarray(ep.observations, np.float64) for ep in episodes])
        if obs.shape[1] != FLAT_DIM:
            raise ValueError(f"SafetyBox.from_demos: observations of size {obs.shape[1]}; "
                             f"the box reads the flat state ({FLAT_DIM})")
        ref = _tcp_pose(np.asarray(episodes[0].observations[-1]))[1]
        pos, rot = [], []
        for row in obs:
            p, mat = _tcp_pose(row)
            pos.append(p)
            rot.append(mat_to_rotvec(ref.T @ mat))
        pos, rot, md = np.array(pos), np.array(rot), math.radians(margin_deg)
        return cls(pos.min(0) - margin_m, pos.max(0) + margin_m, rot.min(0) - md,
                   rot.max(0) + md, ref)

    def clip(self, obs: np.ndarray, action: np.ndarray) -> np.ndarray:
        """``action`` (env units, ``(A,)``) changed to command the nearest pose in the box
        from the state of ``obs`` (the env's step: target = p + R a[:3] * POS_SCALE and
        R rotvec(a[3:6] * ROT_SCALE)); entries stay in [-1, 1], the vacuum is untouched."""
        p, mat = _tcp_pose(obs)
        a = np.asarray(action, np.float64).copy()
        target = np.clip(p + mat @ (a[:3] * POS_SCALE), self.pos_low, self.pos_high)
        a[:3] = mat.T @ (target - p) / POS_SCALE
        turned = mat @ rotvec_to_mat(a[3:6] * ROT_SCALE)
        v = np.clip(mat_to_rotvec(self.rot_ref.T @ turned), self.rot_low, self.rot_high)
        a[3:6] = mat_to_rotvec(mat.T @ self.rot_ref @ rotvec_to_mat(v)) / ROT_SCALE
        a[:6] = np.clip(a[:6], -1.0, 1.0)
        return a.astype(np.float32)

    def state(self) -> dict:
        return {k: torch.as_tensor(np.asarray(getattr(self, k)), dtype=torch.float64)
                for k in ("pos_low", "pos_high", "rot_low", "rot_high", "rot_ref")}

    @classmethod
    def from_state(cls, state: dict) -> "SafetyBox":
        return cls(**{k: np.asarray(state[k], np.float64) for k in
                      ("pos_low", "pos_high", "rot_low", "rot_high", "rot_ref")})


def obs_normalizer(episodes: list[EpisodeLog]) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard deviation of every observation row of ``episodes`` (float64);
    pass them to :class:`HILSERLAgent` (which floors the std at ``obs_std_floor``)."""
    if not episodes:
        raise ValueError("obs_normalizer: got no episodes; need at least one")
    obs = np.concatenate([np.asarray(ep.observations, np.float64) for ep in episodes])
    return obs.mean(axis=0), obs.std(axis=0)


# --------------------------------------------------------------------------- the agent
class HILSERLAgent(Agent):
    """Soft actor-critic learner of HIL-SERL / RLPD with ``h = 1`` (one-step "chunks").

    Parameters
    ----------
    obs_dim : int
        Size of the flat observation (52 for ``obs_mode="flat"``).
    action_dim : int
        Action size (7).
    config : HILSERLConfig
        Hyperparameters.
    seed : int
        Seeds the initial weights and the agent's two generators (one for acting, one for
        the updates' samples). The global torch RNG is neither used nor changed.
    obs_mean, obs_std : array-like of shape (obs_dim,), optional
        Statistics for z-scoring observations inside the networks (e.g. from
        :func:`obs_normalizer` over the demos); the std is floored at
        ``config.obs_std_floor``. Omitted: no normalisation.
    """

    h = 1
    takeovers_to_demo = True   # HIL-SERL: intervened transitions are demonstrations too
    #: The modules ``act(obs, deterministic=True)`` reads (those that exist in this agent).
    ACTING_MODULES = ("actor", "grasp_critic")

    # ------------------------------------------------------------------ the harness's interface
    @classmethod
    def make_config(cls, h: int, profile, overrides: dict) -> HILSERLConfig:
        return with_overrides(HILSERLConfig(hidden=tuple(profile.hidden),
                                            batch_size=profile.batch_size), overrides)

    @classmethod
    def create(cls, spec) -> "HILSERLAgent":
        """The default construction, plus the safety box from D_demo when configured."""
        agent = super().create(spec)
        if agent.config.safety_box is not None:
            agent.fit_safety_box(spec.demos)
        return agent

    def fit_safety_box(self, episodes: list[EpisodeLog]) -> None:
        """Set the box of ``config.safety_box`` from these (demonstration) episodes."""
        if self.config.safety_box is None:
            raise ValueError("fit_safety_box: config.safety_box is None (no box)")
        self.box = SafetyBox.from_demos(episodes, *self.config.safety_box)

    @property
    def offline_steps(self) -> int | None:
        """Stage I gradient steps for the harness: the config's, None for the profile's."""
        return self.config.offline_steps

    def learn(self, sample) -> tuple[dict[str, float], int]:
        """One :meth:`update`: ``critic_actor_ratio`` critic steps, each on a fresh batch."""
        return self.update(sample), self.config.critic_actor_ratio

    def policy_state_dict(self) -> dict:
        """The acting networks (:data:`ACTING_MODULES`), the normaliser, sizes and config."""
        return {"config": plain(dataclasses.asdict(self.config)), "obs_dim": self.obs_dim,
                "action_dim": self.action_dim, "seed": self.seed,
                "obs_mean": self.obs_mean.clone(), "obs_std": self.obs_std.clone(),
                **{name: module_state(getattr(self, name)) for name in self.ACTING_MODULES
                   if getattr(self, name, None) is not None}, **self._box_state()}

    def _box_state(self) -> dict:
        return {} if self.box is None else {"safety_box": self.box.state()}

    def _load_box(self, state: dict) -> None:
        if (self.config.safety_box is None) != ("safety_box" not in state):
            raise ValueError(f"a state with{'out' if 'safety_box' not in state else ''} a "
                             f"safety box for a config with safety_box = "
                             f"{self.config.safety_box}")
        self.box = (SafetyBox.from_state(state["safety_box"]) if "safety_box" in state
                    else None)

    @classmethod
    def from_policy_state_dict(cls, state: dict) -> "HILSERLAgent":
        """An agent that acts like the one :meth:`policy_state_dict` came from (its critics
        keep their initial weights: for acting only)."""
        agent = cls(state["obs_dim"], state["action_dim"],
                    config_from_plain(HILSERLConfig, _state_config(state)), seed=state["seed"])
        agent.obs_mean, agent.obs_std = state["obs_mean"].clone(), state["obs_std"].clone()
        agent._load_box(state)
        for name in cls.ACTING_MODULES:
            if getattr(agent, name, None) is not None:
                getattr(agent, name).load_state_dict(state[name])
        return agent

    def __init__(self, obs_dim: int, action_dim: int = 7,
                 config: HILSERLConfig = HILSERLConfig(), seed: int = 0,
                 obs_mean=None, obs_std=None):
        _check_int("obs_dim", obs_dim, 1)
        _check_int("action_dim", action_dim, 1)
        _check_int("seed", seed, 0)
        if not isinstance(config, HILSERLConfig):
            raise TypeError(f"config must be a HILSERLConfig, got {type(config).__name__}")
        self.obs_dim, self.action_dim, self.config, self.seed = obs_dim, action_dim, config, seed
        self.target_entropy = (-action_dim / 2.0 if config.target_entropy is None
                               else float(config.target_entropy))
        self.obs_mean, self.obs_std = self._check_stats(obs_mean, obs_std)

        # The grasp critic's commands ("discrete": three, "binary": two; none otherwise).
        self.grasp_commands = {"discrete": VACUUM_COMMANDS,
                               "binary": BINARY_COMMANDS}.get(config.vacuum_head, ())
        self.discrete_vacuum = bool(self.grasp_commands)
        self.held_vacuum = config.vacuum_head == "held"
        # HIL-SERL's ACTION_SCALE: translation, rotation, then the vacuum entry as it is.
        t, r = config.action_scale
        self._motion_scale = torch.tensor([t if i < 3 else r if i < 6 else 1.0
                                           for i in range(action_dim)], dtype=torch.float32)
        self.box: SafetyBox | None = None     # fit_safety_box (create does it from D_demo)
        if config.safety_box is not None and obs_dim != FLAT_OBS_DIM:
            raise ValueError(f"safety_box = {list(config.safety_box)} needs the flat state "
                             f"observation (obs_dim {FLAT_OBS_DIM}); this agent has obs_dim = "
                             f"{obs_dim}")
        if config.suction_loss_terminal and obs_dim != FLAT_OBS_DIM:
            raise ValueError(f"suction_loss_terminal = true needs the flat state observation "
                             f"(obs_dim {FLAT_OBS_DIM}, vacuum flag at index "
                             f"{VACUUM_OBS_INDEX}); this agent has obs_dim = {obs_dim}")
        if (self.discrete_vacuum or self.held_vacuum) and action_dim < 2:
            raise ValueError(f"action_dim = {action_dim} is not allowed with vacuum_head = "
                             f"{config.vacuum_head!r}: it needs at least one pose dimension "
                             f"and the vacuum")
        in_dim = obs_dim + extra_inputs(config, obs_dim)
        # With the grasp critic or a held vacuum, the actor and the critic ensemble see the
        # pose dimensions only (HIL-SERL's critic takes actions[..., :-1]).
        self.pose_dim = (action_dim - 1 if self.discrete_vacuum or self.held_vacuum
                         else action_dim)

        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            self.actor = TanhGaussianActor(in_dim, self.pose_dim, config)
            self.critic = CriticEnsemble(in_dim, self.pose_dim, config)
            self.grasp_critic = (GraspCritic(in_dim, config, len(self.grasp_commands))
                                 if self.discrete_vacuum else None)
        self.target_critic = copy.deepcopy(self.critic).requires_grad_(False)
        self.target_grasp_critic = (copy.deepcopy(self.grasp_critic).requires_grad_(False)
                                    if self.discrete_vacuum else None)
        self.log_alpha = nn.Parameter(torch.tensor(math.log(config.init_temperature)))

        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=config.actor_lr)
        self.critic_opt = torch.optim.Adam(self.critic.parameters(), lr=config.critic_lr)
        self.grasp_critic_opt = (torch.optim.Adam(self.grasp_critic.parameters(),
                                                  lr=config.critic_lr)
                                 if self.discrete_vacuum else None)
        self.temperature_opt = torch.optim.Adam([self.log_alpha], lr=config.temperature_lr)
        self._act_rng = torch.Generator().manual_seed(2 * seed)
        self._update_rng = torch.Generator().manual_seed(2 * seed + 1)
        self.critic_steps = 0
        self.actor_steps = 0

    def _check_stats(self, mean, std) -> tuple[torch.Tensor, torch.Tensor]:
        if (mean is None) != (std is None):
            raise ValueError("obs_mean and obs_std must be given together or both omitted")
        if mean is None:
            return torch.zeros(self.obs_dim), torch.ones(self.obs_dim)
        out = []
        for name, arr in (("obs_mean", mean), ("obs_std", std)):
            arr = np.asarray(arr, dtype=np.float64)
            if arr.shape != (self.obs_dim,):
                raise ValueError(f"{name} has shape {arr.shape}, expected ({self.obs_dim},)")
            if not np.isfinite(arr).all():
                raise ValueError(f"{name} has non-finite values at indices "
                                 f"{np.flatnonzero(~np.isfinite(arr)).tolist()}")
            out.append(arr)
        if (out[1] < 0).any():
            raise ValueError(f"obs_std has negative values at indices "
                             f"{np.flatnonzero(out[1] < 0).tolist()}")
        std = np.maximum(out[1], self.config.obs_std_floor)
        return (torch.as_tensor(out[0], dtype=torch.float32),
                torch.as_tensor(std, dtype=torch.float32))

    @property
    def temperature(self) -> float:
        """The current entropy temperature alpha."""
        return float(self.log_alpha.detach().exp())

    def _normalize(self, obs: torch.Tensor) -> torch.Tensor:
        z = (obs - self.obs_mean) / self.obs_std
        clip = self.config.obs_clip
        z = z if clip is None else z.clamp(-clip, clip)
        if not self.config.fine_pose_mm:
            return z
        fine = fine_pose_features(obs, self.config.fine_pose_mm, self.config.fine_pose_deg)
        return torch.cat([z, fine.to(z.dtype)], dim=-1)

    # ------------------------------------------------------------------ acting
    def act(self, obs, deterministic: bool = False, vacuum_flag=None) -> np.ndarray:
        """Action chunk(s) of length 1: (1, A) for one observation (obs_dim,), (B, 1, A) for
        a batch (B, obs_dim). ``deterministic`` returns ``tanh(mean)``; otherwise a sample
        drawn with the agent's acting generator. float32, in [-1, 1]. With a grasp critic
        the last entry executes the command of :meth:`vacuum_command` (argmax of the grasp
        critic; epsilon-greedy when sampling): ``VACUUM_OFF`` for release, ``VACUUM_ON`` for
        engage (and the binary head's hold), and for stay the value that keeps the vacuum
        state of the observation; with the held vacuum it is always ``VACUUM_ON``.

        ``vacuum_flag``: one value per observation, 1 while the vacuum is on, for
        observations that are not the flat state (the pixel track's); by default the flag at
        :data:`VACUUM_OBS_INDEX` of ``obs``."""
        x = np.ascontiguousarray(obs, dtype=np.float32)
        if x.ndim not in (1, 2) or x.shape[-1] != self.obs_dim:
            raise ValueError(f"obs has shape {x.shape}; expected ({self.obs_dim},) or "
                             f"(B, {self.obs_dim})")
        with torch.no_grad():
            raw = torch.from_numpy(x).reshape(-1, self.obs_dim)
            o = self._normalize(raw)
            a = self.actor.mode(o) if deterministic else self.actor.sample(o, self._act_rng)[0]
            a = a * self._motion_scale[: a.shape[-1]]
            if self.discrete_vacuum:
                cmd = self._vacuum_command(o, deterministic)
                vacuum = self._executed_vacuum(cmd, raw, vacuum_flag)
                a = torch.cat([a, vacuum[:, None].to(a.dtype)], dim=-1)
            elif self.held_vacuum:
                a = torch.cat([a, a.new_full((a.shape[0], 1), VACUUM_ON)], dim=-1)
        a = a.numpy().astype(np.float32)
        if self.config.safety_box is not None:
            if self.box is None:
                raise RuntimeError("safety_box is configured but not fitted: call "
                                   "fit_safety_box(demos) (HILSERLAgent.create does)")
            a = np.stack([self.box.clip(o, row) for o, row in zip(x.reshape(-1, self.obs_dim), a)])
        return a.reshape(1, self.action_dim) if x.ndim == 1 else a[:, None, :]

    def vacuum_command(self, obs, deterministic: bool = True) -> np.ndarray:
        """Indices into the grasp critic's commands (:data:`VACUUM_COMMANDS`: 0 release,
        1 stay, 2 engage; the binary head's :data:`BINARY_COMMANDS`) for raw observations
        (obs_dim,) or (B, obs_dim): ``argmax_c Q_g(s, c)``, or with probability
        ``vacuum_epsilon`` a uniform command when not ``deterministic``. Grasp critic only."""
        if not self.discrete_vacuum:
            raise ValueError("vacuum_command needs a grasp critic (vacuum_head 'discrete' or "
                             f"'binary'); this agent has {self.config.vacuum_head!r}")
        x = torch.as_tensor(np.asarray(obs, dtype=np.float32)).reshape(-1, self.obs_dim)
        with torch.no_grad():
            return self._vacuum_command(self._normalize(x), deterministic).numpy()

    def _vacuum_command(self, o: torch.Tensor, deterministic: bool) -> torch.Tensor:
        cmd = self.grasp_critic(o).argmax(dim=-1)
        eps = self.config.vacuum_epsilon
        if not deterministic and eps > 0:
            # Draws only when exploring, so eps = 0 leaves the acting stream as without it.
            explore = torch.rand(cmd.shape, generator=self._act_rng) < eps
            random_cmd = torch.randint(len(self.grasp_commands), cmd.shape,
                                       generator=self._act_rng)
            cmd = torch.where(explore, random_cmd, cmd)
        return cmd

    def _executed_vacuum(self, cmd: torch.Tensor, obs: torch.Tensor,
                         vacuum_flag=None) -> torch.Tensor:
        """The executed vacuum values (B,) of grasp-critic commands at raw observations."""
        if self.config.vacuum_head == "binary":
            return torch.where(cmd == 1, VACUUM_ON, VACUUM_OFF)
        return vacuum_values(cmd, self._vacuum_held(obs, vacuum_flag))

    def _vacuum_held(self, obs: torch.Tensor, vacuum_flag=None) -> torch.Tensor:
        """(B,) bool, the vacuum is on at each raw observation (B, obs_dim): from
        ``vacuum_flag`` when given, else from the flag of the flat state observation."""
        if vacuum_flag is not None:
            flag = torch.as_tensor(vacuum_flag, dtype=torch.float32).reshape(-1)
            if flag.shape[0] != obs.shape[0]:
                raise ValueError(f"vacuum_flag has {flag.shape[0]} values for "
                                 f"{obs.shape[0]} observations")
            return flag > 0.5
        if self.obs_dim != FLAT_OBS_DIM:
            raise ValueError(f"vacuum_head = 'discrete' reads the vacuum flag of the flat state "
                             f"observation (obs_dim {FLAT_OBS_DIM}, index {VACUUM_OBS_INDEX}); "
                             f"this agent has obs_dim = {self.obs_dim}: pass vacuum_flag")
        return obs[:, VACUUM_OBS_INDEX] > 0.5

    # ------------------------------------------------------------------ learning
    def _prepare(self, batch: TensorDict) -> dict[str, torch.Tensor]:
        missing = [k for k in BATCH_KEYS if k not in batch.keys()]
        if missing:
            raise ValueError(f"batch lacks keys {missing}; it needs {BATCH_KEYS} "
                             f"(and optionally 'valid')")
        B = batch.batch_size[0]
        actions = batch["actions"].to(torch.float32)
        if actions.ndim == 3:
            if actions.shape[1] != 1:
                raise ValueError(f"batch['actions'] has shape {tuple(actions.shape)}: chunks "
                                 f"of length {actions.shape[1]}, but this agent has h = 1")
            actions = actions[:, 0]
        if actions.shape != (B, self.action_dim):
            raise ValueError(f"batch['actions'] has shape {tuple(batch['actions'].shape)}; "
                             f"expected ({B}, 1, {self.action_dim}) or ({B}, {self.action_dim})")
        if self.config.action_scale != (1.0, 1.0):   # env units -> the policy's units
            motion = (actions[:, :6] / self._motion_scale[:6]).clamp(-1.0, 1.0)
            actions = torch.cat([motion, actions[:, 6:]], dim=-1)
        for key in ("obs", "next_obs"):
            if tuple(batch[key].shape) != (B, self.obs_dim):
                raise ValueError(f"batch[{key!r}] has shape {tuple(batch[key].shape)}; "
                                 f"expected ({B}, {self.obs_dim})")
        discount = batch["discount"].to(torch.float32).reshape(B)
        if (discount - self.config.gamma).abs().max() > 1e-6:
            raise ValueError(f"batch['discount'] holds values in [{float(discount.min())}, "
                             f"{float(discount.max())}], but h = 1 and gamma = "
                             f"{self.config.gamma} need gamma ** 1 everywhere; build the "
                             f"chunks with the agent's gamma")
        valid = batch["valid"] if "valid" in batch.keys() else torch.ones(B, dtype=torch.bool)
        obs, next_obs = batch["obs"].to(torch.float32), batch["next_obs"].to(torch.float32)
        terminal = batch["terminal"].to(torch.float32).reshape(B)
        if self.config.suction_loss_terminal:
            lost = (obs[:, VACUUM_OBS_INDEX] > 0.5) & (next_obs[:, VACUUM_OBS_INDEX] < 0.5)
            terminal = torch.maximum(terminal, lost.to(torch.float32))
        reward = batch["reward"].to(torch.float32).reshape(B)
        prepared = {"obs": self._normalize(obs), "next_obs": self._normalize(next_obs),
                    "actions": actions[:, :self.pose_dim], "discount": discount,
                    "reward": reward, "terminal": terminal,
                    "valid": valid.to(torch.float32).reshape(B)}
        if self.discrete_vacuum:
            flag = batch["vacuum_flag"] if "vacuum_flag" in batch.keys() else None
            prepared["vacuum_cmd"], prepared["grasp_reward"] = self._grasp_labels(
                actions[:, -1], obs, reward, flag)
        return prepared

    def _grasp_labels(self, vacuum: torch.Tensor, obs: torch.Tensor, reward: torch.Tensor,
                      vacuum_flag=None) -> tuple[torch.Tensor, torch.Tensor]:
        """The grasp critic's command labels (B,) of executed vacuum values and its reward:
        the task reward plus ``grasp_penalty`` where the command changed the vacuum state
        (HIL-SERL adds its ``grasp_penalty`` to the grasp critic's reward only)."""
        if self.config.vacuum_head == "binary":
            return (vacuum > VACUUM_THRESHOLD).long(), reward
        labels = grasp_command_labels(vacuum, self._vacuum_held(obs, vacuum_flag))
        return labels, reward + self.config.grasp_penalty * (labels != STAY).to(reward.dtype)

    def td_target(self, batch: TensorDict) -> torch.Tensor:
        """The TD target ``y`` (B,) of one batch, with the current target critics:
        ``y = r + discount * (1 - terminal) * (min_{k in K} Qbar_k(s', a') - [alpha log pi])``
        with ``a' ~ pi(.|s')``, ``K`` = ``num_min`` members drawn without replacement and
        the bracket only if ``backup_entropy``, clipped to ``target_range`` when set. Draws
        from the update generator."""
        return self._td_target(self._prepare(batch))

    @torch.no_grad()
    def _td_target(self, b: dict[str, torch.Tensor]) -> torch.Tensor:
        cfg = self.config
        next_action, next_log_prob = self.actor.sample(b["next_obs"], self._update_rng)
        next_q = self.target_critic(b["next_obs"], next_action)  # (E, B)
        if cfg.num_min < cfg.num_critics:
            members = torch.randperm(cfg.num_critics, generator=self._update_rng)[:cfg.num_min]
            next_q = next_q[members]
        next_v = next_q.min(dim=0).values
        if cfg.backup_entropy:
            next_v = next_v - self.log_alpha.exp() * next_log_prob
        return self._clip_target(b["reward"] + b["discount"] * (1.0 - b["terminal"]) * next_v)

    def _clip_target(self, y: torch.Tensor) -> torch.Tensor:
        bounds = self.config.target_range
        return y if bounds is None else y.clamp(*bounds)

    def grasp_td_target(self, batch: TensorDict) -> torch.Tensor:
        """The grasp critic's double-DQN target ``y_g`` (B,), with the current networks:
        ``y_g = r_g + discount * (1 - terminal) * Qbar_g(s', argmax_c Q_g(s', c))``: the
        online grasp critic picks the next command, the target grasp critic values it, and
        ``r_g`` is the task reward plus ``grasp_penalty`` on the rows whose command changed
        the vacuum state (HIL-SERL's ``grasp_critic_loss_fn``). Grasp critic only."""
        if not self.discrete_vacuum:
            raise ValueError("grasp_td_target needs a grasp critic (vacuum_head 'discrete' or "
                             f"'binary'); this agent has {self.config.vacuum_head!r}")
        return self._grasp_td_target(self._prepare(batch))

    @torch.no_grad()
    def _grasp_td_target(self, b: dict[str, torch.Tensor]) -> torch.Tensor:
        best = self.grasp_critic(b["next_obs"]).argmax(dim=-1, keepdim=True)
        next_q = self.target_grasp_critic(b["next_obs"]).gather(-1, best).squeeze(-1)
        return self._clip_target(b["grasp_reward"]
                                 + b["discount"] * (1.0 - b["terminal"]) * next_q)

    def _valid_mean(self, per_row: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        return (per_row * valid).sum() / valid.sum().clamp(min=1.0)

    def _critic_step(self, b: dict[str, torch.Tensor]) -> dict[str, float]:
        y = self._td_target(b)
        q = self.critic(b["obs"], b["actions"])  # (E, B)
        loss = self._valid_mean((q - y).pow(2).mean(dim=0), b["valid"])  # mean over members
        self.critic_opt.zero_grad(set_to_none=True)
        loss.backward()
        self.critic_opt.step()
        info = {"critic_loss": loss.item(), "q_mean": float(q.detach().mean()),
                "target_mean": float(y.mean())}
        if self.discrete_vacuum:  # HIL-SERL updates the grasp critic with every critic step
            y_g = self._grasp_td_target(b)
            q_g = self.grasp_critic(b["obs"]).gather(-1, b["vacuum_cmd"][:, None]).squeeze(-1)
            grasp_loss = self._valid_mean((q_g - y_g).pow(2), b["valid"])
            self.grasp_critic_opt.zero_grad(set_to_none=True)
            grasp_loss.backward()
            self.grasp_critic_opt.step()
            info.update(grasp_critic_loss=grasp_loss.item(),
                        grasp_q_mean=float(q_g.detach().mean()))
        self._polyak()
        self.critic_steps += 1
        return info

    @torch.no_grad()
    def _polyak(self) -> None:
        pairs = [(self.critic, self.target_critic)]
        if self.discrete_vacuum:
            pairs.append((self.grasp_critic, self.target_grasp_critic))
        for net, target_net in pairs:
            online = list(net.parameters()) + list(net.buffers())
            target = list(target_net.parameters()) + list(target_net.buffers())
            torch._foreach_lerp_(target, online, self.config.tau)

    def _actor_temperature_step(self, b: dict[str, torch.Tensor]) -> dict[str, float]:
        alpha = self.log_alpha.detach().exp()
        action, log_prob = self.actor.sample(b["obs"], self._update_rng)
        self.critic.requires_grad_(False)  # the critic is frozen in the actor loss
        try:
            q = self.critic(b["obs"], action).mean(dim=0)  # mean over members (RLPD, SERL)
        finally:
            self.critic.requires_grad_(True)
        actor_loss = (alpha * log_prob - q).mean()
        self.actor_opt.zero_grad(set_to_none=True)
        actor_loss.backward()
        self.actor_opt.step()

        entropy = -log_prob.detach().mean()
        # alpha * (H - H_target): lowers alpha while the entropy is above its target.
        temperature_loss = self.log_alpha.exp() * (entropy - self.target_entropy)
        self.temperature_opt.zero_grad(set_to_none=True)
        temperature_loss.backward()
        self.temperature_opt.step()
        self.actor_steps += 1
        return {"actor_loss": actor_loss.item(), "entropy": float(entropy),
                "temperature_loss": temperature_loss.item(), "temperature": self.temperature}

    def update(self, batch: TensorDict | Callable[[], TensorDict]) -> dict[str, float]:
        """One learner step: ``critic_actor_ratio`` critic steps (Polyak after each), then
        one actor step and one temperature step on the last critic step's batch.

        ``batch`` is either a callable ``sample() -> TensorDict`` (called once per critic
        step, e.g. :func:`symmetric_sampler` or ``lambda: mixed_batch(demo, online, 256)``),
        as HIL-SERL draws a fresh half/half batch per critic step; or one TensorDict whose
        rows are split into ``critic_actor_ratio`` equal consecutive minibatches (its size
        must be a multiple of the ratio; a symmetric batch per critic step then needs its
        rows interleaved accordingly). Keys: :data:`BATCH_KEYS` and optionally ``valid``
        (rows with ``valid`` False are left out of the TD loss); ``actions`` (B, 1, A).

        Returns floats: ``critic_loss`` (mean over the critic steps), ``q_mean``,
        ``target_mean``, ``actor_loss``, ``entropy``, ``temperature_loss``,
        ``temperature`` (after the step); with the discrete vacuum head also
        ``grasp_critic_loss`` and ``grasp_q_mean`` (means over the critic steps).
        """
        ratio = self.config.critic_actor_ratio
        if callable(batch) and not isinstance(batch, TensorDict):
            minibatches = [batch() for _ in range(ratio)]
        elif isinstance(batch, TensorDict):
            B = batch.batch_size[0]
            if B < ratio or B % ratio:
                raise ValueError(f"a batch of {B} rows cannot be split into "
                                 f"critic_actor_ratio = {ratio} equal minibatches")
            minibatches = list(batch.split(B // ratio, dim=0))
        else:
            raise TypeError(f"batch must be a TensorDict or a callable returning one, got "
                            f"{type(batch).__name__}")
        prepared = [self._prepare(mb) for mb in minibatches]
        critic_infos = [self._critic_step(b) for b in prepared]
        info = {k: float(np.mean([ci[k] for ci in critic_infos])) for k in critic_infos[0]}
        info.update(self._actor_temperature_step(prepared[-1]))
        return info

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict:
        """Everything an exact resume needs: weights, targets, temperature, optimiser
        states, both generators, step counters, the config and the normalisation."""
        return {
            "config": plain(dataclasses.asdict(self.config)), "obs_dim": self.obs_dim,
            "action_dim": self.action_dim, "seed": self.seed,
            "obs_mean": self.obs_mean.clone(), "obs_std": self.obs_std.clone(),
            "actor": copy.deepcopy(self.actor.state_dict()),
            "critic": copy.deepcopy(self.critic.state_dict()),
            "target_critic": copy.deepcopy(self.target_critic.state_dict()),
            "log_alpha": self.log_alpha.detach().clone(),
            "actor_opt": optimizer_state(self.actor_opt),
            "critic_opt": optimizer_state(self.critic_opt),
            "temperature_opt": optimizer_state(self.temperature_opt),
            "act_rng": self._act_rng.get_state(), "update_rng": self._update_rng.get_state(),
            "critic_steps": self.critic_steps, "actor_steps": self.actor_steps,
            **({"grasp_critic": copy.deepcopy(self.grasp_critic.state_dict()),
                "target_grasp_critic": copy.deepcopy(self.target_grasp_critic.state_dict()),
                "grasp_critic_opt": optimizer_state(self.grasp_critic_opt)}
               if self.discrete_vacuum else {}),
            **self._box_state(),
        }

    @classmethod
    def from_state_dict(cls, state: dict) -> "HILSERLAgent":
        """A new agent restored from :meth:`state_dict` output (e.g. in an evaluation
        worker)."""
        config = config_from_plain(HILSERLConfig, _state_config(state))
        agent = cls(state["obs_dim"], state["action_dim"], config, seed=state["seed"])
        agent.load_state_dict(state)
        return agent

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict`. The config and the sizes must match this agent's."""
        mine = dataclasses.asdict(self.config)
        theirs = _state_config(state)
        theirs["hidden"] = tuple(theirs["hidden"])
        for key in ("target_range", "safety_box"):
            if theirs.get(key) is not None:
                theirs[key] = tuple(theirs[key])
        if theirs != mine:
            diff = sorted(k for k in mine if mine[k] != theirs.get(k))
            raise ValueError(f"load_state_dict: config differs in {diff}: "
                             f"{ {k: theirs.get(k) for k in diff} } vs this agent's "
                             f"{ {k: mine[k] for k in diff} }")
        for key in ("obs_dim", "action_dim"):
            if state[key] != getattr(self, key):
                raise ValueError(f"load_state_dict: {key} = {state[key]} in the state, "
                                 f"{getattr(self, key)} in this agent")
        self.seed = state["seed"]
        self.obs_mean, self.obs_std = state["obs_mean"].clone(), state["obs_std"].clone()
        self._load_box(state)
        self.actor.load_state_dict(state["actor"])
        self.critic.load_state_dict(state["critic"])
        self.target_critic.load_state_dict(state["target_critic"])
        with torch.no_grad():
            self.log_alpha.copy_(state["log_alpha"])
        load_optimizer_state(self.actor_opt, state["actor_opt"])
        load_optimizer_state(self.critic_opt, state["critic_opt"])
        load_optimizer_state(self.temperature_opt, state["temperature_opt"])
        self._act_rng.set_state(state["act_rng"])
        self._update_rng.set_state(state["update_rng"])
        self.critic_steps, self.actor_steps = state["critic_steps"], state["actor_steps"]
        if self.discrete_vacuum:
            self.grasp_critic.load_state_dict(state["grasp_critic"])
            self.target_grasp_critic.load_state_dict(state["target_grasp_critic"])
            load_optimizer_state(self.grasp_critic_opt, state["grasp_critic_opt"])


def _state_config(state: dict) -> dict:
    """The config of a :meth:`HILSERLAgent.state_dict`; states saved before the grasp critic
    and the observation clip were added are what they were: Gaussian vacuum, no clip; and
    those saved before the three-way grasp critic (no ``grasp_penalty``) had no toggle
    penalty, and their grasp critic, if any, is the two-way one (``"binary"``); those saved
    before ``action_scale`` acted in the env's units."""
    config = {"vacuum_head": "gaussian", "obs_clip": None, "vacuum_epsilon": 0.0,
              "offline_steps": None, "suction_loss_terminal": False, "target_range": None,
              "action_scale": (1.0, 1.0), "safety_box": None, **state["config"]}
    config["action_scale"] = tuple(config["action_scale"])
    if "grasp_penalty" not in config:
        config["grasp_penalty"] = 0.0
        if config["vacuum_head"] == "discrete":
            config["vacuum_head"] = "binary"
    return config
