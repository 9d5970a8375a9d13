"""Does QC-FQL's critic rank the online chunks by what happened to them?

Reads a finished run's ``state.safetensors`` (the full agent and its online replay) and
compares the critic's Q(s, a) of every stored online chunk with its Monte Carlo return
(gamma ** steps-to-acceptance, 0 in an episode that was not accepted): Spearman correlation,
and the AUC of Q for chunks of accepted against failed episodes, for the policy's and the
installer's chunks ([the online phase on B](../../docs/results/diagnoses/b-online.md)).

    python experiments/sanity/critic_rank.py RUN/state.safetensors
"""
import sys, numpy as np, torch
from window_bench.harness.files import load_state
from baselines.qcfql import QCFQLAgent
torch.set_num_threads(1)
tree, _ = load_state(sys.argv[1], "state")
agent = QCFQLAgent.from_state_dict(tree["agent"])
data = tree["online_rb"]["data"]
n = int(tree["online_rb"]["chunks_added"]); n = min(n, len(data["obs"]))
ep = data["episode_id"][:n].numpy(); start = data["chunk_start"][:n].numpy()
acc = data["episode_accepted"][:n].numpy(); take = data["any_takeover"][:n].numpy()
T = {}
for e, s, ns in zip(ep, start, data["n_steps"][:n].numpy()):
    T[e] = max(T.get(e, 0), s + ns)
g = agent.config.gamma
mc = np.array([g ** (T[e] - s - 1) if a else 0.0 for e, s, a in zip(ep, start, acc)])
with torch.no_grad():
    o = agent.normalize(data["obs"][:n].float())
    u = data["actions"][:n].float().reshape(n, -1)
    q = agent.critic(agent.critic_input(o, u)).mean(0).numpy()
from scipy.stats import spearmanr
pol = ~take
print("chunks", n, "episodes", len(T), "accepted share", acc.mean().round(2))
for name, m in (("all", np.ones(n, bool)), ("policy chunks", pol), ("takeover chunks", take)):
    r = spearmanr(q[m], mc[m]).correlation
    # AUC: does Q separate chunks of accepted from failed episodes?
    a, b = q[m & acc], q[m & ~acc]
    auc = (a[:, None] > b[None, :]).mean() if len(a) and len(b) else float("nan")
    print(f"{name}: n {m.sum()}, spearman(Q, MC) {r:.2f}, AUC accepted vs failed {auc:.2f}, "
          f"mean Q {q[m].mean():.3f}, mean MC {mc[m].mean():.3f}")
