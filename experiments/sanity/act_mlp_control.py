r"""Is the transformer pathway what makes our ACT ignore the panel's offset? The same
ACTAgent pipeline (normaliser, chunk sampler, masked L1 loss, AdamW, ``z = 0`` acting,
temporal ensembling, the harness's rollout) with only the network swapped: ``--arch mlp``
is a plain deterministic MLP chunk regressor on the whole z-scored state (no CVAE, no
tokens, no attention), ``--arch act`` the ACT network of ``--profile``. Trained on the same
demonstrations, then: held-out L1, the lateral feedback gain (``act_feedback_gain.py``) and,
optionally, closed-loop success on dev seeds and on the training starts.

    # MLP 2 x 256 (the flow teacher's width), L1, batch 256, 4,000 steps; gain only
    python experiments/sanity/act_mlp_control.py --arch mlp --demos-dir /tmp/act15/demos \
        --steps 4000 --batch 256 --lr 3e-4 --out mlp_l1.json
    # ... and 20 dev seeds + 20 training starts with temporal ensembling
    python experiments/sanity/act_mlp_control.py --arch mlp --demos-dir /tmp/act15/demos \
        --steps 4000 --batch 256 --lr 3e-4 --dev 20 --train-starts 20 --out mlp_l1.json

If the MLP imitates where ACT does not, the fault is in the transformer pathway; if it fails
as ACT does while flow BC succeeds, it is the regression (a deterministic average of the
demonstrations) and not our ACT code.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import torch
from torch import nn

from baselines.act import ACT_PROFILES, ACTAgent, _collect_demos, _harness_demos, _rollout
from window_bench.harness.evaluation import atomic_write_text, provenance
from window_bench.harness.seeds import eval_seeds

sys.path.insert(0, str(Path(__file__).resolve().parent))
from act_feedback_gain import gains  # noqa: E402
from act_trainset import summarize  # noqa: E402


class MLPChunk(nn.Module):
    """Deterministic chunk regressor with ACTModel's interface: ``forward(obs, actions=None,
    is_pad=None, noise=None) -> (pred (B, k, A), mu, logvar)``; ``mu = logvar = 0`` (no
    latent, so the KL term is exactly 0)."""

    def __init__(self, obs_dim: int, action_dim: int, chunk: int, hidden=(256, 256),
                 latent_dim: int = 1):
        super().__init__()
        dims, layers = (obs_dim, *hidden), []
        for i, o in zip(dims[:-1], dims[1:]):
            layers += [nn.Linear(i, o), nn.GELU()]
        self.net = nn.Sequential(*layers, nn.Linear(dims[-1], chunk * action_dim))
        self.k, self.a, self.latent_dim = chunk, action_dim, latent_dim

    def forward(self, obs, actions=None, is_pad=None, noise=None):
        pred = self.net(obs).view(-1, self.k, self.a)
        zero = pred.new_zeros(obs.shape[0], self.latent_dim)
        return pred, (None if actions is None else zero), (None if actions is None else zero)


def make_agent(arch: str, obs_dim: int, profile: str, overrides: dict, hidden, seed: int):
    cfg = replace(ACT_PROFILES[profile], **overrides)
    agent = ACTAgent(obs_dim, config=cfg, seed=seed)
    if arch == "mlp":
        torch.manual_seed(seed)
        agent.model = MLPChunk(obs_dim, agent.action_dim, cfg.chunk, hidden, cfg.latent_dim)
        agent.optimizer = torch.optim.AdamW(agent.model.parameters(), lr=cfg.lr,
                                            weight_decay=cfg.weight_decay)
    return agent


def main(argv=None) -> dict:
    torch.set_num_threads(1)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--arch", choices=("mlp", "act"), default="mlp")
    p.add_argument("--profile", default="cpu", choices=sorted(ACT_PROFILES))
    p.add_argument("--hidden", type=int, nargs="+", default=[256, 256])
    p.add_argument("--loss", choices=("l1", "l2"), default="l1")
    p.add_argument("--steps", type=int, default=4000)
    p.add_argument("--batch", type=int, default=None, help="default: the profile's")
    p.add_argument("--lr", type=float, default=None, help="default: the profile's")
    p.add_argument("--cvae", choices=("true", "false"), default=None,
                   help="ACT only; default: the profile's (the MLP has none)")
    p.add_argument("--dropout", type=float, default=None, help="ACT only")
    p.add_argument("--env", default="WindowInstall-A-v0")
    p.add_argument("--operator", default="average",
                   help="operator model of the harness's D_demo, or 'scripted'")
    p.add_argument("--demos-dir", default=None,
                   help="Minari root (held-out under heldout/); not for 'scripted'")
    p.add_argument("--train-demos", type=int, default=50)
    p.add_argument("--heldout", type=int, default=10)
    p.add_argument("--dev", type=int, default=0)
    p.add_argument("--train-starts", type=int, default=0)
    p.add_argument("--modes", nargs="+", default=["temporal_ensembling"],
                   choices=["temporal_ensembling", "chunked"])
    p.add_argument("--max-steps", type=int, default=None,
                   help="episode step limit (default: the environment's, 600)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True)
    a = p.parse_args(argv)
    if a.operator != "scripted" and a.demos_dir is None:
        p.error(f"--operator {a.operator} needs --demos-dir")
    if (a.steps < 1 or a.dev < 0 or not 0 <= a.train_starts <= a.train_demos
            or (a.max_steps is not None and a.max_steps < 1)):
        p.error(f"--steps {a.steps} >= 1, --dev {a.dev} >= 0, --train-starts "
                f"{a.train_starts} in [0, --train-demos], --max-steps {a.max_steps} >= 1")
    if a.operator == "scripted":   # the deterministic scripted installer, seeds 0, 1, ...
        demos = _collect_demos(a.env, range(a.train_demos))
        heldout = _collect_demos(a.env, range(a.train_demos, a.train_demos + a.heldout))
    else:
        demos = _harness_demos(a.env, a.operator, a.demos_dir, a.train_demos,
                               1_000_000 + a.seed)
        heldout = _harness_demos(a.env, a.operator, str(Path(a.demos_dir) / "heldout"),
                                 a.heldout, 2_000_000)
    over = {"loss": a.loss}
    if a.arch == "mlp":
        over.update(cvae=False, dropout=0.0)
    for key, v in (("batch_size", a.batch), ("lr", a.lr), ("dropout", a.dropout),
                   ("cvae", None if a.cvae is None else a.cvae == "true")):
        if v is not None:
            over[key] = v
    agent = make_agent(a.arch, demos[0].observations.shape[1], a.profile, over,
                       tuple(a.hidden), a.seed)
    t0 = time.perf_counter()
    logs = agent.train_offline(demos, a.steps)
    result = {"arch": a.arch, "hidden": a.hidden if a.arch == "mlp" else None,
              "config": asdict(agent.config), "seed": a.seed, "grad_steps": a.steps,
              "parameters": sum(q.numel() for q in agent.model.parameters()),
              "train_s": round(time.perf_counter() - t0, 1),
              "final_loss": float(np.mean([g["loss"] for g in logs[-100:]])),
              "heldout_l1": agent.chunk_l1(heldout), "train_l1": agent.chunk_l1(demos)}
    obs = np.concatenate([ep.observations[:-1] for ep in heldout]).astype(np.float32)
    result["gain_panel"] = gains(agent.predict_chunks, obs, 0.005, "panel")
    print({k: result[k] for k in ("arch", "train_s", "final_loss", "heldout_l1", "train_l1")})
    print("gain", {k: v["median_mm"] for k, v in result["gain_panel"].items()}, flush=True)
    sets = {}
    if a.train_starts:
        sets["train_starts"] = [ep.seed for ep in demos[: a.train_starts]]
    if a.dev:
        sets["dev"] = eval_seeds("dev", a.dev)
    for set_name, seeds in sets.items():
        for mode in a.modes:
            agent.config = replace(agent.config, temporal_ensembling=mode == "temporal_ensembling")
            t0 = time.perf_counter()
            rows = _rollout(agent, a.env, seeds, a.max_steps)
            s = result[f"{set_name}/{mode}"] = {**summarize(rows), "rows": rows,
                                                "wall_s": round(time.perf_counter() - t0, 1)}
            print(f"{set_name:12s} {mode:20s} {s['successes']}/{s['episodes']} Wilson "
                  f"{s['wilson95']} {s['failure_modes']} closest {s['closest_mm_median']} "
                  f"lateral {s['lateral_at_closest_mm_median']}", flush=True)
            atomic_write_text(a.out, json.dumps({**result, "provenance": provenance()},
                                                indent=1))
    result["provenance"] = provenance()
    atomic_write_text(a.out, json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
