"""Teleoperation: device adapters driven by injected events, the human takeover source,
headless recording sessions and the ``bench teleop`` arguments.

No hardware, display, pynput or pyspacemouse is needed. Keys are passed in the shape pynput's
listener hands them over: ``_KeyCode`` stands in for ``pynput.keyboard.KeyCode`` (a ``char``
attribute) and ``_Key`` for ``pynput.keyboard.Key`` (an ``enum.Enum`` whose members have a
``name`` and no ``char``). SpaceMouse states are a namedtuple with the fields of
``pyspacemouse.read()``'s result.
"""

from __future__ import annotations

import argparse
import collections
import enum
import json
import sys

import gymnasium as gym
import numpy as np
import pytest
import torch

from window_bench.data.dataset import load_episodes
from window_bench.installer.scripted import ScriptedInstaller
from window_bench.installer.teleop import (INSTALL_HINT, DeviceTakeover, KeyboardDevice, SpaceMouseDevice,
                                 TeleopDevice, TeleopUnavailable, add_teleop_parser, cmd_teleop,
                                 key_name, legacy_to_z_up, make_device, teleop_dataset_id,
                                 teleop_session)

torch.set_num_threads(1)


class _KeyCode:
    """Stand-in for ``pynput.keyboard.KeyCode``: printable keys carry ``char``."""

    def __init__(self, char):
        self.char = char


class _Key(enum.Enum):
    """Stand-in for ``pynput.keyboard.Key``: special keys are enum members (``.name``)."""

    space = 1
    enter = 2
    backspace = 3
    esc = 4
    shift = 5


def K(c):
    return _KeyCode(c)


SpaceNavigator = collections.namedtuple("SpaceNavigator", "t x y z roll pitch yaw buttons")


def sm_state(buttons=(0, 0), **axes):
    v = {k: 0.0 for k in ("x", "y", "z", "roll", "pitch", "yaw")}
    v.update(axes)
    return SpaceNavigator(t=0.0, buttons=list(buttons), **v)


def vec(**components):
    """Expected 6-D motion from named action components a0..a5."""
    m = np.zeros(6, dtype=np.float32)
    for k, v in components.items():
        m[int(k[1])] = v
    return m


# ------------------------------------------------------------------------------ keyboard
# The documented key map (docs/teleop.md), written out independently of KEY_MAP.
KEY_TABLE = {
    "w": vec(a2=1), "s": vec(a2=-1), "d": vec(a0=1), "a": vec(a0=-1),
    "r": vec(a1=-1), "f": vec(a1=1), "i": vec(a3=-1), "k": vec(a3=1),
    "j": vec(a4=-1), "l": vec(a4=1), "u": vec(a5=-1), "o": vec(a5=1),
}


@pytest.mark.parametrize("key", sorted(KEY_TABLE))
def test_keyboard_key_map(key):
    dev = KeyboardDevice(speed=0.5)
    assert not dev.active
    dev.press(K(key))
    assert dev.active
    a = dev.action()
    assert a.dtype == np.float32 and a.shape == (7,)
    np.testing.assert_allclose(a[:6], 0.5 * KEY_TABLE[key])
    assert a[6] == -1.0  # vacuum released by default
    dev.release(K(key))
    assert not dev.active
    np.testing.assert_array_equal(dev.action()[:6], np.zeros(6))


def test_keyboard_combinations_add_and_opposites_cancel():
    dev = KeyboardDevice(speed=0.25)
    for c in "wdi":
        dev.press(K(c))
    np.testing.assert_allclose(dev.action()[:6], 0.25 * vec(a2=1, a0=1, a3=-1))
    dev.press(K("s"))  # opposes w
    np.testing.assert_allclose(dev.action()[:6], 0.25 * vec(a0=1, a3=-1))
    for c in "dis":
        dev.release(K(c))
    np.testing.assert_allclose(dev.action()[:6], 0.25 * vec(a2=1))
    dev.press(K("s"))  # w and s both held: no motion, but the operator is on the keys
    np.testing.assert_array_equal(dev.action()[:6], np.zeros(6))
    assert dev.active
    dev.release(K("w"))
    dev.release(K("s"))
    assert not dev.active


def test_keyboard_shift_case_and_key_identifiers():
    dev = KeyboardDevice(speed=0.5)
    dev.press(K("W"))  # Shift held: pynput reports the upper-case char
    np.testing.assert_allclose(dev.action()[:6], 0.5 * vec(a2=1))
    dev.release(K("w"))  # released after Shift: lower case
    assert not dev.active
    dev.press(K(None))  # a KeyCode without a char (e.g. a media key) is ignored
    dev.press(_Key.shift)  # modifiers do nothing
    assert not dev.active
    assert key_name(_Key.space) == "space" and key_name(K(" ")) == "space"
    assert key_name(_Key.enter) == "enter" and key_name("W") == "w" and key_name(K(None)) is None


def test_keyboard_vacuum_toggles_and_latches():
    dev = KeyboardDevice()
    assert dev.action()[6] == -1.0
    dev.press(_Key.space)
    assert dev.active
    assert dev.action()[6] == 1.0
    dev.press(_Key.space)  # OS auto-repeat while held: no second toggle
    assert dev.action()[6] == 1.0
    dev.release(_Key.space)
    assert not dev.active
    for _ in range(3):  # latched across steps
        assert dev.action()[6] == 1.0
    dev.press(_Key.space)
    dev.release(_Key.space)  # a tap between two ticks is not lost
    assert dev.active
    assert dev.action()[6] == -1.0
    assert not dev.active  # the pending toggle was consumed by action()
    assert dev.action()[6] == -1.0
    dev.reset(vacuum=True)
    assert dev.action()[6] == 1.0 and not dev.active


def test_keyboard_speed_scale():
    dev = KeyboardDevice(speed=0.5)
    dev.press(K("="))
    dev.release(K("="))
    assert dev.speed == 1.0 and not dev.active  # speed keys do not take over
    dev.press(K("+"))  # already at the top level
    dev.release(K("+"))
    assert dev.speed == 1.0
    dev.press(K("w"))
    np.testing.assert_allclose(dev.action()[:6], vec(a2=1.0))
    for _ in range(2):
        dev.press(K("-"))
        dev.release(K("-"))
    assert dev.speed == 0.25
    np.testing.assert_allclose(dev.action()[:6], vec(a2=0.25))
    for _ in range(5):
        dev.press(K("-"))
        dev.release(K("-"))
    assert dev.speed == KeyboardDevice.SPEED_LEVELS[0]
    np.testing.assert_allclose(dev.action()[:6], vec(a2=KeyboardDevice.SPEED_LEVELS[0]))


def test_keyboard_session_commands():
    dev = KeyboardDevice()
    for key in (_Key.enter, _Key.backspace, _Key.esc):
        dev.press(key)
        dev.release(key)
    assert not dev.active
    assert [dev.take_command() for _ in range(4)] == ["end", "discard", "quit", None]
    dev.press(_Key.enter)
    dev.press(_Key.esc)
    dev.reset(vacuum=False)  # a new episode drops stale episode commands, not a quit
    assert dev.take_command() == "quit" and dev.take_command() is None


@pytest.mark.parametrize("speed", [0, -0.5, 1.5, True, "fast"])
def test_keyboard_bad_speed(speed):
    with pytest.raises(ValueError, match="speed"):
        KeyboardDevice(speed=speed)


def test_keyboard_start_without_pynput(monkeypatch):
    monkeypatch.setitem(sys.modules, "pynput", None)  # import pynput -> ImportError
    dev = KeyboardDevice()
    with pytest.raises(TeleopUnavailable) as e:
        dev.start()
    assert INSTALL_HINT in str(e.value) and "display" in str(e.value)
    assert not dev.started


# ------------------------------------------------------------------------------ spacemouse
# The documented axis map (docs/teleop.md), written out independently of DEFAULT_AXIS_MAP.
AXIS_TABLE = {"x": (0, 1), "y": (2, 1), "z": (1, -1), "roll": (3, 1), "yaw": (4, -1),
              "pitch": (5, 1)}


@pytest.mark.parametrize("field", sorted(AXIS_TABLE))
@pytest.mark.parametrize("value", [1.0, -1.0])
def test_spacemouse_axis_mapping_and_sign(field, value):
    dev = SpaceMouseDevice(deadzone=0.1, translation_scale=0.5, rotation_scale=0.25)
    dev.inject(sm_state(**{field: value}))
    assert dev.active
    i, sign = AXIS_TABLE[field]
    scale = 0.5 if i < 3 else 0.25
    expected = np.zeros(6)
    expected[i] = sign * value * scale
    np.testing.assert_allclose(dev.action()[:6], expected, atol=1e-7)


def test_spacemouse_deadzone():
    dev = SpaceMouseDevice(deadzone=0.1, translation_scale=1.0)
    dev.inject(sm_state(x=0.09, y=-0.1, yaw=0.05))
    assert not dev.active
    np.testing.assert_array_equal(dev.action()[:6], np.zeros(6))
    dev.inject(sm_state(x=0.55))  # (0.55 - 0.1) / 0.9 = 0.5: continuous past the edge
    np.testing.assert_allclose(dev.action()[0], 0.5, rtol=1e-6)
    dev.inject(sm_state(x=-0.325))
    np.testing.assert_allclose(dev.action()[0], -0.25, rtol=1e-6)
    dev.inject(sm_state(x=3.0))  # out-of-range reports clip to full scale
    np.testing.assert_allclose(dev.action()[0], 1.0)
    dev.inject(sm_state())
    assert not dev.active


def test_spacemouse_custom_axis_map():
    ident = [(k, 1) for k in SpaceMouseDevice.AXES]
    dev = SpaceMouseDevice(deadzone=0.0, translation_scale=1.0, rotation_scale=1.0, axis_map=ident)
    dev.inject(sm_state(x=0.1, y=0.2, z=0.3, roll=0.4, pitch=0.5, yaw=0.6))
    np.testing.assert_allclose(dev.action()[:6], [0.1, 0.2, 0.3, 0.4, 0.5, 0.6], rtol=1e-6)


def test_legacy_to_z_up():
    legacy = sm_state(buttons=[1, 0], x=0.1, y=0.2, z=0.3, roll=0.4, pitch=0.5, yaw=0.6)
    z = legacy_to_z_up(legacy)
    assert (z.x, z.y, z.z, z.roll, z.pitch, z.yaw) == (0.1, 0.2, 0.3, -0.5, 0.4, -0.6)
    assert list(z.buttons) == [1, 0]
    # Tilting the cap about the right (x) axis turns the tool about TCP x either way.
    dev = SpaceMouseDevice(deadzone=0.0, rotation_scale=1.0)
    dev.inject(legacy_to_z_up(sm_state(pitch=-0.5)))
    np.testing.assert_allclose(dev.action()[:6], vec(a3=0.5))


def test_spacemouse_buttons():
    dev = SpaceMouseDevice()
    assert dev.action()[6] == -1.0
    dev.inject(sm_state(buttons=[1, 0]))  # press edge of button 0: toggle
    assert dev.active and dev.action()[6] == 1.0
    dev.inject(sm_state(buttons=[1, 0]))  # still held: no second toggle, still active
    assert dev.active and dev.action()[6] == 1.0
    dev.inject(sm_state(buttons=[0, 0]))
    assert not dev.active and dev.action()[6] == 1.0  # latched
    dev.inject(sm_state(buttons=[1, 0]))
    dev.inject(sm_state(buttons=[0, 0]))  # a click between two ticks is not lost
    assert dev.active and dev.action()[6] == -1.0
    assert not dev.active
    dev.inject(sm_state(buttons=[0, 1]))  # button 1: end the episode
    assert not dev.active and dev.take_command() == "end"
    dev.inject(sm_state(buttons=[0, 1]))
    assert dev.take_command() is None  # only on the edge
    dev.inject(SpaceNavigator(0, 0, 0, 0, 0, 0, 0, []))  # a device without buttons
    assert not dev.active


@pytest.mark.parametrize("kwargs, match", [
    ({"deadzone": 1.0}, "deadzone"), ({"deadzone": -0.1}, "deadzone"),
    ({"translation_scale": 0.0}, "translation_scale"), ({"rotation_scale": 2}, "rotation_scale"),
    ({"poll_hz": 5}, "poll_hz"),
    ({"axis_map": [("x", 1)] * 5}, "6"),
    ({"axis_map": [("x", 1)] * 5 + [("spin", 1)]}, "spin"),
    ({"axis_map": [("x", 1)] * 5 + [("yaw", 2)]}, "sign"),
])
def test_spacemouse_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        SpaceMouseDevice(**kwargs)


def test_spacemouse_start_without_pyspacemouse(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyspacemouse", None)
    with pytest.raises(TeleopUnavailable, match="pyspacemouse") as e:
        SpaceMouseDevice().start()
    assert INSTALL_HINT in str(e.value)


def test_make_device():
    assert isinstance(make_device("keyboard", speed=0.25), KeyboardDevice)
    assert isinstance(make_device("spacemouse"), SpaceMouseDevice)
    with pytest.raises(ValueError, match="'joystick'.*keyboard.*spacemouse"):
        make_device("joystick")


# ------------------------------------------------------------------------------ takeover
def test_device_takeover_binary(make_env):
    env = make_env("WindowInstall-A-v0", obs_mode="flat")
    obs, info = env.reset(seed=0)
    dev = KeyboardDevice(speed=0.5)
    src = DeviceTakeover(dev)
    src.reset(env, seed=0)
    assert src.intervene(obs, info) is None  # idle: the policy keeps control
    dev.press(K("w"))
    out = src.intervene(obs, info)
    assert out is not None
    a, kind = out
    assert kind == "safety"
    np.testing.assert_allclose(a, [0, 0, 0.5, 0, 0, 0, 1.0])  # vacuum follows A's held panel
    obs, _, _, _, info = env.step(a)
    dev.release(K("w"))
    assert src.intervene(obs, info) is None
    # While idle the latch tracks the robot's suction; a toggle acts on that state.
    assert src.intervene(obs, {**info, "suction_engaged": False}) is None
    assert dev.vacuum is False
    dev.press(_Key.space)
    dev.release(_Key.space)  # a tap: a takeover for exactly one step
    a, kind = src.intervene(obs, info)
    assert a[6] == 1.0 and np.all(a[:6] == 0)
    assert src.intervene(obs, info) is None
    assert src.takeover_steps == 2
    with pytest.raises(ValueError, match="coverage"):
        DeviceTakeover(dev, kind="manual")
    with pytest.raises(ValueError, match="TeleopDevice"):
        DeviceTakeover("keyboard")


def test_device_takeover_spacemouse_coverage_kind():
    dev = SpaceMouseDevice()
    src = DeviceTakeover(dev, kind="coverage")
    src.reset(None)
    info = {"suction_engaged": True}
    dev.inject(sm_state(y=0.05))  # inside the deadzone: hand resting on the cap
    assert src.intervene(None, info) is None
    dev.inject(sm_state(y=1.0))
    a, kind = src.intervene(None, info)
    assert kind == "coverage" and a[2] == pytest.approx(0.5) and a[6] == 1.0


# ------------------------------------------------------------------------------ sessions
class ScriptedKeyboard(KeyboardDevice):
    """A keyboard whose events come from a script ``{tick: [(method, key), ...]}``, replayed
    through the pynput callbacks in :meth:`poll`; every returned action is kept."""

    def __init__(self, script, **kwargs):
        super().__init__(**kwargs)
        self.script = script
        self.tick = 0
        self.emitted = []

    def start(self):  # no pynput listener: events come from the script
        TeleopDevice.start(self)

    def stop(self):
        TeleopDevice.stop(self)

    def poll(self):
        for method, key in self.script.get(self.tick, ()):
            getattr(self, method)(key)
        self.tick += 1

    def action(self):
        a = super().action()
        self.emitted.append(a.copy())
        return a


class InstallerDevice(TeleopDevice):
    """A 'device' whose hand is the scripted installer (to reach acceptance in a session)."""

    name = "installer-hand"

    def __init__(self):
        super().__init__()
        self.controller = None
        self.tcp_mat = None

    def bind(self, env):
        self.env = env
        self.controller = ScriptedInstaller(env, seed=0)

    def poll(self):
        self._a = self.controller.act()
        self.set_vacuum(self._a[6] > 0.5)
        self.tcp_mat = self.env.unwrapped.tcp_pose()[1]

    def _motion(self):
        return self._a[:6]


def _session_script():
    # Idle for 2 ticks, W for 4, W+D for 3, tap Space (release the panel), then Enter.
    return {
        2: [("press", K("w"))],
        6: [("press", K("d"))],
        9: [("release", K("w")), ("release", K("d")), ("press", _Key.space)],
        10: [("release", _Key.space)],
        12: [("press", _Key.enter), ("release", _Key.enter)],
    }


def test_session_records_demo_dataset(tmp_path):
    dev = ScriptedKeyboard({**_session_script(),
                            # episode 2 is discarded after a few steps
                            13: [("press", K("s"))], 16: [("press", _Key.backspace)]})
    res = teleop_session("WindowInstall-A-v0", dev, record_dir=tmp_path, episodes=2,
                         viewer=False, seed=5, keep_all=True, verbose=False)
    assert [o.outcome for o in res.outcomes] == ["ended", "discarded"]
    assert [o.kept for o in res.outcomes] == [True, False]
    assert res.outcomes[0].steps == 10  # ticks 2..11: no idle lead-in, Enter at tick 12
    assert res.dataset_id == "window-bench/teleop-a-v0"
    assert res.dataset_path == tmp_path / "window-bench" / "teleop-a-v0"

    (ep,) = load_episodes(res.dataset_id, data_path=tmp_path)
    assert ep.T == 10 and ep.seed == 5 and ep.episode_id == 0
    assert ep.env_id == "WindowInstall-A-v0" and ep.operator == "human"
    assert set(ep.provenance) == {"demo"} and set(ep.takeover_kind) == {""}
    assert ep.truncated[-1] and not ep.terminated.any()  # ended by the user: truncated
    # Executed actions are the device's actions, step for step.
    np.testing.assert_array_equal(ep.actions, np.stack(dev.emitted[:10]))
    np.testing.assert_allclose(ep.actions[:4, :6], np.tile(0.5 * vec(a2=1), (4, 1)))
    np.testing.assert_allclose(ep.actions[4:7, :6], np.tile(0.5 * vec(a2=1, a0=1), (3, 1)))
    assert np.all(ep.actions[9:, :6] == 0)
    # Experiment A starts with the panel held: the latch starts engaged, Space released it.
    np.testing.assert_array_equal(ep.actions[:, 6], [1.0] * 7 + [-1.0] * 3)
    assert ep.stage_flags[0, 0]  # suction acquired (held from the reset)
    assert set(ep.randomization) >= {"friction_buck", "friction_window"}
    meta = json.loads((res.dataset_path / "data" / "metadata.json").read_text())
    assert meta["operator"] == "human" and meta["device"] == "keyboard"
    assert meta["env_id"] == "WindowInstall-A-v0" and meta["seeds"] == [5]
    assert meta["teleop_sessions"][0]["episode_ids"] == [0]


def test_session_keeps_only_accepted_by_default_and_appends(tmp_path, monkeypatch):
    # An ended (not accepted) episode is not kept by default: nothing is written.
    dev = ScriptedKeyboard(_session_script())
    res = teleop_session("WindowInstall-A-v0", dev, record_dir=tmp_path, viewer=False,
                         verbose=False)
    assert res.outcomes[0].outcome == "ended" and not res.outcomes[0].kept
    assert res.dataset_path is None and not (tmp_path / "window-bench").exists()

    # First session with keep_all, then an accepted episode appended by a second session.
    teleop_session("WindowInstall-A-v0", ScriptedKeyboard(_session_script()),
                   record_dir=tmp_path, viewer=False, keep_all=True, verbose=False)
    hand = InstallerDevice()
    real_make = gym.make

    def make_and_bind(*args, **kwargs):  # the real env, handed to the installer's hand too
        env = real_make(*args, **kwargs)
        hand.bind(env)
        return env

    monkeypatch.setattr(gym, "make", make_and_bind)
    res = teleop_session("WindowInstall-A-v0", hand, record_dir=tmp_path, viewer=False,
                         seed=3, verbose=False, start_on_input=False)
    assert res.outcomes[0].outcome == "accepted" and res.outcomes[0].kept
    eps = load_episodes("window-bench/teleop-a-v0", data_path=tmp_path)
    assert [e.episode_id for e in eps] == [0, 1]
    assert eps[1].terminated[-1] and not eps[1].truncated.any() and eps[1].rewards[-1] == 1.0
    assert eps[1].stage_flags[-1].all()  # suction, insertion entered, seated
    meta = json.loads((tmp_path / "window-bench" / "teleop-a-v0" / "data" /
                       "metadata.json").read_text())
    assert meta["seeds"] == [0, 3] and len(meta["teleop_sessions"]) == 2
    assert meta["device"] == "installer-hand"
    # The operator frame of the docs: at the seat, forward (TCP z) is into the wall (-y),
    # right (TCP x) is world -x for someone facing the wall, up (TCP -y) is world +z.
    R = hand.tcp_mat
    assert R[:, 2] @ [0, -1, 0] > 0.99 and R[:, 0] @ [-1, 0, 0] > 0.99
    assert -R[:, 1] @ [0, 0, 1] > 0.99


def test_forward_key_moves_along_the_tool_axis():
    # Setting B starts with the tool pointing down in free space: W moves along it.
    dev = ScriptedKeyboard({0: [("press", K("w"))]})
    env = gym.make("WindowInstall-B-v0", obs_mode="flat")
    try:
        env.reset(seed=0)
        p0, R0 = env.unwrapped.tcp_pose()
        for _ in range(3):
            dev.poll()
            env.step(dev.action())
        d = env.unwrapped.tcp_pose()[0] - p0
    finally:
        env.close()
    along = d @ R0[:, 2]
    assert along == pytest.approx(3 * 0.5 * 0.025, rel=0.25)
    assert np.linalg.norm(d - along * R0[:, 2]) < 0.2 * along


def test_session_argument_errors():
    dev = KeyboardDevice()
    with pytest.raises(ValueError, match="registered"):
        teleop_session("WindowInstall-C-v0", dev, viewer=False)
    with pytest.raises(ValueError, match="episodes = 0"):
        teleop_session("WindowInstall-A-v0", dev, episodes=0, viewer=False)
    with pytest.raises(ValueError, match=r"max_steps = 601.*\[1, 600\]"):
        teleop_session("WindowInstall-A-v0", dev, max_steps=601, viewer=False)
    with pytest.raises(ValueError, match="TeleopDevice"):
        teleop_session("WindowInstall-A-v0", "keyboard", viewer=False)
    with pytest.raises(ValueError, match="registered"):
        teleop_dataset_id("Window-v0")
    assert teleop_dataset_id("WindowInstall-B-Panel60x40-v0") == "window-bench/teleop-b-panel60x40-v0"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="display check is Linux's")
def test_session_viewer_needs_a_display(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    dev = ScriptedKeyboard({})
    with pytest.raises(TeleopUnavailable, match="display"):
        teleop_session("WindowInstall-A-v0", dev, viewer=True, verbose=False)
    assert not dev.started  # nothing left running


# ------------------------------------------------------------------------------ CLI
def _parser():
    p = argparse.ArgumentParser(prog="bench")
    add_teleop_parser(p.add_subparsers(dest="command", required=True))
    return p


def test_cli_defaults():
    args = _parser().parse_args(["teleop"])
    assert (args.env, args.device, args.record, args.episodes) == (
        "WindowInstall-A-v0", "keyboard", None, 1)
    assert args.func is cmd_teleop and not args.no_viewer and args.max_steps == 600
    args = _parser().parse_args(["teleop", "--env", "WindowInstall-B-v0", "--device",
                                 "spacemouse", "--record", "demos", "--episodes", "50",
                                 "--seed", "100", "--no-viewer", "--keep-all"])
    assert (args.env, args.device, args.record, args.episodes, args.seed) == (
        "WindowInstall-B-v0", "spacemouse", "demos", 50, 100)
    assert args.no_viewer and args.keep_all


@pytest.mark.parametrize("argv, needles", [
    (["--device", "joystick"], ["joystick", "keyboard", "spacemouse"]),
    (["--env", "WindowInstall-C-v0"], ["WindowInstall-C-v0", "WindowInstall-A-v0"]),
    (["--episodes", "0"], ["--episodes", ">= 1", "0"]),
    (["--episodes", "many"], ["many", "integer"]),
    (["--seed", "-1"], ["--seed", ">= 0"]),
    (["--max-steps", "601"], ["--max-steps", "[1, 600]", "601"]),
])
def test_cli_argument_errors(argv, needles, capsys):
    with pytest.raises(SystemExit) as e:
        _parser().parse_args(["teleop", *argv])
    assert e.value.code == 2
    err = capsys.readouterr().err
    for needle in needles:
        assert needle in err


@pytest.mark.parametrize("device, module", [("keyboard", "pynput"),
                                            ("spacemouse", "pyspacemouse")])
def test_cli_missing_library(device, module, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, module, None)
    args = _parser().parse_args(["teleop", "--device", device, "--no-viewer"])
    assert cmd_teleop(args) == 2
    err = capsys.readouterr().err
    assert INSTALL_HINT in err and module in err
