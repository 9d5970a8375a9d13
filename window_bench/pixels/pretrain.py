"""``bench encoder train``: the in-domain default backbone, pretrained on rendered frames.

Machines here cannot download ImageNet weights, so the pixel track ships a ResNet-10 trained
in-domain by this module (the paper's is ImageNet-pretrained; ``--encoder-weights`` loads
such a file instead).

* **Data.** Scripted-installer episodes (``ScriptedInstaller``) on the given envs, half of
  them with exploration noise on the motion commands so that the frames also cover states off
  the expert's path. Every ``every``-th step of an episode is kept: the wrist and side views
  (128 x 128 RGB, rendered by the env itself) and the privileged state at that step.
  Training episodes use seeds ``seed + i``, held-out episodes ``seed + 10_000 + i``: no
  held-out frame comes from a training episode.
* **Objective.** Regress the privileged state the pixel agent does not observe, from both
  views through the shared backbone and a linear head on the two flattened 512 x 4 x 4 maps
  (:data:`TARGETS`: panel pose relative to the seat, TCP position, panel position in the
  TCP frame, suction), each target standardised; mean squared error; random +-4 px shifts.
* **Held-out quality.** RMSE per target group in physical units, beside the RMSE of
  predicting the training mean (what an encoder that sees nothing achieves), and R^2.

The backbone's weights are written as float16 safetensors with this record in the metadata
(:func:`window_bench.pixels.weights.weights_record`); the head is discarded.
"""

from __future__ import annotations

import time

import gymnasium as gym
import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from window_bench.envs.env import mat_to_rotvec
from window_bench.pixels.encoder import VIEW_FEATURES, VIEWS, ResNet10

HELDOUT_SEED_OFFSET = 10_000
#: Regression targets (privileged state) and their groups, in order.
TARGETS = ("panel_dx", "panel_dy", "panel_dz", "panel_rx", "panel_ry", "panel_rz",
           "tcp_x", "tcp_y", "tcp_z", "panel_in_tcp_x", "panel_in_tcp_y", "panel_in_tcp_z",
           "suction")
GROUPS = {"panel position rel. seat (mm)": (slice(0, 3), 1000.0),
          "panel rotation rel. seat (deg)": (slice(3, 6), 180.0 / np.pi),
          "TCP position (mm)": (slice(6, 9), 1000.0),
          "panel position in TCP frame (mm)": (slice(9, 12), 1000.0),
          "suction engaged (0/1)": (slice(12, 13), 1.0)}
SHIFT_PX = 4


def privileged_state(env) -> np.ndarray:
    """The :data:`TARGETS` of the env's current state (reads the simulator, as the scripted
    installer does)."""
    u = env.unwrapped
    p_pos, p_mat = u.panel_pose()
    t_pos, t_mat = u.tcp_pose()
    s_pos, s_mat = u.seated_pose
    return np.concatenate([p_pos - s_pos, mat_to_rotvec(s_mat.T @ p_mat), t_pos,
                           t_mat.T @ (p_pos - t_pos), [float(u.suction_engaged)]])


def collect(env_ids: list[str], episodes: int, seed: int, every: int, max_steps: int = 200,
            noise: float = 0.5, desc: str = "frames") -> dict[str, np.ndarray]:
    """Rendered frames and privileged states of ``episodes`` scripted episodes (env ids
    taken in turn, seeds ``seed .. seed + episodes - 1``, at most ``max_steps`` steps each:
    a noisy episode that fails would otherwise fill the data with 600 steps of one failure).
    Odd episodes add N(0, noise^2) to the motion commands on a random 30 % of steps."""
    from window_bench.installer.scripted import ScriptedInstaller

    envs = {e: gym.make(e, obs_mode="state", max_episode_steps=max_steps) for e in env_ids}
    views = {v: [] for v in VIEWS}
    states, episode = [], []
    for i in tqdm(range(episodes), desc=desc, unit="episode"):
        env_id = env_ids[i % len(env_ids)]
        env, s = envs[env_id], seed + i
        rng = np.random.default_rng(s)
        installer = ScriptedInstaller(env, seed=s)
        obs, _ = env.reset(seed=s)
        installer.reset(seed=s)
        offset, t, done = int(rng.integers(every)), 0, False
        while not done:
            if t % every == offset:
                # The env renders its own views (same cameras as obs_mode="pixels"), only on
                # the kept steps: rendering every step would triple the collection time.
                for v, img in zip(VIEWS, env.unwrapped._render_views()):
                    views[v].append(img)
                states.append(privileged_state(env))
                episode.append(i)
            a = installer.act(obs)
            if i % 2 and rng.random() < 0.3:
                a = a.copy()
                a[:6] = np.clip(a[:6] + noise * rng.standard_normal(6), -1, 1)
            obs, _, term, trunc, _ = env.step(a)
            t, done = t + 1, term or trunc
    for env in envs.values():
        env.close()
    return {**{v: np.stack(x) for v, x in views.items()},
            "state": np.asarray(states, np.float32), "episode": np.asarray(episode)}


class StateHead(torch.nn.Module):
    """Both views' 512 x 4 x 4 maps, flattened and concatenated -> the targets."""

    def __init__(self, n_targets: int):
        super().__init__()
        self.linear = torch.nn.Linear(len(VIEWS) * VIEW_FEATURES, n_targets)

    def forward(self, fmaps: torch.Tensor) -> torch.Tensor:
        return self.linear(fmaps.reshape(-1, len(VIEWS) * VIEW_FEATURES))


def _images(data: dict, idx: np.ndarray) -> torch.Tensor:
    """(2B, H, W, 3) uint8: frame-major, the views of frame j at rows 2j and 2j + 1."""
    return torch.from_numpy(np.stack([data[v][idx] for v in VIEWS], axis=1)
                            .reshape(-1, *data[VIEWS[0]].shape[1:]))


def _shift(images: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """Random +-SHIFT_PX translations with edge replication (DrQ's augmentation)."""
    x = images.permute(0, 3, 1, 2).float()
    n, _, hgt, wid = x.shape
    padded = F.pad(x, (SHIFT_PX,) * 4, mode="replicate")
    dx, dy = torch.randint(0, 2 * SHIFT_PX + 1, (2, n), generator=gen).tolist()
    crops = [padded[i, :, dy[i]:dy[i] + hgt, dx[i]:dx[i] + wid] for i in range(n)]
    return torch.stack(crops).permute(0, 2, 3, 1)


@torch.inference_mode()
def predict(backbone: ResNet10, head: StateHead, data: dict, batch: int = 64) -> np.ndarray:
    backbone.eval()
    out = []
    for start in range(0, len(data["state"]), batch):
        idx = np.arange(start, min(start + batch, len(data["state"])))
        out.append(head(backbone(_images(data, idx))).numpy())
    return np.concatenate(out)


def heldout_quality(pred: np.ndarray, truth: np.ndarray, train_mean: np.ndarray) -> dict:
    """Per group: RMSE of the encoder, RMSE of predicting the training mean, and R^2."""
    rows = {}
    for name, (sl, scale) in GROUPS.items():
        err = (pred[:, sl] - truth[:, sl]) * scale
        base = (train_mean[sl] - truth[:, sl]) * scale
        sst = ((truth[:, sl] - truth[:, sl].mean(0)) ** 2).sum()
        rows[name] = {"rmse": float(np.sqrt((err ** 2).mean())),
                      "rmse_mean_predictor": float(np.sqrt((base ** 2).mean())),
                      "r2": float(1.0 - (err ** 2).sum() / (scale ** 2 * sst))
                      if sst > 0 else None}
    return rows


def train(train_data: dict, epochs: int, batch: int, lr: float, seed: int,
          max_minutes: float | None = None) -> tuple[ResNet10, StateHead, dict]:
    """Supervised pretraining of a fresh backbone (in train mode: BatchNorm statistics are
    learned too); returns the backbone, the head and the training record."""
    torch.manual_seed(seed)
    backbone, head = ResNet10(), StateHead(len(TARGETS))
    for block in (backbone.layer1, backbone.layer2, backbone.layer3, backbone.layer4):
        torch.nn.init.zeros_(block[0].bn2.weight)   # each block starts as its shortcut
    mean = train_data["state"].mean(0)
    std = np.maximum(train_data["state"].std(0), 1e-3)
    y_all = torch.from_numpy((train_data["state"] - mean) / std)
    params = [*backbone.parameters(), *head.parameters()]
    opt = torch.optim.AdamW(params, lr=lr, weight_decay=1e-4)
    n = len(y_all)
    steps = epochs * (n // batch)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=max(steps, 1),
                                                pct_start=0.1)
    gen = torch.Generator().manual_seed(seed)
    rng = np.random.default_rng(seed)
    backbone.train()
    losses, t0, done = [], time.perf_counter(), 0
    bar = tqdm(total=steps, desc="encoder", unit="step")
    for _ in range(epochs):
        order = rng.permutation(n)
        for k in range(n // batch):
            idx = np.sort(order[k * batch:(k + 1) * batch])
            pred = head(backbone(_shift(_images(train_data, idx), gen)))
            loss = F.mse_loss(pred, y_all[idx])
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            losses.append(loss.item())
            done += 1
            bar.update()
            bar.set_postfix(loss=f"{np.mean(losses[-20:]):.3f}")
            if max_minutes is not None and time.perf_counter() - t0 > 60 * max_minutes:
                break
        else:
            continue
        break
    bar.close()
    record = {"steps": done, "planned_steps": steps, "final_loss": float(np.mean(losses[-20:])),
              "train_seconds": round(time.perf_counter() - t0, 1),
              "target_mean": mean.tolist(), "target_std": std.tolist()}
    # the head predicts standardised targets; fold the scaling in for predict()
    with torch.no_grad():
        s = torch.from_numpy(std).float()
        head.linear.weight.mul_(s[:, None])
        head.linear.bias.mul_(s).add_(torch.from_numpy(mean).float())
    return backbone, head, record


def pretrain_encoder(out, env_ids=("WindowInstall-A-v0", "WindowInstall-B-v0"),
                     episodes: int = 64, heldout_episodes: int = 12, every: int = 4,
                     max_steps: int = 200, epochs: int = 2, batch: int = 32,
                     lr: float = 2e-3, seed: int = 0,
                     max_minutes: float | None = None, command: str = "") -> dict:
    """Collect, train, evaluate on held-out episodes and write the backbone to ``out``;
    returns the record stored in the file's metadata."""
    from window_bench.harness.evaluation import provenance
    from window_bench.pixels.weights import save_backbone

    env_ids = list(env_ids)
    t0 = time.perf_counter()
    train_data = collect(env_ids, episodes, seed, every, max_steps, desc="train frames")
    test_data = collect(env_ids, heldout_episodes, seed + HELDOUT_SEED_OFFSET, every,
                        max_steps, desc="held-out frames")
    collect_s = time.perf_counter() - t0
    backbone, head, record = train(train_data, epochs, batch, lr, seed, max_minutes)
    quality = heldout_quality(predict(backbone, head, test_data), test_data["state"],
                              train_data["state"].mean(0))
    record.update({
        "command": command, "objective": "regress the privileged state from both views "
                                         "(MSE on standardised targets)",
        "targets": list(TARGETS), "envs": env_ids, "seed": seed,
        "train": {"episodes": episodes, "seeds": [seed, seed + episodes - 1],
                  "frames": len(train_data["state"])},
        "heldout": {"episodes": heldout_episodes,
                    "seeds": [seed + HELDOUT_SEED_OFFSET,
                              seed + HELDOUT_SEED_OFFSET + heldout_episodes - 1],
                    "frames": len(test_data["state"])},
        "every": every, "max_steps": max_steps, "epochs": epochs, "batch": batch, "lr": lr,
        "collect_seconds": round(collect_s, 1), "heldout_quality": quality,
        "provenance": provenance()})
    record["bytes"] = save_backbone(backbone, out, record)
    return record


def quality_table(record: dict) -> str:
    """The held-out quality as a markdown table."""
    lines = ["| target | RMSE | RMSE of the training mean | R^2 |", "|---|---|---|---|"]
    for name, q in record["heldout_quality"].items():
        r2 = "-" if q["r2"] is None else f"{q['r2']:.2f}"
        lines.append(f"| {name} | {q['rmse']:.2f} | {q['rmse_mean_predictor']:.2f} | {r2} |")
    return "\n".join(lines)
