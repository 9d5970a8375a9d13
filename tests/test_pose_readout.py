"""The pose read-out (window_bench.pixels.pose_readout): a fixed linear map of the frozen
features to the panel's pose relative to the seat, fitted once, checked when loaded, carried
in the policy files of the agents that see it."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from window_bench.pixels.encoder import EMBED_DIM, OBS_DIM, PROPRIO_DIM, PixelObsEncoder
from window_bench.pixels.pose_readout import (DEFAULT_READOUT, FEATURES, FORMAT, POSE_DIM,
                                              POSE_UNITS, PoseReadout,
                                              PoseReadoutError, load_pose_readout, ridge)


def _readout(seed: int = 0, mm: float = 10.0, deg: float = 2.0) -> PoseReadout:
    g = torch.Generator().manual_seed(seed)
    return PoseReadout(torch.randn(POSE_DIM, OBS_DIM, generator=g) * 1e-4,
                       torch.randn(POSE_DIM, generator=g) * 1e-3,
                       torch.randn(POSE_DIM, PROPRIO_DIM, generator=g) * 0.1,
                       torch.randn(POSE_DIM, generator=g) * 0.1, 0.1, mm, deg)


def _coarse():
    return torch.zeros(POSE_DIM, PROPRIO_DIM), torch.zeros(POSE_DIM)


def _write(path, weight, bias, **record):
    rec = {"format": FORMAT, "cameras": "seat", "backbone_sha256": "ab" * 32,
           "fine_pose_mm": 10.0, "fine_pose_deg": 2.0, "switch_mm": 115.0, **record}
    cw, cb = _coarse()
    save_file({"weight": weight, "bias": bias, "coarse_weight": cw, "coarse_bias": cb},
              str(path), metadata={"window_bench.record": json.dumps(rec)})
    return path


def test_ridge_recovers_a_linear_map_with_more_inputs_than_rows():
    """The dual-form ridge returns a primal map on the raw (unstandardised) inputs: with a
    small penalty it recovers a linear target exactly enough on held-out rows, and a larger
    penalty shrinks it towards the mean."""
    rng = np.random.default_rng(0)
    z = rng.normal(0, 1, (80, 10))                   # 200 inputs spanning 10 directions
    x = 3.0 + z @ rng.normal(0, 2, (10, 200))
    y = z @ rng.normal(0, 1, (10, 2)) + np.array([1.0, -2.0])
    (w, b), (w_big, b_big) = ridge(x[:60], y[:60], [1e-6, 1e6])
    pred = x[60:] @ w.T + b
    assert w.shape == (2, 200) and b.shape == (2,)
    assert np.sqrt(((pred - y[60:]) ** 2).mean()) < 0.05 * y[60:].std()
    [(w2, b2)] = ridge(x[:, :5], x[:, :5] @ np.arange(1.0, 6.0)[:, None] + 0.5, [1e-9])
    np.testing.assert_allclose(w2[0], np.arange(1.0, 6.0), rtol=1e-6)   # primal: rows > inputs
    np.testing.assert_allclose(b2, [0.5], atol=1e-6)
    big = x[60:] @ w_big.T + b_big
    np.testing.assert_allclose(big, np.broadcast_to(y[:60].mean(0), big.shape), atol=0.1 * y.std())


def test_the_readout_gives_the_fine_pose_features_of_its_estimate():
    """The estimate on a linear scale (units of 0.1 m / 0.1 rad), then ``tanh(estimate / mm)``
    for the position and ``tanh(estimate / deg)`` for the rotation, as the state track's
    fine pose features of the same pose; the fine estimate where the
    coarse (proprioception) estimate puts the panel within ``switch_m``, the coarse one
    farther out; a saved state restores it bit for bit."""
    w = torch.zeros(POSE_DIM, OBS_DIM)
    b = torch.tensor([0.005, -0.001, 0.0, np.deg2rad(1.0), 0.0, -np.deg2rad(4.0)])
    cw = torch.zeros(POSE_DIM, PROPRIO_DIM)
    cw[1, 0] = 1.0                   # coarse depth = the first proprioceptive value (m)
    r = PoseReadout(w, b, cw, torch.zeros(POSE_DIM), 0.1, mm=10.0, deg=2.0)
    obs = torch.zeros(3, OBS_DIM)
    obs[:, -PROPRIO_DIM] = torch.tensor([0.0, 0.05, 0.3])       # 0, 50 and 300 mm out
    out = r(obs)
    assert out.shape == (3, FEATURES)
    fine = torch.tanh(torch.tensor([0.5, -0.1, 0.0, 0.5, 0.0, -2.0]))
    torch.testing.assert_close(out[:2, POSE_DIM:], fine.expand(2, -1))   # near: the fine estimate
    torch.testing.assert_close(out[:2, :POSE_DIM], (b.float() / POSE_UNITS).expand(2, -1))  # linear
    torch.testing.assert_close(out[2, POSE_DIM:], torch.tanh(torch.tensor([0.0, 30.0, 0, 0, 0, 0])))
    torch.testing.assert_close(out[2, :POSE_DIM], torch.tensor([0.0, 3.0, 0, 0, 0, 0]))
    again = PoseReadout.from_state(dict(r.state_dict()))
    x = torch.rand(4, OBS_DIM)
    assert torch.equal(again(x), r(x))


def test_wrong_readout_files_are_refused_in_one_line(tmp_path):
    w, b = torch.zeros(POSE_DIM, OBS_DIM), torch.zeros(POSE_DIM)
    good = _write(tmp_path / "good.safetensors", w, b)
    readout, record = load_pose_readout(good, "ab" * 32, "seat")
    assert record["cameras"] == "seat" and float(readout.scale[0]) == 100.0
    assert float(readout.switch_m) == pytest.approx(0.115)
    cases = {
        "no such file": tmp_path / "missing.safetensors",
        "is not a safetensors read-out file": tmp_path / "junk.safetensors",
        "has no 'window-bench pose read-out' record": _write(tmp_path / "f.safetensors", w, b,
                                                             format="pickle"),
        r"holds tensors \['bias'\]; expected bias, coarse_bias": tmp_path / "t.safetensors",
        "non-finite": _write(tmp_path / "n.safetensors", w.clone().fill_(float("nan")), b),
        r"weight of shape \(6, 10\), expected \(6, 16402\)":
            _write(tmp_path / "s.safetensors", w[:, :10].contiguous(), b),
        "fine pose scales": _write(tmp_path / "m.safetensors", w, b, switch_mm="import os"),
    }
    (tmp_path / "junk.safetensors").write_bytes(b"\x80\x04not a safetensors file")
    save_file({"bias": b}, str(tmp_path / "t.safetensors"),
              metadata={"window_bench.record": json.dumps({"format": FORMAT})})
    for message, path in cases.items():
        with pytest.raises(PoseReadoutError, match=message) as e:
            load_pose_readout(path)
        assert "\n" not in str(e.value)
    with pytest.raises(PoseReadoutError, match="fitted for the backbone abababababab, not cdcd"):
        load_pose_readout(good, "cd" * 32, "seat")
    with pytest.raises(PoseReadoutError, match="camera set 'seat', not 'paper'"):
        load_pose_readout(good, "ab" * 32, "paper")


def test_the_shipped_readout_belongs_to_the_shipped_backbone_and_the_seat_cameras():
    """The file the ``pixels-seat`` track loads: fitted for the shipped backbone and the seat
    cameras, with its command and held-out quality recorded; on A its held-out lateral error
    near the seat is at most a quarter of the 2 mm clearance."""
    from window_bench.harness.files import sha256_file
    from window_bench.pixels.weights import DEFAULT_WEIGHTS

    readout, record = load_pose_readout(DEFAULT_READOUT, sha256_file(DEFAULT_WEIGHTS), "seat")
    assert record["command"].startswith("bench encoder readout")
    q = record["heldout_quality"]["WindowInstall-A-v0"]
    assert q["frames"] > 100 and max(q["rmse_pos_mm"][0], q["rmse_pos_mm"][2]) <= 0.5
    assert DEFAULT_READOUT.stat().st_size < 1_000_000


def test_pixel_agents_carry_the_readout_in_their_policy_files():
    """With the track's read-out, the front end's output is the 82 values and the 6 fine pose
    features (94); the policy state carries the read-out, so a restored policy acts
    bit-identically without the file; ACT's robot token stays the proprioception; the
    hyperparameters name the read-out's digest (Stage I cache key)."""
    from window_bench.harness.agent import AgentSpec, check_plain
    from window_bench.harness.methods import PROFILES, agent_class

    rng = np.random.default_rng(0)
    obs = rng.random((3, OBS_DIM)).astype(np.float32)
    enc = PixelObsEncoder(0, pose_readout=_readout())
    assert enc.out_dim == 2 * EMBED_DIM + PROPRIO_DIM + FEATURES == 94 and PixelObsEncoder.out_dim == 82
    out = enc(torch.from_numpy(obs))
    torch.testing.assert_close(out[:, -FEATURES:], enc.pose_readout(torch.from_numpy(obs)))
    torch.testing.assert_close(out[:, :-FEATURES], PixelObsEncoder(0)(torch.from_numpy(obs)))
    spec = AgentSpec(obs_dim=OBS_DIM, action_dim=7, h=10, seed=0, profile=PROFILES["smoke"],
                     demos=[], front_end={"pose_readout": _readout(1)})
    for kind in ("qcfql-pixels", "hilserl-pixels"):
        cls = agent_class(kind)
        agent = cls.create(dataclasses.replace(spec, h=10 if kind == "qcfql-pixels" else 1))
        plain = cls.create(dataclasses.replace(spec, front_end=None))
        assert agent.encoder.out_dim == 94 and plain.encoder.out_dim == 82
        assert len(agent.hyperparameters()["pose_readout_sha256"]) == 64
        assert "pose_readout_sha256" not in plain.hyperparameters()
        state = agent.policy_state_dict()
        check_plain(state)
        again = cls.from_policy_state_dict(state)
        assert again.encoder.pose_readout is not None
        np.testing.assert_array_equal(again.act(obs[0], deterministic=True),
                                      agent.act(obs[0], deterministic=True))
        assert cls.from_policy_state_dict(plain.policy_state_dict()).encoder.pose_readout is None
    act = agent_class("act-pixels")
    emb = torch.arange(94, dtype=torch.float32)[None]
    tokens = act.tokens(emb)[0].tolist()
    assert tokens[:PROPRIO_DIM] == list(range(64, 82)) and tokens[PROPRIO_DIM:] == \
        list(range(64)) + list(range(82, 94))


def test_cli_readout_rejects_bad_arguments_before_work(tmp_path, capsys):
    """``bench encoder readout``: a bad value is one line and exit code 2, and nothing is
    written; an existing --out is kept without --force."""
    from window_bench.cli import main

    out = tmp_path / "r.safetensors"
    for argv in (["--episodes", "0"], ["--align-error-mm", "60"], ["--near-mm", "-1"],
                 ["--cameras", "nope"], ["--fine-pose-deg", "91"]):
        with pytest.raises(SystemExit) as exc:
            main(["encoder", "readout", "--out", str(out), *argv])
        assert exc.value.code == 2
    assert main(["encoder", "readout", "--out", str(out), "--weights",
                 str(tmp_path / "missing.safetensors")]) == 2
    err = capsys.readouterr().err
    assert "no such file" in err and not out.exists()
    out.write_bytes(b"keep")
    assert main(["encoder", "readout", "--out", str(out)]) == 2
    assert out.read_bytes() == b"keep" and "--force" in capsys.readouterr().err


def test_a_small_fit_writes_a_file_the_track_loads(tmp_path):
    """``fit_pose_readout`` end to end on two scripted episodes (a random backbone: this is
    plumbing, not quality): the file loads for its backbone digest and camera set, records
    its command, switch and held-out quality, and reads the features it was fitted on."""
    from window_bench.pixels.encoder import ResNet10, frozen
    from window_bench.pixels.pose_readout import fit_pose_readout

    with torch.random.fork_rng():
        torch.manual_seed(0)
        backbone = frozen(ResNet10())
    out = tmp_path / "r.safetensors"
    record = fit_pose_readout(out, backbone, "cd" * 32, env_ids=["WindowInstall-A-v0"],
                              episodes=2, heldout_episodes=1, align_error_mm=10.0,
                              align_error_deg=1.0, near_mm=100.0, cameras="seat", mm=10.0,
                              deg=2.0, seed=300_000, command="bench encoder readout (test)")
    readout, saved = load_pose_readout(out, "cd" * 32, "seat")
    assert saved["switch_mm"] == 115.0 and saved["fit_mm"] == 125.0 and record["train_frames"] > 10
    q = saved["heldout_quality"]["WindowInstall-A-v0"]
    assert q["frames"] > 0 and all(np.isfinite(q["rmse_pos_mm"]))
    assert readout(torch.zeros(2, OBS_DIM)).shape == (2, FEATURES)


def test_operator_episodes_join_the_fit_and_are_scored(tmp_path):
    """``operator_episodes``: episodes of the operator demonstrating (its own eye error and
    hand noise, as the demonstrations are made) join the training frames, and the read-out is
    scored on held-out ones as well; the record names the operator."""
    from window_bench.pixels.encoder import ResNet10, frozen
    from window_bench.pixels.pose_readout import fit_pose_readout, installer_episodes

    with torch.random.fork_rng():
        torch.manual_seed(0)
        backbone = frozen(ResNet10())
    common = dict(env_ids=["WindowInstall-A-v0"], episodes=2, heldout_episodes=1,
                  align_error_mm=10.0, align_error_deg=1.0, near_mm=100.0, cameras="seat",
                  mm=10.0, deg=2.0, seed=300_000, command="bench encoder readout (test)")
    alone = fit_pose_readout(tmp_path / "a.safetensors", backbone, "cd" * 32, **common)
    both = fit_pose_readout(tmp_path / "b.safetensors", backbone, "cd" * 32, **common,
                            operator_episodes=1, operator="average")
    assert alone["operator"] is None and alone["heldout_quality_operator"] is None
    assert both["operator"] == "average" and both["train_frames"] > alone["train_frames"]
    q = both["heldout_quality_operator"]["WindowInstall-A-v0"]
    assert q["frames"] > 0 and all(np.isfinite(q["rmse_pos_mm"]))
    # The operator's episode is not the scripted installer's: its hands shake.
    [scripted] = installer_episodes("WindowInstall-A-v0", [5], 0.0, 0.0, 0.0, "seat")
    [shown] = installer_episodes("WindowInstall-A-v0", [5], 0.0, 0.0, 0.0, "seat", "average")
    assert len(scripted) != len(shown) or not np.allclose(scripted[-1][1], shown[-1][1])


def test_policy_episodes_need_a_policy_file(tmp_path, capsys):
    """``--policy`` and ``--policy-episodes`` go together, and a policy file that is not
    there is refused in one line before anything is written."""
    from window_bench.cli import main

    out = tmp_path / "r.safetensors"
    assert main(["encoder", "readout", "--out", str(out), "--policy-episodes", "3"]) == 2
    assert "go together" in capsys.readouterr().err
    assert main(["encoder", "readout", "--out", str(out), "--policy",
                 str(tmp_path / "none.safetensors"), "--policy-episodes", "3"]) == 2
    err = capsys.readouterr().err
    assert "--policy" in err and len(err.strip().splitlines()) == 1 and not out.exists()
