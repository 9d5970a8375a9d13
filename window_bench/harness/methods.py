"""The methods registry: the rows of the paper's Table 1 as named methods with their
component flags, and the run profiles (``paper``, ``cpu``, ``long``, ``smoke``).

``bench methods`` prints Table 1 from :data:`METHODS`. A method names the agent that learns
(``qcfql``; HIL-SERL, ACT and SAC come with their own agents) and which protocol
components are on: demonstrations, offline pretraining (Stage I), the non-updating warm
start (Stage II), online RL updates (Stage III), installer takeovers, and the chunk
horizon ``h``. :data:`AGENTS` maps each agent kind to the class that implements
:class:`window_bench.harness.agent.Agent`, and :data:`PRESETS` names published agent configs
(``--agent-config`` overrides); both are filled from above the harness
(:mod:`window_bench.catalog`). A new method is a new row here (and, for a new learner, a
:func:`register_agent` call), never a change to the harness.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from window_bench.harness.registry import Registry


@dataclass(frozen=True)
class Method:
    name: str
    label: str                 # the paper's row name
    agent: str                 # which learner
    h: int                     # chunk horizon (1 = step-wise)
    demos: bool = True
    offline_pretrain: bool = True
    warm_start: bool = True
    online_updates: bool = True
    interventions: bool = True
    note: str = ""

    @property
    def chunking(self) -> bool:
        return self.h > 1

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


METHODS: dict[str, Method] = {m.name: m for m in (   # in the order of Table 1
    Method("act", "ACT (offline IL)", "act", 10, warm_start=False, online_updates=False,
           interventions=False,
           note="trained on D_demo only; sizes and steps from baselines.act.ACT_PROFILES"),
    Method("sac", "SAC (online RL)", "sac", 1, offline_pretrain=False, warm_start=False,
           interventions=False,
           note="Stable-Baselines3 SAC as is; its replay buffer is pre-filled with D_demo"),
    Method("hil-serl", "HIL-SERL", "hilserl", 1,
           note="RLPD-style learner; takeover transitions also go to the demo buffer"),
    Method("qcfql-stepwise", "Ours (step-wise)", "qcfql", 1, interventions=False),
    Method("qcfql-stepwise-intervention", "Ours (step-wise + intervention)", "qcfql", 1),
    Method("qcfql-offline", "Ours (offline-only)", "qcfql", 10, warm_start=False,
           online_updates=False, interventions=False),
    Method("qcfql-offline-warmstart", "Ours (offline + warm-start)", "qcfql", 10,
           online_updates=False, interventions=False,
           note="warm-start transitions are collected but never trained on"),
    Method("qcfql-no-warmstart", "Ours (w/o warm-start)", "qcfql", 10, warm_start=False),
    Method("qcfql-no-intervention", "Ours (w/o intervention)", "qcfql", 10, interventions=False),
    Method("qcfql", "Ours (complete pipeline)", "qcfql", 10),
)}


#: Agent kind -> the class implementing ``window_bench.harness.agent.Agent``.
AGENTS = Registry("agent kind")
#: Published agent configs: name -> ``--agent-config`` overrides (e.g. the paper's QC-FQL).
PRESETS = Registry("agent preset")


def register_agent(kind: str, cls: type | None = None, *, load=None) -> None:
    """Register the agent class of ``kind``, or ``load``, a function that imports and
    returns it on first use (so that ``bench methods`` loads no learner)."""
    AGENTS.register(kind, cls, load=load)


def agent_class(kind: str) -> type:
    """The agent class registered for ``kind``."""
    return AGENTS.lookup(kind)


def register_preset(name: str, overrides: dict | None = None, *, load=None) -> None:
    """Register a named agent config (its ``--agent-config`` overrides), or ``load``."""
    PRESETS.register(name, overrides, load=load)


def get_preset(name: str) -> dict:
    """The ``--agent-config`` overrides of the preset ``name``."""
    return PRESETS.lookup(name)


def get_method(name: str) -> Method:
    try:
        return METHODS[name]
    except KeyError:
        raise ValueError(f"unknown method {name!r}; choose from {', '.join(METHODS)}") from None


def methods_table() -> str:
    """Table 1 (component activation matrix) as markdown, from the registry."""
    tick = lambda b: "✓" if b else "×"  # noqa: E731
    lines = ["| Method | name | Demo | Online RL updates | Intervention | Warm-start | Chunking (h) |",
             "|---|---|---|---|---|---|---|"]
    for m in METHODS.values():
        lines.append(f"| {m.label} | `{m.name}` | {tick(m.demos)} | {tick(m.online_updates)} | "
                     f"{tick(m.interventions)} | {tick(m.warm_start)} | "
                     f"{tick(m.chunking)} ({m.h}) |")
    return "\n".join(lines)


# ---------------------------------------------------------------------------- profiles
@dataclass(frozen=True)
class Profile:
    """Budget and sizes of one run. ``reductions`` lists every departure from the paper."""

    name: str
    budget_steps: int              # environment steps, warm start included (paper 108,000)
    warm_steps: int                # N_warm (paper 10,000)
    offline_steps: int             # Stage I gradient steps
    utd: float                     # gradient steps per environment step in Stage III
    checkpoint_every: int          # environment steps between evaluations (paper 3,000)
    eval_episodes: int             # M
    eval_workers: int
    n_demos: int                   # |D_demo| (paper 50)
    hidden: tuple[int, ...]
    batch_size: int
    max_episode_steps: int = 600
    reductions: tuple[str, ...] = ()

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


PROFILES: dict[str, Profile] = {p.name: p for p in (
    Profile("paper", budget_steps=108_000, warm_steps=10_000, offline_steps=1_000_000, utd=2,
            checkpoint_every=3_000, eval_episodes=100, eval_workers=2, n_demos=50,
            hidden=(512, 512, 512, 512), batch_size=256,
            reductions=("offline_steps: Table 8 does not state it; 1,000,000 is the QC-FQL "
                        "reference's default",)),
    Profile("cpu", budget_steps=24_000, warm_steps=3_000, offline_steps=20_000, utd=1,
            checkpoint_every=3_000, eval_episodes=20, eval_workers=2, n_demos=50,
            hidden=(256, 256), batch_size=256,
            reductions=("budget 24,000 env steps (0.67 simulated h) instead of 108,000 (3.0 h)",
                        "warm start 3,000 transitions instead of 10,000",
                        "offline pretraining 20,000 gradient steps instead of 1,000,000",
                        "UTD 1 gradient step per env step instead of 2",
                        "MLPs 2 x 256 instead of 4 x 512 (about 6x faster per update here)",
                        "M = 20 evaluation rollouts per checkpoint instead of 100")),
    # The paper's interaction budget with the `cpu` learner: what 3.0 h buys on one core.
    Profile("long", budget_steps=108_000, warm_steps=10_000, offline_steps=20_000, utd=1,
            checkpoint_every=3_600, eval_episodes=20, eval_workers=2, n_demos=50,
            hidden=(256, 256), batch_size=256,
            reductions=("offline pretraining 20,000 gradient steps instead of 1,000,000 (the "
                        "`cpu` Stage I; 24,000 more demo-only updates do not raise B's dev "
                        "success)",
                        "UTD 1 gradient step per env step instead of 2",
                        "MLPs 2 x 256 instead of 4 x 512 (about 6x faster per update here)",
                        "M = 20 evaluation rollouts per checkpoint (every 0.1 simulated h) "
                        "instead of 100")),
    Profile("smoke", budget_steps=400, warm_steps=100, offline_steps=20, utd=0.05,
            checkpoint_every=200, eval_episodes=2, eval_workers=2, n_demos=2,
            hidden=(32, 32), batch_size=16, max_episode_steps=100,
            reductions=("a CI-sized run that exercises every stage; its numbers mean nothing",)),
)}


def get_profile(name: str) -> Profile:
    try:
        return PROFILES[name]
    except KeyError:
        raise ValueError(f"unknown profile {name!r}; choose from {', '.join(PROFILES)}") from None
