r"""Does a trained pixel policy keep what its frozen features see? Near the seat (panel within
100 mm of it), ridge-regress the panel's offset from the seat (``window_pos_rel``) on the
demonstrations' states twice: from the policy's learnt 82-value embedding (its per-view
aggregation + proprioception, what its MLPs read) and from the frozen feature maps +
proprioception it was computed from. Episodes split 3:1 into fit and held out; RMSE in mm on
the held-out states, beside a constant (the fit states' mean).

    python experiments/sanity/pixel_embedding_probe.py RUN/policies/step_0000000.safetensors \
        --demos DEMOS --cache DEMOS/pixel_cache \
        --out experiments/sanity/results/pixel_embedding_probe_seat_A_s0.json

The demonstrations must be those the policy learnt from (the same re-observed pixel demos:
the camera set is read from the policy file).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from rollout_args import env_errors, out_errors  # noqa: E402

#: Ridge strengths tried (on z-scored inputs); the best held-out one is reported per input.
LAMBDAS = (1.0, 10.0, 100.0, 1000.0, 10000.0)
NEAR_SEAT_M = 0.1


def ridge_rmse(x: np.ndarray, y: np.ndarray, fit: np.ndarray, lam: float) -> np.ndarray:
    """Held-out RMSE per target column of a ridge fit on the ``fit`` rows (dual form, so
    16,000 map values cost no more than 82)."""
    mu, sd = x[fit].mean(0), x[fit].std(0) + 1e-6
    z = ((x - mu) / sd).astype(np.float64)
    ym = y[fit].mean(0)
    a = np.linalg.solve(z[fit] @ z[fit].T + lam * np.eye(int(fit.sum())), y[fit] - ym)
    pred = z[~fit] @ (z[fit].T @ a) + ym
    return np.sqrt(((pred - y[~fit]) ** 2).mean(0))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("policy", help="a policies/step_*.safetensors file of a pixel agent")
    p.add_argument("--env", default="WindowInstall-A-v0")
    p.add_argument("--demos", required=True, help="the demonstrations directory of the run")
    p.add_argument("--operator", default="average")
    p.add_argument("--cache", required=True, help="the pixel-demo cache the run used")
    p.add_argument("--out", required=True, help="JSON file to write (not overwritten)")
    args = p.parse_args(argv)
    errs = env_errors(args.env) + out_errors(args.out)
    if errs:
        print("error: " + "; ".join(errs), file=sys.stderr)
        return 2
    from window_bench.envs import scene as S
    from window_bench.harness.evaluation import load_policy_file, provenance
    from window_bench.installer.demos import load_or_collect_demos
    from window_bench.installer.supervisor import FLAT_SLICES
    from window_bench.pixels.cameras import saved_cameras
    from window_bench.pixels.demo_cache import cached_pixel_demos
    from window_bench.pixels.weights import resolve_backbone

    torch.set_num_threads(1)
    cls, policy, _ = load_policy_file(args.policy)
    if getattr(cls, "track", "state") != "pixels":
        print(f"error: {args.policy} is not a pixel policy", file=sys.stderr)
        return 2
    agent = cls.from_policy_state_dict(policy)
    cameras = saved_cameras(policy)
    raw = load_or_collect_demos(Path(args.demos), args.env, args.operator, 50,
                                seed=1_000_000, progress=False)[:50]
    backbone, _ = resolve_backbone(policy.get("encoder_weights"))
    pix, _ = cached_pixel_demos(raw, args.env, backbone, args.cache, False, cameras=cameras)
    emb, maps, y, episode = [], [], [], []
    for i, (r, q) in enumerate(zip(raw, pix)):
        rel = r.observations[:, FLAT_SLICES["window_pos_rel"]]
        idx = np.flatnonzero(np.linalg.norm(rel, axis=1) < NEAR_SEAT_M)
        if len(idx):
            obs = q.observations[idx].astype(np.float32)
            emb.append(agent.embed(obs).numpy())
            maps.append(obs)
            y.append(rel[idx])
            episode.append(np.full(len(idx), i))
    emb, maps, y, episode = map(np.concatenate, (emb, maps, y, episode))
    fit = episode % 4 != 0
    axes = {"x": 0, "depth": 1, "z": 2}
    assert np.allclose(np.abs(S.INSERTION_AXIS), [0, 1, 0])   # depth is the y column
    out = {"policy": str(args.policy), "cameras": cameras, "env_id": args.env,
           "states": {"fit": int(fit.sum()), "held_out": int((~fit).sum())},
           "constant_mm": {a: round(float(np.sqrt(((y[~fit, j] - y[fit, j].mean()) ** 2)
                                                  .mean()) * 1000), 3)
                           for a, j in axes.items()}}
    for name, x in (("embedding", emb), ("maps_proprio", maps)):
        errs = {lam: ridge_rmse(x, y, fit, lam) for lam in LAMBDAS}
        best = min(errs, key=lambda lam: errs[lam][[0, 2]].mean())   # best on the lateral axes
        out[name + "_mm"] = {a: round(float(errs[best][j]) * 1000, 3) for a, j in axes.items()}
        out[name + "_lambda"] = best
        print(f"{name}: " + " / ".join(f"{a} {out[name + '_mm'][a]:.2f}" for a in axes)
              + f" mm (lambda {best:g}); constant "
              + " / ".join(f"{out['constant_mm'][a]:.2f}" for a in axes), flush=True)
    out["provenance"] = provenance()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
