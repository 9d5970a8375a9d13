"""The pose read-out: the panel's pose relative to the seat, read from the frozen features.

The seat cameras show the panel's lateral offset to about 0.2 mm (a ridge read-out of the
frozen maps, docs/pixels.md), but a policy's trainable aggregation, trained by the critic
(or the flow teacher too), keeps only about what a constant knows (0.7 / 0.5 mm against 0.68
/ 0.56): the clearance is visible and still lost. The pose read-out keeps it by
construction: a **fixed** linear map of the pixel observation (both views' frozen maps +
proprioception, what :class:`~window_bench.pixels.features.PixelFeatures` returns) to the
panel's position and rotation relative to the seat, fitted once, in-domain, by ridge
regression on rendered frames of scripted-installer episodes whose seat estimate is off by
up to ``align_error_mm`` / ``align_error_deg`` (so the frames spread over millimetre
offsets); privileged labels are used only here, at fit time. The policy then sees
``tanh(pos / mm)`` and ``tanh(rot / deg)`` of the estimate, the state track's fine pose
features (:func:`~window_bench.installer.supervisor.fine_pose_features`) computed from
pixels. It belongs to one backbone and one camera set; both are recorded and checked.

    bench encoder readout --out window_bench/pixels/assets/pose_readout_seat.safetensors --force

A read-out file is safetensors (``weight`` (6, OBS_DIM), ``bias`` (6,), float32) with its
fit record in the metadata; a file that is not one, or that belongs to another backbone or
camera set, is refused in one line (:class:`PoseReadoutError`).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

from window_bench.pixels.encoder import OBS_DIM

#: The read-out the ``pixels-seat`` track uses (``bench encoder readout`` writes it).
DEFAULT_READOUT = Path(__file__).with_name("assets") / "pose_readout_seat.safetensors"
FORMAT = "window-bench pose read-out"
#: What it estimates: the flat state's ``window_pos_rel`` (m) then ``window_rot_rel`` (rad).
TARGETS = ("window_pos_rel", "window_rot_rel")
POSE_DIM = 6
LAMBDAS = (1e-1, 1e0, 1e1, 1e2, 1e3, 1e4)


class PoseReadoutError(ValueError):
    """A file that is not a pose read-out for this backbone and camera set."""


class PoseReadout(nn.Module):
    """Flat pixel observations ``(B, OBS_DIM)`` -> 6 fine pose features in (-1, 1):
    ``tanh`` of the estimated position / ``mm`` and rotation / ``deg``. Buffers only: it is
    fixed, saved with the policy and never trained."""

    def __init__(self, weight: torch.Tensor, bias: torch.Tensor, mm: float, deg: float):
        super().__init__()
        if tuple(weight.shape) != (POSE_DIM, OBS_DIM) or tuple(bias.shape) != (POSE_DIM,):
            raise PoseReadoutError(f"pose read-out: weight {tuple(weight.shape)} and bias "
                                   f"{tuple(bias.shape)}, expected ({POSE_DIM}, {OBS_DIM}) "
                                   f"and ({POSE_DIM},)")
        if not (0 < mm <= 1000 and 0 < deg <= 90):
            raise PoseReadoutError(f"pose read-out scales {mm} mm / {deg} deg: allowed "
                                   f"(0, 1000] mm and (0, 90] deg")
        self.register_buffer("weight", weight.float().clone())
        self.register_buffer("bias", bias.float().clone())
        scale = [1000.0 / mm] * 3 + [1.0 / float(np.deg2rad(deg))] * 3
        self.register_buffer("scale", torch.tensor(scale, dtype=torch.float32))

    @classmethod
    def from_state(cls, state: dict) -> "PoseReadout":
        """From a saved encoder state's ``pose_readout.*`` tensors."""
        scale = state["scale"].double()
        out = cls(state["weight"], state["bias"], 1000.0 / float(scale[0]),
                  float(np.rad2deg(1.0 / float(scale[3]))))
        out.scale.copy_(state["scale"])
        return out

    def estimate(self, obs: torch.Tensor) -> torch.Tensor:
        """The estimated pose (m, rad), ``(B, 6)``."""
        return torch.nn.functional.linear(obs.float(), self.weight, self.bias)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.estimate(obs) * self.scale)


# ---------------------------------------------------------------------------- fitting
def offset_frames(env_id: str, backbone, seeds, align_error_mm: float, align_error_deg: float,
                  near_m: float, cameras: str) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per scripted episode, the pixel observations (exactly as :class:`PixelFeatures` makes
    them) and the 6 target values of every step with the panel within ``near_m`` of the
    seat; only those steps are rendered. The installer's seat estimate is off by a uniform
    draw of up to ``align_error_mm`` per lateral axis and ``align_error_deg`` per axis."""
    import gymnasium as gym

    from window_bench.installer.scripted import ScriptedInstaller
    from window_bench.installer.supervisor import FLAT_SLICES
    from window_bench.pixels.cameras import render_views
    from window_bench.pixels.features import encode_views
    from window_bench.pixels.encoder import VIEWS
    from window_bench.pixels.track import privileged_state

    env = gym.make(env_id, obs_mode="state")
    out = []
    for seed in seeds:
        obs, _ = env.reset(seed=int(seed))
        inst = ScriptedInstaller(env, align_error_mm=align_error_mm,
                                 align_error_deg=align_error_deg, seed=int(seed))
        xs, ys = [], []
        done = False
        while not done:
            flat = privileged_state(env)
            pos = flat[FLAT_SLICES["window_pos_rel"]]
            if np.linalg.norm(pos) < near_m:
                views = dict(zip(VIEWS, render_views(env, cameras)))
                xs.append(encode_views(backbone, {**views, "robot0_proprio": obs["robot0_proprio"]}))
                ys.append(np.concatenate([pos, flat[FLAT_SLICES["window_rot_rel"]]]))
            obs, _, term, trunc, _ = env.step(inst.act())
            done = term or trunc
        if xs:
            out.append((np.stack(xs).astype(np.float32), np.stack(ys).astype(np.float64)))
    env.close()
    return out


def ridge(x_tr: np.ndarray, y_tr: np.ndarray, lambdas) -> list[tuple[np.ndarray, np.ndarray]]:
    """Ridge regressions on standardised inputs, one per penalty in ``lambdas``, solved in the
    dual form (fewer rows than inputs; one eigendecomposition of the kernel serves every
    penalty) and returned in the primal: ``(weight (targets, D), bias (targets,))`` each, on
    the raw inputs."""
    x = x_tr.astype(np.float64)
    mu, sd = x.mean(0), x.std(0) + 1e-6
    a = (x - mu) / sd
    y_mu = y_tr.mean(0)
    evals, evecs = np.linalg.eigh(a @ a.T)
    proj = evecs.T @ (y_tr - y_mu)
    out = []
    for lam in lambdas:
        alpha = evecs @ (proj / (evals + lam)[:, None])
        w = (a.T @ alpha) / sd[:, None]                    # (D, targets)
        out.append((w.T, y_mu - mu @ w))
    return out


def rmse(weight: np.ndarray, bias: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return np.sqrt((((x.astype(np.float64) @ weight.T + bias) - y) ** 2).mean(0))


def fit_pose_readout(out: Path, backbone, backbone_sha256: str, *, env_ids, episodes: int,
                     heldout_episodes: int, align_error_mm: float, align_error_deg: float,
                     near_mm: float, cameras: str, mm: float, deg: float, seed: int,
                     command: str) -> dict:
    """Fit, score on held-out episodes and write the read-out file; returns its record.
    Episodes alternate over ``env_ids``; training seeds ``seed + i``, held-out seeds
    ``seed + 100,000 + i``; each target's ridge penalty is chosen on the last eighth of the
    training episodes."""
    from safetensors.torch import save_file

    t0 = time.perf_counter()
    near = near_mm / 1000.0

    def collect(first: int, n: int) -> list:
        eps = []
        for i, env_id in enumerate(env_ids):
            seeds = [first + k for k in range(n) if k % len(env_ids) == i]
            eps += [(env_id, x, y) for x, y in offset_frames(env_id, backbone, seeds, align_error_mm,
                                                             align_error_deg, near, cameras)]
        return eps

    train = collect(seed, episodes)
    held = collect(seed + 100_000, heldout_episodes)
    collect_s = time.perf_counter() - t0
    n_val = max(1, len(train) // 8)
    fit_part, val_part = train[:-n_val], train[-n_val:]
    stack = lambda eps: (np.concatenate([x for _, x, _ in eps]),  # noqa: E731
                         np.concatenate([y for _, _, y in eps]))
    x_fit, y_fit = stack(fit_part)
    x_val, y_val = stack(val_part)
    y_sd = y_fit.std(0) + 1e-9
    val_err = np.stack([rmse(w, b, x_val, y_val) / y_sd
                        for w, b in ridge(x_fit, y_fit, LAMBDAS)])     # (lambdas, targets)
    lam = [LAMBDAS[i] for i in val_err.argmin(0)]                       # one per target
    x_tr, y_tr = stack(train)
    fits = dict(zip(LAMBDAS, ridge(x_tr, y_tr, LAMBDAS)))
    weight = np.stack([fits[v][0][j] for j, v in enumerate(lam)])
    bias = np.array([fits[v][1][j] for j, v in enumerate(lam)])
    quality = {}
    for env_id in env_ids:
        eps = [e for e in held if e[0] == env_id]
        if not eps:
            continue
        x_te, y_te = stack(eps)
        err = rmse(weight, bias, x_te, y_te)
        quality[env_id] = {"frames": int(len(x_te)), "episodes": len(eps),
                           "rmse_pos_mm": (err[:3] * 1000).round(3).tolist(),
                           "rmse_rot_deg": np.rad2deg(err[3:]).round(3).tolist(),
                           "std_pos_mm": (y_te[:, :3].std(0) * 1000).round(3).tolist(),
                           "std_rot_deg": np.rad2deg(y_te[:, 3:].std(0)).round(3).tolist()}
    record = {"format": FORMAT, "targets": list(TARGETS), "cameras": cameras,
              "backbone_sha256": backbone_sha256, "fine_pose_mm": mm, "fine_pose_deg": deg,
              "env_ids": list(env_ids), "episodes": episodes, "heldout_episodes": heldout_episodes,
              "align_error_mm": align_error_mm, "align_error_deg": align_error_deg,
              "near_mm": near_mm, "seed": seed, "train_frames": int(len(x_tr)),
              "ridge_lambda": lam, "heldout_quality": quality, "command": command,
              "collect_seconds": round(collect_s, 1),
              "fit_seconds": round(time.perf_counter() - t0 - collect_s, 1)}
    out = Path(out)
    tmp = out.with_name(out.name + ".tmp")
    save_file({"weight": torch.from_numpy(np.ascontiguousarray(weight, np.float32)),
               "bias": torch.from_numpy(np.ascontiguousarray(bias, np.float32))}, str(tmp),
              metadata={"window_bench.record": json.dumps(record)})
    tmp.replace(out)
    record["bytes"] = out.stat().st_size
    return record


# ---------------------------------------------------------------------------- loading
def load_pose_readout(path: str | Path, backbone_sha256: str | None = None,
                      cameras: str | None = None) -> tuple[PoseReadout, dict]:
    """The read-out in ``path`` and its record, after checking the file is one (format,
    tensors, shapes, finite values) and, when given, that it was fitted for this backbone
    (sha256 of its weights file) and camera set."""
    from safetensors import SafetensorError, safe_open
    from safetensors.torch import load_file

    path = Path(path)
    if not path.is_file():
        raise PoseReadoutError(f"pose read-out {str(path)!r}: no such file")
    try:
        with safe_open(str(path), framework="pt") as f:
            meta = dict(f.metadata() or {})
        tensors = load_file(str(path))
        record = json.loads(meta.get("window_bench.record", "null"))
    except (SafetensorError, OSError, ValueError) as e:
        raise PoseReadoutError(f"pose read-out {str(path)!r} is not a safetensors read-out "
                               f"file ({str(e).splitlines()[0][:120]})") from None
    if not isinstance(record, dict) or record.get("format") != FORMAT:
        raise PoseReadoutError(f"pose read-out {str(path)!r} has no {FORMAT!r} record")
    if set(tensors) != {"weight", "bias"}:
        raise PoseReadoutError(f"pose read-out {str(path)!r} holds tensors {sorted(tensors)}; "
                               f"expected bias, weight")
    if not all(bool(torch.isfinite(t).all()) for t in tensors.values()):
        raise PoseReadoutError(f"pose read-out {str(path)!r} holds non-finite values")
    if backbone_sha256 is not None and record.get("backbone_sha256") != backbone_sha256:
        raise PoseReadoutError(f"pose read-out {str(path)!r} was fitted for the backbone "
                               f"{str(record.get('backbone_sha256'))[:12]}, not "
                               f"{backbone_sha256[:12]}")
    if cameras is not None and record.get("cameras") != cameras:
        raise PoseReadoutError(f"pose read-out {str(path)!r} was fitted for the camera set "
                               f"{record.get('cameras')!r}, not {cameras!r}")
    mm, deg = record.get("fine_pose_mm"), record.get("fine_pose_deg")
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (mm, deg)):
        raise PoseReadoutError(f"pose read-out {str(path)!r}: fine pose scales {mm!r} / "
                               f"{deg!r} are not numbers")
    return PoseReadout(tensors["weight"], tensors["bias"], float(mm), float(deg)), record
