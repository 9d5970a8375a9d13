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

**Observing on the chunk grid** (``observe_every=h``). A chunked policy reads the
observation only where it proposes a chunk, on the fixed grid ``t = k*h``, and the chunked
transitions of the replay (Eq. 4) only store ``s_kh`` and the episode's last state. With
``observe_every=h`` the wrapper renders and encodes exactly those: the reset observation,
every step ``t`` with ``t % h == 0`` (counted from the reset) and the step that ends the
episode (terminated or truncated). Any other step returns :data:`UNOBSERVED`-filled vectors
(all NaN, so a consumer that reads one fails loudly instead of learning from it;
``EpisodeLog`` accepts such rows and ``chunk_transitions`` refuses to use one). Rendering
never touches the physics, so the episode, every observation on the grid, every action and
reward are bit-identical to ``observe_every=1`` (tested); only the work differs. The default,
1, observes every step, as step-wise learners (h = 1) need.

**Camera set** (``cameras``, :mod:`window_bench.pixels.cameras`). ``"paper"`` (default)
encodes the env's own wrist and side views. ``"seat"`` encodes the two fixed seat cameras on
the opening's corners in their place (same layout: two 512 x 4 x 4 maps + proprioception);
the env is then told not to render its own views, and the wrapper renders the seat cameras.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces

from window_bench.pixels.cameras import DEFAULT_CAMERAS, camera_names, render_views
from window_bench.pixels.encoder import OBS_DIM, VIEWS, ResNet10

#: The value of every entry of an observation the wrapper skipped (``observe_every > 1``).
UNOBSERVED = np.float32(np.nan)


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
    ``observe_every``: observe only on the grid of a chunked policy (module docstring).
    """

    def __init__(self, env: gym.Env, backbone: ResNet10, observe_every: int = 1,
                 cameras: str = DEFAULT_CAMERAS):
        camera_names(cameras)       # a bad set name fails here, in one line
        if (isinstance(observe_every, bool) or not isinstance(observe_every, (int, np.integer))
                or observe_every < 1):
            raise ValueError(f"observe_every={observe_every!r}; allowed: an integer >= 1 "
                             "(1: every step; h: the chunk grid of a policy with horizon h)")
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
        self.cameras = cameras
        self.observe_every = int(observe_every)
        self.observation_space = spaces.Box(-np.inf, np.inf, (OBS_DIM,), np.float32)
        self._t = 0

    def observation(self, observation: dict) -> np.ndarray:
        if self.cameras != DEFAULT_CAMERAS:
            observation = {**observation, **dict(zip(VIEWS, render_views(self.env, self.cameras)))}
        return encode_views(self.backbone, observation)

    def reset(self, *, seed=None, options=None):
        self._t = 0
        base = self.env.unwrapped
        base._skip_views = self.cameras != DEFAULT_CAMERAS   # its own views: not encoded
        try:
            return super().reset(seed=seed, options=options)
        finally:
            base._skip_views = False

    def step(self, action):
        self._t += 1
        skip = self._t % self.observe_every != 0
        base = self.env.unwrapped
        base._skip_views = skip or self.cameras != DEFAULT_CAMERAS
        try:
            obs, reward, terminated, truncated, info = self.env.step(action)
        finally:
            base._skip_views = False
        if not skip:
            return self.observation(obs), reward, terminated, truncated, info
        if terminated or truncated:     # the episode's last state s_T: always observed
            base._skip_views = self.cameras != DEFAULT_CAMERAS
            try:
                obs = base._observation()
            finally:
                base._skip_views = False
            return self.observation(obs), reward, terminated, truncated, info
        return np.full(OBS_DIM, UNOBSERVED), reward, terminated, truncated, info


def make_pixel_env(env_id: str, backbone: ResNet10, observe_every: int = 1,
                   cameras: str = DEFAULT_CAMERAS, **kwargs) -> PixelFeatures:
    """``gym.make(env_id, obs_mode="pixels", **kwargs)`` wrapped in :class:`PixelFeatures`:
    the pixel track's counterpart of the harness's ``obs_mode="flat"`` env."""
    extra = {} if cameras == DEFAULT_CAMERAS else {"cameras": cameras}
    return PixelFeatures(gym.make(env_id, obs_mode="pixels", **kwargs), backbone,
                         observe_every=observe_every, **extra)
