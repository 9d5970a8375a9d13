"""ACT (Action Chunking with Transformers) in plain torch, trained only on demonstrations.

The offline imitation-learning reference of the paper's baseline table ("ACT (offline IL)",
Zhao et al. 2023): a conditional VAE whose decoder is a transformer policy that predicts a
chunk of ``k`` future actions from the current observation. It is trained on ``D_demo``
only and is evaluated with no online interaction and no RL updates.

What this module owns, top to bottom:

* :class:`ACTConfig` and :data:`ACT_PROFILES` (``paper`` = the reference sizes, ``cpu`` =
  reduced sizes for a 2-core machine, ``smoke`` = tiny, for tests).
* :func:`act_loss` (L1 on the real steps of the chunk + ``kl_weight`` * KL) and
  :func:`temporal_ensemble` (the exp(-m i) average of overlapping chunk predictions).
* The network :class:`ACTModel`: DETR-style post-norm transformer layers, a CVAE encoder
  over ``[CLS, robot state, a_t .. a_{t+k-1}]`` that gives the style latent ``z``, and the
  policy: an encoder over ``[z, robot state, object state]`` tokens and a decoder with ``k``
  learned queries, one action per query.
* :class:`ACTAgent`: normalisation, batch sampling from step logs, the AdamW update, the
  inference loop (open-loop chunks or temporal ensembling) and an exact ``state_dict``.
* ``python -m baselines.act``: collect scripted demonstrations, train, evaluate at
  checkpoints, write a JSON (the measurements in ``docs/act.md``).

Choices for this benchmark (see ``docs/act.md``):

* Observation tokens. The 52-float ``flat`` observation is split in two tokens: the first
  :data:`FLAT_ROBOT_DIM` = 40 floats are the robot (``robot0_*`` keys: joint positions and
  velocities, TCP position and quaternion, vacuum, and the 18-float proprio vector) and the
  remaining 12 are the object / env state (window pose relative to the seat, contact proxy).
  This mirrors ACT's separate ``qpos`` and ``env_state`` inputs; as in ACT, the CVAE encoder
  sees the robot token only.
* Chunk length ``k`` = 10 (1.0 s at 10 Hz), the benchmark's chunk grid ``h``. The original
  uses 100 steps at 50 Hz (2.0 s).
* The vacuum command (action dim 6) is regressed with L1 like the other dims; the
  environment engages iff it exceeds 0.5, so the regression only has to land on the right
  side of the threshold.
* The L1 term is averaged over the REAL steps of the batch. The reference implementations
  zero the padded entries but divide by all ``B * k * A`` entries, which down-weights
  windows near the episode end; here every demonstrated step weighs the same, and a chunk
  with an all-pad tail gives exactly the loss of the shorter chunk.
* In the reference's state-only branch the latent is computed but never fed to the policy;
  here it always is (token 0 of the policy encoder), as in the image-based ACT.
"""

from __future__ import annotations

import copy
import math
import numbers
from collections import deque
from dataclasses import asdict, dataclass, replace

import numpy as np
import torch
from torch import nn

from window_bench.data.steplog import ACTION_DIM, EpisodeLog, without_noops
from window_bench.envs.task import FAILURE_MODE_NAMES, STAGES
from window_bench.harness.agent import (Agent, AgentSpec, arm_power, generator_state,
                                        load_optimizer_state, module_state, optimizer_state,
                                        with_overrides)
from window_bench.installer.supervisor import check_fine_pose, extra_features, extra_inputs

#: Number of leading floats of the ``flat`` observation that belong to the robot: the
#: ``robot0_*`` entries of ``window_bench.envs.env.STATE_KEYS`` (7 + 7 + 3 + 4 + 1 + 18).
FLAT_ROBOT_DIM = 40


# ----------------------------------------------------------------------------- config
@dataclass(frozen=True)
class ACTConfig:
    """Hyper-parameters of ACT. The defaults are the reference sizes (the ``paper`` profile)."""

    chunk: int = 10
    """Actions predicted per query, ``k``. 10 = the benchmark's chunk grid (1.0 s at 10 Hz);
    the original uses 100 at 50 Hz (2.0 s)."""
    temporal_ensembling: bool = True
    """Query every step and average all predictions for the current step (``h`` = 1), as
    ACT is evaluated (Zhao et al. 2023, Sec. 3.3); False executes each chunk open-loop
    (``h`` = ``chunk``)."""
    ensemble_coeff: float = 0.01
    """``m`` in the ensembling weights ``exp(-m i)``, ``i`` = 0 for the oldest prediction.
    ACT's ``m`` >= 0 weights the oldest most ("a smaller m means faster incorporation of new
    observations"); ``m`` < 0 carries that on and weights the newest most (docs/act.md, "The
    ensembling weights move each policy differently"). ``m`` lies in [-5, 5]."""
    d_model: int = 512
    """Width of every transformer token."""
    n_heads: int = 8
    """Attention heads; must divide ``d_model``."""
    ff: int = 3200
    """Hidden width of the feed-forward block of every transformer layer."""
    enc_layers: int = 4
    """Layers of the policy's transformer encoder."""
    vae_enc_layers: int = 4
    """Layers of the CVAE encoder."""
    dec_layers: int = 1
    """Layers of the policy's transformer decoder (the original's 7 only use the first)."""
    latent_dim: int = 32
    """Size of the CVAE style latent ``z``."""
    dropout: float = 0.1
    """Dropout in attention and feed-forward blocks (training only)."""
    kl_weight: float = 10.0
    """Weight of the KL term of the CVAE loss."""
    lr: float = 1e-5
    """AdamW learning rate."""
    weight_decay: float = 1e-4
    """AdamW weight decay."""
    batch_size: int = 8
    """Chunks per gradient step in :meth:`ACTAgent.train_offline`."""
    offline_steps: int = 10_000
    """Suggested number of gradient steps for this profile (the harness's default). 10,000
    ~ the reference's 2,000 epochs over 40 training episodes at batch 8."""
    robot_dim: int = FLAT_ROBOT_DIM
    """Leading observation floats that form the robot token; the rest form the object-state
    token. 0 (or ``obs_dim``) uses the whole observation as one token."""
    std_floor: float = 1e-2
    """Lower bound of the z-score standard deviations (constant dims such as the vacuum in
    setting A)."""
    obs_clip: float = 0.0
    """Bound on the z-scored observations (QC-FQL clips at 10); 0 = no clipping (ACT)."""
    cvae: bool = True
    """Train with the CVAE (ACT): the latent ``z`` from the encoder, which sees the target
    actions. ``False`` trains the policy with ``z = 0``, as it acts (no encoder, no KL):
    ACT's "w/o CVAE" ablation (Zhao et al. 2023, Sec. 5)."""
    fine_pose_mm: float = 0.0
    """Fine pose features (not in ACT; state track, as QC-FQL's option of the same name):
    ``0`` off; else the object-state token also reads ``tanh(window_pos_rel / fine_pose_mm)``
    and ``tanh(window_rot_rel / fine_pose_deg)``
    (:func:`window_bench.installer.supervisor.fine_pose_features`), which resolve the
    panel's millimetres around the seat where the z-score of whole episodes does not."""
    fine_pose_deg: float = 1.0
    """Angle scale of the fine rotation features (used when ``fine_pose_mm > 0``)."""
    grasp_mm: float = 0.0
    """Grasp features (not in ACT; state track, as QC-FQL's option of the same name): ``0``
    off; else the object-state token also reads ``tanh`` of the cup's offset from the
    panel's centre in the panel's face plane at this scale
    (:func:`window_bench.installer.supervisor.grasp_features`): where the cup holds the
    panel, which on B changes from one pick to the next."""
    action_power: float = 1.0
    """Action companding (not in ACT; as QC-FQL's option of the same name): ``1``, the model
    learns the env's actions; ``p > 1``, it learns ``sign(a) |a|^(1/p)`` on the arm's entries
    (z-scored like any target) and the env receives ``sign(c) |c|^p``, so the millimetre
    corrections near contact take more of the regression's range."""
    loss: str = "l1"
    """Reconstruction term: ``"l1"`` (ACT) or ``"l2"`` (squared error, a departure measured in
    docs/act.md "Why ACT fails where flow BC succeeds")."""
    drop_noops: bool = False
    """Train on the demonstrations without their no-op steps in free space (not in ACT; the
    operator model's hesitation pauses before the panel enters the opening,
    :func:`window_bench.data.steplog.without_noops`), as OpenVLA's data preparation drops
    no-op actions: a deterministic imitator may learn to stand still where a demonstrator
    paused. Pauses once the panel is in the opening stay. The normaliser is fitted on the
    same steps. Measured in docs/act.md: it seats fewer on A."""

    def __post_init__(self):
        for name in ("chunk", "d_model", "n_heads", "ff", "enc_layers", "vae_enc_layers",
                     "dec_layers", "latent_dim", "batch_size", "offline_steps"):
            _check_int(f"ACTConfig.{name}", getattr(self, name), 1)
        _check_int("ACTConfig.robot_dim", self.robot_dim, 0)
        if self.d_model % self.n_heads:
            raise ValueError(f"ACTConfig.n_heads = {self.n_heads} must divide "
                             f"d_model = {self.d_model}")
        for name in ("cvae", "temporal_ensembling", "drop_noops"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"ACTConfig.{name} = {getattr(self, name)!r} must be True "
                                 f"or False")
        for name, lo, hi, hi_open in (("dropout", 0.0, 1.0, True),
                                      ("ensemble_coeff", -5.0, 5.0, False),
                                      ("kl_weight", 0.0, math.inf, True),
                                      ("weight_decay", 0.0, math.inf, True)):
            v = getattr(self, name)
            ok = _is_real(v) and lo <= v and (v < hi if hi_open else v <= hi)
            if not ok:
                raise ValueError(f"ACTConfig.{name} = {v!r} is not allowed: must lie in "
                                 f"[{lo}, {hi}{')' if hi_open else ']'}")
        if self.loss not in ("l1", "l2"):
            raise ValueError(f"ACTConfig.loss = {self.loss!r} is not allowed: use 'l1' or 'l2'")
        if not (_is_real(self.obs_clip) and self.obs_clip >= 0):
            raise ValueError(f"ACTConfig.obs_clip = {self.obs_clip!r} is not allowed: must be "
                             f"0 (no clipping) or a finite number > 0")
        check_fine_pose("ACTConfig", self.fine_pose_mm, self.fine_pose_deg)
        for name, lo, hi in (("grasp_mm", 0.0, 1000.0), ("action_power", 1.0, 4.0)):
            v = getattr(self, name)
            if not (_is_real(v) and lo <= v <= hi):
                raise ValueError(f"ACTConfig.{name} = {v!r} is not allowed: must lie in "
                                 f"[{lo}, {hi}]")
        for name, hi in (("lr", 1.0), ("std_floor", math.inf)):
            v = getattr(self, name)
            if not (_is_real(v) and 0.0 < v <= hi):
                raise ValueError(f"ACTConfig.{name} = {v!r} is not allowed: must be a "
                                 f"finite number in (0, {hi}]")


def _is_real(v) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v)


def _check_int(name: str, v, lo: int) -> None:
    if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < lo:
        raise ValueError(f"{name} = {v!r} is not allowed: must be an integer >= {lo}")


#: Parameter-name prefixes of the CVAE encoder (training only; not in the policy state).
_CVAE_ENCODER = ("cls_embed", "vae_", "latent_proj.")

#: Fields that do not change what is trained; a checkpoint may be loaded into an agent
#: that sets them differently.
_INFERENCE_ONLY = ("temporal_ensembling", "ensemble_coeff", "offline_steps")


#: Named configurations. ``paper``: the reference sizes. ``cpu``: reduced for the 2-core
#: machine (measured step times and the choice of steps in docs/act.md); ``long`` the same
#: (ACT never interacts). ``smoke``: tiny, for tests and CI.
ACT_PROFILES: dict[str, ACTConfig] = {
    "paper": ACTConfig(),
    # Acting weights (policy_state_dict) 0.22 M parameters, a 0.90 MB policy file; the
    # CVAE encoder (training only) keeps the reference depth. 16,000 steps: the held-out L1
    # on the harness's D_demo changes by < 2 % after 10,000 (docs/act.md "Train length").
    "cpu": ACTConfig(d_model=64, n_heads=4, ff=256, enc_layers=3, vae_enc_layers=4,
                     dec_layers=1, latent_dim=32, lr=1e-4, offline_steps=16_000),
    "smoke": ACTConfig(d_model=32, n_heads=2, ff=64, enc_layers=1, vae_enc_layers=1,
                       dec_layers=1, latent_dim=4, dropout=0.0, lr=1e-3, offline_steps=100),
}
# ACT learns from D_demo only: the interaction budget of `long` does not reach it.
ACT_PROFILES["long"] = ACT_PROFILES["cpu"]


# ----------------------------------------------------------------------------- losses
def kl_to_prior(mu: torch.Tensor, logvar: torch.Tensor) -> torch.Tensor:
    """KL( N(mu, exp(logvar)) || N(0, I) ), summed over latent dims, averaged over the batch."""
    return (-0.5 * (1.0 + logvar - mu.pow(2) - logvar.exp())).sum(-1).mean()


def act_loss(pred: torch.Tensor, target: torch.Tensor, is_pad: torch.Tensor,
             mu: torch.Tensor, logvar: torch.Tensor, kl_weight: float,
             loss: str = "l1") -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """ACT's CVAE loss: ``l1 + kl_weight * kl``; returns ``(loss, l1, kl)``.

    ``pred`` / ``target`` are (B, k, A) normalised actions, ``is_pad`` (B, k) is True on
    steps past the episode end. The L1 term is the mean absolute error over the real
    (non-padded) entries only: whatever sits at padded positions, even NaN, has no effect.
    ``loss="l2"`` trains on the mean squared error instead (the returned ``l1`` is still the
    absolute error, for comparison).
    """
    if pred.shape != target.shape or pred.shape[:2] != is_pad.shape:
        raise ValueError(f"act_loss: pred {tuple(pred.shape)}, target {tuple(target.shape)} "
                         f"and is_pad {tuple(is_pad.shape)} do not agree on (B, k)")
    real = ~is_pad.bool().unsqueeze(-1).expand_as(pred)
    err = torch.where(real, (pred - target).abs(), torch.zeros((), dtype=pred.dtype))
    l1 = err.sum() / real.sum().clamp_min(1)
    kl = kl_to_prior(mu, logvar)
    rec = l1 if loss == "l1" else err.square().sum() / real.sum().clamp_min(1)
    return rec + kl_weight * kl, l1, kl


def temporal_ensemble(chunks, coeff: float = 0.01) -> np.ndarray:
    """Average of every prediction for the current step, oldest prediction weighted most
    (``coeff`` > 0; the newest most for ``coeff`` < 0).

    ``chunks`` are the chunks predicted at the last ``n`` consecutive steps, oldest first,
    each (k, A) with ``n <= k``: chunk ``j`` was predicted ``n - 1 - j`` steps ago, so its
    row ``n - 1 - j`` is its prediction for now. Weights ``exp(-coeff * i)``, ``i = 0`` for
    the oldest, normalised to sum to 1 (Zhao et al. 2023, Sec. 3.3).
    """
    chunks = [np.asarray(c, dtype=np.float64) for c in chunks]
    n = len(chunks)
    if n == 0:
        raise ValueError("temporal_ensemble: got no chunks")
    if n > chunks[0].shape[0]:
        raise ValueError(f"temporal_ensemble: {n} chunks but chunk length "
                         f"{chunks[0].shape[0]}; at most k chunks overlap the current step")
    preds = np.stack([c[n - 1 - j] for j, c in enumerate(chunks)])  # (n, A), oldest first
    e = -coeff * np.arange(n)
    w = np.exp(e - e.max())          # the same normalised weights, finite for any coeff < 0
    return (w[:, None] * preds).sum(0) / w.sum()


# ----------------------------------------------------------------------------- network
def _sinusoid_table(n: int, d: int) -> torch.Tensor:
    """Fixed sine/cosine position table (n, d), as in "Attention is all you need"."""
    pos = torch.arange(n, dtype=torch.float64)[:, None]
    div = torch.pow(10000.0, torch.arange(0, d, 2, dtype=torch.float64) / d)
    table = torch.zeros(n, d, dtype=torch.float64)
    table[:, 0::2] = torch.sin(pos / div)
    table[:, 1::2] = torch.cos(pos / div)[:, : d // 2]
    return table.float()


class _FeedForward(nn.Sequential):
    def __init__(self, d: int, ff: int, dropout: float):
        super().__init__(nn.Linear(d, ff), nn.ReLU(), nn.Dropout(dropout), nn.Linear(ff, d))


class _EncoderLayer(nn.Module):
    """Post-norm self-attention layer; DETR-style, positions are added to queries and keys
    at every layer (not to values)."""

    def __init__(self, d: int, heads: int, ff: int, dropout: float):
        super().__init__()
        self.attn = nn.MultiheadAttention(d, heads, dropout=dropout, batch_first=True)
        self.ff = _FeedForward(d, ff, dropout)
        self.norm1, self.norm2 = nn.LayerNorm(d), nn.LayerNorm(d)
        self.drop1, self.drop2 = nn.Dropout(dropout), nn.Dropout(dropout)

    def forward(self, x, pos, key_padding_mask=None):
        q = k = x + pos
        a = self.attn(q, k, x, key_padding_mask=key_padding_mask, need_weights=False)[0]
        x = self.norm1(x + self.drop1(a))
        return self.norm2(x + self.drop2(self.ff(x)))


class _DecoderLayer(nn.Module):
    """Post-norm decoder layer: self-attention over the queries, cross-attention to the
    encoder output, feed-forward."""

    def __init__(self, d: int, heads: int, ff: int, dropout: float):
        super().__init__()
        self.self_attn = nn.MultiheadAttention(d, heads, dropout=dropout, batch_first=True)
        self.cross_attn = nn.MultiheadAttention(d, heads, dropout=dropout, batch_first=True)
        self.ff = _FeedForward(d, ff, dropout)
        self.norm1, self.norm2, self.norm3 = nn.LayerNorm(d), nn.LayerNorm(d), nn.LayerNorm(d)
        self.drop1, self.drop2, self.drop3 = (nn.Dropout(dropout), nn.Dropout(dropout),
                                              nn.Dropout(dropout))

    def forward(self, tgt, query_pos, memory, memory_pos):
        q = k = tgt + query_pos
        tgt = self.norm1(tgt + self.drop1(self.self_attn(q, k, tgt, need_weights=False)[0]))
        a = self.cross_attn(tgt + query_pos, memory + memory_pos, memory, need_weights=False)[0]
        tgt = self.norm2(tgt + self.drop2(a))
        return self.norm3(tgt + self.drop3(self.ff(tgt)))


class ACTModel(nn.Module):
    """CVAE encoder + transformer policy on normalised observations and actions.

    ``forward(obs, actions=None, is_pad=None, noise=None)`` returns ``(pred, mu, logvar)``:
    ``pred`` (B, k, A). With ``actions`` (training) the CVAE encoder gives ``mu, logvar`` and
    ``z = mu + exp(logvar / 2) * noise``; without (inference) the encoder is not run,
    ``z = 0`` (the prior mean) and ``mu = logvar = None``.
    """

    def __init__(self, obs_dim: int, action_dim: int, cfg: ACTConfig):
        super().__init__()
        d, k = cfg.d_model, cfg.chunk
        # Token split of the observation: [robot | object state], or one token.
        self.robot_dim = cfg.robot_dim if 0 < cfg.robot_dim < obs_dim else obs_dim
        self.env_dim = obs_dim - self.robot_dim
        self.latent_dim = cfg.latent_dim

        def layers(cls, n):
            return nn.ModuleList(cls(d, cfg.n_heads, cfg.ff, cfg.dropout) for _ in range(n))

        # CVAE encoder: [CLS, robot, a_t .. a_{t+k-1}] -> (mu, logvar) from the CLS output.
        self.cls_embed = nn.Parameter(torch.zeros(1, 1, d))
        self.vae_robot_proj = nn.Linear(self.robot_dim, d)
        self.vae_action_proj = nn.Linear(action_dim, d)
        self.register_buffer("vae_pos", _sinusoid_table(k + 2, d)[None], persistent=False)
        self.vae_encoder = layers(_EncoderLayer, cfg.vae_enc_layers)
        self.latent_proj = nn.Linear(d, 2 * cfg.latent_dim)

        # Policy: encoder over [z, robot, object state] tokens, decoder with k queries.
        self.latent_out_proj = nn.Linear(cfg.latent_dim, d)
        self.robot_proj = nn.Linear(self.robot_dim, d)
        self.env_proj = nn.Linear(self.env_dim, d) if self.env_dim else None
        n_tokens = 3 if self.env_dim else 2
        self.token_pos = nn.Parameter(torch.zeros(1, n_tokens, d))
        self.encoder = layers(_EncoderLayer, cfg.enc_layers)
        self.query_pos = nn.Parameter(torch.zeros(1, k, d))
        self.decoder = layers(_DecoderLayer, cfg.dec_layers)
        self.decoder_norm = nn.LayerNorm(d)
        self.action_head = nn.Linear(d, action_dim)

        for p in (self.cls_embed, self.token_pos, self.query_pos):
            nn.init.normal_(p)  # as nn.Embedding, which the reference uses for these
        for block in (self.vae_encoder, self.encoder, self.decoder):
            for p in block.parameters():
                if p.dim() > 1:
                    nn.init.xavier_uniform_(p)

    def encode(self, robot: torch.Tensor, actions: torch.Tensor, is_pad: torch.Tensor):
        """CVAE encoder: ``(mu, logvar)``, each (B, latent_dim). Padded actions are masked
        out of attention, so they cannot change the latent."""
        B = robot.shape[0]
        tokens = torch.cat([self.cls_embed.expand(B, -1, -1),
                            self.vae_robot_proj(robot)[:, None],
                            self.vae_action_proj(actions)], dim=1)
        keep = torch.zeros(B, 2, dtype=torch.bool, device=robot.device)
        mask = torch.cat([keep, is_pad.bool()], dim=1)  # True = ignore this key
        x = tokens
        for layer in self.vae_encoder:
            x = layer(x, self.vae_pos, key_padding_mask=mask)
        mu, logvar = self.latent_proj(x[:, 0]).chunk(2, dim=-1)
        return mu, logvar

    def forward(self, obs, actions=None, is_pad=None, noise=None):
        B = obs.shape[0]
        robot = obs[:, : self.robot_dim]
        if actions is None:
            mu = logvar = None
            z = obs.new_zeros(B, self.latent_dim)
        else:
            mu, logvar = self.encode(robot, actions, is_pad)
            if noise is None:
                noise = torch.randn_like(mu)
            z = mu + (0.5 * logvar).exp() * noise
        tokens = [self.latent_out_proj(z), self.robot_proj(robot)]
        if self.env_proj is not None:
            tokens.append(self.env_proj(obs[:, self.robot_dim:]))
        memory = torch.stack(tokens, dim=1)
        for layer in self.encoder:
            memory = layer(memory, self.token_pos)
        tgt = torch.zeros_like(self.query_pos).expand(B, -1, -1)
        query_pos = self.query_pos.expand(B, -1, -1)
        for layer in self.decoder:
            tgt = layer(tgt, query_pos, memory, self.token_pos)
        return self.action_head(self.decoder_norm(tgt)), mu, logvar


# ----------------------------------------------------------------------------- data
def _stack_episodes(episodes, obs_dim: int, k: int) -> dict:
    """Concatenate episodes for chunk sampling: observations ``s_0 .. s_{T-1}`` and actions
    padded with ``k`` zero rows after each episode, with the offsets to index them."""
    if isinstance(episodes, EpisodeLog):
        episodes = [episodes]
    episodes = list(episodes)
    if not episodes:
        raise ValueError("ACT: got no episodes; need at least one demonstration")
    obs, act, lengths = [], [], []
    for i, ep in enumerate(episodes):
        if not isinstance(ep, EpisodeLog):
            raise TypeError(f"ACT: episode {i} is a {type(ep).__name__}, not an EpisodeLog")
        ep.validate()
        if ep.observations.shape[1] != obs_dim:
            raise ValueError(f"ACT: episode {i} has obs_dim {ep.observations.shape[1]}, the "
                             f"agent was built for {obs_dim}")
        obs.append(ep.observations[:-1])
        act.append(np.concatenate([ep.actions, np.zeros((k, ep.actions.shape[1]), np.float32)]))
        lengths.append(ep.T)
    lengths = np.asarray(lengths, dtype=np.int64)
    return {"obs": np.concatenate(obs), "actions": np.concatenate(act), "lengths": lengths,
            "obs_offset": np.concatenate([[0], np.cumsum(lengths)[:-1]]),
            "act_offset": np.concatenate([[0], np.cumsum(lengths + k)[:-1]]), "k": k}


def _draw(stack: dict, batch_size: int, generator: np.random.Generator) -> dict:
    """``batch_size`` chunks whose start steps are uniform over all demonstrated steps."""
    _check_int("batch_size", batch_size, 1)
    if not isinstance(generator, np.random.Generator):
        raise TypeError(f"generator must be a numpy.random.Generator, got "
                        f"{type(generator).__name__}")
    lengths, k = stack["lengths"], stack["k"]
    flat = generator.integers(0, int(lengths.sum()), size=batch_size)
    ep = np.searchsorted(np.cumsum(lengths), flat, side="right")
    t = flat - stack["obs_offset"][ep]
    steps = t[:, None] + np.arange(k)[None, :]
    return {
        "obs": stack["obs"][flat],
        "actions": stack["actions"][stack["act_offset"][ep][:, None] + steps],
        "is_pad": steps >= lengths[ep][:, None],
        "episode": ep, "start": t,
    }


# ----------------------------------------------------------------------------- agent
class ACTAgent(Agent):
    """ACT trained offline on step logs; acts in chunks (or with temporal ensembling).

    Parameters
    ----------
    obs_dim : int
        Size of the flat observation (52 for ``obs_mode="flat"``).
    action_dim : int
        Size of the action (7: TCP increment + vacuum).
    config : ACTConfig or str
        A configuration or the name of one of :data:`ACT_PROFILES`.
    seed : int
        Seeds the weights, the batch sampling and the dropout / latent noise.

    The agent keeps its own torch random stream (forked around every update), so its
    training is reproducible whatever else uses torch's global generator, and
    :meth:`state_dict` captures it. Sets ``torch.set_num_threads(1)`` (2-core machines).
    """

    def __init__(self, obs_dim: int, action_dim: int = ACTION_DIM,
                 config: ACTConfig | str = ACT_PROFILES["paper"], seed: int = 0):
        torch.set_num_threads(1)
        if isinstance(config, str):
            if config not in ACT_PROFILES:
                raise ValueError(f"ACT profile {config!r} is unknown; allowed "
                                 f"{sorted(ACT_PROFILES)}")
            config = ACT_PROFILES[config]
        if not isinstance(config, ACTConfig):
            raise TypeError(f"config must be an ACTConfig or a profile name, got "
                            f"{type(config).__name__}")
        _check_int("obs_dim", obs_dim, 1)
        _check_int("action_dim", action_dim, 1)
        _check_int("seed", seed, 0)
        fine = extra_inputs(config, obs_dim)
        if config.robot_dim > obs_dim:
            raise ValueError(f"ACTConfig.robot_dim = {config.robot_dim} is not allowed for "
                             f"obs_dim = {obs_dim}: must lie in [0, {obs_dim}]")
        self.config, self.obs_dim, self.action_dim = config, int(obs_dim), int(action_dim)
        self.seed = int(seed)
        torch_gen = torch.Generator().manual_seed(self.seed)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(int(torch.randint(2**62, (1,), generator=torch_gen)))
            # the fine pose and grasp features join the end of the observation: the
            # object-state token
            self.model = ACTModel(self.obs_dim + fine,
                                  self.action_dim, config)
            self._torch_rng = torch.get_rng_state()
        self.optimizer = torch.optim.AdamW(self.model.parameters(), lr=config.lr,
                                           weight_decay=config.weight_decay)
        self.rng = np.random.default_rng(self.seed)
        self.norm: dict[str, torch.Tensor] | None = None
        self.grad_steps = 0
        self._history: deque = deque(maxlen=config.chunk)

    @property
    def h(self) -> int:
        """Actions the harness executes per :meth:`act` call: ``chunk``, or 1 with ensembling."""
        return 1 if self.config.temporal_ensembling else self.config.chunk

    # ------------------------------------------------------------------ the harness's interface
    own_normalizer = True   # z-scores observations and actions with its own demo statistics

    @classmethod
    def make_config(cls, h: int, profile, overrides: dict) -> ACTConfig:
        return with_overrides(ACT_PROFILES[profile.name], overrides)

    @classmethod
    def create(cls, spec: AgentSpec) -> "ACTAgent":
        """The profile's ACT sizes (:data:`ACT_PROFILES`), its normaliser fitted on the demos."""
        agent = cls(spec.obs_dim, spec.action_dim,
                    cls.make_config(spec.h, spec.profile, spec.overrides), seed=spec.seed)
        agent.fit_normalizer(spec.demos)
        return agent

    @property
    def offline_steps(self) -> int:
        return self.config.offline_steps

    def attach_demos(self, demos) -> None:
        self._demo_stack = self._training_stack(demos, self.config.chunk)

    def learn(self, sample) -> tuple[dict[str, float], int]:
        """One :meth:`update` on ``batch_size`` chunks of the demos (:meth:`attach_demos`);
        ACT trains on D_demo only, so the harness's ``sample`` is not used."""
        return self.update(_draw(self._demo_stack, self.config.batch_size, self.rng)), 1

    def _training_stack(self, episodes, k: int) -> dict:
        """The chunk stack of the episodes ACT trains on (without their no-op steps when
        ``config.drop_noops``)."""
        episodes = [episodes] if isinstance(episodes, EpisodeLog) else list(episodes)
        if self.config.drop_noops:
            episodes = [without_noops(ep, before="insertion_entered")
                        if isinstance(ep, EpisodeLog) else ep
                        for ep in episodes]
        return _stack_episodes(episodes, self.obs_dim, k)

    # ------------------------------------------------------------------ normalisation
    def fit_normalizer(self, episodes) -> None:
        """Z-score statistics of the observations ``s_0 .. s_{T-1}`` and the actions of
        ``episodes``; standard deviations are floored at ``config.std_floor``."""
        stack = self._training_stack(episodes, 1)
        real = np.concatenate([np.arange(n) + o for n, o in zip(stack["lengths"],
                                                                  stack["act_offset"])])
        obs = stack["obs"].astype(np.float64)
        act = self._compand(torch.as_tensor(stack["actions"][real])).numpy().astype(np.float64)
        floor = self.config.std_floor
        self.norm = {
            "obs_mean": torch.tensor(obs.mean(0), dtype=torch.float32),
            "obs_std": torch.tensor(np.maximum(obs.std(0), floor), dtype=torch.float32),
            "act_mean": torch.tensor(act.mean(0), dtype=torch.float32),
            "act_std": torch.tensor(np.maximum(act.std(0), floor), dtype=torch.float32),
        }

    def normalize_obs(self, obs: torch.Tensor) -> torch.Tensor:
        """Z-scored observations, clipped to ``+-config.obs_clip`` when it is set; with
        ``config.fine_pose_mm`` the 6 fine pose features follow, then with ``config.grasp_mm``
        the 2 grasp features."""
        norm = self._need_norm()
        obs_n = (obs - norm["obs_mean"]) / norm["obs_std"]
        clip = self.config.obs_clip
        obs_n = obs_n.clamp(-clip, clip) if clip else obs_n
        c = self.config
        extra = extra_features(obs, c.fine_pose_mm, c.fine_pose_deg, c.grasp_mm)
        return torch.cat([obs_n, *(e.to(obs_n.dtype) for e in extra)], dim=-1)

    def _compand(self, actions: torch.Tensor, inverse: bool = False) -> torch.Tensor:
        """The env's actions as the model learns them (``config.action_power``), or with
        ``inverse`` the model's back to the env's."""
        p = self.config.action_power
        return arm_power(actions, p if inverse else 1.0 / p)

    def _need_norm(self) -> dict:
        if self.norm is None:
            raise RuntimeError("ACTAgent: no normalizer yet; call fit_normalizer(episodes) "
                               "or train_offline(episodes, steps) first")
        return self.norm

    # ------------------------------------------------------------------ training
    def sample_batch(self, episodes, batch_size: int, generator: np.random.Generator) -> dict:
        """A batch of chunks from ``episodes`` (raw, not normalised).

        Start steps ``t`` are drawn uniformly over all steps of all episodes. Returns numpy
        arrays: ``obs`` (B, obs_dim) = ``s_t``; ``actions`` (B, k, A) = ``a_t .. a_{t+k-1}``,
        zero past the episode end; ``is_pad`` (B, k) True there; ``episode`` and ``start``
        (B,) say where each chunk came from.
        """
        return _draw(self._training_stack(episodes, self.config.chunk),
                     batch_size, generator)

    def update(self, batch: dict) -> dict[str, float]:
        """One AdamW step on ``act_loss``; returns ``{"loss", "l1", "kl", "grad_step"}``."""
        norm = self._need_norm()
        obs = batch["obs"]   # a tensor with a graph on the pixel track: its front end trains too
        obs = (obs.float() if isinstance(obs, torch.Tensor)
               else torch.as_tensor(np.asarray(obs), dtype=torch.float32))
        actions = self._compand(torch.as_tensor(np.asarray(batch["actions"]),
                                                dtype=torch.float32))
        is_pad = torch.as_tensor(np.asarray(batch["is_pad"]), dtype=torch.bool)
        B, k = is_pad.shape[0], self.config.chunk
        if (obs.shape != (B, self.obs_dim) or actions.shape != (B, k, self.action_dim)
                or is_pad.shape != (B, k)):
            raise ValueError(f"ACTAgent.update: expected obs (B, {self.obs_dim}), actions "
                             f"(B, {k}, {self.action_dim}), is_pad (B, {k}); got "
                             f"{tuple(obs.shape)}, {tuple(actions.shape)}, {tuple(is_pad.shape)}")
        obs_n = self.normalize_obs(obs)
        act_n = (actions - norm["act_mean"]) / norm["act_std"]
        # Padded targets are masked in the loss and in the CVAE encoder; zero them anyway so
        # no garbage value there can reach a float operation.
        act_n = act_n.masked_fill(is_pad[..., None], 0.0)
        self.model.train()
        with torch.random.fork_rng(devices=[]):
            torch.set_rng_state(self._torch_rng)
            if self.config.cvae:
                pred, mu, logvar = self.model(obs_n, act_n, is_pad)
            else:   # z = 0 in training as in acting: mu = logvar = 0 gives KL = 0 exactly
                pred = self.model(obs_n)[0]
                mu = logvar = pred.new_zeros(B, self.config.latent_dim)
            loss, l1, kl = act_loss(pred, act_n, is_pad, mu, logvar, self.config.kl_weight,
                                    self.config.loss)
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            self.optimizer.step()
            self._torch_rng = torch.get_rng_state()
        self.grad_steps += 1
        return {"loss": loss.item(), "l1": l1.item(), "kl": kl.item(),
                "grad_step": self.grad_steps}

    def train_offline(self, episodes, steps: int, progress: bool = False) -> list[dict]:
        """``steps`` gradient steps on batches of ``config.batch_size`` chunks of ``episodes``.

        Fits the normalizer first if it has not been fitted (a resumed agent keeps its own).
        Returns one ``update`` dict per step.
        """
        _check_int("steps", steps, 0)
        stack = self._training_stack(episodes, self.config.chunk)
        if self.norm is None:
            self.fit_normalizer(episodes)
        it = range(steps)
        if progress:
            from tqdm import tqdm
            it = tqdm(it, desc="ACT offline", unit="step")
        logs = []
        for _ in it:
            logs.append(self.update(_draw(stack, self.config.batch_size, self.rng)))
            if progress and len(logs) % 50 == 0:
                it.set_postfix(loss=f"{logs[-1]['loss']:.4f}")
        return logs

    @torch.no_grad()
    def chunk_l1(self, episodes) -> float:
        """Held-out metric: the masked L1 (normalised units) of the ``z = 0`` predictions for
        the chunk starting at EVERY step of ``episodes`` (no dropout, no sampling)."""
        norm = self._need_norm()
        stack = _stack_episodes(episodes, self.obs_dim, self.config.chunk)
        k, total, count = self.config.chunk, 0.0, 0
        self.model.eval()
        for n, o_off, a_off in zip(stack["lengths"], stack["obs_offset"], stack["act_offset"]):
            steps = np.arange(n)[:, None] + np.arange(k)[None, :]
            obs = torch.from_numpy(stack["obs"][o_off:o_off + n])
            target = self._compand(torch.from_numpy(stack["actions"][a_off + steps]))
            is_pad = torch.from_numpy(steps >= n)
            pred = self.model(self.normalize_obs(obs))[0]
            err = ((pred - (target - norm["act_mean"]) / norm["act_std"]).abs()
                   * (~is_pad)[..., None])
            total += float(err.sum())
            count += int((~is_pad).sum()) * self.action_dim
        return total / count

    # ------------------------------------------------------------------ acting
    def reset(self) -> None:
        """Start of an episode: forget the chunks kept for temporal ensembling."""
        self._history.clear()

    @torch.no_grad()
    def predict_chunk(self, obs: np.ndarray) -> np.ndarray:
        """The (k, A) chunk the policy predicts for ``obs`` with ``z = 0``, in [-1, 1]."""
        self._need_norm()
        obs = np.asarray(obs, dtype=np.float32)
        if obs.shape != (self.obs_dim,):
            raise ValueError(f"ACTAgent.act: expected an observation of shape "
                             f"({self.obs_dim},), got {obs.shape}")
        if not np.isfinite(obs).all():
            raise ValueError("ACTAgent.act: the observation has non-finite values")
        return self.predict_chunks(obs[None])[0]

    @torch.no_grad()
    def predict_chunks(self, obs: np.ndarray) -> np.ndarray:
        """(n, k, A) chunks for a batch of observations (n, obs_dim), ``z = 0``, in [-1, 1]."""
        norm = self._need_norm()
        self.model.eval()
        pred = self.model(self.normalize_obs(torch.as_tensor(np.asarray(obs, np.float32))))[0]
        actions = (pred * norm["act_std"] + norm["act_mean"]).clamp(-1.0, 1.0)
        return self._compand(actions, inverse=True).numpy().astype(np.float32)

    def act(self, obs: np.ndarray, deterministic: bool = True) -> np.ndarray:
        """Actions to execute next: the whole chunk (k, A), or (1, A) with temporal
        ensembling (the average of every chunk predicted so far in this episode that
        covers this step; call :meth:`reset` at the start of each episode).

        ACT always acts with ``z = 0``; ``deterministic`` is accepted for the harness's
        policy interface and must be True."""
        if not deterministic:
            raise ValueError("ACTAgent.act: deterministic=False is not supported; ACT acts "
                             "with the prior mean z = 0 (there is no exploration noise)")
        chunk = self.predict_chunk(obs)
        if not self.config.temporal_ensembling:
            return chunk
        self._history.append(chunk)
        avg = temporal_ensemble(self._history, self.config.ensemble_coeff)
        return np.clip(avg, -1.0, 1.0).astype(np.float32)[None]

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict:
        """Everything needed to resume exactly: weights, optimizer, normalizer, both random
        streams, the gradient-step counter and the configuration (a deep copy; loadable
        with ``torch.load(..., weights_only=True)``). The ensembling history is not kept:
        checkpoints are taken between episodes."""
        return copy.deepcopy({
            "config": asdict(self.config), "obs_dim": self.obs_dim,
            "action_dim": self.action_dim, "seed": self.seed,
            "model": module_state(self.model), "optimizer": optimizer_state(self.optimizer),
            "norm": self.norm, "rng": generator_state(self.rng),
            "torch_rng": self._torch_rng, "grad_steps": self.grad_steps,
        })

    def policy_state_dict(self) -> dict:
        """What acting needs: the policy's weights (not the CVAE encoder, which only
        training runs), the normaliser, sizes and config."""
        return copy.deepcopy({
            "config": asdict(self.config), "obs_dim": self.obs_dim,
            "action_dim": self.action_dim, "seed": self.seed, "norm": self.norm,
            "model": {k: v for k, v in module_state(self.model).items()
                      if not k.startswith(_CVAE_ENCODER)}})

    @classmethod
    def from_policy_state_dict(cls, sd: dict) -> "ACTAgent":
        """An agent that acts like the one :meth:`policy_state_dict` came from (its CVAE
        encoder keeps its initial weights: for acting only)."""
        agent = cls(sd["obs_dim"], sd["action_dim"], ACTConfig(**sd["config"]), seed=sd["seed"])
        missing = agent.model.load_state_dict(sd["model"], strict=False).missing_keys
        if any(not k.startswith(_CVAE_ENCODER) for k in missing):
            raise ValueError(f"ACTAgent.from_policy_state_dict: policy weights missing: "
                             f"{[k for k in missing if not k.startswith(_CVAE_ENCODER)]}")
        agent.norm = copy.deepcopy(sd["norm"])
        return agent

    @classmethod
    def from_state_dict(cls, sd: dict) -> "ACTAgent":
        """A new agent built from the configuration stored in ``sd`` and loaded from it
        (e.g. in an evaluation worker)."""
        agent = cls(sd["obs_dim"], sd["action_dim"], ACTConfig(**sd["config"]), seed=sd["seed"])
        agent.load_state_dict(sd)
        return agent

    def load_state_dict(self, sd: dict) -> None:
        """Restore :meth:`state_dict`. Raises ``ValueError`` if it was saved by an agent of
        another configuration or size; the inference-only settings (``temporal_ensembling``,
        ``ensemble_coeff``, ``offline_steps``) may differ and stay this agent's, so one
        trained model can be evaluated both ways."""
        for key in ("obs_dim", "action_dim"):
            if sd[key] != getattr(self, key):
                raise ValueError(f"ACTAgent.load_state_dict: checkpoint {key} = {sd[key]}, "
                                 f"this agent has {getattr(self, key)}")
        saved = replace(self.config, **{k: v for k, v in sd["config"].items()
                                        if k not in _INFERENCE_ONLY})
        if saved != self.config:
            diff = {k: (v, getattr(self.config, k)) for k, v in asdict(saved).items()
                    if getattr(self.config, k) != v}
            raise ValueError(f"ACTAgent.load_state_dict: checkpoint config differs "
                             f"(checkpoint, this agent): {diff}")
        sd = copy.deepcopy(sd)
        self.model.load_state_dict(sd["model"])
        load_optimizer_state(self.optimizer, sd["optimizer"])
        self.norm = sd["norm"]
        self.rng = np.random.default_rng()
        self.rng.bit_generator.state = sd["rng"]
        self._torch_rng = sd["torch_rng"]
        self.grad_steps = int(sd["grad_steps"])
        self.seed = int(sd["seed"])
        self.reset()



# ----------------------------------------------------------------------------- script
def _collect_demos(env_id: str, seeds) -> list[EpisodeLog]:
    """Scripted-installer episodes as ``"demo"`` step logs (a stand-in for teleoperation)."""
    import gymnasium as gym

    from window_bench.installer.scripted import ScriptedInstaller  # importing it registers the ids

    env = gym.make(env_id, obs_mode="flat")
    episodes = []
    for i, seed in enumerate(seeds):
        obs, _ = env.reset(seed=int(seed))
        expert = ScriptedInstaller(env, seed=int(seed))
        observations, actions, rewards, ends = [obs], [], [], (False, False)
        while not any(ends):
            a = expert.act(obs)
            obs, r, term, trunc, _ = env.step(a)
            observations.append(obs), actions.append(a), rewards.append(r)
            ends = (bool(term), bool(trunc))
        T = len(actions)
        episodes.append(EpisodeLog(
            observations=np.stack(observations), actions=np.stack(actions), rewards=rewards,
            terminated=np.arange(T) == T - 1 if ends[0] else np.zeros(T, bool),
            truncated=np.arange(T) == T - 1 if ends[1] else np.zeros(T, bool),
            provenance=["demo"] * T, takeover_kind=[""] * T, episode_id=i, env_id=env_id,
            seed=int(seed)))
    env.close()
    return episodes


def _lateral_mm(obs: np.ndarray) -> list[float]:
    """|offset| of the panel centre from the seat axis (mm) along the two lateral world axes
    (x, z; the insertion axis is -y), read from the ``flat`` observation's
    ``window_pos_rel``."""
    from window_bench.envs import scene as S

    rel = np.asarray(obs[FLAT_ROBOT_DIM:FLAT_ROBOT_DIM + 3], dtype=np.float64)
    lateral = rel - (rel @ S.INSERTION_AXIS) * S.INSERTION_AXIS
    return [round(1000 * abs(float(lateral[0])), 2), round(1000 * abs(float(lateral[2])), 2)]


def _rollout(agent, env_id: str, seeds, max_steps: int | None = None) -> list[dict]:
    """Seeded evaluation episodes, ``agent.h`` actions executed per ``agent.act(obs)`` (any
    agent with ``act``, ``reset`` and ``h``); each row says how
    the episode ended and where it stalled (the step its furthest stage was reached, the
    closest the panel came to the seat, the lateral offset from the seat axis there and at
    the end, the last step that brought it 1 mm closer, the
    cause of any suction loss) and what the policy commanded (mean |action| per dim, over
    the episode and over its last 50 steps; steps with the vacuum command at or below the
    environment's 0.5 threshold). ``max_steps`` shortens the episodes (tests)."""
    import importlib

    import gymnasium as gym

    importlib.import_module("window_bench")  # registers the ids
    env = gym.make(env_id, obs_mode="flat",
                   **({} if max_steps is None else {"max_episode_steps": max_steps}))
    rows = []
    for seed in seeds:
        obs, info = env.reset(seed=int(seed))
        agent.reset()
        queue: deque = deque()
        actions, stage, stage_step, term, trunc = [], int(info["stage"]), 0, False, False
        closest, progress_step = float(info["position_error"]), 0
        nearest, lateral_closest = float(info["position_error"]), _lateral_mm(obs)
        while not (term or trunc):
            if not queue:
                queue.extend(agent.act(obs)[: agent.h])
            actions.append(queue.popleft())
            obs, _, term, trunc, info = env.step(actions[-1])
            if info["stage"] > stage:
                stage, stage_step = int(info["stage"]), len(actions)
            if info["position_error"] < closest - 1e-3:
                closest, progress_step = float(info["position_error"]), len(actions)
            if info["position_error"] < nearest:
                nearest, lateral_closest = float(info["position_error"]), _lateral_mm(obs)
        actions = np.asarray(actions, dtype=np.float64)
        rows.append({"seed": int(seed), "success": bool(term), "steps": len(actions),
                     "failure_mode": FAILURE_MODE_NAMES[info["failure_code"]] or None,
                     "suction_acquired": bool(info["suction_acquired"]),
                     "insertion_entered": bool(info["insertion_entered"]),
                     "position_error_mm": round(1000 * float(info["position_error"]), 2),
                     "stage": STAGES[stage], "stage_step": stage_step,
                     "closest_mm": round(1000 * min(closest, float(info["position_error"])), 2),
                     "progress_end_step": progress_step,
                     "lateral_at_closest_mm": lateral_closest, "lateral_end_mm": _lateral_mm(obs),
                     "commanded_releases": int(info["suction_releases"]),
                     "grip_breaks": int(info["suction_failures"]),
                     "vacuum_off_steps": int((actions[:, -1] <= 0.5).sum()),
                     "abs_action_mean": np.abs(actions).mean(0).round(4).tolist(),
                     "abs_action_mean_last50": np.abs(actions[-50:]).mean(0).round(4).tolist()})
    env.close()
    return rows


def _harness_demos(env_id: str, operator: str, root, n: int, seed: int) -> list[EpisodeLog]:
    """``n`` demonstrations of an operator model, collected (or loaded) exactly as ``bench run``
    collects its D_demo: Minari under ``root``, episode ``i`` from seed ``seed + i``."""
    from window_bench.installer.demos import load_or_collect_demos

    eps = load_or_collect_demos(root, env_id, operator, n, seed=seed, progress=False)
    if len(eps) < n:
        raise ValueError(f"{root}: {len(eps)} demonstrations of {operator!r}, need {n}")
    return eps[:n]


def main(argv=None) -> dict:
    """Collect demos, train ACT offline, evaluate at checkpoints; write a JSON.

    ``python -m baselines.act --profile cpu --steps 10000 --out act_cpu.json`` (scripted
    installer demos); ``--operator average --demos-dir DIR`` trains on the harness's D_demo
    (seed ``1,000,000 + --seed``, as ``bench run``) with held-out demos from seed 2,000,000.
    """
    import argparse
    import json
    import os
    import time

    from window_bench.harness.evaluation import (atomic_write, atomic_write_text, provenance,
                                                 wilson_interval)

    p = argparse.ArgumentParser(description=main.__doc__.splitlines()[0])
    p.add_argument("--env", default="WindowInstall-A-v0")
    p.add_argument("--profile", default="cpu", choices=sorted(ACT_PROFILES))
    p.add_argument("--lr", type=float, default=None, help="override the profile's lr")
    p.add_argument("--agent-config", action="append", metavar="KEY=VALUE",
                   help="override an ACTConfig field (repeatable), as bench run --agent-config")
    p.add_argument("--operator", default=None,
                   help="demos of this operator model (bench's D_demo); default: the scripted "
                        "installer on seeds 0..")
    p.add_argument("--demos-dir", default="runs/act_demos",
                   help="Minari root for --operator demos (held-out ones under heldout/)")
    p.add_argument("--policies", default=None,
                   help="write each checkpoint's acting weights here as step_N.safetensors")
    p.add_argument("--demos", type=int, default=50, help="demo seeds 0 .. demos-1")
    p.add_argument("--heldout", type=int, default=10, help="held-out demo seeds after those")
    p.add_argument("--steps", type=int, default=None, help="default: the profile's")
    p.add_argument("--eval-every", type=int, default=2000)
    p.add_argument("--episodes", type=int, default=20, help="evaluation seeds from --eval-seed")
    p.add_argument("--eval-seed", type=int, default=1000,
                   help="first evaluation seed (the harness's dev seeds start at 100000)")
    p.add_argument("--modes", nargs="+", default=["chunked", "temporal_ensembling"],
                   choices=["chunked", "temporal_ensembling"], help="evaluation modes")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True)
    p.add_argument("--save", default=None, help="torch.save the agent here at checkpoints")
    p.add_argument("--resume", action="store_true",
                   help="continue from --save (and the checkpoints already in --out)")
    args = p.parse_args(argv)
    if args.resume and not (args.save and os.path.exists(args.save)):
        p.error("--resume needs --save pointing to an existing checkpoint")

    from window_bench.harness.agent import with_overrides
    from window_bench.harness.files import dump_state
    from window_bench.harness.run import parse_overrides

    cfg = ACT_PROFILES[args.profile]
    try:
        cfg = with_overrides(cfg, parse_overrides(args.agent_config))
    except ValueError as e:
        p.error(str(e))
    if args.lr is not None:
        cfg = replace(cfg, lr=args.lr)
    steps = cfg.offline_steps if args.steps is None else args.steps
    t0 = time.perf_counter()
    if args.operator is None:
        demos = _collect_demos(args.env, range(args.demos))
        heldout = _collect_demos(args.env, range(args.demos, args.demos + args.heldout))
    else:
        demos = _harness_demos(args.env, args.operator, args.demos_dir, args.demos,
                               1_000_000 + args.seed)
        heldout = _harness_demos(args.env, args.operator, os.path.join(args.demos_dir, "heldout"),
                                 args.heldout, 2_000_000)
    result = {"method": "act", "env_id": args.env, "profile": args.profile,
              "operator": args.operator or "scripted", "config": asdict(cfg), "seed": args.seed,
              "demo_seeds": [demos[0].seed, demos[-1].seed],
              "heldout_seeds": [heldout[0].seed, heldout[-1].seed],
              "demo_successes": sum(bool(e.terminated[-1]) for e in demos),
              "collect_s": round(time.perf_counter() - t0, 1), "provenance": provenance(),
              "checkpoints": []}
    agent = ACTAgent(demos[0].observations.shape[1],
                     config=replace(cfg, temporal_ensembling=False), seed=args.seed)
    te_agent = ACTAgent(agent.obs_dim, config=replace(cfg, temporal_ensembling=True))
    eval_seeds = range(args.eval_seed, args.eval_seed + args.episodes)
    train_s, done = 0.0, 0
    if args.resume:
        agent.load_state_dict(torch.load(args.save, weights_only=True))
        done = agent.grad_steps
        if os.path.exists(args.out):
            with open(args.out) as f:
                result["checkpoints"] = json.load(f)["checkpoints"]
            train_s = result["checkpoints"][-1]["train_s"] if result["checkpoints"] else 0.0
    while done < steps:
        n = min(args.eval_every, steps - done)
        t1 = time.perf_counter()
        logs = agent.train_offline(demos, n)
        train_s += time.perf_counter() - t1
        done += n
        te_agent.load_state_dict(agent.state_dict())
        row = {"grad_steps": agent.grad_steps, "train_s": round(train_s, 1),
               "loss": float(np.mean([g["loss"] for g in logs])),
               "l1": float(np.mean([g["l1"] for g in logs])),
               "kl": float(np.mean([g["kl"] for g in logs])),
               "heldout_l1": agent.chunk_l1(heldout)}
        policy = dump_state(agent.policy_state_dict(), "policy", {"agent_kind": "act"})
        row["policy_bytes"] = len(policy)
        if args.policies:
            os.makedirs(args.policies, exist_ok=True)
            atomic_write(os.path.join(args.policies, f"step_{agent.grad_steps:07d}.safetensors"),
                         lambda f: f.write(policy))
        for name, a in (("chunked", agent), ("temporal_ensembling", te_agent)):
            if name not in args.modes:
                continue
            rows = _rollout(a, args.env, eval_seeds) if args.episodes else []
            k = sum(r["success"] for r in rows)
            row[name] = {"successes": k, "episodes": len(rows),
                         "wilson95": list(wilson_interval(k, len(rows))) if rows else None,
                         "rows": rows}
        result["checkpoints"].append(row)
        print(json.dumps({k: row[k] for k in list(row)[:6]}),
              {m: row[m]["successes"] for m in args.modes}, flush=True)
        atomic_write_text(args.out, json.dumps(result, indent=1))
        if args.save:
            torch.save(agent.state_dict(), args.save + ".tmp")
            os.replace(args.save + ".tmp", args.save)
    return result


if __name__ == "__main__":
    main()
