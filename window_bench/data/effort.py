"""Installer-effort accounting from step logs (paper Section 4.2, "Intervention-related metrics").

* human effort in minutes = takeover steps / 10 Hz / 60, summed over a run;
* takeover count = rising edges of the takeover flag (a takeover spanning many steps or
  chunk boundaries counts once);
* intervention rate = the fraction of 10 Hz action steps executed under takeover, over a
  sliding window of the most recent 20 training episodes (the paper's curve).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from window_bench.data.steplog import STEP_DT, EpisodeLog

RATE_WINDOW = 20   # episodes, as in the paper and HIL-SERL


def takeover_mask(episode: EpisodeLog) -> np.ndarray:
    return np.asarray(episode.provenance) == "takeover"


def takeover_count(episode: EpisodeLog) -> int:
    """Rising edges of the takeover flag within one episode."""
    m = takeover_mask(episode)
    return int(m[0]) + int(np.count_nonzero(m[1:] & ~m[:-1])) if m.size else 0


def effort_minutes(episodes: Sequence[EpisodeLog]) -> float:
    """Cumulative human effort: takeover steps converted to wall-clock minutes."""
    steps = sum(int(takeover_mask(ep).sum()) for ep in episodes)
    return steps * STEP_DT / 60.0


def intervention_rate(episodes: Sequence[EpisodeLog], window: int = RATE_WINDOW) -> np.ndarray:
    """Per episode i: takeover steps / all steps over episodes max(0, i-window+1) .. i."""
    if window < 1:
        raise ValueError(f"window must be >= 1 episode, got {window}")
    take = np.array([takeover_mask(ep).sum() for ep in episodes], dtype=float)
    total = np.array([len(ep.rewards) for ep in episodes], dtype=float)
    if not len(episodes):
        return np.zeros(0)
    ct, cn = np.cumsum(take), np.cumsum(total)
    lo = np.arange(len(episodes)) - window
    ct_lo = np.where(lo >= 0, ct[np.maximum(lo, 0)], 0.0)
    cn_lo = np.where(lo >= 0, cn[np.maximum(lo, 0)], 0.0)
    return (ct - ct_lo) / (cn - cn_lo)


def effort_summary(episodes: Sequence[EpisodeLog]) -> dict:
    """The run-level numbers a results file records."""
    rates = intervention_rate(episodes)
    return {
        "episodes": len(episodes),
        "takeover_steps": int(sum(takeover_mask(ep).sum() for ep in episodes)),
        "takeover_count": int(sum(takeover_count(ep) for ep in episodes)),
        "effort_minutes": effort_minutes(episodes),
        "intervention_rate_last20": float(rates[-1]) if len(rates) else 0.0,
    }
