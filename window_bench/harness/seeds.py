"""The evaluation seeds protocol: development seeds for tuning, held-out test seeds for
reported numbers.

Every design choice of our QC-FQL (noise scales, prior data, policy averaging, ...) was tuned
on evaluation episodes seeded 100000, 100001, ... . A number measured on those seeds is
optimistic by construction, so reported numbers come from a disjoint **test** set whose base
no tuning run ever used:

* ``dev``  - seeds ``DEV_SEED0 + i``: checkpoint evaluations while developing, ``bench eval``
  by default, every row of the leaderboard that predates this protocol;
* ``test`` - seeds ``TEST_SEED0 + i``: the final M = 100 evaluation of every reported run
  (``bench sweep`` grids) and Table 7's out-of-distribution evaluations.

The two ranges cannot overlap for any M below ``TEST_SEED0 - DEV_SEED0`` (400,000), and
neither meets the other seeds we use: training episodes ``seed * 1_000_003 + episode``
(below 100,000 for seed 0, above 1,000,002 for seed >= 1), demonstrations
``1_000_000 + seed + attempt``, calibration ``0 ...``.
"""

from __future__ import annotations

DEV_SEED0 = 100_000
TEST_SEED0 = 500_000
SEED_SETS = {"dev": DEV_SEED0, "test": TEST_SEED0}
MAX_EPISODES = TEST_SEED0 - DEV_SEED0
#: The largest run or first-episode seed a command accepts: what numpy's legacy seeding (SB3)
#: takes is below 2**32, and the seeds derived by an offset (``seed + 1``, demonstrations'
#: ``1_000_000 + seed``) stay there; env reset seeds may be larger (Gymnasium takes any).
MAX_SEED = 2**31 - 1


def eval_seeds(seed_set: str, episodes: int) -> list[int]:
    """The ``episodes`` evaluation seeds of ``seed_set`` (``dev`` or ``test``)."""
    if seed_set not in SEED_SETS:
        raise ValueError(f"seed set {seed_set!r}; allowed: {', '.join(SEED_SETS)}")
    if not 1 <= episodes <= MAX_EPISODES:
        raise ValueError(f"episodes = {episodes}; allowed 1..{MAX_EPISODES}")
    base = SEED_SETS[seed_set]
    return list(range(base, base + episodes))


def seed_set_of(first_seed: int) -> str:
    """Which set a recorded ``eval_seeds`` range starts in (old results files only record
    the range)."""
    for name, base in SEED_SETS.items():
        if base <= first_seed < base + MAX_EPISODES:
            return name
    raise ValueError(f"evaluation seed {first_seed} lies in no seed set "
                     f"({', '.join(f'{k} from {v}' for k, v in SEED_SETS.items())})")
