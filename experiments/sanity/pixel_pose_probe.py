"""How well do the pixel track's frozen features resolve the panel's pose relative to the seat?

The pixel policies carry the panel into the opening and almost never seat it (Pr(T|I)
0-0.03, docs/pixels.md), where the state-track policies, which read the panel's exact pose
relative to the seat (``window_pos_rel``), seat 65-92 % of their insertions. This probe asks
whether that pose is in the pixel observation at all: ridge regressions, fitted on the
demonstrations of 40 episodes and scored on the other 10, from

* the 18 proprioceptive values alone (what the robot knows without cameras),
* those plus the frozen ResNet-10's cached feature maps of both views (2 x 512 x 4 x 4, what
  every pixel learner's trainable aggregation reads),

to ``window_pos_rel`` (3 values, metres). Reported: the held-out RMSE per axis in millimetres,
over all steps and over the steps near the opening (panel within 100 mm of the seat), where
the 2 mm clearance is decided. Linear read-out is a lower bound on what a trained aggregation
can extract (the aggregation is linear in the maps before its LayerNorm and tanh).

    python experiments/sanity/pixel_pose_probe.py \
        --demos leaderboard/runs/demos/WindowInstall-A-v0-average-n50-s2 --seed 2 \
        --offset-episodes 96

``--offset-episodes N`` adds the probe that matters near the seat: N scripted-installer
episodes with a deliberate seat-estimate error (``--align-error-mm``), a quarter held out
(the demonstrations are aligned to under 1 mm there, too little spread to probe).

Which features the offset probe reads (the demonstration probe reads the pixel track's own
cached maps, so the first four need ``--demos`` left out):

* ``--cameras seat``: the two fixed seat cameras on opposite corners of the opening
  (``window_bench.pixels.cameras``) instead of the paper's wrist and side views;
* ``--layer layer3`` / ``layer2``: an earlier, finer map of the backbone;
* ``--readout keypoints``: per channel the spatial-softmax position instead of the map;
* ``--align-error-deg D``: the seat estimate is also off by up to D degrees per axis;
* ``--weights PATH``: another backbone (default: the shipped in-domain one).

    python experiments/sanity/pixel_pose_probe.py --offset-episodes 96 --cameras seat

With any of the first four the episodes run on a state env and only the steps near the seat
are rendered. Without ``--demos`` results go to ``pixel_pose_probe_<env>_<options>.json``
(``..._offset.json`` with no options).

It reads the harness's demonstrations and their pixel re-observation from the pixel demo
cache (recomputed, about 4 min, if the cache is missing); results go to
``experiments/sanity/results/pixel_pose_probe_<env>_s<seed>.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]


def flat_slice(key: str) -> slice:
    """Where ``key`` of the state Dict sits in the 52-float flat observation."""
    import gymnasium as gym

    from window_bench.envs.env import STATE_KEYS

    env = gym.make("WindowInstall-A-v0")
    start = 0
    for k in STATE_KEYS:
        n = int(np.prod(env.observation_space[k].shape))
        if k == key:
            env.close()
            return slice(start, start + n)
        start += n
    env.close()
    raise KeyError(key)


class DualRidge:
    """Ridge regression in its dual form (fewer training rows than features), inputs
    standardised with the training statistics; the kernel is computed once per split, so
    several ``lam`` cost one solve each."""

    def __init__(self, x_tr: np.ndarray, y_tr: np.ndarray, x_te: np.ndarray):
        mu, sd = x_tr.mean(0), x_tr.std(0) + 1e-6
        a, b = (x_tr - mu) / sd, (x_te - mu) / sd
        self.y_mu = y_tr.mean(0)
        self.y = y_tr - self.y_mu
        self.k, self.k_te = a @ a.T, b @ a.T

    def predict(self, lam: float) -> np.ndarray:
        alpha = np.linalg.solve(self.k + lam * np.eye(len(self.k), dtype=self.k.dtype), self.y)
        return self.k_te @ alpha + self.y_mu


LAMBDAS = (1e-1, 1e0, 1e1, 1e2, 1e3, 1e4)


def fit_probe(x_tr, y_tr, x_te, n_val: int) -> tuple[float, np.ndarray]:
    """Ridge probe: lambda chosen on the last ``n_val`` training rows (whole episodes), then
    refitted on all training rows; returns (lambda, predictions for ``x_te``)."""
    val = DualRidge(x_tr[:-n_val], y_tr[:-n_val], x_tr[-n_val:])
    errs = [float(np.sqrt(((val.predict(lam) - y_tr[-n_val:]) ** 2).mean())) for lam in LAMBDAS]
    lam = LAMBDAS[int(np.argmin(errs))]
    del val
    return lam, DualRidge(x_tr, y_tr, x_te).predict(lam)


def offset_episodes(env_id: str, backbone, seeds, align_error_mm: float, near_m: float,
                    align_error_deg: float = 0.0):
    """Pixel observations and ``window_pos_rel`` of every step with the panel within
    ``near_m`` of the seat, from scripted-installer episodes whose estimate of the seat is off
    by up to ``align_error_mm`` per lateral axis (uniform, per episode; contact stalls shrink
    it 4-fold). This spreads the states near the opening over millimetre offsets, which the
    demonstrations (aligned to about 1 mm) barely cover. One (x, y) pair per episode."""
    from window_bench.installer.scripted import ScriptedInstaller
    from window_bench.pixels.track import make_track_env, privileged_state

    pos = flat_slice("window_pos_rel")
    env = make_track_env(env_id, "pixels", backbone)
    out = []
    for seed in seeds:
        obs, _ = env.reset(seed=int(seed))
        inst = ScriptedInstaller(env, align_error_mm=align_error_mm,
                                 align_error_deg=align_error_deg, seed=int(seed))
        xs, ys = [], []
        done = False
        while not done:
            y = privileged_state(env)[pos]
            if np.linalg.norm(y) < near_m:
                xs.append(np.asarray(obs, np.float32)), ys.append(y.astype(np.float32))
            obs, _, term, trunc, _ = env.step(inst.act())
            done = term or trunc
        if xs:
            out.append((np.stack(xs), np.stack(ys)))
    env.close()
    return out


def offset_frames(env_id: str, seeds, align_error_mm: float, near_m: float,
                  cameras: str, align_error_deg: float = 0.0):
    """The episodes of :func:`offset_episodes` on a state env, rendering ``cameras`` only
    on the steps within ``near_m`` of the seat: per episode the two views (uint8), the 18
    proprioceptive values and ``window_pos_rel``."""
    from window_bench.pixels.pose_readout import installer_episodes

    pos = flat_slice("window_pos_rel")
    out = []
    for steps in installer_episodes(env_id, seeds, align_error_mm, align_error_deg, near_m,
                                    cameras):
        near = [(obs, flat, views) for obs, flat, views in steps if views is not None]
        if near:
            out.append((np.stack([v[0] for _, _, v in near]), np.stack([v[1] for _, _, v in near]),
                        np.stack([np.asarray(o["robot0_proprio"], np.float32) for o, _, _ in near]),
                        np.stack([f[pos] for _, f, _ in near]).astype(np.float32)))
    return out


def option_errors(args) -> list[str]:
    """One line per bad option value, naming it and what is allowed."""
    from window_bench.pixels.cameras import CAMERA_SETS
    from window_bench.pixels.readout import LAYERS, READOUTS

    errs = []
    if args.cameras not in CAMERA_SETS:
        errs.append(f"--cameras {args.cameras!r} must be one of {', '.join(CAMERA_SETS)}")
    if args.layer not in LAYERS:
        errs.append(f"--layer {args.layer!r} must be one of {', '.join(LAYERS)}")
    if args.readout not in READOUTS:
        errs.append(f"--readout {args.readout!r} must be one of {', '.join(READOUTS)}")
    if not 0 <= args.align_error_deg <= 10:
        errs.append(f"--align-error-deg {args.align_error_deg} must lie in [0, 10]")
    if args.weights is not None and not Path(args.weights).is_file():
        errs.append(f"--weights {args.weights!r} is not a file (a safetensors ResNet-10 "
                    f"weights file, see `bench encoder info`)")
    return errs


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--env", default="WindowInstall-A-v0")
    p.add_argument("--demos", default=None,
                   help="the harness's demos directory (left out: only the offset probe)")
    p.add_argument("--seed", type=int, default=2, help="the grid seed the demos belong to")
    p.add_argument("--n-demos", type=int, default=50)
    p.add_argument("--test-demos", type=int, default=10)
    p.add_argument("--near-mm", type=float, default=100.0)
    p.add_argument("--offset-episodes", type=int, default=0,
                   help="also probe N scripted episodes with a deliberate alignment error "
                        "(seeds 300,000...: neither the dev nor the test seeds)")
    p.add_argument("--align-error-mm", type=float, default=10.0)
    p.add_argument("--align-error-deg", type=float, default=0.0,
                   help="offset episodes: rotation error of the seat estimate, 0..10 deg")
    p.add_argument("--cameras", default="paper", help="camera set: paper (wrist, side) or seat")
    p.add_argument("--layer", default="layer4", help="backbone layer: layer2, layer3, layer4")
    p.add_argument("--readout", default="maps", help="maps or keypoints (spatial softmax)")
    p.add_argument("--weights", default=None, help="backbone weights (default: the shipped one)")
    args = p.parse_args(argv)
    errs = option_errors(args)
    if errs:
        print(f"error: {errs[0]}", file=sys.stderr)
        return 2
    custom = (args.cameras, args.layer, args.readout) != ("paper", "layer4", "maps") \
        or args.align_error_deg != 0
    if args.demos is None and not args.offset_episodes:
        print("error: --demos DIR or --offset-episodes N (>= 8) is needed: nothing to probe",
              file=sys.stderr)
        return 2
    if args.demos is not None and custom:
        print("error: --demos probes the pixel track's cached wrist/side layer4 maps; leave it "
              "out with --cameras, --layer, --readout or --align-error-deg", file=sys.stderr)
        return 2
    if not 1 <= args.test_demos < args.n_demos:
        print(f"error: --test-demos {args.test_demos} must lie in 1..{args.n_demos - 1}",
              file=sys.stderr)
        return 2

    if args.offset_episodes != 0 and args.offset_episodes < 8:
        print(f"error: --offset-episodes {args.offset_episodes} must be 0 or at least 8 "
              f"(a quarter held out, half of that again for validation)", file=sys.stderr)
        return 2
    if not args.align_error_mm >= 0:
        print(f"error: --align-error-mm {args.align_error_mm} must be >= 0", file=sys.stderr)
        return 2

    import torch

    from window_bench.installer.demos import load_or_collect_demos
    from window_bench.pixels.demo_cache import DEFAULT_SUBDIR, cached_pixel_demos
    from window_bench.pixels.encoder import PROPRIO_DIM
    from window_bench.pixels.weights import resolve_backbone

    torch.set_num_threads(1)
    backbone, label = resolve_backbone(args.weights)
    pos = flat_slice("window_pos_rel")
    out = {"env": args.env, "encoder": label}
    if args.demos is not None:
        demos_root = Path(args.demos)
        eps = load_or_collect_demos(demos_root, args.env, "average", args.n_demos,
                                    seed=1_000_000 + args.seed)[: args.n_demos]
        pix, record = cached_pixel_demos(eps, args.env, backbone, demos_root / DEFAULT_SUBDIR)

        def stack(idx):
            x = np.concatenate([pix[i].observations for i in idx]).astype(np.float32)
            y = np.concatenate([eps[i].observations[:, pos] for i in idx]).astype(np.float32)
            return x, y

        test_idx = list(range(args.n_demos - args.test_demos, args.n_demos))
        x_tr, y_tr = stack(range(args.n_demos - args.test_demos))
        x_te, y_te = stack(test_idx)
        near = np.linalg.norm(y_te, axis=1) < args.near_mm / 1000.0
        inputs = {"proprio (18)": slice(x_tr.shape[1] - PROPRIO_DIM, None),
                  "maps of both views + proprio (16,402)": slice(0, None)}
        out = {"env": args.env, "seed": args.seed, "encoder": label, "pixel_demos": record,
               "train_steps": int(len(x_tr)), "test_steps": int(len(x_te)),
               "test_steps_near": int(near.sum()), "near_mm": args.near_mm,
               "target_std_mm_test": (y_te.std(0) * 1000).round(2).tolist(),
               "target_std_mm_test_near": (y_te[near].std(0) * 1000).round(2).tolist(),
               "probes": {}}
        for name, sl in inputs.items():
            n_val = int(sum(len(pix[i].observations) for i in range(
                args.n_demos - args.test_demos - 5, args.n_demos - args.test_demos)))
            lam, pred = fit_probe(x_tr[:, sl], y_tr, x_te[:, sl], n_val)   # on the last 5 training demos
            rmse = lambda m: (np.sqrt(((pred[m] - y_te[m]) ** 2).mean(0)) * 1000).round(2).tolist()  # noqa: E731
            out["probes"][name] = {"lambda": lam, "rmse_mm_xyz": rmse(slice(None)),
                                   "rmse_mm_xyz_near": rmse(near)}
            print(f"{name}: held-out RMSE (mm, x y z) all steps {out['probes'][name]['rmse_mm_xyz']}, "
                  f"within {args.near_mm:.0f} mm of the seat {out['probes'][name]['rmse_mm_xyz_near']}"
                  f" (lambda {lam:g})")
        print(f"target std (mm): all {out['target_std_mm_test']}, near {out['target_std_mm_test_near']}")
    if args.offset_episodes:
        import time
        t0 = time.perf_counter()
        seeds = range(300_000, 300_000 + args.offset_episodes)
        if custom:
            from window_bench.pixels.readout import readout_features

            frames = offset_frames(args.env, seeds, args.align_error_mm, args.near_mm / 1000.0,
                                   args.cameras, args.align_error_deg)
            eps_off = [(np.concatenate([readout_features(backbone, v0, args.layer, args.readout),
                                        readout_features(backbone, v1, args.layer, args.readout),
                                        prop], 1), y) for v0, v1, prop, y in frames]
        else:
            eps_off = offset_episodes(args.env, backbone, seeds, args.align_error_mm,
                                      args.near_mm / 1000.0)
        dim = eps_off[0][0].shape[1]
        inputs = {"proprio (18)": slice(dim - PROPRIO_DIM, None),
                  (f"{args.readout} ({args.layer}) of the {args.cameras} views + proprio "
                   f"({dim:,})" if custom else "maps of both views + proprio (16,402)"):
                  slice(0, None)}
        n_te = max(1, len(eps_off) // 4)
        x_tr = np.concatenate([x for x, _ in eps_off[:-n_te]])
        y_tr = np.concatenate([y for _, y in eps_off[:-n_te]])
        x_te = np.concatenate([x for x, _ in eps_off[-n_te:]])
        y_te = np.concatenate([y for _, y in eps_off[-n_te:]])
        n_val = int(sum(len(x) for x, _ in eps_off[-n_te - max(1, n_te // 2):-n_te]))
        res = {"episodes": len(eps_off), "test_episodes": n_te, "train_steps": int(len(x_tr)),
               "test_steps": int(len(x_te)), "align_error_mm": args.align_error_mm,
               "align_error_deg": args.align_error_deg, "cameras": args.cameras,
               "layer": args.layer, "readout": args.readout,
               "target_std_mm_test": (y_te.std(0) * 1000).round(2).tolist(),
               "wall_clock_s": round(time.perf_counter() - t0, 1), "probes": {}}
        for name, sl in inputs.items():
            lam, pred = fit_probe(x_tr[:, sl], y_tr, x_te[:, sl], n_val)
            rm = (np.sqrt(((pred - y_te) ** 2).mean(0)) * 1000).round(2).tolist()
            res["probes"][name] = {"lambda": lam, "rmse_mm_xyz": rm}
            print(f"offset episodes, {name}: held-out RMSE (mm, x y z) {rm} (lambda {lam:g})")
        print(f"offset episodes: target std (mm) {res['target_std_mm_test']}, "
              f"{res['train_steps']} train / {res['test_steps']} test steps")
        out["offset_episodes"] = res
    tag = [t for t, on in ((args.cameras, args.cameras != "paper"),
                           (args.layer, args.layer != "layer4"),
                           (args.readout, args.readout != "maps"),
                           (f"rot{args.align_error_deg:g}deg", args.align_error_deg != 0),
                           (f"w-{Path(args.weights or '').stem}", args.weights is not None)) if on]
    name = "_".join([f"pixel_pose_probe_{args.env}"] + [f"s{args.seed}"] * (args.demos is not None)
                    + (tag or ["offset"] * (args.demos is None)))
    dest = REPO / "experiments" / "sanity" / "results" / f"{name}.json"
    tmp = dest.with_suffix(".tmp")
    tmp.write_text(json.dumps(out, indent=1))
    tmp.replace(dest)
    print(f"wrote {dest.relative_to(REPO)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
