"""Installer-effort accounting: minutes, takeover count (rising edges), intervention rate."""

import numpy as np
import pytest

from window_bench.data.effort import (effort_minutes, effort_summary, intervention_rate,
                                 takeover_count)
from window_bench.data.steplog import EpisodeLog


def log(provenance, end="truncated"):
    T = len(provenance)
    term, trunc = np.zeros(T, bool), np.zeros(T, bool)
    (term if end == "terminated" else trunc)[-1] = True
    return EpisodeLog(
        observations=np.zeros((T + 1, 2), np.float32), actions=np.zeros((T, 7), np.float32),
        rewards=np.zeros(T, np.float32), terminated=term, truncated=trunc,
        provenance=list(provenance),
        takeover_kind=["safety" if p == "takeover" else "" for p in provenance],
        episode_id=0, env_id="WindowInstall-A-v0", seed=0)


P, X = "policy", "takeover"


@pytest.mark.parametrize("prov,count", [
    ([P, P, P], 0),
    ([X, X, X], 1),                 # one takeover from the first step
    ([P, X, X, P, X, P], 2),        # two separate takeovers
    ([P, X, P, X, P, X], 3),
    ([X, P, P, P, P, X], 2),
])
def test_takeover_count_is_rising_edges(prov, count):
    assert takeover_count(log(prov)) == count


def test_effort_minutes_converts_10hz_steps():
    eps = [log([X] * 300 + [P] * 300), log([P] * 10 + [X] * 300)]
    assert effort_minutes(eps) == pytest.approx(600 * 0.1 / 60)   # 1.0 minute
    assert effort_minutes([log([P] * 5)]) == 0.0


def test_intervention_rate_uses_the_last_20_episodes():
    # Episode i has i takeover steps out of 100: the windowed rate is a ratio of sums.
    eps = [log([X] * i + [P] * (100 - i)) for i in range(30)]
    rate = intervention_rate(eps)
    assert rate[0] == 0.0
    assert rate[4] == pytest.approx(sum(range(5)) / 500)
    assert rate[29] == pytest.approx(sum(range(10, 30)) / 2000)
    assert intervention_rate(eps, window=1)[7] == pytest.approx(0.07)
    with pytest.raises(ValueError, match="window must be >= 1"):
        intervention_rate(eps, window=0)


def test_rate_weights_by_steps_not_episodes():
    eps = [log([X] * 10), log([P] * 90)]
    assert intervention_rate(eps)[-1] == pytest.approx(10 / 100)


def test_effort_summary():
    eps = [log([P, X, X, P]), log([X, P, X, P], end="terminated")]
    s = effort_summary(eps)
    assert s == {"episodes": 2, "takeover_steps": 4, "takeover_count": 3,
                 "effort_minutes": pytest.approx(4 * 0.1 / 60),
                 "intervention_rate_last20": pytest.approx(0.5)}
    assert effort_summary([])["intervention_rate_last20"] == 0.0
