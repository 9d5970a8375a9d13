"""Render the pictures of the scene used in ``docs/environments.md``.

Usage (headless; needs Pillow)::

    MUJOCO_GL=egl python docs/scripts/render_scene.py [--out docs/img] [--width 800 --height 600]

Writes to ``docs/img/``:

* ``overview_A.png``       Experiment A at reset: the robot holds the panel on the tilted rack.
* ``overview_B.png``       Experiment B at reset: the panel lies on the ground, suction off.
* ``opening_empty.png``    the wall opening from the robot side, no panel: wood buck lining
                           with its eased entry edge, back stop strips behind.
* ``opening_seated.png``   the same view with the panel at the seated pose
                           (``env.unwrapped.seated_pose`` written into the panel free joint).
* ``opening_section.png``  a labelled cut through the sill at the opening's centre plane
                           (x = ``OPENING_CENTER_X``): wall, buck and stop strips and the panel
                           keep only their +x part, the robot is hidden.
* ``obs_A.png``, ``obs_B.png``  the wrist and side 128x128 observation views at reset,
                           exactly as ``obs_mode="pixels"`` returns them, upscaled 2x
                           (nearest) side by side.

Every free-camera view is a ``mujoco.MjvCamera`` with lookat/distance/azimuth/elevation
(azimuth 0 looks along +x, -90 along -y; negative elevation looks down). Renders use a
copy of the model (larger offscreen buffer, brighter headlight); the envs are untouched.
"""

from __future__ import annotations

import argparse
import copy
import os
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")  # before the first mujoco import

import gymnasium as gym  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from PIL import Image, ImageDraw, ImageFont  # noqa: E402

import window_bench  # noqa: E402,F401  (registers the ids)
from window_bench.envs import scene as S  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
CX, CZ, WY = S.OPENING_CENTER_X, S.OPENING_CENTER_Z, S.WALL_Y


def views(cfg: S.SceneConfig) -> dict:
    """name -> (lookat, distance, azimuth, elevation, fovy or None)."""
    sill_z = CZ - cfg.opening[1] / 2
    mid_y = -WY - S.WALL_THICKNESS / 2
    return {
        "overview": ((0.42, -0.20, 0.45), 2.35, -45.0, -28.0, None),
        "opening": ((CX, -WY, CZ), 1.1, -65.0, -25.0, None),
        # Far and narrow: an almost orthographic look along +x at the sill.
        "section": ((CX, mid_y, sill_z + 0.02), 3.0, -10.0, -8.0, 4.0),
    }


def free_camera(lookat, distance, azimuth, elevation) -> mujoco.MjvCamera:
    cam = mujoco.MjvCamera()
    cam.type = mujoco.mjtCamera.mjCAMERA_FREE
    cam.lookat[:] = lookat
    cam.distance = distance
    cam.azimuth = azimuth
    cam.elevation = elevation
    return cam


def render(model, data, view, width, height) -> np.ndarray:
    lookat, distance, azimuth, elevation, fovy = view
    model = copy.copy(model)
    model.vis.global_.offwidth = max(model.vis.global_.offwidth, width)
    model.vis.global_.offheight = max(model.vis.global_.offheight, height)
    model.vis.headlight.ambient[:] = 0.3
    model.vis.headlight.diffuse[:] = 0.5
    if fovy is not None:
        model.vis.global_.fovy = fovy
    r = mujoco.Renderer(model, height, width)
    try:
        r.update_scene(data, camera=free_camera(lookat, distance, azimuth, elevation))
        return r.render().copy()
    finally:
        r.close()


def project(view, point, width, height, model_fovy) -> tuple[float, float]:
    """Pixel coordinates of a world point in a free-camera view (MuJoCo's convention)."""
    lookat, distance, az, el, fovy = view
    az, el = np.deg2rad(az), np.deg2rad(el)
    fwd = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    v = np.asarray(point) - (np.asarray(lookat) - distance * fwd)
    f = (height / 2) / np.tan(np.deg2rad(fovy if fovy is not None else model_fovy) / 2)
    return width / 2 + f * (v @ right) / (v @ fwd), height / 2 - f * (v @ up) / (v @ fwd)


def label(img: np.ndarray, items, view, model_fovy) -> np.ndarray:
    """Draw text labels with leader lines to world points: items = (text, point, (dx, dy))."""
    h, w = img.shape[:2]
    im = Image.fromarray(img)
    draw = ImageDraw.Draw(im)
    font = ImageFont.load_default(size=max(12, h // 36))
    for text, point, (dx, dy) in items:
        x, y = project(view, point, w, h, model_fovy)
        tx, ty = x + dx, y + dy
        draw.line([(x, y), (tx, ty)], fill=(255, 220, 60), width=2)
        draw.ellipse([x - 3, y - 3, x + 3, y + 3], fill=(255, 220, 60))
        box = draw.textbbox((tx, ty), text, font=font, anchor="lm" if dx >= 0 else "rm")
        draw.rectangle([box[0] - 4, box[1] - 3, box[2] + 4, box[3] + 3], fill=(0, 0, 0))
        draw.text((tx, ty), text, fill=(255, 255, 255), font=font, anchor="lm" if dx >= 0 else "rm")
    return np.asarray(im)


def save(img: np.ndarray, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(img).save(path, optimize=True)
    shown = path.relative_to(ROOT) if path.is_relative_to(ROOT) else path
    print(f"wrote {shown} ({img.shape[1]}x{img.shape[0]}, {path.stat().st_size // 1024} KB)")


def obs_strip(obs: dict) -> np.ndarray:
    up = [np.kron(obs[k], np.ones((2, 2, 1), np.uint8)) for k in ("wrist_rgb", "side_rgb")]
    gap = np.full((up[0].shape[0], 8, 3), 255, np.uint8)
    return np.concatenate([up[0], gap, up[1]], axis=1)


def set_panel(model, data, sc, pos, mat) -> None:
    a = sc.panel_qpos_adr
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(mat).ravel())
    data.qpos[a:a + 3] = pos
    data.qpos[a + 3:a + 7] = q
    mujoco.mj_forward(model, data)


def cut_section(m, d, sc, cut: float = CX) -> None:
    """Keep the world-x > ``cut`` part of the wall and of the seated panel (boxes whose
    x axis lies along world x are shortened; others on the -x side are hidden), hide the
    robot, and make the panel opaque so its cut face reads clearly."""
    for g in range(m.ngeom):
        if g in sc.robot_geoms:
            m.geom_rgba[g, 3] = 0.0
            continue
        name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g) or ""
        body = m.geom_bodyid[g]
        if body == sc.panel_body:
            m.geom_rgba[g] = (0.45, 0.65, 0.85, 1.0) if g == sc.panel_geom else (0, 0, 0, 0)
        elif not name.startswith(("wall_", "buck_", "stop_")):
            continue
        if abs(abs(d.geom_xmat[g][0]) - 1.0) > 1e-9:   # geom x not along world x (bevels)
            if d.geom_xpos[g][0] < cut:
                m.geom_rgba[g, 3] = 0.0
            continue
        gx, half = d.geom_xpos[g][0], m.geom_size[g, 0]
        lo, hi = max(gx - half, cut), gx + half
        if hi <= lo:
            m.geom_rgba[g, 3] = 0.0
            continue
        m.geom_size[g, 0] = (hi - lo) / 2
        shift_world = np.array([(hi + lo) / 2 - gx, 0.0, 0.0])
        m.geom_pos[g] += d.xmat[body].reshape(3, 3).T @ shift_world
        m.geom_sameframe[g] = 0   # else MuJoCo keeps placing it at the body frame


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, default=ROOT / "docs" / "img")
    p.add_argument("--width", type=int, default=800)
    p.add_argument("--height", type=int, default=600)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    W, H = args.width, args.height

    for exp in ("A", "B"):
        env = gym.make(f"WindowInstall-{exp}-v0", obs_mode="pixels")
        obs, _ = env.reset(seed=args.seed)
        u = env.unwrapped
        V = views(u.cfg)
        save(render(u.model, u.data, V["overview"], W, H), args.out / f"overview_{exp}.png")
        save(obs_strip(obs), args.out / f"obs_{exp}.png")
        if exp == "A":
            # The opening, on a copy of the model/data; suction off so nothing holds the panel.
            m = copy.copy(u.model)
            d = mujoco.MjData(m)
            d.qpos[:] = u.data.qpos
            d.eq_active[u.scene.suction_eq] = 0
            set_panel(m, d, u.scene, np.array([0.0, 2.0, 0.1]), np.eye(3))  # out of view
            save(render(m, d, V["opening"], W, H), args.out / "opening_empty.png")
            set_panel(m, d, u.scene, *u.seated_pose)
            save(render(m, d, V["opening"], W, H), args.out / "opening_seated.png")
            cut_section(m, d, u.scene)
            mujoco.mj_forward(m, d)
            img = render(m, d, V["section"], W, H)
            cfg = u.cfg
            sill = CZ - cfg.opening[1] / 2
            depth = cfg.seated_depth
            t = cfg.panel_thickness
            items = [
                (f"wall face y = {-WY:.2f} m (robot side)", (CX, -WY, sill - 0.06), (40, 45)),
                ("eased entry edge", (CX, -WY - 0.003, sill - 0.003), (-40, -70)),
                ("wood buck (sill)", (CX, -WY - 0.07, sill - 0.012), (-60, 90)),
                (f"{cfg.clearance * 1e3:.0f} mm clearance", (CX, -WY - depth, sill + 0.001), (90, 110)),
                (f"panel, seated ({t * 1e3:.0f} mm deep)", (CX, -WY - depth, sill + 0.06), (60, -40)),
                ("back stop", (CX, -WY - S.STOP_DEPTH - 0.01, sill + S.STOP_LIP / 2), (40, 30)),
            ]
            save(label(img, items, V["section"], u.model.vis.global_.fovy), args.out / "opening_section.png")
        env.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
