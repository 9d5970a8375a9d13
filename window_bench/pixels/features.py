"""``PixelFeatures``: the frozen backbone applied once per observation, in the env worker.

The paper's agent observes two 128 x 128 RGB views and 18 proprioceptive values through a
frozen ResNet-10. Because the backbone never changes, its output is a property of the
observation, not of the learner: this wrapper runs it once per step where the env renders,
and the flat vector it returns is what rollouts log and the replay stores. A gradient update
then reads cached feature maps and trains only the aggregation and the MLPs
(:class:`window_bench.pixels.encoder.PixelObsEncoder`).

Observation: ``Box((OBS_DIM,), float32)`` = wrist feature map (512 x 4 x 4), side feature map,
proprioception (q, q-dot, end-effector position, vacuum). The feature maps are rounded to
float16 before they are widened to float32, so a store that keeps them as float16 (32 KiB
per observation) loses nothing, and cached features are bit-identical to recomputed ones.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces

from window_bench.pixels.encoder import OBS_DIM, VIEWS, ResNet10


@torch.inference_mode()
def encode_views(backbone: ResNet10, obs: dict) -> np.ndarray:
    """One pixel-mode observation (``wrist_rgb``, ``side_rgb``, ``robot0_proprio``) -> the
    flat float32 vector of :class:`PixelFeatures` (feature maps rounded to float16)."""
    images = torch.from_numpy(np.stack([np.asarray(obs[v]) for v in VIEWS]))
    fmaps = backbone(images).to(torch.float16).float().reshape(-1).numpy()
    return np.concatenate([fmaps, np.asarray(obs["robot0_proprio"], np.float32)])


class PixelFeatures(gym.ObservationWrapper):
    """Wraps an env made with ``obs_mode="pixels"``; see the module docstring.

    ``backbone``: a frozen :class:`ResNet10` (:func:`window_bench.pixels.weights.resolve_backbone`).
    """

    def __init__(self, env: gym.Env, backbone: ResNet10):
        super().__init__(env)
        space = env.observation_space
        if not isinstance(space, spaces.Dict) or set(space.spaces) != {*VIEWS, "robot0_proprio"}:
            raise ValueError("PixelFeatures needs an env made with obs_mode='pixels' "
                             f"(keys {VIEWS} + robot0_proprio), got {space}")
        size = space[VIEWS[0]].shape
        if size != (128, 128, 3):
            raise ValueError(f"PixelFeatures: views of shape {size}; the encoder expects "
                             f"(128, 128, 3) (image_size=128)")
        if backbone.training or any(p.requires_grad for p in backbone.parameters()):
            raise ValueError("PixelFeatures: the backbone must be frozen "
                             "(window_bench.pixels.encoder.frozen)")
        self.backbone = backbone
        self.observation_space = spaces.Box(-np.inf, np.inf, (OBS_DIM,), np.float32)

    def observation(self, observation: dict) -> np.ndarray:
        return encode_views(self.backbone, observation)


def make_pixel_env(env_id: str, backbone: ResNet10, **kwargs) -> PixelFeatures:
    """``gym.make(env_id, obs_mode="pixels", **kwargs)`` wrapped in :class:`PixelFeatures`:
    the pixel track's counterpart of the harness's ``obs_mode="flat"`` env."""
    return PixelFeatures(gym.make(env_id, obs_mode="pixels", **kwargs), backbone)
