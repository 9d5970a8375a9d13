"""Does the offline policy on B change without any online data? Stage I continued on D_demo.

Loads a Stage I cache entry (``bench run --stage1-cache DIR``), continues the same demo-only
updates for EXTRA more gradient steps and evaluates the averaged student on the 20 dev seeds
every EVERY updates ([the online phase on B](../../docs/results/diagnoses/b-online.md)).

    python experiments/sanity/offline_continuation.py CACHE/<key>.safetensors RUN/demos 24000 6000

RUN/demos holds the run's ``attentive`` demonstrations of WindowInstall-B-v0. One process, one
thread, about 15 minutes.
"""
import sys, numpy as np, torch
from window_bench.harness.files import load_state
from baselines.qcfql import QCFQLAgent
from window_bench.harness.evaluation import AgentPolicy
from window_bench.envs.wrappers import make_training_env
from window_bench.installer.rollout import Rollout
from window_bench.installer.demos import load_demos
from window_bench.data.replay import ChunkReplay
torch.set_num_threads(1)
cache, demos_dir, extra, every = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
tree, _ = load_state(cache, "stage1")
agent = QCFQLAgent.from_state_dict(tree["agent"])
torch.set_rng_state(tree["torch_rng"])
demos = load_demos(demos_dir, "WindowInstall-B-v0", "attentive")
rb = ChunkReplay(sum(-(-e.T // 10) for e in demos) + 10, 10, agent.config.gamma, seed=123)
for e in demos:
    rb.add_episode(e)
env = make_training_env("WindowInstall-B-v0", None, obs_mode="flat", max_episode_steps=600)
def evaluate(n=20):
    ok = 0
    for i in range(n):
        log = Rollout(env, AgentPolicy(agent, True), env_id="WindowInstall-B-v0").run(seed=100000 + i)
        ok += bool(log.terminated[-1])
    return ok
print("updates +0:", evaluate(), "/ 20", flush=True)
for k in range(1, extra // every + 1):
    for _ in range(every):
        agent.update(rb.sample(256))
    print(f"updates +{k * every}:", evaluate(), "/ 20", flush=True)
