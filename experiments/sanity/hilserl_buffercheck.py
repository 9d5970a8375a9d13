"""What ``hil-serl``'s online learner actually sees: the two replay buffers of a saved run.

Reads a run's ``state.safetensors`` (checked against its manifest) and checks, row by row:
that D_demo starts with exactly the demonstrations (observations and actions); what the
takeover segments added to D_demo after them are made of (action range and magnitude, the
vacuum commands in the actor's convention, the panel held or not, rewards, terminals,
discounts); that every takeover row of D_demo is also in D_online (HIL-SERL stores
intervened transitions in both); how the panel is lost in D_online (commanded release vs
not); how many reward rows a 1:1 batch carries; and that acting and learning z-score
observations with the same statistics.

    python experiments/sanity/hilserl_buffercheck.py /tmp/hil_nooff \\
        --json experiments/sanity/results/hilserl_buffercheck_nooff.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from baselines.hilserl import VACUUM_OBS_INDEX, HILSERLAgent
from window_bench.data.replay import mixed_batch
from window_bench.envs.env import VACUUM_THRESHOLD
from window_bench.harness.evaluation import atomic_write_text
from window_bench.harness.files import load_state, verify_files
from window_bench.harness.run import _replay_from_state
from window_bench.installer.demos import load_demos


def describe(rows) -> dict:
    a, o = rows["actions"][:, 0].numpy(), rows["obs"].numpy()
    return {"rows": len(a), "action_min": float(a.min()), "action_max": float(a.max()),
            "pose_abs_mean": [round(float(v), 3) for v in np.abs(a[:, :6]).mean(0)],
            "vacuum_values": sorted({round(float(v), 3) for v in a[:, 6]}),
            "hold_command_frac": float(np.mean(a[:, 6] > VACUUM_THRESHOLD)),
            "panel_held_frac": float(np.mean(o[:, VACUUM_OBS_INDEX] > 0.5)),
            "reward_sum": float(rows["reward"].sum()), "terminal": int(rows["terminal"].sum()),
            "discounts": sorted({round(float(v), 6) for v in rows["discount"].reshape(-1)})}


def main(argv=None) -> dict:
    torch.set_num_threads(1)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run_dir", type=Path)
    p.add_argument("--demos", type=Path, default=Path("runs/sanity/demos_s0"))
    p.add_argument("--env", default="WindowInstall-A-v0")
    p.add_argument("--n-demos", type=int, default=50)
    p.add_argument("--json", type=Path, default=None)
    a = p.parse_args(argv)
    verify_files(a.run_dir, ["state.safetensors"])
    st, _ = load_state(a.run_dir / "state.safetensors", "state")
    agent = HILSERLAgent.from_state_dict(st["agent"])
    demo_rb, online_rb = (_replay_from_state(st[k]) for k in ("demo_rb", "online_rb"))
    D = demo_rb._buffer.storage[:len(demo_rb)]
    O = online_rb._buffer.storage[:len(online_rb)]
    demos = load_demos(a.demos, a.env, "average")[:a.n_demos]
    nd = sum(e.T for e in demos)
    dobs = np.concatenate([e.observations[:-1] for e in demos])
    dact = np.concatenate([e.actions for e in demos])
    tk = D[nd:]
    online_keys = {r.tobytes() for r in O["obs"].numpy()}
    vo, vn = (O[k][:, VACUUM_OBS_INDEX].numpy() > 0.5 for k in ("obs", "next_obs"))
    release = O["actions"][:, 0, 6].numpy() <= VACUUM_THRESHOLD
    batch_rewards = [float(mixed_batch(demo_rb, online_rb, 256, 0.5)["reward"].sum())
                     for _ in range(200)]
    x = O["obs"][:256].float()
    b = mixed_batch(demo_rb, online_rb, 256, 0.5)
    out = {"run_dir": str(a.run_dir), "env_steps": st["counters"]["env_steps"],
           "grad_steps": st["counters"]["grad_steps"],
           "demo_rows_are_the_demos": bool(np.allclose(D["obs"][:nd].numpy(), dobs)
                                           and np.allclose(D["actions"][:nd, 0].numpy(), dact)),
           "demos": describe(D[:nd]), "takeover_rows_in_demo_buffer": describe(tk),
           "online": describe(O),
           "takeover_rows_also_online": int(sum(r.tobytes() in online_keys
                                                for r in tk["obs"].numpy())),
           "online_panel_lost_transitions": int((vo & ~vn).sum()),
           "online_panel_lost_by_release_command": int((vo & ~vn & release).sum()),
           "online_panel_reacquired_transitions": int((~vo & vn).sum()),
           "reward_rows_per_1to1_batch_mean": float(np.mean(batch_rewards)),
           "batches_without_reward_frac": float(np.mean(np.asarray(batch_rewards) == 0)),
           "same_normalisation_acting_and_learning": bool(torch.equal(
               agent._prepare(b)["obs"], agent._normalize(b["obs"].float()))),
           "online_obs_at_clip_frac": float((agent._normalize(x).abs() >= 10).any(1)
                                            .float().mean())}
    print(json.dumps(out, indent=1))
    if a.json is not None:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(a.json, json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
