"""``sac-pixels``: Stable-Baselines3 SAC on the pixel track, through an SB3 features extractor.

The ``sac`` baseline (:mod:`baselines.sac`) stays SB3's SAC as is; on the pixel track its
policy is built with :class:`PixelFeaturesExtractor` instead of SB3's ``FlattenExtractor``:
the trainable part of the paper's encoder (:class:`~window_bench.pixels.encoder.PixelObsEncoder`:
per-view spatial aggregation to 32 values, fused with the normalised proprioception) over
the cached backbone features of :class:`~window_bench.pixels.features.PixelFeatures`, which
SB3's replay buffer stores with the feature maps in float16 (:class:`PixelReplayBuffer`, an
SB3 ``ReplayBuffer`` returning the float32 batches of SB3's own for the same draws).

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
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.type_aliases import ReplayBufferSamples

from baselines.sac import SACAgent, SACPolicy
from window_bench.harness.agent import AgentSpec
from window_bench.pixels.agent import check_pixel_spec
from window_bench.pixels.cameras import DEFAULT_CAMERAS, saved_cameras
from window_bench.pixels.encoder import FEATURE_VALUES, OBS_DIM, PixelObsEncoder


class PixelReplayBuffer(ReplayBuffer):
    """SB3's ``ReplayBuffer`` with the pixel observation's feature maps stored as float16.

    ``observations`` / ``next_observations`` hold the 18 proprioceptive values (float32),
    ``observation_maps`` / ``next_observation_maps`` the 16,384 feature-map values (float16:
    lossless, :class:`~window_bench.pixels.features.PixelFeatures` rounds them so; a value
    float16 cannot hold exactly is refused), half the bytes of SB3's float32 rows. SB3's
    ``sample`` draws the rows (its global NumPy RNG, as ever); :meth:`_get_samples` gathers
    the maps with ``index_select`` and widens them once into the float32 batch that SB3's
    float32 buffer returns for the same draws, without its two float32 copies (NumPy
    gather, then ``torch.tensor``) of 64 KiB per row and key."""

    #: The arrays that, besides SB3's own, hold the stored transitions.
    map_fields = ("observation_maps", "next_observation_maps")

    def __init__(self, buffer_size: int, observation_space: spaces.Box, action_space,
                 device="auto", n_envs: int = 1, optimize_memory_usage: bool = False,
                 handle_timeout_termination: bool = True):
        if observation_space.shape != (OBS_DIM,):
            raise ValueError(f"PixelReplayBuffer: observation space {observation_space.shape}, "
                             f"the pixel observation has ({OBS_DIM},) values")
        proprio = spaces.Box(-np.inf, np.inf, (OBS_DIM - FEATURE_VALUES,), np.float32)
        super().__init__(buffer_size, proprio, action_space, device, n_envs,
                         optimize_memory_usage, handle_timeout_termination)
        if optimize_memory_usage:
            raise ValueError("PixelReplayBuffer: optimize_memory_usage = True is not supported")
        self.observation_space, self.obs_shape = observation_space, observation_space.shape
        for name in self.map_fields:
            setattr(self, name, np.zeros((self.buffer_size, self.n_envs, FEATURE_VALUES),
                                         np.float16))

    def add(self, obs, next_obs, action, reward, done, infos) -> None:
        parts = []
        for name, x in zip(self.map_fields, (obs, next_obs)):
            x = np.asarray(x, np.float32).reshape(self.n_envs, OBS_DIM)
            maps = x[:, :FEATURE_VALUES].astype(np.float16)
            if not np.array_equal(maps, x[:, :FEATURE_VALUES]):
                raise ValueError(f"PixelReplayBuffer: the feature maps of {name} are not "
                                 f"float16-exact; storing them as float16 would change them")
            getattr(self, name)[self.pos] = maps
            parts.append(x[:, FEATURE_VALUES:])
        super().add(*parts, action, reward, done, infos)

    def _joined(self, maps: np.ndarray, proprio: np.ndarray, rows: torch.Tensor) -> torch.Tensor:
        out = torch.empty(len(rows), OBS_DIM)
        out[:, :FEATURE_VALUES].copy_(torch.from_numpy(maps.reshape(-1, FEATURE_VALUES))
                                      .index_select(0, rows))      # widened in the copy
        out[:, FEATURE_VALUES:].copy_(torch.from_numpy(proprio.reshape(-1, proprio.shape[-1]))
                                      .index_select(0, rows))
        return out

    def _get_samples(self, batch_inds: np.ndarray, env=None) -> ReplayBufferSamples:
        if env is not None:
            raise ValueError("PixelReplayBuffer: observation normalisation by a VecNormalize "
                             "env is not supported")
        env_indices = np.random.randint(0, high=self.n_envs, size=(len(batch_inds),))  # SB3's draw
        rows = torch.from_numpy(batch_inds * self.n_envs + env_indices)
        obs = self._joined(self.observation_maps, self.observations, rows)
        next_obs = self._joined(self.next_observation_maps, self.next_observations, rows)
        done = self.dones[batch_inds, env_indices] * (1 - self.timeouts[batch_inds, env_indices])
        return ReplayBufferSamples(obs, self.to_torch(self.actions[batch_inds, env_indices, :]),
                                   next_obs, self.to_torch(done.reshape(-1, 1)),
                                   self.to_torch(self.rewards[batch_inds, env_indices]
                                                 .reshape(-1, 1)))


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
    also names the encoder weights and the camera set, so evaluation workers build the same
    observation."""

    features_extractor_class = PixelFeaturesExtractor
    encoder_weights: str | None = None
    cameras: str = DEFAULT_CAMERAS
    track = "pixels"

    def policy_state_dict(self) -> dict:
        return {**super().policy_state_dict(), "encoder_weights": self.encoder_weights,
                "cameras": self.cameras}

    @classmethod
    def from_policy_state_dict(cls, state: dict) -> "PixelSACPolicy":
        out = super().from_policy_state_dict(state)
        out.encoder_weights = state.get("encoder_weights")
        out.cameras = saved_cameras(state)
        return out


class PixelSACAgent(SACAgent):
    """:class:`baselines.sac.SACAgent` on the pixel track (see the module docstring)."""

    track = "pixels"
    policy_class = PixelSACPolicy
    policy_kwargs = {"features_extractor_class": PixelFeaturesExtractor}
    replay_buffer_class = PixelReplayBuffer

    @property
    def encoder_weights(self) -> str | None:
        return self.policy.encoder_weights

    @encoder_weights.setter
    def encoder_weights(self, path: str | None) -> None:
        self.policy.encoder_weights = path

    @property
    def cameras(self) -> str:
        return self.policy.cameras

    @cameras.setter
    def cameras(self, name: str) -> None:
        self.policy.cameras = name

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
        state = super().state_dict()
        rb, replay = self.model.replay_buffer, state["replay"]
        n = len(replay["observations"])
        replay.update({f: getattr(rb, f)[:n].copy() for f in rb.map_fields})
        return {**state, "encoder_weights": self.encoder_weights, "cameras": self.cameras}

    def load_state_dict(self, state: dict) -> None:
        replay = state["replay"]
        if replay["observations"].shape[-1] == OBS_DIM:  # saved when SB3's float32 rows held it all
            replay = {**replay, **{f: replay[k][..., :FEATURE_VALUES].astype(np.float16)
                                   for f, k in zip(PixelReplayBuffer.map_fields,
                                                   ("observations", "next_observations"))},
                      **{k: replay[k][..., FEATURE_VALUES:]
                         for k in ("observations", "next_observations")}}
            state = {**state, "replay": replay}
        super().load_state_dict(state)
        rb = self.model.replay_buffer
        for f in rb.map_fields:
            getattr(rb, f)[:len(replay[f])] = replay[f]
        self.encoder_weights = state.get("encoder_weights")
        self.cameras = saved_cameras(state)
