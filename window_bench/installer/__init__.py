"""The installer loop: who acts besides the learner, and the loop that runs them together.

* ``scripted.py`` - the scripted installer, the straight-push baseline, random actions;
* ``operators.py`` - operator profiles and the human-like demonstrator;
* ``supervisor.py`` - the event-driven takeover protocol (the installer as supervisor);
* ``rollout.py`` - the rollout loop: action queue on the chunk grid, takeovers, step logs;
* ``demos.py`` - ``bench demos`` and ``bench supervise``;
* ``teleop.py`` - a person at the keyboard or SpaceMouse, recording and takeovers.
"""

from window_bench.installer.scripted import (CONTROLLERS, RandomPolicy, ScriptedInstaller,
                                             StraightPush, pose_action)

__all__ = ["CONTROLLERS", "RandomPolicy", "ScriptedInstaller", "StraightPush", "pose_action"]
