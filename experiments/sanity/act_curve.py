"""Plot ACT's held-out L1 against gradient steps from ``python -m baselines.act`` JSON files
(one line per file), e.g. the `cpu` curve in docs/act.md:

    python experiments/sanity/act_curve.py curve.json --png docs/img/act_heldout_l1.png
"""

from __future__ import annotations

import argparse
import io
import json

from window_bench.harness.evaluation import atomic_write


def label(result: dict) -> str:
    c = result["config"]
    return (f"d_model {c['d_model']}, FF {c['ff']}, {c['enc_layers']}+{c['dec_layers']} layers "
            f"({result['operator']} demos, seed {result['seed']})")


def main(argv=None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("results", nargs="+", help="JSON files written by python -m baselines.act")
    p.add_argument("--png", required=True)
    a = p.parse_args(argv)
    fig, ax = plt.subplots(figsize=(6.4, 3.8), dpi=120)
    for path in a.results:
        with open(path) as f:
            r = json.load(f)
        rows = r["checkpoints"]
        steps = [c["grad_steps"] for c in rows]
        line, = ax.plot(steps, [c["heldout_l1"] for c in rows], "o-", ms=3,
                        label=f"held-out, {label(r)}")
        ax.plot(steps, [c["l1"] for c in rows], ":", color=line.get_color(),
                label="training batches (dropout, sampled z)")
        print(path, [(s, round(c["heldout_l1"], 4)) for s, c in zip(steps, rows)])
    ax.set_xlabel("gradient steps (batch 8)")
    ax.set_ylabel("chunk L1 (z-scored actions)")
    ax.set_title(f"ACT on {r['env_id']}: held-out chunk L1 (z = 0)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    atomic_write(a.png, lambda f: f.write(buf.getvalue()))


if __name__ == "__main__":
    main()
