"""Camera sets of the pixel track and the views they render.

* ``paper`` - the paper's views and the env's own ``obs_mode="pixels"`` images: the wrist
  camera on the vacuum tool and the side camera on the whole opening (``robot0_wrist``,
  ``side``).
* ``seat`` - two fixed cameras, each looking at one corner of the opening from diagonally
  outside it (``seat_top_right``, ``seat_bottom_left``, 25 deg field of view, built in
  :mod:`window_bench.envs.scene`): the panel's edges and the buck's lining fill the 128 x 128
  pixels near the seat, about 0.7 mm per pixel at the corner, where the side camera spends
  about 20 mm per pixel on the opening. Two diagonal corners separate a lateral offset from
  an in-plane rotation.

:func:`render_views` renders a set from an env's current state with the env's own renderer
(the same image size and backend as its ``obs_mode="pixels"`` views); rendering never touches
the physics.
"""

from __future__ import annotations

import numpy as np

from window_bench.envs.scene import SEAT_CAMERAS

CAMERA_SETS: dict[str, tuple[str, str]] = {
    "paper": ("robot0_wrist", "side"),
    "seat": tuple(name for name, _, _ in SEAT_CAMERAS),
}
DEFAULT_CAMERAS = "paper"


def camera_names(camera_set: str) -> tuple[str, str]:
    """The two MuJoCo camera names of ``camera_set``, in view order."""
    if camera_set not in CAMERA_SETS:
        raise ValueError(f"camera set {camera_set!r} is not one of {', '.join(CAMERA_SETS)}")
    return CAMERA_SETS[camera_set]


def saved_cameras(state: dict) -> str:
    """The camera set a saved (policy) state names; a state saved before camera sets existed
    names none and was observed through ``"paper"``. Anything but a known set's name is
    refused: a policy file never makes the env render a camera it does not list."""
    name = state.get("cameras", DEFAULT_CAMERAS)
    if not isinstance(name, str) or name not in CAMERA_SETS:
        raise ValueError(f"the saved state names the camera set {name!r}; allowed: "
                         f"{', '.join(CAMERA_SETS)}")
    return name


def render_views(env, camera_set: str = DEFAULT_CAMERAS) -> list[np.ndarray]:
    """The views of ``camera_set`` at ``env``'s current state: two (H, W, 3) uint8 images of
    the env's ``image_size``. ``"paper"`` returns exactly the env's own pixel observation."""
    names = camera_names(camera_set)
    u = env.unwrapped
    if names == CAMERA_SETS["paper"]:
        return u._render_views()
    if u._renderer is None:
        from window_bench.gl import renderer

        u._renderer = renderer(u.model, u.image_size, u.image_size)
    out = []
    for cam in names:
        u._renderer.update_scene(u.data, camera=cam)
        out.append(u._renderer.render().copy())
    return out
