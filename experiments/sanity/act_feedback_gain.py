r"""Does the policy close the loop on the panel's lateral offset? The feedback gain of ACT
policies and of QC-FQL's Stage I flow teacher / student, on held-out demonstrated states (no
environment): shift the observed panel position relative to the seat (``window_pos_rel``)
by ``--delta`` mm along one lateral axis and measure how much the commanded motion over the
predicted chunk changes along that axis (the chunk's summed translation, which the controller
applies in the TCP frame, rotated to the world frame with the observed TCP orientation, x
0.025 m per action unit), median over the held-out states in a band of distances to the seat.
A policy that corrects the offset has a negative gain (``-delta`` would cancel it within
the chunk's second).

    python experiments/sanity/act_feedback_gain.py \
        --act /tmp/act15/curve/policies/step_0016000.safetensors \
        --stage1 leaderboard/runs/stage1_cache/849017b6...safetensors \
        --demos-dir /tmp/act15/demos/heldout --out experiments/sanity/results/bc_feedback_gain.json

A policy that imitates the transport but not the alignment has a gain near 0: it carries the
panel to where the demonstrations went, whatever the panel's observed offset. ``--shift
panel`` (default) shifts only the observed ``window_pos_rel``: the panel moved in the
gripper, the robot where it was (the grasp offset varies from episode to episode; only this
input says where the panel is); ``--shift tcp`` shifts only the observed TCP position
(``robot0_eef_pos`` and its copy in ``robot0_proprio``): the robot moved, the panel's
observed pose not; ``--shift both`` is the arm and the panel moved together.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import torch

from baselines.act import FLAT_ROBOT_DIM, ACTAgent, _harness_demos
from baselines.qcfql import QCFQLAgent
from window_bench.harness.evaluation import atomic_write_text, provenance
from window_bench.harness.files import load_state, sha256_file

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bc_heldout_error import parse_policy_args, policy_parser  # noqa: E402  (the shared CLI core)

#: Metres of TCP motion per action unit (the controller's translation scale).
M_PER_UNIT = 0.025
#: Distance-to-seat bands (m): transport, approach, the alignment hover in front of the seat.
BANDS = ((0.30, 2.0), (0.13, 0.30), (0.09, 0.13))
#: Lateral world axes (x, z; the insertion axis is -y) and their index in a 3-vector.
AXES = {"x": 0, "z": 2}
#: First index of each shifted 3-vector in the flat observation: window_pos_rel; the TCP
#: position (robot0_eef_pos) and its copy in robot0_proprio (q, qd, eef, vacuum).
SHIFTS = {"panel": (FLAT_ROBOT_DIM,), "tcp": (14, 36), "both": (FLAT_ROBOT_DIM, 14, 36)}
#: Where the TCP orientation (MuJoCo quaternion w, x, y, z) sits in the flat observation.
EEF_QUAT = slice(17, 21)


def tcp_rotations(obs: np.ndarray) -> np.ndarray:
    """(n, 3, 3) TCP-to-world rotations from the observed unit quaternions."""
    w, x, y, z = np.asarray(obs[:, EEF_QUAT], np.float64).T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], 1)


def world_motion(chunks: np.ndarray, rot: np.ndarray) -> np.ndarray:
    """(n, 3) world-frame TCP displacement (m) commanded by (n, k, A) chunks."""
    return np.einsum("nij,nj->ni", rot, chunks[:, :, :3].sum(1)) * M_PER_UNIT


def act_predictor(path: str):
    return ACTAgent.from_policy_state_dict(load_state(path, "policy")[0]).predict_chunks


def gains(predict, obs: np.ndarray, delta_m: float, shift: str = "panel") -> dict:
    dist = np.linalg.norm(obs[:, FLAT_ROBOT_DIM:FLAT_ROBOT_DIM + 3], axis=1)
    out = {}
    for lo, hi in BANDS:
        o = obs[(dist > lo) & (dist < hi)]
        rot = tcp_rotations(o)
        base = world_motion(predict(o), rot)
        for name, wi in AXES.items():
            shifted = o.copy()
            for first in SHIFTS[shift]:
                shifted[:, first + wi] += delta_m
            change = world_motion(predict(shifted), rot)[:, wi] - base[:, wi]
            out[f"{lo:.2f}-{hi:.2f} m/{name}"] = {
                "states": int(len(o)), "median_mm": round(1000 * float(np.median(change)), 3),
                "mean_abs_mm": round(1000 * float(np.abs(change).mean()), 3)}
    return out


def main(argv=None) -> dict:
    torch.set_num_threads(1)
    p = policy_parser(__doc__)
    p.add_argument("--delta", type=float, default=5.0, help="lateral shift (mm)")
    p.add_argument("--shift", nargs="+", default=["panel"], choices=sorted(SHIFTS),
                   help="what the shift moves (see the module docstring)")
    a = parse_policy_args(p, argv)
    if not 0 < a.delta <= 50:
        p.error(f"--delta {a.delta} must lie in (0, 50] mm")
    eps = _harness_demos(a.env, a.operator, a.demos_dir, a.heldout, 2_000_000)
    obs = np.concatenate([ep.observations[:-1] for ep in eps]).astype(np.float32)
    result = {"heldout_seeds": [eps[0].seed, eps[-1].seed], "delta_mm": a.delta,
              "shifts": a.shift,
              "m_per_action_unit": M_PER_UNIT, "policies": {}}
    preds = {f"act:{f}": act_predictor(f) for f in a.act}
    for f in a.stage1:
        agent = QCFQLAgent.from_state_dict(load_state(f, "stage1")[0]["agent"])
        for policy in ("teacher", "student"):
            preds[f"qcfql-{policy}:{f}"] = (
                lambda o, agent=agent, policy=policy: agent.act(o, deterministic=True,
                                                                policy=policy))
    for name, predict in preds.items():
        result["policies"][name] = {"sha256": sha256_file(name.split(":", 1)[1])}
        for shift in a.shift:
            g = gains(predict, obs, a.delta / 1000, shift)
            result["policies"][name][f"gain_{shift}"] = g
            print(name[-50:], shift, {k: v["median_mm"] for k, v in g.items()}, flush=True)
    result["provenance"] = provenance()
    atomic_write_text(a.out, json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
