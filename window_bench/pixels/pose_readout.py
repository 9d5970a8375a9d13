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

Far from the seat, where the fine read-out was never fitted, a coarse read-out of the
proprioception alone takes its place (:class:`PoseReadout`). A read-out file is safetensors
(``weight`` (6, OBS_DIM), ``bias`` (6,), ``coarse_weight`` (6, 18), ``coarse_bias`` (6,),
float32) with its fit record in the metadata; a file that is not one, or that belongs to another backbone or
camera set, is refused in one line (:class:`PoseReadoutError`).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from window_bench.pixels.encoder import OBS_DIM, PROPRIO_DIM

#: The read-out the ``pixels-seat`` track uses (``bench encoder readout`` writes it).
DEFAULT_READOUT = Path(__file__).with_name("assets") / "pose_readout_seat.safetensors"
FORMAT = "window-bench pose read-out"
#: What it estimates: the flat state's ``window_pos_rel`` (m) then ``window_rot_rel`` (rad).
TARGETS = ("window_pos_rel", "window_rot_rel")
POSE_DIM = 6
#: The linear pose features' units: 0.1 m and 0.1 rad. :class:`PoseReadout` gives 12 values.
POSE_UNITS = 0.1
FEATURES = 2 * POSE_DIM
LAMBDAS = (1e-1, 1e0, 1e1, 1e2, 1e3, 1e4)
#: The fine estimate is fitted this far beyond ``near_mm`` and switched on this far beyond it.
FIT_MARGIN_MM, SWITCH_MARGIN_MM = 25.0, 15.0


class PoseReadoutError(ValueError):
    """A file that is not a pose read-out for this backbone and camera set."""


class PoseReadout(nn.Module):
    """Flat pixel observations ``(B, OBS_DIM)`` -> 12 pose features: the estimated position
    and rotation relative to the seat on a linear scale (in units of :data:`POSE_UNITS`,
    clipped to +-10, as the state track's z-scored ``window_pos_rel`` / ``window_rot_rel``),
    then the fine pose features ``tanh(position / mm)``, ``tanh(rotation / deg)``. (On A's
    dev seeds a state-track policy observing the proprioception and the fine pose features
    seats 7 of 20, with the linear pose too 12, with the whole state 13.)

    Two linear estimates: the **fine** one reads the whole observation (both views' maps and
    the proprioception) and is fitted near the seat, where it resolves tenths of a
    millimetre; the **coarse** one reads the proprioception alone, fitted over whole
    episodes (centimetres). The fine estimate is used where the coarse one puts the panel
    within ``switch_m`` of the seat; farther out, where the fine one was never fitted and is
    meaningless, the coarse one. Buffers only: fixed, saved with the policy, never trained."""

    def __init__(self, weight: torch.Tensor, bias: torch.Tensor, coarse_weight: torch.Tensor,
                 coarse_bias: torch.Tensor, switch_m: float, mm: float, deg: float):
        super().__init__()
        shapes = {"weight": (weight, (POSE_DIM, OBS_DIM)), "bias": (bias, (POSE_DIM,)),
                  "coarse_weight": (coarse_weight, (POSE_DIM, PROPRIO_DIM)),
                  "coarse_bias": (coarse_bias, (POSE_DIM,))}
        for name, (t, shape) in shapes.items():
            if tuple(t.shape) != shape:
                raise PoseReadoutError(f"pose read-out: {name} of shape {tuple(t.shape)}, "
                                       f"expected {shape}")
            self.register_buffer(name, t.float().clone())
        if not (0 < mm <= 1000 and 0 < deg <= 90 and 0 < switch_m <= 1):
            raise PoseReadoutError(f"pose read-out scales {mm} mm / {deg} deg / near "
                                   f"{switch_m} m: allowed (0, 1000] mm, (0, 90] deg, (0, 1] m")
        scale = [1000.0 / mm] * 3 + [1.0 / float(np.deg2rad(deg))] * 3
        self.register_buffer("scale", torch.tensor(scale, dtype=torch.float32))
        self.register_buffer("switch_m", torch.tensor(float(switch_m), dtype=torch.float32))

    @classmethod
    def from_state(cls, state: dict) -> "PoseReadout":
        """From a saved encoder state's ``pose_readout.*`` tensors (bit for bit)."""
        out = cls(state["weight"], state["bias"], state["coarse_weight"], state["coarse_bias"],
                  float(state["switch_m"]), 10.0, 2.0)
        out.scale.copy_(state["scale"])
        out.switch_m.copy_(state["switch_m"])
        return out

    def estimate(self, obs: torch.Tensor) -> torch.Tensor:
        """The estimated pose (m, rad), ``(B, 6)``: fine near the seat, coarse elsewhere."""
        obs = obs.float()
        coarse = F.linear(obs[:, -PROPRIO_DIM:], self.coarse_weight, self.coarse_bias)
        fine = F.linear(obs, self.weight, self.bias)
        near = coarse[:, :3].norm(dim=1, keepdim=True) < self.switch_m
        return torch.where(near, fine, coarse)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        est = self.estimate(obs)
        return torch.cat([(est / POSE_UNITS).clamp(-10.0, 10.0), torch.tanh(est * self.scale)], 1)


# ---------------------------------------------------------------------------- fitting
def installer_episodes(env_id: str, seeds, align_error_mm: float, align_error_deg: float,
                       near_m: float, cameras: str, operator: str | None = None):
    """Per episode (one per seed), every step's ``(obs, flat state, views)``: the state
    observation, the privileged flat state and the two rendered ``cameras`` views (uint8),
    rendered only where the panel is within ``near_m`` of the seat (else ``None``).
    ``operator=None``: the scripted installer, its seat estimate off by a uniform draw of up to
    ``align_error_mm`` per lateral axis and ``align_error_deg`` per axis; an operator's name:
    that operator demonstrating (its own eye error, hand noise and hesitations), as the
    demonstrations are made - the states a policy imitating them visits."""
    import gymnasium as gym

    from window_bench.installer.operators import HumanlikeInstaller
    from window_bench.installer.supervisor import FLAT_SLICES
    from window_bench.installer.scripted import ScriptedInstaller
    from window_bench.pixels.cameras import render_views
    from window_bench.pixels.track import privileged_state

    pos = FLAT_SLICES["window_pos_rel"]
    env = gym.make(env_id, obs_mode="state")
    try:
        for seed in seeds:
            obs, _ = env.reset(seed=int(seed))
            inst = (ScriptedInstaller(env, align_error_mm=align_error_mm,
                                      align_error_deg=align_error_deg, seed=int(seed))
                    if operator is None else HumanlikeInstaller(env, operator, seed=int(seed)))
            steps, done = [], False
            while not done:
                flat = privileged_state(env)
                near = np.linalg.norm(flat[pos]) < near_m
                steps.append((obs, flat, render_views(env, cameras) if near else None))
                obs, _, term, trunc, _ = env.step(inst.act(obs))
                done = term or trunc
            yield steps
    finally:
        env.close()


def offset_frames(env_id: str, backbone, seeds, align_error_mm: float, align_error_deg: float,
                  near_m: float, cameras: str, operator: str | None = None
                  ) -> list[tuple[np.ndarray, ...]]:
    """Per :func:`installer_episodes` episode: the pixel observations (exactly as
    :class:`PixelFeatures` makes them) and the 6 target values of every step with the panel
    within ``near_m`` of the seat, then the proprioception and the targets of every step."""
    from window_bench.installer.supervisor import FLAT_SLICES
    from window_bench.pixels.encoder import VIEWS
    from window_bench.pixels.features import encode_views

    out = []
    for steps in installer_episodes(env_id, seeds, align_error_mm, align_error_deg, near_m,
                                    cameras, operator):
        xs, ys, props, targets = [], [], [], []
        for obs, flat, views in steps:
            y = np.concatenate([flat[FLAT_SLICES[k]] for k in TARGETS])
            props.append(np.asarray(obs["robot0_proprio"], np.float32)), targets.append(y)
            if views is not None:
                xs.append(encode_views(backbone, {**dict(zip(VIEWS, views)),
                                                  "robot0_proprio": obs["robot0_proprio"]}))
                ys.append(y)
        if xs:
            out.append((np.stack(xs).astype(np.float32), np.stack(ys).astype(np.float64),
                        np.stack(props), np.stack(targets).astype(np.float64)))
    return out


def policy_frames(policy_file: str | Path, env_id: str, seeds, near_m: float
                  ) -> list[tuple[np.ndarray, ...]]:
    """:func:`offset_frames`-shaped episodes of a frozen ``pixels-seat`` policy acting as it
    is evaluated (deterministic, no takeovers): the states the policy itself visits. Only the
    steps it observes (its chunk grid) with the panel held and within ``near_m`` of the
    seat; the proprioception and targets are those same steps."""
    from window_bench.harness.evaluation import _eval_rollout, load_policy_file
    from window_bench.installer.supervisor import FLAT_SLICES
    from window_bench.pixels.track import privileged_state

    agent_cls, state, meta = load_policy_file(policy_file)
    if meta["env_id"] != env_id:
        raise PoseReadoutError(f"policy {str(policy_file)!r} was trained on {meta['env_id']}, "
                               f"not {env_id}")
    rollout, env = _eval_rollout(agent_cls, state, env_id, 600)
    out = []
    try:
        for seed in seeds:
            rollout.reset(seed=int(seed), episode_id=int(seed))
            xs, ys = [], []
            while not rollout.done:
                obs = np.asarray(rollout.obs, np.float32)
                if env.unwrapped.suction_engaged and not np.isnan(obs).all():
                    flat = privileged_state(env)
                    y = np.concatenate([flat[FLAT_SLICES[k]] for k in TARGETS])
                    if np.linalg.norm(y[:3]) < near_m:
                        xs.append(obs), ys.append(y)
                rollout.step()
            if xs:
                x, y = np.stack(xs), np.stack(ys).astype(np.float64)
                out.append((x, y, x[:, -PROPRIO_DIM:], y))
    finally:
        env.close()
    return out


def ridge(x_tr: np.ndarray, y_tr: np.ndarray, lambdas) -> list[tuple[np.ndarray, np.ndarray]]:
    """Ridge regressions on standardised inputs, one per penalty in ``lambdas``, returned on
    the raw inputs as ``(weight (targets, D), bias (targets,))`` each. Solved in the dual
    form when there are fewer rows than inputs, else in the primal: one Cholesky solve per
    penalty (a third of n^3 operations each)."""
    x = x_tr.astype(np.float64)
    mu, sd = x.mean(0), x.std(0) + 1e-6
    a = torch.from_numpy((x - mu) / sd)
    y = torch.from_numpy(y_tr - y_tr.mean(0))
    dual = len(a) < a.shape[1]
    gram = a @ a.T if dual else a.T @ a
    rhs = y if dual else a.T @ y
    eye = torch.eye(len(gram), dtype=torch.float64)
    out = []
    for lam in lambdas:
        coef = torch.cholesky_solve(rhs, torch.linalg.cholesky(gram + lam * eye))
        w = ((a.T @ coef) if dual else coef).numpy() / sd[:, None]      # (D, targets)
        out.append((np.ascontiguousarray(w.T), y_tr.mean(0) - mu @ w))
    return out


def rmse(weight: np.ndarray, bias: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return np.sqrt((((x.astype(np.float64) @ weight.T + bias) - y) ** 2).mean(0))


def fit_pose_readout(out: Path, backbone, backbone_sha256: str, *, env_ids, episodes: int,
                     heldout_episodes: int, align_error_mm: float, align_error_deg: float,
                     near_mm: float, cameras: str, mm: float, deg: float, seed: int,
                     command: str, operator_episodes: int = 0,
                     operator: str = "average", policy: str | Path | None = None,
                     policy_episodes: int = 0) -> dict:
    """Fit, score on held-out episodes and write the read-out file; returns its record.
    Episodes alternate over ``env_ids``; training seeds ``seed + i``, held-out seeds
    ``seed + 100,000 + i``. The fine estimate is fitted on the steps within ``near_mm +``
    :data:`FIT_MARGIN_MM` of the seat, each target's ridge penalty chosen on the last eighth
    of the training episodes; the coarse one on every step's proprioception; the read-out
    switches to the fine estimate where the coarse one is within ``near_mm +``
    :data:`SWITCH_MARGIN_MM` (the coarse estimate is off by about 3 mm, so a step within
    ``near_mm`` is read finely and a step read finely lies inside the fitted range). The
    held-out quality is the switched estimate's, as the policy sees it, on the steps within
    ``near_mm``. ``operator_episodes`` more training episodes (seeds ``seed + 50,000 + i``)
    are ``operator`` demonstrating, the states a policy imitating its demonstrations visits;
    then the quality is scored on as many held-out operator episodes as scripted ones too
    (seeds ``seed + 150,000 + i``). ``policy_episodes`` more (seeds ``seed + 60,000 + i``;
    held out ``seed + 160,000 + i``) are a ``pixels-seat`` ``policy`` file acting
    (:func:`policy_frames`): the states that policy visits, which an imitation of the
    demonstrations strays into (tilted several degrees, in contact)."""
    from safetensors.torch import save_file

    from window_bench.harness.files import sha256_file

    t0 = time.perf_counter()
    near = near_mm / 1000.0
    fit_m, switch_m = (near_mm + FIT_MARGIN_MM) / 1000.0, (near_mm + SWITCH_MARGIN_MM) / 1000.0

    def collect(first: int, n: int, by: str | None = None) -> list:
        eps = []
        for i, env_id in enumerate(env_ids):
            seeds = [first + k for k in range(n) if k % len(env_ids) == i]
            eps += [(env_id, *e) for e in offset_frames(env_id, backbone, seeds, align_error_mm,
                                                        align_error_deg, fit_m, cameras, by)]
        return eps

    scripted = collect(seed, episodes)
    held = collect(seed + 100_000, heldout_episodes)
    shown = collect(seed + 50_000, operator_episodes, operator) if operator_episodes else []
    held_shown = collect(seed + 150_000, heldout_episodes, operator) if operator_episodes else []

    def acted(first: int, n: int) -> list:
        seeds = range(first, first + n)
        return [(env_ids[0], *e) for e in policy_frames(policy, env_ids[0], seeds, fit_m)]

    by_policy = acted(seed + 60_000, policy_episodes) if policy_episodes else []
    held_policy = acted(seed + 160_000, heldout_episodes) if policy_episodes else []
    collect_s = time.perf_counter() - t0

    def stack(eps, i: int) -> np.ndarray:
        return np.concatenate([e[i] for e in eps])

    # Each source's last eighth of episodes chooses the penalties.
    fit_eps, val_eps = [], []
    for eps in (scripted, shown, by_policy):
        n_val = max(1, len(eps) // 8) if len(eps) > 1 else 0
        fit_eps, val_eps = fit_eps + eps[:len(eps) - n_val], val_eps + eps[len(eps) - n_val:]
    train = scripted + shown + by_policy
    x_fit, y_fit = stack(fit_eps, 1), stack(fit_eps, 2)
    x_val, y_val = stack(val_eps, 1), stack(val_eps, 2)
    val_err = np.stack([rmse(w, b, x_val, y_val) / (y_fit.std(0) + 1e-9)
                        for w, b in ridge(x_fit, y_fit, LAMBDAS)])     # (lambdas, targets)
    lam = [LAMBDAS[i] for i in val_err.argmin(0)]                       # one per target
    fits = dict(zip(LAMBDAS, ridge(stack(train, 1), stack(train, 2), LAMBDAS)))
    weight = np.stack([fits[v][0][j] for j, v in enumerate(lam)])
    bias = np.array([fits[v][1][j] for j, v in enumerate(lam)])
    [(coarse_w, coarse_b)] = ridge(stack(train, 3), stack(train, 4), [1e-3])
    f32 = lambda a: torch.from_numpy(np.ascontiguousarray(a, np.float32))  # noqa: E731
    tensors = {"weight": f32(weight), "bias": f32(bias), "coarse_weight": f32(coarse_w),
               "coarse_bias": f32(coarse_b)}
    readout = PoseReadout(*tensors.values(), switch_m, mm, deg)
    record = {"format": FORMAT, "targets": list(TARGETS), "cameras": cameras,
              "backbone_sha256": backbone_sha256, "fine_pose_mm": mm, "fine_pose_deg": deg,
              "near_mm": near_mm, "fit_mm": near_mm + FIT_MARGIN_MM,
              "switch_mm": near_mm + SWITCH_MARGIN_MM, "env_ids": list(env_ids),
              "episodes": episodes, "heldout_episodes": heldout_episodes,
              "align_error_mm": align_error_mm, "align_error_deg": align_error_deg,
              "seed": seed, "train_frames": int(len(stack(train, 1))), "ridge_lambda": lam,
              "operator": operator if operator_episodes else None,
              "operator_episodes": operator_episodes,
              "heldout_quality": heldout_quality(readout, held, env_ids, near),
              "heldout_quality_operator": (heldout_quality(readout, held_shown, env_ids, near)
                                           if operator_episodes else None),
              "policy_sha256": sha256_file(policy) if policy_episodes else None,
              "policy_episodes": policy_episodes,
              "heldout_quality_policy": (heldout_quality(readout, held_policy, env_ids[:1], near)
                                         if policy_episodes else None),
              "command": command, "collect_seconds": round(collect_s, 1),
              "fit_seconds": round(time.perf_counter() - t0 - collect_s, 1)}
    return write_readout(out, tensors, record)


def heldout_quality(readout: PoseReadout, held: list, env_ids, near: float) -> dict:
    """Per env: the read-out's RMSE (as the policy sees it) on the held-out steps within
    ``near`` m of the seat, the targets' spread there, and the coarse estimate's RMSE over
    every step. ``held``: :func:`offset_frames` episodes, each led by its env id."""
    def stack(eps, i: int) -> np.ndarray:
        return np.concatenate([e[i] for e in eps])

    quality = {}
    for env_id in env_ids:
        eps = [e for e in held if e[0] == env_id]
        if not eps:
            continue
        y_te = stack(eps, 2)
        inside = np.linalg.norm(y_te[:, :3], axis=1) < near
        x_te, y_te = stack(eps, 1)[inside], y_te[inside]
        err = np.sqrt(((readout.estimate(torch.from_numpy(x_te)).double().numpy() - y_te) ** 2)
                      .mean(0))
        coarse = rmse(readout.coarse_weight.double().numpy(), readout.coarse_bias.double().numpy(),
                      stack(eps, 3), stack(eps, 4))
        quality[env_id] = {"frames": int(len(x_te)), "episodes": len(eps),
                           "rmse_pos_mm": (err[:3] * 1000).round(3).tolist(),
                           "rmse_rot_deg": np.rad2deg(err[3:]).round(3).tolist(),
                           "std_pos_mm": (y_te[:, :3].std(0) * 1000).round(3).tolist(),
                           "std_rot_deg": np.rad2deg(y_te[:, 3:].std(0)).round(3).tolist(),
                           "coarse_rmse_pos_mm_all_steps": (coarse[:3] * 1000).round(1).tolist()}
    return quality


def write_readout(out: Path, tensors: dict, record: dict) -> dict:
    """Write a read-out file (atomically, mode 644); returns its record with its size."""
    from safetensors.torch import save_file

    out = Path(out)
    tmp = out.with_name(out.name + ".tmp")
    save_file(tensors, str(tmp), metadata={"window_bench.record": json.dumps(record)})
    tmp.replace(out)
    out.chmod(0o644)
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
    names = ("weight", "bias", "coarse_weight", "coarse_bias")
    if set(tensors) != set(names):
        raise PoseReadoutError(f"pose read-out {str(path)!r} holds tensors {sorted(tensors)}; "
                               f"expected {', '.join(sorted(names))}")
    if not all(bool(torch.isfinite(t).all()) for t in tensors.values()):
        raise PoseReadoutError(f"pose read-out {str(path)!r} holds non-finite values")
    if backbone_sha256 is not None and record.get("backbone_sha256") != backbone_sha256:
        raise PoseReadoutError(f"pose read-out {str(path)!r} was fitted for the backbone "
                               f"{str(record.get('backbone_sha256'))[:12]}, not "
                               f"{backbone_sha256[:12]}")
    if cameras is not None and record.get("cameras") != cameras:
        raise PoseReadoutError(f"pose read-out {str(path)!r} was fitted for the camera set "
                               f"{record.get('cameras')!r}, not {cameras!r}")
    mm, deg, switch = (record.get(k) for k in ("fine_pose_mm", "fine_pose_deg", "switch_mm"))
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (mm, deg, switch)):
        raise PoseReadoutError(f"pose read-out {str(path)!r}: fine pose scales {mm!r} / "
                               f"{deg!r} / switch {switch!r} are not numbers")
    return PoseReadout(*(tensors[k] for k in names), switch / 1000.0, float(mm),
                       float(deg)), record
