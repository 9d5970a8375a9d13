"""``bench encoder``: train the in-domain default backbone, or inspect a weights file.

    bench encoder train --out window_bench/pixels/assets/resnet10_window.safetensors --force
    bench encoder info  PATH      # loads PATH as the pixel track would; prints its record
    bench encoder readout --out window_bench/pixels/assets/pose_readout_seat.safetensors --force
"""

from __future__ import annotations

import json
import os
import sys

from window_bench import cli_args as arg


def _number_in(upper: float):
    """A number in (0, upper]: checked by argparse, before any work."""
    return arg.checked_number(float, lambda v: 0.0 < v <= upper, f"in (0, {upper}]")


def cannot_render() -> str | None:
    """Why this machine cannot render (None when it can), from one frame of an empty model:
    a backend that is set but not installed fails deep inside PyOpenGL or MuJoCo, and here
    before any work rather than after the episodes are collected."""
    import mujoco

    from window_bench.gl import renderer

    try:
        r = renderer(mujoco.MjModel.from_xml_string("<mujoco/>"), 8, 8)
        r.render()
        r.close()
    except Exception as e:  # noqa: BLE001 - an empty model fails to render for the machine only
        why = str(e).splitlines()[0] if str(e) else type(e).__name__
        return why if why.startswith("cannot render") else \
            f"cannot render with MUJOCO_GL={os.environ.get('MUJOCO_GL')}: {why}"
    return None


def cmd_encoder_train(args) -> int:
    import torch

    from window_bench.pixels.pretrain import pretrain_encoder, quality_table

    why = cannot_render()
    if why is not None:   # as bench teleop without a display: one line, exit code 2
        print(f"error: {why}", file=sys.stderr)
        return 2
    torch.set_num_threads(1)
    command = (f"bench encoder train --env {' '.join(args.env)} --episodes {args.episodes} "
               f"--heldout-episodes {args.heldout_episodes} --every {args.every} "
               f"--max-steps {args.max_steps} "
               f"--epochs {args.epochs} --batch {args.batch} --lr {args.lr} --seed {args.seed}"
               + (f" --max-minutes {args.max_minutes}" if args.max_minutes else ""))
    record = pretrain_encoder(args.out, env_ids=args.env, episodes=args.episodes,
                              heldout_episodes=args.heldout_episodes, every=args.every,
                              max_steps=args.max_steps,
                              epochs=args.epochs, batch=args.batch, lr=args.lr,
                              seed=args.seed, max_minutes=args.max_minutes,
                              command=command)
    print(f"wrote {args.out} ({record['bytes'] / 1e6:.2f} MB); {record['train']['frames']} "
          f"training frames, {record['heldout']['frames']} held-out frames, "
          f"{record['steps']} steps in {record['train_seconds']:.0f} s")
    print(quality_table(record))
    return 0


def cmd_encoder_info(args) -> int:
    from window_bench.pixels.pretrain import quality_table
    from window_bench.pixels.weights import WeightsError, load_backbone, weights_record

    try:
        load_backbone(args.path)
        record = weights_record(args.path)
    except (WeightsError, OSError) as e:   # OSError: e.g. a name too long to look up
        print(f"error: {e}", file=sys.stderr)
        return 2
    if not record:
        print(f"{args.path}: a ResNet-10 (timm resnet10t) backbone without a window-bench "
              f"training record (e.g. ImageNet weights)")
        return 0
    print(json.dumps({k: v for k, v in record.items()
                      if k not in ("heldout_quality", "target_mean", "target_std")}, indent=1))
    if "heldout_quality" in record:
        print(quality_table(record))
    return 0


def cmd_encoder_readout(args) -> int:
    import torch

    from window_bench.harness.files import sha256_file
    from window_bench.pixels.pose_readout import fit_pose_readout
    from window_bench.pixels.weights import DEFAULT_WEIGHTS, WeightsError, resolve_backbone

    why = cannot_render()
    if why is not None:
        print(f"error: {why}", file=sys.stderr)
        return 2
    try:
        backbone, _ = resolve_backbone(args.weights)
    except (WeightsError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if (args.policy is None) != (args.policy_episodes == 0):
        print("error: --policy FILE and --policy-episodes N (1-10000) go together",
              file=sys.stderr)
        return 2
    if args.policy is not None:
        from window_bench.harness.evaluation import load_policy_file
        from window_bench.harness.files import RunFileError

        try:
            _, _, meta = load_policy_file(args.policy)
        except (RunFileError, OSError) as e:
            print(f"error: --policy: {str(e).splitlines()[0]}", file=sys.stderr)
            return 2
        if meta["env_id"] != args.env[0] or len(args.env) != 1:
            print(f"error: --policy {args.policy!r} acts on {meta['env_id']}; give "
                  f"--env {meta['env_id']} alone", file=sys.stderr)
            return 2
    torch.set_num_threads(1)
    command = (f"bench encoder readout --env {' '.join(args.env)} --episodes {args.episodes} "
               f"--heldout-episodes {args.heldout_episodes} --align-error-mm "
               f"{args.align_error_mm:g} --align-error-deg {args.align_error_deg:g} --near-mm "
               f"{args.near_mm:g} --cameras {args.cameras} --fine-pose-mm {args.fine_pose_mm:g} "
               f"--fine-pose-deg {args.fine_pose_deg:g} --seed {args.seed}"
               + f" --operator-episodes {args.operator_episodes}"
               + (f" --operator {args.operator}" if args.operator_episodes else "")
               + (f" --policy {args.policy} --policy-episodes {args.policy_episodes}"
                  if args.policy else ""))
    record = fit_pose_readout(
        args.out, backbone, sha256_file(args.weights or DEFAULT_WEIGHTS), env_ids=args.env,
        episodes=args.episodes, heldout_episodes=args.heldout_episodes,
        align_error_mm=args.align_error_mm, align_error_deg=args.align_error_deg,
        near_mm=args.near_mm, cameras=args.cameras, mm=args.fine_pose_mm,
        deg=args.fine_pose_deg, seed=args.seed, command=command,
        operator_episodes=args.operator_episodes, operator=args.operator,
        policy=args.policy, policy_episodes=args.policy_episodes)
    print(f"wrote {args.out} ({record['bytes'] / 1e6:.2f} MB): {record['train_frames']} "
          f"training frames, ridge penalties {record['ridge_lambda']}")
    for env_id, q in record["heldout_quality"].items():
        print(f"{env_id}: held-out RMSE position (mm) {q['rmse_pos_mm']} (spread "
              f"{q['std_pos_mm']}), rotation (deg) {q['rmse_rot_deg']} (spread "
              f"{q['std_rot_deg']}), {q['frames']} frames of {q['episodes']} episodes")
    for env_id, q in (record["heldout_quality_operator"] or {}).items():
        print(f"{env_id}, {args.operator} demonstrating: held-out RMSE position (mm) "
              f"{q['rmse_pos_mm']} (spread {q['std_pos_mm']}), {q['frames']} frames")
    for env_id, q in (record["heldout_quality_policy"] or {}).items():
        print(f"{env_id}, the policy acting: held-out RMSE position (mm) "
              f"{q['rmse_pos_mm']} (spread {q['std_pos_mm']}), {q['frames']} frames")
    return 0


def add_encoder_parser(sub) -> None:
    from window_bench import ENV_IDS

    enc = sub.add_parser("encoder", help="the pixel track's backbone: pretrain it in-domain "
                                         "or inspect a weights file")
    esub = enc.add_subparsers(dest="encoder_command", required=True)
    t = esub.add_parser("train", help="pretrain the ResNet-10 on rendered frames of "
                                      "scripted-installer episodes (docs/pixels.md)")
    arg.add_out_file(t, "weights file to write (.safetensors)", required=True)
    t.add_argument("--env", nargs="+", choices=ENV_IDS,
                   default=["WindowInstall-A-v0", "WindowInstall-B-v0"])
    t.add_argument("--episodes", type=arg.positive, default=64, help="training episodes")
    t.add_argument("--heldout-episodes", type=arg.positive, default=12)
    t.add_argument("--every", type=arg.positive, default=4, help="keep every n-th step's frames")
    t.add_argument("--max-steps", type=arg.positive, default=200, help="steps per episode at most")
    t.add_argument("--epochs", type=arg.positive, default=2)
    t.add_argument("--batch", type=arg.positive, default=32, help="frames per step (2 views each)")
    t.add_argument("--lr", type=_number_in(1.0), default=2e-3)
    t.add_argument("--seed", type=arg.seed, default=0)
    t.add_argument("--max-minutes", type=_number_in(float("inf")), default=None,
                   help="stop training after this many minutes (the record says so)")
    t.set_defaults(func=cmd_encoder_train)
    i = esub.add_parser("info", help="load a weights file as the pixel track would and "
                                     "print its training record")
    i.add_argument("path")
    i.set_defaults(func=cmd_encoder_info)
    from window_bench.installer.operators import OPERATORS
    from window_bench.pixels.cameras import CAMERA_SETS

    r = esub.add_parser("readout", help="fit the fixed pose read-out of the frozen features "
                                        "(the pixels-seat track's; docs/pixels.md)")
    arg.add_out_file(r, "read-out file to write (.safetensors)", required=True)
    r.add_argument("--env", nargs="+", choices=ENV_IDS, default=["WindowInstall-A-v0"])
    r.add_argument("--episodes", type=arg.positive, default=96,
                   help="scripted training episodes (seat estimate off by --align-error-*)")
    r.add_argument("--heldout-episodes", type=arg.positive, default=24)
    r.add_argument("--align-error-mm", type=_number_in(50.0), default=25.0,
                   help="the scripted installer's seat estimate is off by up to this (mm)")
    r.add_argument("--align-error-deg", type=_number_in(10.0), default=1.0)
    r.add_argument("--near-mm", type=_number_in(1000.0), default=100.0,
                   help="fit on the steps with the panel this close to the seat")
    r.add_argument("--cameras", choices=sorted(CAMERA_SETS), default="seat")
    r.add_argument("--fine-pose-mm", type=_number_in(1000.0), default=10.0)
    r.add_argument("--fine-pose-deg", type=_number_in(90.0), default=2.0)
    r.add_argument("--weights", default=None, help="backbone weights (default: the shipped one)")
    r.add_argument("--operator-episodes", type=arg.int_in(0, 10_000), default=64,
                   help="more training episodes of an operator demonstrating (the states "
                        "its demonstrations visit); also scores the read-out on held-out ones")
    r.add_argument("--operator", choices=sorted(OPERATORS), default="average")
    r.add_argument("--policy", default=None,
                   help="a pixels-seat policy file: its own episodes (deterministic, as "
                        "evaluated) join the fit, the states it visits")
    r.add_argument("--policy-episodes", type=arg.int_in(0, 10_000), default=0)
    r.add_argument("--seed", type=arg.seed, default=300_000,
                   help="first training seed (held out: +100,000)")
    r.set_defaults(func=cmd_encoder_readout)
