"""``PixelQCFQL``: QC-FQL on the pixel track (cached backbone features + proprioception).

The paper's networks take ``concat(view embeddings, proprioception)`` (Appendix): here a
:class:`~window_bench.pixels.encoder.PixelObsEncoder` turns the flat observation of
:class:`~window_bench.pixels.features.PixelFeatures` into those 82 values, and an unchanged
:class:`baselines.qcfql.QCFQLAgent` (``obs_dim = 82``) learns on them.

Who trains the aggregation: the critic loss, as in HIL-SERL and DrQ; the actor and the flow
teacher read the embedding with the gradient stopped, so the actor's Q-maximisation cannot
reshape the representation. The TD target embeds ``s'`` with the current aggregation, the
gradient stopped (as DrQ-v2 embeds its next observations; the target critic still
stabilises the bootstrap), which lets one fold of the weights serve both. The backbone is not part of the agent: its features
come cached in the batch, which is why an update costs about what a state-track update costs.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch

from window_bench.harness.agent import (Agent, AgentSpec, load_optimizer_state, module_state,
                                        optimizer_state)
from window_bench.pixels.encoder import OBS_DIM, PROPRIO_DIM, PixelObsEncoder


class PixelQCFQL(Agent):
    """The harness's :class:`~window_bench.harness.agent.Agent` interface, as
    :class:`baselines.qcfql.QCFQLAgent`, on flat pixel observations (``OBS_DIM`` values).
    ``proprio_mean``/``proprio_std``: the fixed proprioception normaliser (18 values each).
    ``encoder_weights``: the backbone's weights file (``None``: the shipped default), kept in
    the saved states so that an evaluation worker builds the same observation."""

    track = "pixels"
    encoder_weights: str | None = None

    def __init__(self, config=None, seed: int = 0, proprio_mean=None, proprio_std=None):
        from baselines.qcfql import QCFQLAgent, QCFQLConfig

        config = QCFQLConfig() if config is None else config
        self.obs_dim = OBS_DIM
        self.encoder = PixelObsEncoder(seed, proprio_mean, proprio_std)
        self.agent = QCFQLAgent(PixelObsEncoder.out_dim, 7, config, seed=seed)
        self.encoder_optimizer = torch.optim.Adam(self.encoder.parameters(), lr=config.lr)

    @classmethod
    def make_config(cls, h: int, profile, overrides: dict):
        from baselines.qcfql import QCFQLAgent

        return QCFQLAgent.make_config(h, profile, overrides)

    @classmethod
    def create(cls, spec: AgentSpec) -> "PixelQCFQL":
        """From the harness's spec: ``obs_mean``/``obs_std`` are the demo statistics of the
        whole pixel observation; only their proprioception part is used."""
        if spec.obs_dim != OBS_DIM:
            raise ValueError(f"PixelQCFQL: obs_dim = {spec.obs_dim}, the pixel observation "
                             f"has {OBS_DIM} values (PixelFeatures)")
        cfg = cls.make_config(spec.h, spec.profile, spec.overrides)
        stats = [None if a is None else np.asarray(a)[-PROPRIO_DIM:]
                 for a in (spec.obs_mean, spec.obs_std)]
        return cls(cfg, spec.seed, *stats)

    @property
    def config(self):
        return self.agent.config

    @property
    def h(self) -> int:
        return self.agent.config.h

    @property
    def gamma(self) -> float:
        return self.agent.config.gamma

    @property
    def num_updates(self) -> int:
        return self.agent.num_updates

    def embed(self, obs) -> torch.Tensor:
        """Flat pixel observations (B, OBS_DIM) -> the 82-value agent input (no gradient)."""
        with torch.no_grad():
            return self.encoder(torch.as_tensor(np.asarray(obs, np.float32)).reshape(-1, OBS_DIM))

    def learn(self, sample) -> tuple[dict[str, float], int]:
        return self.update(sample()), 1

    def update(self, batch: Mapping) -> dict[str, float]:
        """One gradient step (critic + encoder aggregation, teacher, student) and the Polyak
        steps; ``batch`` as for ``QCFQLAgent.update`` with ``obs``/``next_obs`` of OBS_DIM."""
        agent = self.agent
        emb, next_emb = self.encoder.encode_pair(torch.as_tensor(batch["obs"]),
                                                 torch.as_tensor(batch["next_obs"]))
        b = agent.prepare({**{k: batch[k] for k in batch.keys()},
                           "obs": emb, "next_obs": next_emb})
        critic_loss, q = agent.critic_loss(b)
        stopped = {**b, "obs": b["obs"].detach()}
        flow_loss = agent.flow_loss(stopped)
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
        single = np.ndim(obs) == 1
        u = self.agent.act(self.embed(obs).numpy(), deterministic=deterministic, policy=policy)
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
        load_optimizer_state(self.encoder_optimizer, sd["encoder_optimizer"])

    @classmethod
    def from_state_dict(cls, sd: dict) -> "PixelQCFQL":
        from baselines.qcfql import _config_from

        out = cls(_config_from(sd["agent"]["config"]), seed=sd["agent"]["seed"])
        out.load_state_dict(sd)
        return out

    def policy_state_dict(self) -> dict:
        return {"agent": self.agent.policy_state_dict(), "encoder": module_state(self.encoder),
                "encoder_weights": self.encoder_weights}

    @classmethod
    def from_policy_state_dict(cls, sd: dict) -> "PixelQCFQL":
        from baselines.qcfql import QCFQLAgent, _config_from

        out = cls(_config_from(sd["agent"]["config"]), seed=sd["agent"]["seed"])
        out.agent = QCFQLAgent.from_policy_state_dict(sd["agent"])
        out.encoder.load_state_dict(sd["encoder"])
        out.encoder_weights = sd.get("encoder_weights")
        return out
