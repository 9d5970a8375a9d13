"""The learners of the pixel track: a state-track learner behind the trainable pixel front end.

The paper's networks take ``concat(view embeddings, proprioception)`` (Appendix): a
:class:`~window_bench.pixels.encoder.PixelObsEncoder` turns the flat observation of
:class:`~window_bench.pixels.features.PixelFeatures` into those 82 values, and an unchanged
state-track learner (``obs_dim = 82``) learns on them. :class:`PixelAgent` owns what every
such pairing shares (the front end, its optimiser, acting, plain-data states, the encoder
weights named in the policy); a subclass says which learner sits behind it and how a
gradient step trains the front end:

* :class:`PixelQCFQL` - QC-FQL (``qcfql-pixels``);
* :class:`PixelHILSERL` - HIL-SERL's SAC/RLPD learner with its grasp critic
  (``hilserl-pixels``);
* :class:`PixelACT` - ACT, trained offline on D_demo (``act-pixels``);
* SB3 SAC uses the same front end as its features extractor
  (:mod:`window_bench.pixels.sac`, ``sac-pixels``).

Who trains the aggregation: the critic losses, as in HIL-SERL and DrQ; the actor (and
QC-FQL's flow teacher) read the embedding with the gradient stopped, so the actor's
Q-maximisation cannot reshape the representation. The TD target embeds ``s'`` with the
current aggregation, the gradient stopped (as DrQ-v2 embeds its next observations; the target
critic still stabilises the bootstrap), which lets one fold of the weights serve both. The
backbone is not part of the agent: its features come cached in the batch, which is why an
update costs about what a state-track update costs.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from importlib import import_module

import numpy as np
import torch

from window_bench.harness.agent import (Agent, AgentSpec, load_optimizer_state, module_state,
                                        optimizer_state)
from window_bench.pixels.cameras import DEFAULT_CAMERAS, saved_cameras
from window_bench.pixels.encoder import (EMBED_DIM, FEATURE_VALUES, OBS_DIM, PROPRIO_DIM,
                                         VIEW_FEATURES, VIEWS, PixelObsEncoder)

#: Index of the vacuum flag in the flat pixel observation: the last proprioceptive value
#: (``robot0_proprio`` = joint positions, joint velocities, end-effector position, vacuum).
VACUUM_INDEX = OBS_DIM - 1


def check_pixel_spec(name: str, spec: AgentSpec) -> list:
    """The proprioception part of the harness's demo statistics (``obs_mean``/``obs_std``
    cover the whole pixel observation), after checking the observation size."""
    if spec.obs_dim != OBS_DIM:
        raise ValueError(f"{name}: obs_dim = {spec.obs_dim}, the pixel observation has "
                         f"{OBS_DIM} values (PixelFeatures)")
    return [None if a is None else np.asarray(a)[-PROPRIO_DIM:]
            for a in (spec.obs_mean, spec.obs_std)]


class PixelAgent(Agent):
    """The harness's :class:`~window_bench.harness.agent.Agent` interface for a state-track
    learner (``self.agent``, built on ``PixelObsEncoder.out_dim`` inputs) behind a
    :class:`PixelObsEncoder` (``self.encoder``) on flat pixel observations (``OBS_DIM``).

    Subclasses set :attr:`inner` and implement ``__init__(config, seed, proprio_mean,
    proprio_std)``, :meth:`config_of` and :meth:`update`. ``encoder_weights``: the backbone's
    weights file (``None``: the shipped default), and ``cameras``: the camera set
    (:mod:`window_bench.pixels.cameras`), kept in the saved states so that an evaluation
    worker builds the same observation."""

    track = "pixels"
    encoder_weights: str | None = None
    cameras: str = DEFAULT_CAMERAS
    #: ``"module:Class"`` of the state-track learner behind the front end.
    inner = ""

    def _build(self, seed: int, proprio_mean, proprio_std, make_agent, lr: float,
               pose_readout=None, view_embeddings: bool = True) -> None:
        self.obs_dim = OBS_DIM
        self.encoder = PixelObsEncoder(seed, proprio_mean, proprio_std, pose_readout,
                                       view_embeddings)
        self.agent = make_agent(self.encoder.out_dim)
        self.encoder_optimizer = torch.optim.Adam(self.encoder.parameters(), lr=lr)

    @classmethod
    def inner_class(cls) -> type:
        module, name = cls.inner.split(":")
        return getattr(import_module(module), name)

    @classmethod
    def config_of(cls, inner_state: dict):
        """The learner's config from its saved (policy) state."""
        raise NotImplementedError

    @classmethod
    def make_config(cls, h: int, profile, overrides: dict):
        """The inner learner's config; features that read the flat state are off here unless
        ``overrides`` asks for one, which is refused before a run writes any file."""
        from window_bench.installer.supervisor import STATE_ONLY_FIELDS, check_flat_state_fields

        config = cls.inner_class().make_config(h, profile, overrides)
        off = {f: (0.0 if isinstance(getattr(config, f), (int, float)) else None)
               for f in STATE_ONLY_FIELDS if getattr(config, f, None) and f not in overrides}
        config = dataclasses.replace(config, **off)
        check_flat_state_fields(config, "the pixel track (cameras and proprioception)")
        return config

    @classmethod
    def create(cls, spec: AgentSpec) -> "PixelAgent":
        """``spec.front_end``: the track's ``{"pose_readout": PoseReadout}``, if it has one."""
        stats = check_pixel_spec(cls.__name__, spec)
        readout = (spec.front_end or {}).get("pose_readout")
        return cls(cls.make_config(spec.h, spec.profile, spec.overrides), spec.seed, *stats,
                   pose_readout=readout)

    @staticmethod
    def saved_readout(encoder_state: dict):
        """The fixed pose read-out a saved encoder state holds, or None."""
        from window_bench.pixels.pose_readout import PoseReadout

        prefix = "pose_readout."
        part = {k[len(prefix):]: v for k, v in encoder_state.items() if k.startswith(prefix)}
        return PoseReadout.from_state(part) if part else None

    def hyperparameters(self) -> dict:
        """The learner's configuration; with a pose read-out, also the sha256 of its
        weights (so a Stage I cached without it, or with another, is not reused)."""
        out = super().hyperparameters()
        readout = self.encoder.pose_readout
        if readout is not None:
            import hashlib

            h = hashlib.sha256()
            for t in (readout.weight, readout.bias, readout.scale):
                h.update(t.numpy().tobytes())
            out["pose_readout_sha256"] = h.hexdigest()
        return out

    @property
    def config(self):
        return self.agent.config

    @property
    def ONLINE_FIELDS(self) -> tuple[str, ...]:   # noqa: N802 (the learner's class attribute)
        return self.agent.ONLINE_FIELDS

    def begin_online(self) -> None:
        self.agent.begin_online()

    def take_online_settings(self, other: "PixelAgent") -> None:
        self.agent.take_online_settings(other.agent)

    @property
    def h(self) -> int:
        return int(self.agent.h)

    @property
    def gamma(self) -> float:
        return self.agent.gamma

    @property
    def demo_chunk_stride(self) -> int | None:
        return getattr(self.agent, "demo_chunk_stride", None)

    def embed(self, obs) -> torch.Tensor:
        """Flat pixel observations (B, OBS_DIM) -> the 82-value learner input (no gradient)."""
        with torch.no_grad():
            return self.encoder(torch.as_tensor(np.asarray(obs, np.float32)).reshape(-1, OBS_DIM))

    def learn(self, sample) -> tuple[dict[str, float], int]:
        return self.update(sample()), 1

    def update(self, batch: Mapping) -> dict[str, float]:
        raise NotImplementedError

    def act(self, obs, deterministic: bool = False, **kwargs) -> np.ndarray:
        """``(h, 7)`` for one observation, ``(B, h, 7)`` for a batch, as the learner's own."""
        single = np.ndim(obs) == 1
        u = self.agent.act(self.embed(obs).numpy(), deterministic=deterministic, **kwargs)
        return u[0] if single and u.ndim == 3 else u

    # ------------------------------------------------------------------ state (plain data)
    def state_dict(self) -> dict:
        return {**self.policy_state_dict(),
                "agent": self.agent.state_dict(),
                "encoder_optimizer": optimizer_state(self.encoder_optimizer)}

    def load_state_dict(self, sd: dict) -> None:
        self.agent.load_state_dict(sd["agent"])
        self.encoder.load_state_dict(sd["encoder"])
        self.encoder_weights = sd.get("encoder_weights")
        self.cameras = saved_cameras(sd)
        load_optimizer_state(self.encoder_optimizer, sd["encoder_optimizer"])

    @classmethod
    def from_state_dict(cls, sd: dict) -> "PixelAgent":
        out = cls(cls.config_of(sd["agent"]), seed=sd["agent"]["seed"],
                  pose_readout=cls.saved_readout(sd["encoder"]))
        out.load_state_dict(sd)
        return out

    def policy_state_dict(self) -> dict:
        return {"agent": self.agent.policy_state_dict(), "encoder": module_state(self.encoder),
                "encoder_weights": self.encoder_weights, "cameras": self.cameras}

    @classmethod
    def from_policy_state_dict(cls, sd: dict) -> "PixelAgent":
        out = cls(cls.config_of(sd["agent"]), seed=sd["agent"]["seed"],
                  pose_readout=cls.saved_readout(sd["encoder"]))
        out.agent = cls.inner_class().from_policy_state_dict(sd["agent"])
        out.encoder.load_state_dict(sd["encoder"])
        out.encoder_weights = sd.get("encoder_weights")
        out.cameras = saved_cameras(sd)
        return out


class PixelQCFQL(PixelAgent):
    """:class:`baselines.qcfql.QCFQLAgent` on flat pixel observations.
    ``proprio_mean``/``proprio_std``: the fixed proprioception normaliser (18 values each)."""

    inner = "baselines.qcfql:QCFQLAgent"

    def __init__(self, config=None, seed: int = 0, proprio_mean=None, proprio_std=None,
                 pose_readout=None):
        from baselines.qcfql import QCFQLAgent, QCFQLConfig

        config = QCFQLConfig() if config is None else config
        self._build(seed, proprio_mean, proprio_std,
                    lambda dim: QCFQLAgent(dim, 7, config, seed=seed), config.lr, pose_readout,
                    config.view_embeddings)

    @classmethod
    def config_of(cls, inner_state: dict):
        from baselines.qcfql import _config_from

        return _config_from(inner_state["config"])

    @property
    def num_updates(self) -> int:
        return self.agent.num_updates

    def update(self, batch: Mapping) -> dict[str, float]:
        """One gradient step (critic + encoder aggregation, teacher, student) and the Polyak
        steps; ``batch`` as for ``QCFQLAgent.update`` with ``obs``/``next_obs`` of OBS_DIM.
        The critic's loss trains the aggregation; with ``config.flow_trains_encoder`` the
        flow teacher's too; the student reads the embedding with the gradient stopped."""
        agent = self.agent
        emb, next_emb = self.encoder.encode_pair(torch.as_tensor(batch["obs"]),
                                                 torch.as_tensor(batch["next_obs"]))
        b = agent.prepare({**{k: batch[k] for k in batch.keys()},
                           "obs": emb, "next_obs": next_emb})
        critic_loss, q = agent.critic_loss(b)
        stopped = {**b, "obs": b["obs"].detach()}
        flow_loss = agent.flow_loss(b if agent.config.flow_trains_encoder else stopped)
        actor = agent.actor_loss(stopped)
        loss = critic_loss + flow_loss + actor["loss"]
        agent.optimizer.zero_grad(set_to_none=True)
        self.encoder_optimizer.zero_grad(set_to_none=True)
        loss.backward()
        agent.optimizer.step()
        self.encoder_optimizer.step()
        agent.polyak()
        agent.num_updates += 1
        return {"loss": loss.item(), "critic_loss": critic_loss.item(),
                "flow_loss": flow_loss.item(), "actor_loss": actor["loss"].item(),
                "q_mean": q.mean().item()}

    def act(self, obs, deterministic: bool = False, policy: str = "student") -> np.ndarray:
        return super().act(obs, deterministic, policy=policy)


class PixelHILSERL(PixelAgent):
    """:class:`baselines.hilserl.HILSERLAgent` (actor, critic ensemble, grasp critic) on flat
    pixel observations; step-wise, takeovers also join D_demo, as on the state track.

    Each critic step embeds its own fresh batch, the critic and the grasp critic losses
    train the aggregation (HIL-SERL's encoder belongs to its critics and its actor reads it
    with the gradient stopped) and the aggregation's Adam steps with the critic's learning
    rate; the actor and temperature step then reads the last batch embedded by the updated
    aggregation, gradient stopped. The learner's own z-scoring is the identity here: the
    embeddings are tanh outputs and the proprioception is normalised in the front end."""

    inner = "baselines.hilserl:HILSERLAgent"
    takeovers_to_demo = True

    def __init__(self, config=None, seed: int = 0, proprio_mean=None, proprio_std=None,
                 pose_readout=None):
        from baselines.hilserl import HILSERLAgent, HILSERLConfig

        config = HILSERLConfig() if config is None else config
        self._build(seed, proprio_mean, proprio_std,
                    lambda dim: HILSERLAgent(dim, 7, config, seed=seed), config.critic_lr,
                    pose_readout)

    @classmethod
    def config_of(cls, inner_state: dict):
        from baselines.hilserl import HILSERLConfig, _state_config
        from window_bench.harness.agent import config_from_plain

        return config_from_plain(HILSERLConfig, _state_config(inner_state))

    @property
    def offline_steps(self) -> int | None:
        return self.agent.offline_steps

    def learn(self, sample) -> tuple[dict[str, float], int]:
        return self.update(sample), self.config.critic_actor_ratio

    def act(self, obs, deterministic: bool = False, **kwargs) -> np.ndarray:
        """As :meth:`PixelAgent.act`; the grasp critic's "stay" keeps the vacuum state of
        the raw observation (its last value, the proprioception's vacuum flag)."""
        flag = np.asarray(obs, np.float32).reshape(-1, OBS_DIM)[:, VACUUM_INDEX]
        return super().act(obs, deterministic, vacuum_flag=flag, **kwargs)

    def _embedded(self, batch, grad: bool):
        """The learner's prepared batch on embeddings; with ``grad``, also the embedding
        whose gradient trains the aggregation and the leaf the critic losses write it to.
        Without, only ``s`` is embedded: the actor and temperature step reads no ``s'``.
        The raw observations' vacuum flags go with it (the grasp critic's labels)."""
        flag = torch.as_tensor(batch["obs"])[:, VACUUM_INDEX].float()
        rest = batch.exclude("obs", "next_obs").set("vacuum_flag", flag)
        if not grad:
            emb = self.encoder(torch.as_tensor(batch["obs"]))
            return self.agent._prepare(rest.set("obs", emb).set("next_obs", emb)), None, None
        emb, next_emb = self.encoder.encode_pair(torch.as_tensor(batch["obs"]),
                                                 torch.as_tensor(batch["next_obs"]))
        b = self.agent._prepare(rest.set("obs", emb.detach()).set("next_obs", next_emb))
        # The learner's critic and grasp-critic steps each run their own backward through
        # the observation: a leaf collects both gradients, which then flow into the
        # aggregation in one backward (its graph is used once).
        z = self.agent._normalize(emb)
        leaf = b["obs"] = z.detach().requires_grad_(True)
        return b, z, leaf

    def update(self, sample) -> dict[str, float]:
        """``critic_actor_ratio`` critic steps, each on a fresh ``sample()`` and followed by
        an aggregation step; then one actor and temperature step (see the class docstring)."""
        agent = self.agent
        infos, batch = [], None
        for _ in range(agent.config.critic_actor_ratio):
            batch = sample()
            b, z, leaf = self._embedded(batch, grad=True)
            self.encoder_optimizer.zero_grad(set_to_none=True)
            infos.append(agent._critic_step(b))
            z.backward(leaf.grad)
            self.encoder_optimizer.step()
        info = {k: float(np.mean([i[k] for i in infos])) for k in infos[0]}
        with torch.no_grad():
            b, _, _ = self._embedded(batch, grad=False)
        info.update(agent._actor_temperature_step(b))
        return info


class PixelACT(PixelAgent):
    """:class:`baselines.act.ACTAgent` on flat pixel observations (``act-pixels``), trained
    offline on D_demo only, as on the state track.

    ACT's transformer reads the 82 front-end values as its two observation tokens: the
    normalised proprioception (the robot token, the one ACT's CVAE encoder also sees, as
    ACT's ``qpos``) and both views' embeddings (the image token). ACT's loss trains the
    aggregation end to end with the transformer (ACT trains its image encoder too; here the
    backbone stays frozen), with AdamW at ACT's learning rate and weight decay. ACT's own
    observation z-scoring is the identity on this track: the proprioception is normalised
    in the front end by the demos' statistics and the embeddings are tanh outputs that move
    while the aggregation trains; its action normaliser is fitted on the demos as ever.

    The backbone ran once per demo step when the harness re-observed the demos;
    :meth:`attach_demos` keeps those feature maps as contiguous float16 tensors, one per view
    (lossless: ``PixelFeatures`` rounds them to float16), and an update gathers its batch's
    rows and widens them to float32 in one operation per view."""

    inner = "baselines.act:ACTAgent"

    def __init__(self, config=None, seed: int = 0, proprio_mean=None, proprio_std=None,
                 pose_readout=None):
        from baselines.act import ACT_PROFILES, ACTAgent

        config = ACT_PROFILES["paper"] if config is None else config
        self._build(seed, proprio_mean, proprio_std,
                    lambda dim: ACTAgent(dim, 7, config, seed=seed), config.lr, pose_readout)
        self.encoder_optimizer = torch.optim.AdamW(self.encoder.parameters(), lr=config.lr,
                                                   weight_decay=config.weight_decay)

    @classmethod
    def make_config(cls, h: int, profile, overrides: dict):
        """ACT's profile sizes; the robot token is the proprioception (first in
        :meth:`tokens`) unless ``--agent-config robot_dim=...`` says otherwise."""
        config = super().make_config(h, profile, overrides)
        return config if "robot_dim" in overrides else dataclasses.replace(
            config, robot_dim=PROPRIO_DIM)

    @classmethod
    def create(cls, spec: AgentSpec) -> "PixelACT":
        agent = super().create(spec)
        actions = np.concatenate([np.asarray(ep.actions) for ep in spec.demos]).astype(np.float64)
        dim = agent.encoder.out_dim
        agent.agent.norm = {
            "obs_mean": torch.zeros(dim), "obs_std": torch.ones(dim),
            "act_mean": torch.tensor(actions.mean(0), dtype=torch.float32),
            "act_std": torch.tensor(np.maximum(actions.std(0), agent.config.std_floor),
                                    dtype=torch.float32)}
        return agent

    @classmethod
    def config_of(cls, inner_state: dict):
        from baselines.act import ACTConfig

        return ACTConfig(**inner_state["config"])

    @property
    def offline_steps(self) -> int:
        return self.agent.offline_steps

    @staticmethod
    def tokens(emb: torch.Tensor) -> torch.Tensor:
        """Front-end output (view embeddings, proprioception[, pose read-out]) -> ACT's order:
        the robot token (proprioception) first, then the image token (the embeddings and
        the pose the views show)."""
        n = len(VIEWS) * EMBED_DIM
        return torch.cat([emb[:, n:n + PROPRIO_DIM], emb[:, :n], emb[:, n + PROPRIO_DIM:]], dim=1)

    def attach_demos(self, demos) -> None:
        """ACT's chunk stack of D_demo (actions, padding, offsets; its observations are the
        proprioception) and the demos' feature maps as float16, ``(views, steps, 8,192)``."""
        from baselines.act import _stack_episodes

        for i, ep in enumerate(demos):
            if np.shape(ep.observations)[1:] != (OBS_DIM,):
                raise ValueError(f"PixelACT: demo {i} has observations of shape "
                                 f"{np.shape(ep.observations)}, expected (T+1, {OBS_DIM})")
        self._demo_stack = _stack_episodes(
            [dataclasses.replace(ep, observations=np.asarray(ep.observations)[:, FEATURE_VALUES:])
             for ep in demos], PROPRIO_DIM, self.config.chunk)
        self._demo_maps = torch.empty(len(VIEWS), int(self._demo_stack["lengths"].sum()),
                                      VIEW_FEATURES, dtype=torch.float16)
        for ep, row in zip(demos, self._demo_stack["obs_offset"]):
            maps = torch.from_numpy(np.asarray(ep.observations[:-1, :FEATURE_VALUES], np.float32))
            half = maps.to(torch.float16)
            if not torch.equal(half.float(), maps):
                raise ValueError(f"PixelACT: demo {ep.episode_id}'s feature maps are not "
                                 f"float16-exact; they are not PixelFeatures observations")
            self._demo_maps[:, row:row + ep.T] = half.view(ep.T, len(VIEWS), -1).transpose(0, 1)

    def learn(self, sample) -> tuple[dict[str, float], int]:
        """One :meth:`update` on ``batch_size`` chunks of D_demo drawn with ACT's own
        generator (the harness's ``sample`` is not used, as on the state track)."""
        from baselines.act import _draw

        return self.update(_draw(self._demo_stack, self.config.batch_size, self.agent.rng)), 1

    def update(self, batch: Mapping) -> dict[str, float]:
        """One AdamW step of ACT and of the aggregation on a batch of :func:`baselines.act._draw`
        (``obs`` = the proprioception; ``episode`` and ``start`` locate the feature maps)."""
        rows = torch.as_tensor(self._demo_stack["obs_offset"][batch["episode"]] + batch["start"])
        maps = self._demo_maps.index_select(1, rows).float()
        emb = self.encoder.fuse(list(maps), torch.as_tensor(batch["obs"]))
        self.encoder_optimizer.zero_grad(set_to_none=True)
        info = self.agent.update({**batch, "obs": self.tokens(emb)})
        self.encoder_optimizer.step()
        return info

    def act(self, obs, deterministic: bool = True) -> np.ndarray:
        """ACT's next actions for one observation (its chunk, or one ensembled step)."""
        if np.ndim(obs) != 1:
            raise ValueError(f"PixelACT.act: one observation of shape ({OBS_DIM},) at a time "
                             f"(temporal ensembling keeps per-episode history), got "
                             f"{np.shape(obs)}")
        return self.agent.act(self.tokens(self.embed(obs))[0].numpy(), deterministic)

    def reset(self) -> None:
        self.agent.reset()
