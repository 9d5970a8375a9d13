r"""Does ACT's decoder rely on the CVAE latent? On held-out demonstrations, the masked L1
(normalised units) of the chunks predicted with ``z = 0`` (how ACT acts) against those with
``z = mu`` of the CVAE encoder, which sees the demonstrated chunk (how it trains, without
the sampling noise), and the KL of the posterior to the prior. If the latent carried the
chunk's "style", ``z = mu`` would fit clearly better than ``z = 0``; a KL of about 0 means
the posterior has collapsed onto the prior and the decoder cannot use the latent.
The same pass checks that the rollout path (``predict_chunks``) returns exactly the
un-normalised training-pipeline prediction for every held-out observation.

    python experiments/sanity/act_latent_check.py --state /tmp/act15/curve/state.pt \
        --demos-dir /tmp/act15/demos/heldout --out act_latent_check.json

``--state`` is a full ``ACTAgent.state_dict()`` (``python -m baselines.act --save``; a
policy file has no CVAE encoder).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from baselines.act import ACTAgent, _harness_demos, _stack_episodes
from window_bench.harness.evaluation import atomic_write_text, provenance
from window_bench.harness.files import sha256_file


@torch.no_grad()
def latent_check(agent: ACTAgent, episodes) -> dict:
    norm, k = agent.norm, agent.config.chunk
    stack = _stack_episodes(episodes, agent.obs_dim, k)
    agent.model.eval()
    err = {"z0": 0.0, "zmu": 0.0}
    count, kls, path_diff = 0, [], 0.0
    for n, o_off, a_off in zip(stack["lengths"], stack["obs_offset"], stack["act_offset"]):
        steps = np.arange(n)[:, None] + np.arange(k)[None, :]
        raw = stack["obs"][o_off:o_off + n]
        obs_n = agent.normalize_obs(torch.from_numpy(raw))
        is_pad = torch.from_numpy(steps >= n)
        target = ((torch.from_numpy(stack["actions"][a_off + steps]) - norm["act_mean"])
                  / norm["act_std"]).masked_fill(is_pad[..., None], 0.0)
        real = (~is_pad)[..., None].float()
        pred0 = agent.model(obs_n)[0]
        mu, logvar = agent.model.encode(obs_n[:, : agent.model.robot_dim], target, is_pad)
        predmu = agent.model(obs_n, target, is_pad, noise=torch.zeros_like(mu))[0]
        err["z0"] += float(((pred0 - target).abs() * real).sum())
        err["zmu"] += float(((predmu - target).abs() * real).sum())
        count += int(real.sum()) * agent.action_dim
        kls.append((-0.5 * (1 + logvar - mu.pow(2) - logvar.exp())).sum(-1))
        rollout = torch.from_numpy(agent.predict_chunks(raw))
        offline = (pred0 * norm["act_std"] + norm["act_mean"]).clamp(-1.0, 1.0)
        path_diff = max(path_diff, float((rollout - offline).abs().max()))
    kl = torch.cat(kls)
    return {"l1_z0": err["z0"] / count, "l1_zmu": err["zmu"] / count,
            "kl_mean_nats": float(kl.mean()), "kl_max_nats": float(kl.max()),
            "rollout_vs_offline_max_abs_diff": path_diff, "states": int(len(kl))}


def main(argv=None) -> dict:
    torch.set_num_threads(1)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--state", required=True, help="a full ACTAgent.state_dict() (torch.save)")
    p.add_argument("--env", default="WindowInstall-A-v0")
    p.add_argument("--operator", default="average")
    p.add_argument("--demos-dir", required=True, help="Minari root of the held-out demos")
    p.add_argument("--heldout", type=int, default=10)
    p.add_argument("--out", required=True)
    a = p.parse_args(argv)
    if not Path(a.state).is_file():
        p.error(f"--state {a.state}: no such file")
    agent = ACTAgent.from_state_dict(torch.load(a.state, weights_only=True))
    eps = _harness_demos(a.env, a.operator, a.demos_dir, a.heldout, 2_000_000)
    result = {"state": a.state, "sha256": sha256_file(a.state), "grad_steps": agent.grad_steps,
              "config": asdict(agent.config), "heldout_seeds": [eps[0].seed, eps[-1].seed],
              **latent_check(agent, eps), "provenance": provenance()}
    print({k: v for k, v in result.items() if k not in ("config", "provenance")})
    atomic_write_text(a.out, json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
