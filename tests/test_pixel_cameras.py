"""The pixel track's seat cameras (window_bench.pixels.cameras), the probe read-outs
(window_bench.pixels.readout) and the options of experiments/sanity/pixel_pose_probe.py."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import mujoco
import numpy as np
import pytest
import torch

from window_bench.envs import scene as S
from window_bench.pixels.cameras import CAMERA_SETS, camera_names, render_views
from window_bench.pixels.encoder import ResNet10, frozen
from window_bench.pixels.readout import backbone_map, readout_features, spatial_softmax

PROBE = Path(__file__).parents[1] / "experiments/sanity/pixel_pose_probe.py"


def _probe():
    spec = importlib.util.spec_from_file_location("pixel_pose_probe", PROBE)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("env_id", ["WindowInstall-A-v0", "WindowInstall-B-Panel60x40-v0"])
def test_seat_cameras_look_at_the_opening_corners_from_outside_the_panels_path(make_env, env_id):
    env = make_env(env_id, obs_mode="state")
    env.reset(seed=0)
    u = env.unwrapped
    half_w, half_h = u.cfg.opening[0] / 2, u.cfg.opening[1] / 2
    for name, sx, sz in S.SEAT_CAMERAS:
        cid = mujoco.mj_name2id(u.model, mujoco.mjtObj.mjOBJ_CAMERA, name)
        assert cid >= 0
        pos, mat = u.data.cam_xpos[cid], u.data.cam_xmat[cid].reshape(3, 3)
        corner = np.array([S.OPENING_CENTER_X + sx * half_w, -S.WALL_Y,
                           S.OPENING_CENTER_Z + sz * half_h])
        d = mat.T @ (corner - pos)                     # the corner in the camera frame
        assert d[2] < 0 and np.hypot(d[0], d[1]) < 1e-9 * abs(d[2]) + 1e-12   # on the axis
        assert mat[2, 1] > 0                           # the world's up is up in the image
        # outside the panel's footprint (the panel never passes through it), in front of the wall
        assert abs(pos[0] - S.OPENING_CENTER_X) > half_w and abs(pos[2] - S.OPENING_CENTER_Z) > half_h
        assert pos[1] > -S.WALL_Y


def test_paper_set_is_the_envs_own_views_and_rendering_leaves_the_physics(make_env):
    a = make_env("WindowInstall-A-v0", obs_mode="pixels")
    b = make_env("WindowInstall-A-v0", obs_mode="pixels")
    oa, _ = a.reset(seed=4)
    b.reset(seed=4)
    paper = render_views(a, "paper")
    assert all(np.array_equal(x, oa[k]) for x, k in zip(paper, ("wrist_rgb", "side_rgb")))
    seat = render_views(a, "seat")
    assert [v.shape for v in seat] == [(128, 128, 3)] * 2 and seat[0].dtype == np.uint8
    assert not np.array_equal(seat[0], paper[1]) and min(v.std() for v in seat) > 5
    act = np.array([0.2, -0.1, 0.3, 0.0, 0.0, 0.0, 1.0])
    for _ in range(3):
        render_views(a, "seat")
        oa, *_ = a.step(act)
        ob, *_ = b.step(act)
    assert np.array_equal(a.unwrapped.data.qpos, b.unwrapped.data.qpos)
    assert np.array_equal(oa["side_rgb"], ob["side_rgb"])
    with pytest.raises(ValueError, match="'wide' is not one of paper, seat"):
        camera_names("wide")


def test_seat_views_resolve_a_millimetre_the_side_view_does_not(make_env):
    """The panel placed in the opening 40 mm from the seat, then moved 1 mm sideways: the
    seat views change several times as many pixels as the side view does."""
    env = make_env("WindowInstall-A-v0", obs_mode="pixels")
    env.reset(seed=0)
    u = env.unwrapped
    pos, mat = u.seated_pose
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, mat.reshape(-1))
    adr = u.scene.panel_qpos_adr

    def views(dx):
        u.data.qpos[adr:adr + 3] = pos + np.array([dx, 0.04, dx])
        u.data.qpos[adr + 3:adr + 7] = quat
        mujoco.mj_forward(u.model, u.data)
        return [v.astype(int) for v in render_views(env, "paper") + render_views(env, "seat")]

    before, after = views(0.0), views(0.001)
    changed = [int((np.abs(x - y).sum(-1) > 30).sum()) for x, y in zip(before, after)]
    side, seat = changed[1], changed[2:]
    assert min(seat) >= 40 and min(seat) > 4 * max(side, 1), changed


def test_readouts():
    torch.manual_seed(0)
    bb = frozen(ResNet10())
    images = torch.randint(0, 256, (2, 128, 128, 3), dtype=torch.uint8)
    with torch.no_grad():
        assert torch.equal(backbone_map(bb, images, "layer4"), bb(images))
        assert backbone_map(bb, images, "layer3").shape == (2, 256, 8, 8)
        assert backbone_map(bb, images, "layer2").shape == (2, 128, 16, 16)
    assert readout_features(bb, images.numpy(), "layer3", "keypoints").shape == (2, 512)
    maps = readout_features(bb, images.numpy(), "layer4", "maps")
    assert maps.shape == (2, 8192) and np.array_equal(maps, maps.astype(np.float16).astype(np.float32))
    # one hot cell per channel: the keypoint is that cell's centre, x then y, on [-1, 1]
    m = torch.full((1, 2, 5, 5), -1e4)
    m[0, 0, 1, 4] = 0.0     # row 1 (y = -0.5), column 4 (x = 1)
    m[0, 1, 2, 0] = 0.0     # row 2 (y = 0), column 0 (x = -1)
    assert torch.allclose(spatial_softmax(m), torch.tensor([[1.0, -1.0, -0.5, 0.0]]))
    for layer, readout, bad in (("layer5", "maps", "'layer5'"), ("layer3", "pooled", "'pooled'")):
        with pytest.raises(ValueError, match=bad):
            readout_features(bb, images.numpy(), layer, readout)


@pytest.mark.parametrize("argv, says", [
    (["--offset-episodes", "8", "--cameras", "wide"], "--cameras 'wide' must be one of paper, seat"),
    (["--offset-episodes", "8", "--layer", "layer9"], "--layer 'layer9' must be one of layer2, layer3, layer4"),
    (["--offset-episodes", "8", "--readout", "pooled"], "--readout 'pooled' must be one of maps, keypoints"),
    (["--offset-episodes", "8", "--align-error-deg", "-1"], "--align-error-deg -1.0 must lie in [0, 10]"),
    (["--offset-episodes", "8", "--weights", "nope.safetensors"], "--weights 'nope.safetensors' is not a file"),
    ([], "nothing to probe"),
    (["--demos", "d", "--cameras", "seat"], "leave it out with --cameras"),
    (["--offset-episodes", "4", "--cameras", "seat"], "--offset-episodes 4 must be 0 or at least 8"),
])
def test_probe_refuses_bad_options_in_one_line(argv, says, capsys):
    assert _probe().main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: ") and says in err


def test_probe_on_the_seat_cameras_writes_its_result(tmp_path, monkeypatch):
    probe = _probe()
    (tmp_path / "experiments/sanity/results").mkdir(parents=True)
    monkeypatch.setattr(probe, "REPO", tmp_path)
    frames = probe.offset_frames("WindowInstall-A-v0", [300_000], 10.0, 0.1, "seat")
    (v0, v1, prop, y), = frames
    assert v0.shape[1:] == (128, 128, 3) and len(v0) == len(v1) == len(prop) == len(y) > 10
    assert np.linalg.norm(y, axis=1).max() < 0.1
    assert probe.main(["--offset-episodes", "8", "--cameras", "seat", "--layer", "layer3",
                       "--readout", "keypoints"]) == 0
    out = json.loads((tmp_path / "experiments/sanity/results/"
                      "pixel_pose_probe_WindowInstall-A-v0_seat_layer3_keypoints.json").read_text())
    res = out["offset_episodes"]
    assert (res["cameras"], res["layer"], res["readout"]) == ("seat", "layer3", "keypoints")
    assert res["episodes"] == 8 and res["test_episodes"] == 2
    row = res["probes"]["keypoints (layer3) of the seat views + proprio (1,042)"]
    assert all(np.isfinite(row["rmse_mm_xyz"]))
    assert set(CAMERA_SETS) == {"paper", "seat"}


def test_pixel_features_on_the_seat_cameras(make_env):
    """``PixelFeatures(cameras="seat")``: the maps are the seat views' (the env's own views are
    not rendered), the episode is the paper set's, and the chunk grid works as before."""
    from window_bench.pixels.features import PixelFeatures, encode_views, make_pixel_env
    from window_bench.pixels.track import make_track_env

    torch.manual_seed(0)
    bb = frozen(ResNet10())
    seat = make_pixel_env("WindowInstall-A-v0", bb, cameras="seat")
    paper = make_track_env("WindowInstall-A-v0", "pixels", bb)
    grid = make_track_env("WindowInstall-A-v0", "pixels", bb, cameras="seat", observe_every=2)
    obs = [e.reset(seed=5)[0] for e in (seat, paper, grid)]
    act = np.array([0.3, 0.0, -0.2, 0.0, 0.1, 0.0, 1.0])
    for t in range(4):      # obs after t steps; the grid observes t = 0, 2, ...
        want = encode_views(bb, dict(zip(("wrist_rgb", "side_rgb"), render_views(seat, "seat")),
                                     robot0_proprio=obs[1][-18:]))
        assert np.array_equal(obs[0], want)
        assert np.array_equal(obs[2], want) if t % 2 == 0 else np.isnan(obs[2]).all()
        assert not np.array_equal(obs[0][:8192], obs[1][:8192])
        assert np.array_equal(obs[0][-18:], obs[1][-18:])
        obs = [e.step(act)[0] for e in (seat, paper, grid)]
    for e in (seat, paper, grid):
        e.close()
    with pytest.raises(ValueError, match="'wide' is not one of paper, seat"):
        PixelFeatures(make_env("WindowInstall-A-v0", obs_mode="pixels"), bb, cameras="wide")


def _finetune():
    path = Path(__file__).parents[1] / "experiments/sanity/pixel_seat_finetune.py"
    spec = importlib.util.spec_from_file_location("pixel_seat_finetune", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("argv, says", [
    (["--cameras", "wide"], "--cameras 'wide' must be one of paper, seat"),
    (["--episodes", "4"], "--episodes 4 must lie in 8..1000"),
    (["--max-minutes", "0"], "--max-minutes 0.0 must lie in (0, 120]"),
    (["--lr", "1"], "--lr 1.0 must lie in (0, 0.1]"),
    (["--batch", "0"], "--batch 0 must lie in 1..256"),
])
def test_finetune_refuses_bad_options_in_one_line(argv, says, capsys, tmp_path):
    assert _finetune().main(["--out", str(tmp_path / "w.safetensors"), *argv]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: ") and says in err
    assert _finetune().main(["--out", str(tmp_path / "w.pt")]) == 2
    assert "--out" in capsys.readouterr().err


def test_finetune_writes_a_loadable_backbone_that_moved(tmp_path):
    from window_bench.pixels.weights import DEFAULT_WEIGHTS, load_backbone, weights_record

    ft = _finetune()
    z, mean, std = ft.standardise(np.array([[0.0, 0.1, 0.001], [0.002, 0.3, 0.001]]))
    assert np.allclose(z[:, :2], [[-1, -1], [1, 1]]) and np.allclose(z[:, 2], 0)   # floor
    out = tmp_path / "near.safetensors"
    assert ft.main(["--out", str(out), "--episodes", "8", "--max-minutes", "0.01",
                    "--batch", "4"]) == 0
    rec = weights_record(out)
    assert rec["steps"] >= 1 and rec["frames"] > 50 and rec["init"] == DEFAULT_WEIGHTS.name
    new, old = load_backbone(out).state_dict(), load_backbone(DEFAULT_WEIGHTS).state_dict()
    assert not torch.equal(new["conv1.0.weight"], old["conv1.0.weight"])
