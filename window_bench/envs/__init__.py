"""The environment: the composed MuJoCo scene, the 500 Hz controller, the task (acceptance,
stage events, failure modes) and the Gymnasium env with its wrappers.

* ``scene.py`` - arena, wall and buck, window panel, rack, iiwa 14 and vacuum tool;
* ``controller.py`` - operational-space control and the IK for reset postures;
* ``task.py`` - acceptance and the failure-mode taxonomy, testable without stepping;
* ``env.py`` - :class:`WindowInstallEnv`: actions, suction, randomization, observations;
* ``wrappers.py`` - the noisy acceptance sensor used in training;
* ``interop.py`` - the numeric info keys and a TorchRL info reader for third-party consumers.
"""

from window_bench.envs.env import WindowInstallEnv

__all__ = ["WindowInstallEnv"]
