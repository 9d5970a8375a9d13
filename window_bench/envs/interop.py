"""Adapters for libraries that consume the env's ``info``: the numeric info keys and a
TorchRL info-dict reader that puts them into the TensorDict.

TorchRL records no info keys unless told which, and its stock reader expects numpy arrays,
while a single env returns Python bools and ints. ``torchrl_info_reader()`` converts them.
A batched ``GymEnv(..., num_envs=N)`` registers a reader for every info key by itself, which
works because every key is a number unless the env is made with ``info_strings=True`` (see
``docs/third-party.md``).
"""

from __future__ import annotations

import numpy as np

# Stackable info keys worth a TensorDict entry: the outcome, the failure code, the stage
# reached, and why suction was lost on this step (codes in task.py / env.py).
INFO_CODES = ("is_success", "accepted", "failure_code", "stage", "suction_loss_code")


def torchrl_info_reader(keys=INFO_CODES):
    """A ``torchrl.envs.gym_like.default_info_dict_reader`` for ``keys`` that accepts the
    env's Python scalars. Use with a non-batched ``torchrl.envs.GymEnv``::

        env = GymEnv("window_bench:WindowInstall-A-v0")
        env.set_info_dict_reader(torchrl_info_reader())
    """
    from torchrl.envs.gym_like import default_info_dict_reader

    class _Reader(default_info_dict_reader):
        def __call__(self, info_dict, tensordict):
            return super().__call__({k: np.asarray(info_dict[k]) for k in self.keys
                                     if k in info_dict}, tensordict)

    return _Reader(list(keys))
