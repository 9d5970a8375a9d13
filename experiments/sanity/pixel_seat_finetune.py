"""Can in-domain pretraining make the paper's views see the lateral millimetres?

Fine-tunes the shipped backbone (``window_bench/pixels/assets/resnet10_window.safetensors``)
to regress the panel's position relative to the seat (``window_pos_rel``, standardised on
these frames, so a millimetre near the seat counts) from both views of a camera set, on the
states within ``--near-mm`` of the seat of scripted episodes with a deliberate seat-estimate
error (the probe's mechanism, seeds 400,000..., disjoint from the probe's 300,000...). A
linear head on the two flattened 512 x 4 x 4 maps, MSE, AdamW, no pixel shifts (a shift moves
a fixed camera's whole picture, which is the signal here); the head is discarded, the
backbone written as float16 safetensors with the record in its metadata. Then

    python experiments/sanity/pixel_pose_probe.py --offset-episodes 96 --weights OUT
    python experiments/sanity/pixel_pose_probe.py --offset-episodes 96 --weights OUT \\
        --layer layer3 --readout keypoints

says what the fine-tuning bought (same held-out states as every probe row).

    python experiments/sanity/pixel_seat_finetune.py --out enc_near.safetensors \\
        --episodes 96 --max-minutes 25
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

SEED0 = 400_000


def check_args(args) -> str | None:
    """One line naming the first bad value and what is allowed, or ``None``."""
    from window_bench.pixels.cameras import CAMERA_SETS

    if args.cameras not in CAMERA_SETS:
        return f"--cameras {args.cameras!r} must be one of {', '.join(CAMERA_SETS)}"
    if not 8 <= args.episodes <= 1000:
        return f"--episodes {args.episodes} must lie in 8..1000"
    if not 0 < args.max_minutes <= 120:
        return f"--max-minutes {args.max_minutes} must lie in (0, 120]"
    if not 0 < args.lr <= 0.1:
        return f"--lr {args.lr} must lie in (0, 0.1]"
    if not 1 <= args.batch <= 256:
        return f"--batch {args.batch} must lie in 1..256"
    if not Path(args.out).name.endswith(".safetensors"):
        return f"--out {args.out!r} must end in .safetensors"
    return None


def standardise(y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Targets scaled per axis by their own spread (a floor of 0.1 mm): (z, mean, std)."""
    mean, std = y.mean(0), np.maximum(y.std(0), 1e-4)
    return ((y - mean) / std).astype(np.float32), mean, std


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True)
    p.add_argument("--env", default="WindowInstall-A-v0")
    p.add_argument("--cameras", default="paper")
    p.add_argument("--episodes", type=int, default=96)
    p.add_argument("--align-error-mm", type=float, default=10.0)
    p.add_argument("--near-mm", type=float, default=100.0)
    p.add_argument("--max-minutes", type=float, default=25.0)
    p.add_argument("--lr", type=float, default=5e-4)
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    why = check_args(args)
    if why:
        print(f"error: {why}", file=sys.stderr)
        return 2

    import torch
    import torch.nn.functional as F

    sys.path.insert(0, str(Path(__file__).parent))
    from pixel_pose_probe import offset_frames

    from window_bench.pixels.encoder import VIEW_FEATURES
    from window_bench.pixels.weights import DEFAULT_WEIGHTS, load_backbone, save_backbone

    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    t0 = time.perf_counter()
    frames = offset_frames(args.env, range(SEED0, SEED0 + args.episodes), args.align_error_mm,
                           args.near_mm / 1000.0, args.cameras)
    v0 = np.concatenate([f[0] for f in frames])
    v1 = np.concatenate([f[1] for f in frames])
    y, mean, std = standardise(np.concatenate([f[3] for f in frames]))
    collect_s = time.perf_counter() - t0
    print(f"{len(y)} frames of {len(frames)} episodes in {collect_s:.0f} s", flush=True)

    backbone = load_backbone(DEFAULT_WEIGHTS)
    backbone.requires_grad_(True)
    backbone.train()
    head = torch.nn.Linear(2 * VIEW_FEATURES, y.shape[1])
    opt = torch.optim.AdamW([*backbone.parameters(), *head.parameters()], lr=args.lr,
                            weight_decay=1e-4)
    rng = np.random.default_rng(args.seed)
    yt = torch.from_numpy(y)
    losses, steps, t1 = [], 0, time.perf_counter()
    while time.perf_counter() - t1 < 60 * args.max_minutes:
        idx = np.sort(rng.choice(len(y), args.batch, replace=False))
        images = torch.from_numpy(np.stack([v0[idx], v1[idx]], 1).reshape(-1, *v0.shape[1:]))
        pred = head(backbone(images).reshape(len(idx), -1))
        loss = F.mse_loss(pred, yt[idx])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        losses.append(loss.item())
        steps += 1
        if steps % 10 == 0:
            print(f"step {steps} loss {np.mean(losses[-10:]):.3f} "
                  f"({time.perf_counter() - t1:.0f} s)", flush=True)
    record = {"command": "python experiments/sanity/pixel_seat_finetune.py " + " ".join(
                  argv if argv is not None else sys.argv[1:]),
              "objective": "fine-tune the shipped backbone: regress window_pos_rel near the "
                           "seat (standardised on these frames) from both views",
              "init": DEFAULT_WEIGHTS.name, "env": args.env, "cameras": args.cameras,
              "episodes": args.episodes, "seeds": [SEED0, SEED0 + args.episodes - 1],
              "frames": int(len(y)), "steps": steps, "batch": args.batch, "lr": args.lr,
              "final_loss": float(np.mean(losses[-10:])) if losses else None,
              "target_mean_m": mean.tolist(), "target_std_m": std.tolist(),
              "collect_seconds": round(collect_s, 1),
              "train_seconds": round(time.perf_counter() - t1, 1)}
    n = save_backbone(backbone.eval(), args.out, record)
    print(f"wrote {args.out} ({n / 1e6:.2f} MB), {steps} steps, loss "
          f"{record['final_loss']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
