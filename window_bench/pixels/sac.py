"""``sac-pixels``: Stable-Baselines3 SAC on the pixel track, through an SB3 features extractor.

The ``sac`` baseline (:mod:`baselines.sac`) stays SB3's SAC as is; on the pixel track its
policy is built with :class:`PixelFeaturesExtractor` instead of SB3's ``FlattenExtractor``:
the trainable part of the paper's encoder (:class:`~window_bench.pixels.encoder.PixelObsEncoder`:
per-view spatial aggregation to 32 values, fused with the normalised proprioception) over
the cached backbone features of :class:`~window_bench.pixels.features.PixelFeatures`, which
SB3's replay buffer stores like any flat observation.

SB3's own rules decide who trains it: SAC's default ``share_features_extractor=False`` gives
the actor and the critics their own extractor, the actor's trained by the actor loss, the
critics' by the critic loss (the target critics' follow by Polyak averaging); the backbone
is frozen and not part of the policy. Each extractor's aggregation is initialised from a
seed drawn from the global torch generator, which SB3 seeds from the run's seed before it
builds the policy, so one seed gives one run. The proprioception normaliser (the demos'
statistics, as on the other pixel learners) is written into every extractor after the
model is built.
"""

from __future__ import annotations

import numpy as np
import torch
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor

from baselines.sac import SACAgent, SACPolicy
from window_bench.harness.agent import AgentSpec
from window_bench.pixels.agent import check_pixel_spec
from window_bench.pixels.encoder import PixelObsEncoder


class PixelFeaturesExtractor(BaseFeaturesExtractor):
    """SB3 features extractor: flat pixel observations -> the 82 values of
    :class:`PixelObsEncoder` (its weights seeded from the global torch generator)."""

    def __init__(self, observation_space):
        super().__init__(observation_space, PixelObsEncoder.out_dim)
        self.encoder = PixelObsEncoder(seed=int(torch.randint(2 ** 31 - 1, ())))

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        return self.encoder(observations)


class PixelSACPolicy(SACPolicy):
    """:class:`baselines.sac.SACPolicy` with the pixel features extractor; its policy state
    also names the encoder weights, so evaluation workers build the same observation."""

    features_extractor_class = PixelFeaturesExtractor
    encoder_weights: str | None = None
    track = "pixels"

    def policy_state_dict(self) -> dict:
        return {**super().policy_state_dict(), "encoder_weights": self.encoder_weights}

    @classmethod
    def from_policy_state_dict(cls, state: dict) -> "PixelSACPolicy":
        out = super().from_policy_state_dict(state)
        out.encoder_weights = state.get("encoder_weights")
        return out


class PixelSACAgent(SACAgent):
    """:class:`baselines.sac.SACAgent` on the pixel track (see the module docstring)."""

    track = "pixels"
    policy_class = PixelSACPolicy
    policy_kwargs = {"features_extractor_class": PixelFeaturesExtractor}

    @property
    def encoder_weights(self) -> str | None:
        return self.policy.encoder_weights

    @encoder_weights.setter
    def encoder_weights(self, path: str | None) -> None:
        self.policy.encoder_weights = path

    @classmethod
    def create(cls, spec: AgentSpec) -> "PixelSACAgent":
        mean, std = check_pixel_spec(cls.__name__, spec)
        agent = super().create(spec)
        if mean is not None:
            std = np.maximum(std, 1e-3)      # PixelObsEncoder's floor
            for m in agent.model.policy.modules():
                if isinstance(m, PixelObsEncoder):
                    m.proprio_mean.copy_(torch.as_tensor(mean, dtype=torch.float32))
                    m.proprio_std.copy_(torch.as_tensor(std, dtype=torch.float32))
        return agent

    def hyperparameters(self) -> dict:
        return {**super().hyperparameters(),
                "policy": "MlpPolicy over PixelFeaturesExtractor (per-view spatial aggregation "
                          "to 32 + proprioception = 82 inputs; actor and critics each their "
                          "own extractor, SB3's default)"}

    def state_dict(self) -> dict:
        return {**super().state_dict(), "encoder_weights": self.encoder_weights}

    def load_state_dict(self, state: dict) -> None:
        super().load_state_dict(state)
        self.encoder_weights = state.get("encoder_weights")
