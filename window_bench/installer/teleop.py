"""Human teleoperation: input devices, demonstration recording and the human takeover source.

A person drives the shared 7-D action interface (6-D TCP increment in the current TCP frame
+ vacuum, :class:`~window_bench.envs.env.WindowInstallEnv`) with a keyboard (``pynput``) or a
3Dconnexion SpaceMouse (``pyspacemouse``), watching the scene in the MuJoCo viewer. The same
device serves two purposes:

* **demonstrations** - :func:`teleop_session` (``bench teleop``) runs episodes at 10 Hz and
  records each one as an :class:`~window_bench.data.steplog.EpisodeLog` with provenance
  ``"demo"``, saved as a Minari dataset by :func:`window_bench.data.dataset.save_episodes`;
* **takeovers during training** - :class:`DeviceTakeover` is a takeover source for the
  rollout loop (:mod:`window_bench.installer.supervisor`): a binary takeover on every step on which the
  device is active, as in HIL-SERL.

Devices share one interface, :class:`TeleopDevice`: ``start()`` / ``stop()`` open and close
the hardware (the optional dependency is imported there, never at module import), and
``action()`` / ``active`` / ``take_command()`` read it. Hardware events enter through public
methods - :meth:`KeyboardDevice.press` / :meth:`KeyboardDevice.release` are the ``pynput``
listener's callbacks, :meth:`SpaceMouseDevice.inject` receives each state the polling thread
reads - so tests drive the real mapping code with injected events and no hardware.

Operator frame. Both devices are laid out for an operator who stands behind the robot and
faces the wall, with the tool in its insertion pose (tool axis into the opening): *forward*
is the TCP +z (the tool axis), *right* is the TCP +x and *up* is the TCP -y. Increments are
always applied in the current TCP frame, so away from that pose "forward" still means "along
the tool axis" (down toward the panel at the start of Experiment B). See ``docs/teleop.md``.

The vacuum command is latched: a toggle (Space, SpaceMouse button 0) flips it and it stays
until the next toggle; ``action()[6]`` is ``+1`` (engage) or ``-1`` (release). Sessions start
each episode with the latch equal to the env's suction state (engaged in Experiment A).
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from window_bench.data.steplog import ACTION_DIM, STAGE_FLAGS, STEP_DT, TAKEOVER_KINDS, EpisodeLog

#: How to install the optional device libraries.
INSTALL_HINT = 'pip install "window-bench[teleop]"'
#: Device names accepted by :func:`make_device` and ``bench teleop --device``.
DEVICES = ("keyboard", "spacemouse")
#: Session commands a device can issue (see :meth:`TeleopDevice.take_command`).
COMMANDS = ("end", "discard", "quit")
#: Values of ``action()[6]``: the env engages iff ``a[6] > 0.5``.
ENGAGE, RELEASE = 1.0, -1.0
#: Per-episode outcomes reported by :func:`teleop_session`.
OUTCOMES = ("accepted", "ended", "time_limit", "unstable", "discarded", "quit")
#: The env's own horizon (60 s at 10 Hz); ``max_steps`` may shorten it.
MAX_STEPS = 600


class TeleopUnavailable(RuntimeError):
    """A device library, the device itself or a display is missing (message says how to fix)."""


def key_name(key) -> str | None:
    """Normalise a key as ``pynput`` reports it to a lower-case name, or None if it has none.

    ``pynput`` calls the listener with either a ``KeyCode`` (printable keys: ``.char``, e.g.
    ``'w'``, upper case while Shift is held) or a ``Key`` enum member (special keys:
    ``.name``, e.g. ``'space'``, ``'enter'``, ``'backspace'``, ``'esc'``). Anything with a
    ``char`` or a ``name`` attribute works, as does a plain string (``'w'``, ``'space'``).
    A space character maps to ``'space'``.
    """
    if isinstance(key, str):
        name = key
    else:
        name = getattr(key, "char", None) or getattr(key, "name", None)
    if not isinstance(name, str) or not name:
        return None
    if len(name) == 1:
        name = name.lower()
    return {" ": "space", "return": "enter", "escape": "esc"}.get(name, name)


# ---------------------------------------------------------------------------- devices
class TeleopDevice:
    """Common interface and state of a teleoperation device.

    State shared by all devices, guarded by one lock because hardware events arrive on
    another thread: the latched vacuum command, a *pending* flag set by a robot command that
    arrived since the last :meth:`action` (so a tap between two 10 Hz ticks is not lost),
    and a queue of session commands (:data:`COMMANDS`). Subclasses provide
    :meth:`_motion` (the 6-D increment in [-1, 1]) and :meth:`_held` (a robot-command
    button is held).
    """

    name = "device"

    def __init__(self):
        self._lock = threading.RLock()
        self._vacuum = False
        self._pending = False
        self._commands: collections.deque[str] = collections.deque(maxlen=16)
        self._started = False

    # ------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Open the hardware. Raises :class:`TeleopUnavailable` if it cannot be opened."""
        self._started = True

    def stop(self) -> None:
        """Close the hardware (idempotent)."""
        self._started = False

    @property
    def started(self) -> bool:
        return self._started

    def __enter__(self):
        self.start()
        return self

    def __exit__(self, *exc):
        self.stop()

    def poll(self) -> None:
        """Hook called once per 10 Hz tick before the device is read. No-op by default;
        devices without an event thread read their hardware here."""

    # ------------------------------------------------------------ state
    def reset(self, vacuum: bool = False) -> None:
        """Start an episode: latch ``vacuum``, drop pending events and queued ``"end"`` /
        ``"discard"`` commands (meant for the previous episode); a ``"quit"`` stays queued.
        Keys or buttons physically held stay held."""
        with self._lock:
            self._vacuum = bool(vacuum)
            self._pending = False
            quit_queued = "quit" in self._commands
            self._commands.clear()
            if quit_queued:
                self._commands.append("quit")

    @property
    def vacuum(self) -> bool:
        """The latched vacuum command."""
        with self._lock:
            return self._vacuum

    def set_vacuum(self, on: bool) -> None:
        with self._lock:
            self._vacuum = bool(on)

    def sync_if_idle(self, vacuum: bool) -> bool:
        """If the device is idle, latch ``vacuum`` and return False; else return True.

        Atomic with respect to device events: a toggle that arrives concurrently is either
        seen as activity or applied on top of the new latch, never lost in between.
        """
        with self._lock:
            if self._active_locked():
                return True
            self._vacuum = bool(vacuum)
            return False

    def _toggle_vacuum(self) -> None:
        with self._lock:
            self._vacuum = not self._vacuum
            self._pending = True

    def _command(self, cmd: str) -> None:
        with self._lock:
            self._commands.append(cmd)

    def take_command(self) -> str | None:
        """Pop the oldest queued session command (``"end"``, ``"discard"``, ``"quit"``)."""
        with self._lock:
            return self._commands.popleft() if self._commands else None

    def _motion(self) -> np.ndarray:
        return np.zeros(6)

    def _held(self) -> bool:
        return False

    def _active_locked(self) -> bool:
        return bool(np.any(self._motion() != 0.0) or self._held() or self._pending)

    @property
    def active(self) -> bool:
        """True while the operator is commanding the robot: a non-zero motion input, a
        robot-command button held, or a robot command (vacuum toggle) since the last
        :meth:`action`. Session commands (end, discard, quit, speed) do not count."""
        with self._lock:
            return self._active_locked()

    def action(self) -> np.ndarray:
        """The (7,) float32 action in [-1, 1]: motion increments, then the latched vacuum
        (+1 engage / -1 release). Clears the pending flag."""
        with self._lock:
            a = np.empty(ACTION_DIM, dtype=np.float32)
            a[:6] = np.clip(self._motion(), -1.0, 1.0)
            a[6] = ENGAGE if self._vacuum else RELEASE
            self._pending = False
            return a


class KeyboardDevice(TeleopDevice):
    """Keyboard teleoperation through a global ``pynput`` listener.

    Hold a motion key to move; opposite keys cancel, different axes add. Every held key
    contributes ``speed`` action units (``speed * 25 mm`` or ``speed * 5 deg`` per 10 Hz
    step). :data:`KEY_MAP` (operator frame, see the module docstring):

    ====== ============================================== =======================
    key    motion                                         action component
    ====== ============================================== =======================
    W / S  forward / back (along the tool axis)           a[2] = +1 / -1 (TCP z)
    D / A  right / left                                   a[0] = +1 / -1 (TCP x)
    R / F  up / down                                      a[1] = -1 / +1 (TCP y)
    I / K  tilt the top edge away / toward you            a[3] = -1 / +1 (about x)
    J / L  turn left / right (seen from above)            a[4] = -1 / +1 (about y)
    U / O  roll counter-clockwise / clockwise (as seen)   a[5] = -1 / +1 (about z)
    ====== ============================================== =======================

    Space toggles the vacuum; ``=`` (or ``+``) / ``-`` step ``speed`` up / down through
    :data:`SPEED_LEVELS`; Enter ends the episode, Backspace discards it, Esc quits the
    session. Auto-repeat presses of a held key (the OS repeats them without releases) do not
    toggle or step again.

    Parameters
    ----------
    speed : float
        Initial action magnitude per held key, in (0, 1].
    """

    name = "keyboard"
    KEY_MAP = {
        "w": (2, +1.0), "s": (2, -1.0),
        "d": (0, +1.0), "a": (0, -1.0),
        "r": (1, -1.0), "f": (1, +1.0),
        "i": (3, -1.0), "k": (3, +1.0),
        "j": (4, -1.0), "l": (4, +1.0),
        "u": (5, -1.0), "o": (5, +1.0),
    }
    VACUUM_KEY = "space"
    FASTER_KEYS = ("=", "+")
    SLOWER_KEYS = ("-", "_")
    COMMAND_KEYS = {"enter": "end", "backspace": "discard", "esc": "quit"}
    SPEED_LEVELS = (0.05, 0.1, 0.25, 0.5, 1.0)

    def __init__(self, speed: float = 0.5):
        super().__init__()
        if isinstance(speed, bool) or not isinstance(speed, (int, float)) or not (0.0 < speed <= 1.0):
            raise ValueError(f"speed = {speed!r} is not allowed: it must be a number in (0, 1]")
        self.speed = float(speed)
        self._down: set[str] = set()
        self._listener = None

    def start(self) -> None:
        """Start the global ``pynput`` keyboard listener (needs a display session)."""
        if self._listener is not None:
            return
        try:
            from pynput import keyboard
        except ImportError as e:  # not installed, or no usable backend (no display)
            raise TeleopUnavailable(
                f"the keyboard device could not load pynput ({e}). It needs {INSTALL_HINT} and "
                "a display: an X11 (or XWayland) session on Linux, the Accessibility and Input "
                "Monitoring permissions on macOS. See docs/teleop.md.") from e
        self._listener = keyboard.Listener(on_press=self.press, on_release=self.release)
        self._listener.daemon = True
        self._listener.start()
        super().start()

    def stop(self) -> None:
        if self._listener is not None:
            self._listener.stop()
            self._listener = None
        super().stop()

    # ------------------------------------------------------------ pynput callbacks
    def press(self, key) -> None:
        """Listener ``on_press`` callback: ``key`` as ``pynput`` reports it (see :func:`key_name`)."""
        name = key_name(key)
        if name is None:
            return
        with self._lock:
            repeat = name in self._down
            self._down.add(name)
            if repeat:
                return
            if name == self.VACUUM_KEY:
                self._toggle_vacuum()
            elif name in self.FASTER_KEYS:
                faster = [s for s in self.SPEED_LEVELS if s > self.speed + 1e-9]
                self.speed = faster[0] if faster else self.speed
            elif name in self.SLOWER_KEYS:
                slower = [s for s in self.SPEED_LEVELS if s < self.speed - 1e-9]
                self.speed = slower[-1] if slower else self.speed
            elif name in self.COMMAND_KEYS:
                self._command(self.COMMAND_KEYS[name])

    def release(self, key) -> None:
        """Listener ``on_release`` callback."""
        name = key_name(key)
        if name is None:
            return
        with self._lock:
            self._down.discard(name)

    # ------------------------------------------------------------ reading
    def _motion(self) -> np.ndarray:
        m = np.zeros(6)
        for name in self._down:
            if name in self.KEY_MAP:
                i, sign = self.KEY_MAP[name]
                m[i] += sign
        return np.clip(m, -1.0, 1.0) * self.speed

    def _held(self) -> bool:
        return any(k in self.KEY_MAP or k == self.VACUUM_KEY for k in self._down)


class SpaceMouseDevice(TeleopDevice):
    """3Dconnexion SpaceMouse teleoperation through ``pyspacemouse``.

    A background thread reads the device at ``poll_hz`` and hands every state to
    :meth:`inject`. States are in ``pyspacemouse``'s right-handed Z-up convention
    (``AxisConvention.HID_Z_UP``): ``x`` right, ``y`` away from you, ``z`` up, and ``roll`` /
    ``pitch`` / ``yaw`` the rotations about those x / y / z axes, all in [-1, 1].
    :meth:`start` asks ``pyspacemouse`` for that convention; a version without axis
    conventions reports the old "legacy" labels, which :func:`legacy_to_z_up` converts.

    Each axis passes a deadzone, ``v -> sign(v) * max(|v| - deadzone, 0) / (1 - deadzone)``
    (continuous at the edge, full scale at full deflection), then :attr:`axis_map` picks the
    field and sign of each action component, and the translation / rotation scales apply.
    The default map, :data:`DEFAULT_AXIS_MAP`, makes the cap behave like the tool in the
    operator frame (module docstring): push it away to move along the tool axis
    (``a[2] = +y``), right for TCP +x (``a[0] = +x``), lift it to move up (``a[1] = -z``);
    tilting or twisting it turns the tool about the same axes (``a[3] = +roll``,
    ``a[4] = -yaw``, ``a[5] = +pitch``). Check a device with
    ``bench teleop --device spacemouse --probe`` and pass another ``axis_map`` if needed.

    Button 0 (left) toggles the vacuum; button 1 (right) ends the episode.

    Parameters
    ----------
    deadzone : float
        Per-axis deadzone in [0, 1).
    translation_scale, rotation_scale : float
        Action magnitude at full deflection, in (0, 1].
    axis_map : sequence of 6 (field, sign) pairs
        Source field (one of :data:`AXES`) and sign (+1 or -1) of action components 0..5.
    poll_hz : float
        Read rate of the polling thread, in [10, 1000].
    """

    name = "spacemouse"
    AXES = ("x", "y", "z", "roll", "pitch", "yaw")
    DEFAULT_AXIS_MAP = (("x", 1.0), ("z", -1.0), ("y", 1.0),
                        ("roll", 1.0), ("yaw", -1.0), ("pitch", 1.0))
    VACUUM_BUTTON = 0
    END_BUTTON = 1

    def __init__(self, deadzone: float = 0.1, translation_scale: float = 0.5,
                 rotation_scale: float = 0.5, axis_map=DEFAULT_AXIS_MAP, poll_hz: float = 200.0):
        super().__init__()
        if isinstance(deadzone, bool) or not isinstance(deadzone, (int, float)) or not (0.0 <= deadzone < 1.0):
            raise ValueError(f"deadzone = {deadzone!r} is not allowed: it must be in [0, 1)")
        for what, v in (("translation_scale", translation_scale), ("rotation_scale", rotation_scale)):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (0.0 < v <= 1.0):
                raise ValueError(f"{what} = {v!r} is not allowed: it must be in (0, 1]")
        if isinstance(poll_hz, bool) or not isinstance(poll_hz, (int, float)) or not (10.0 <= poll_hz <= 1000.0):
            raise ValueError(f"poll_hz = {poll_hz!r} is not allowed: it must be in [10, 1000]")
        self.axis_map = self._check_axis_map(axis_map)
        self.deadzone = float(deadzone)
        self.scales = np.array([translation_scale] * 3 + [rotation_scale] * 3, dtype=np.float64)
        self.poll_hz = float(poll_hz)
        self._axes = np.zeros(6)        # last state after the deadzone, in AXES order
        self._buttons: tuple[int, ...] = ()
        self._device = None
        self._thread: threading.Thread | None = None
        self._stop_event = threading.Event()
        self._error: BaseException | None = None
        self._legacy = False

    @classmethod
    def _check_axis_map(cls, axis_map) -> tuple[tuple[str, float], ...]:
        try:
            entries = [tuple(e) for e in axis_map]
        except TypeError:
            raise ValueError(f"axis_map = {axis_map!r} is not allowed: expected 6 (field, sign) "
                             "pairs") from None
        if len(entries) != 6 or any(len(e) != 2 for e in entries):
            raise ValueError(f"axis_map = {axis_map!r} is not allowed: expected 6 (field, sign) "
                             "pairs, one per action component 0..5")
        out = []
        for i, (name, sign) in enumerate(entries):
            if name not in cls.AXES:
                raise ValueError(f"axis_map[{i}] field {name!r} is not allowed; allowed {cls.AXES}")
            if sign not in (1, -1):
                raise ValueError(f"axis_map[{i}] sign {sign!r} is not allowed; allowed +1 or -1")
            out.append((str(name), float(sign)))
        return tuple(out)

    # ------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Open the first SpaceMouse found and start the polling thread."""
        if self._thread is not None:
            return
        try:
            import pyspacemouse
        except ImportError as e:
            raise TeleopUnavailable(
                f"the spacemouse device needs pyspacemouse: {e}. Install it with {INSTALL_HINT} "
                "and the hidapi library (Linux: libhidapi-dev plus a udev rule, macOS: brew "
                "install hidapi). See docs/teleop.md.") from e
        conventions = getattr(pyspacemouse, "AxisConvention", None)
        z_up = getattr(conventions, "HID_Z_UP", None) or getattr(conventions, "Z_UP", None)
        try:
            try:
                dev = pyspacemouse.open(axis_convention=z_up) if z_up is not None else None
                self._legacy = z_up is None
            except TypeError:  # a version whose open() takes no axis_convention
                dev, self._legacy = None, True
            if self._legacy:
                dev = pyspacemouse.open()
        except Exception as e:  # noqa: BLE001 - 2.x raises when no device is found
            raise TeleopUnavailable(
                f"no SpaceMouse could be opened ({type(e).__name__}: {e}); check the hidapi "
                "library, the USB connection and the hidraw permissions (docs/teleop.md)") from e
        if not dev:  # 1.x returns None / False when no device is found
            raise TeleopUnavailable("no SpaceMouse could be opened; check the USB connection "
                                    "and the hidraw permissions (docs/teleop.md)")
        self._device = dev if hasattr(dev, "read") else pyspacemouse
        self._stop_event.clear()
        self._error = None
        self._thread = threading.Thread(target=self._poll_loop, name="spacemouse", daemon=True)
        self._thread.start()
        super().start()

    def stop(self) -> None:
        self._stop_event.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
            self._thread = None
        if self._device is not None:
            try:
                self._device.close()
            except Exception:  # noqa: BLE001 - closing a device that vanished
                pass
            self._device = None
        super().stop()

    def _poll_loop(self) -> None:
        period = 1.0 / self.poll_hz
        while not self._stop_event.is_set():
            try:
                state = self._device.read()
                self.inject(legacy_to_z_up(state) if self._legacy else state)
            except BaseException as e:  # noqa: BLE001 - surfaced by poll() on the main thread
                self._error = e
                return
            self._stop_event.wait(period)

    def poll(self) -> None:
        """Re-raise, on the caller's thread, an error of the polling thread."""
        if self._error is not None:
            e, self._error = self._error, None
            raise TeleopUnavailable(f"the SpaceMouse stopped responding: {type(e).__name__}: {e}") from e

    # ------------------------------------------------------------ events
    def inject(self, state) -> None:
        """Feed one device state: anything with the fields of ``pyspacemouse.read()``'s
        result (``x, y, z, roll, pitch, yaw`` in [-1, 1] and ``buttons``, a list of 0/1).

        Button presses act on the press edge (0 -> 1): button 0 toggles the vacuum, button 1
        queues ``"end"``.
        """
        raw = np.array([float(getattr(state, k)) for k in self.AXES])
        if not np.all(np.isfinite(raw)):
            raise ValueError(f"SpaceMouse state has non-finite axes: {dict(zip(self.AXES, raw))}")
        raw = np.clip(raw, -1.0, 1.0)
        mag = np.maximum(np.abs(raw) - self.deadzone, 0.0) / (1.0 - self.deadzone)
        buttons = tuple(int(bool(b)) for b in (getattr(state, "buttons", None) or ()))
        with self._lock:
            self._axes = np.sign(raw) * mag
            prev = self._buttons
            self._buttons = buttons
            for i, b in enumerate(buttons):
                if b and not (i < len(prev) and prev[i]):
                    if i == self.VACUUM_BUTTON:
                        self._toggle_vacuum()
                    elif i == self.END_BUTTON:
                        self._command("end")

    def _motion(self) -> np.ndarray:
        m = np.array([sign * self._axes[self.AXES.index(name)] for name, sign in self.axis_map])
        return m * self.scales

    def _held(self) -> bool:
        b = self._buttons
        return len(b) > self.VACUUM_BUTTON and bool(b[self.VACUUM_BUTTON])


#: A SpaceMouse state: the fields of ``pyspacemouse.read()``'s result.
SpaceMouseState = collections.namedtuple("SpaceMouseState", "t x y z roll pitch yaw buttons")


def legacy_to_z_up(state) -> SpaceMouseState:
    """Convert a state in ``pyspacemouse``'s legacy labels to the Z-up convention.

    Legacy labels are what versions without axis conventions report (and the default of
    those that have them): ``x``, ``y``, ``z`` as in Z-up, but ``roll`` is the rotation
    about y, ``pitch`` minus the rotation about x and ``yaw`` minus the rotation about z.
    """
    return SpaceMouseState(t=getattr(state, "t", 0.0), x=state.x, y=state.y, z=state.z,
                           roll=-state.pitch, pitch=state.roll, yaw=-state.yaw,
                           buttons=list(getattr(state, "buttons", None) or ()))


def make_device(name: str, **kwargs) -> TeleopDevice:
    """A device by name (:data:`DEVICES`); ``kwargs`` go to its constructor. Not started."""
    if name == "keyboard":
        return KeyboardDevice(**kwargs)
    if name == "spacemouse":
        return SpaceMouseDevice(**kwargs)
    raise ValueError(f"device {name!r} is not allowed; allowed {DEVICES}")


# ---------------------------------------------------------------------------- takeover
class DeviceTakeover:
    """A person with a device as the takeover source during training (HIL-SERL style).

    Implements the takeover-source protocol of :mod:`window_bench.installer.supervisor`: once per
    10 Hz step, before the action executes, :meth:`intervene` returns
    ``(device.action(), kind)`` while the device is active and ``None`` otherwise (a binary
    takeover: the operator's action replaces the policy's entirely). While the device is
    idle its vacuum latch follows the robot's actual suction state (``info
    ["suction_engaged"]``), so a takeover starts from what the robot is doing and a Space /
    button-0 toggle acts on that. The caller starts and stops the device.

    Parameters
    ----------
    device : TeleopDevice
    kind : str
        Takeover kind logged for these steps, ``"safety"`` (default) or ``"coverage"``.
    """

    def __init__(self, device: TeleopDevice, kind: str = "safety"):
        if not isinstance(device, TeleopDevice):
            raise ValueError(f"device must be a TeleopDevice, got {type(device).__name__}")
        if kind not in TAKEOVER_KINDS[1:]:
            raise ValueError(f"kind {kind!r} is not allowed; allowed {TAKEOVER_KINDS[1:]}")
        self.device = device
        self.kind = kind
        self.env = None
        self.takeover_steps = 0

    def reset(self, env, seed: int | None = None) -> None:
        """Start an episode on ``env`` (``seed`` is unused: a person is not seeded)."""
        self.env = env
        self.takeover_steps = 0
        self.device.reset(vacuum=_suction_engaged(env))

    def intervene(self, obs, info: dict) -> tuple[np.ndarray, str] | None:
        self.device.poll()
        engaged = (info or {}).get("suction_engaged")
        if engaged is None:
            engaged = _suction_engaged(self.env)
        if not self.device.sync_if_idle(bool(engaged)):
            return None
        self.takeover_steps += 1
        return self.device.action(), self.kind


def _suction_engaged(env) -> bool:
    if env is None:
        return False
    return bool(getattr(getattr(env, "unwrapped", env), "suction_engaged", False))


# ---------------------------------------------------------------------------- sessions
def teleop_dataset_id(env_id: str) -> str:
    """Minari id of the demonstrations of ``env_id``:
    ``WindowInstall-A-v0`` -> ``window-bench/teleop-a-v0``,
    ``WindowInstall-B-Panel60x40-v0`` -> ``window-bench/teleop-b-panel60x40-v0``."""
    import window_bench

    if env_id not in window_bench.ENV_IDS:
        raise ValueError(f"env {env_id!r} is not allowed; registered: {window_bench.ENV_IDS}")
    stem = env_id.removeprefix("WindowInstall-").rsplit("-v", 1)[0].lower()
    return f"window-bench/teleop-{stem}-v0"


@dataclass
class EpisodeOutcome:
    """How one teleoperated episode ended (``outcome`` in :data:`OUTCOMES`)."""

    seed: int
    steps: int
    outcome: str
    kept: bool
    episode_id: int | None = None

    @property
    def cycle_time_s(self) -> float:
        return self.steps * STEP_DT


@dataclass
class TeleopResult:
    """What :func:`teleop_session` did: the kept episodes and every episode's outcome."""

    env_id: str
    device: str
    episodes: list[EpisodeLog] = field(default_factory=list)
    outcomes: list[EpisodeOutcome] = field(default_factory=list)
    dataset_id: str | None = None
    dataset_path: Path | None = None


def _check_int(name, value, lo, hi=None) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} = {value!r} is not allowed: expected an integer")
    if value < lo or (hi is not None and value > hi):
        rng = f"[{lo}, {hi}]" if hi is not None else f">= {lo}"
        raise ValueError(f"{name} = {value!r} is not allowed: it must be {rng}")
    return int(value)


def _open_viewer(env):
    """Passive MuJoCo viewer on the env's model/data, framed from behind the robot."""
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY")
                                                 or os.environ.get("WAYLAND_DISPLAY")):
        raise TeleopUnavailable(
            "the MuJoCo viewer needs a display, and neither DISPLAY nor WAYLAND_DISPLAY is "
            "set: run on a workstation with a desktop session, or pass viewer=False "
            "(bench teleop --no-viewer). See docs/teleop.md.")
    try:
        import mujoco.viewer
        u = env.unwrapped
        handle = mujoco.viewer.launch_passive(u.model, u.data, show_left_ui=False,
                                              show_right_ui=False)
    except Exception as e:  # noqa: BLE001 - GLFW/OpenGL failures come in many types
        raise TeleopUnavailable(
            f"could not open the MuJoCo viewer ({type(e).__name__}: {e}); it needs a display "
            "with OpenGL (on macOS run under `mjpython`). See docs/teleop.md.") from e
    with handle.lock():
        handle.cam.lookat[:] = (0.4, -0.35, 0.45)   # between the robot and the opening
        handle.cam.distance = 2.4
        handle.cam.azimuth = -90.0                   # looking along -y, i.e. at the wall
        handle.cam.elevation = -25.0
    handle.sync()
    return handle


class _Pacer:
    """Wall-clock pacing at 10 Hz (a no-op when not real time)."""

    def __init__(self, realtime: bool):
        self.realtime = realtime
        self.next = time.monotonic()

    def wait(self) -> None:
        if not self.realtime:
            return
        self.next += STEP_DT
        delay = self.next - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        elif delay < -STEP_DT:   # fell behind (slow machine, GC): do not burst to catch up
            self.next = time.monotonic()


def _load_existing(dataset_id, env_id, record_dir) -> tuple[list[EpisodeLog], list]:
    """Episodes and session records already in ``record_dir`` (appending), or empty."""
    from window_bench.data.dataset import load_episodes

    path = Path(record_dir) / dataset_id
    if not path.exists():
        return [], []
    episodes = load_episodes(dataset_id, data_path=record_dir)
    other = sorted({ep.env_id for ep in episodes} - {env_id})
    if other:
        raise ValueError(f"dataset {dataset_id!r} at {path} holds episodes of {other}, "
                         f"not {env_id!r}; record into another directory")
    sessions = []
    meta_file = path / "data" / "metadata.json"
    try:
        sessions = list(json.loads(meta_file.read_text()).get("teleop_sessions", []))
    except (OSError, ValueError, AttributeError):
        pass
    return episodes, sessions


def teleop_session(env_id: str, device: TeleopDevice, record_dir: str | os.PathLike | None = None,
                   episodes: int = 1, viewer: bool = True, seed: int = 0,
                   max_steps: int = MAX_STEPS, *, keep_all: bool = False,
                   realtime: bool | None = None, start_on_input: bool = True,
                   operator: str = "human", verbose: bool = True) -> TeleopResult:
    """Teleoperate ``episodes`` episodes of ``env_id`` and record the demonstrations.

    Episode ``i`` resets with seed ``seed + i``. Each 10 Hz tick polls the device, handles a
    queued session command, executes ``device.action()`` and logs the step with provenance
    ``"demo"``, the stage flags from ``info`` and the Table 9 draws of the reset. With
    ``start_on_input`` the env does not step (and the clock does not run) until the device
    is first active, so demonstrations carry no idle lead-in.

    An episode ends when the env accepts the seating (``terminated``), at the time limit or
    on a simulator divergence (``truncated``), or by a device command: ``"end"`` (Enter,
    SpaceMouse button 1) truncates it where it is, ``"discard"`` (Backspace) drops it,
    ``"quit"`` (Esc, or closing the viewer) drops it and stops the session. Accepted episodes
    are kept; with ``keep_all`` the truncated ones are kept too. Discarded ones never are.

    With ``record_dir`` the kept episodes are saved after each one (so a crash loses at most
    the current episode) as the Minari dataset :func:`teleop_dataset_id` under ``record_dir``
    (the datasets root). An existing dataset there is appended to, episode ids continuing.
    Metadata: ``operator``, ``device``, ``env_id``, ``seeds`` (of all episodes, in order)
    and ``teleop_sessions`` (one record per session: device, seeds, episode ids, provenance).

    Parameters
    ----------
    env_id : str
        A registered id (``window_bench.ENV_IDS``); made with ``obs_mode="flat"``.
    device : TeleopDevice
        Started here if it is not yet (and then stopped at the end).
    viewer : bool
        Show the scene in ``mujoco.viewer.launch_passive`` (needs a display).
    max_steps : int
        Time limit in steps, in [1, 600].
    realtime : bool or None
        Pace the loop at 10 Hz wall clock; default: ``viewer``. False runs as fast as the
        env steps (scripted devices, tests).
    operator : str
        Who teleoperated: stored in each episode and the metadata.
    verbose : bool
        Print prompts and per-episode results to stdout.
    """
    import gymnasium as gym

    import window_bench
    from window_bench.data.dataset import save_episodes
    from window_bench.harness.evaluation import provenance as run_provenance

    if env_id not in window_bench.ENV_IDS:
        raise ValueError(f"env {env_id!r} is not allowed; registered: {window_bench.ENV_IDS}")
    if not isinstance(device, TeleopDevice):
        raise ValueError(f"device must be a TeleopDevice, got {type(device).__name__}")
    n_episodes = _check_int("episodes", episodes, 1)
    seed = _check_int("seed", seed, 0)
    max_steps = _check_int("max_steps", max_steps, 1, MAX_STEPS)
    if not isinstance(operator, str) or not operator:
        raise ValueError(f"operator = {operator!r} is not allowed: expected a non-empty str")
    realtime = bool(viewer) if realtime is None else bool(realtime)
    say = print if verbose else (lambda *a, **k: None)

    dataset_id = teleop_dataset_id(env_id) if record_dir is not None else None
    existing, sessions = ([], [])
    if record_dir is not None:
        existing, sessions = _load_existing(dataset_id, env_id, record_dir)
    next_id = max((ep.episode_id for ep in existing), default=-1) + 1

    result = TeleopResult(env_id=env_id, device=device.name, dataset_id=dataset_id)
    env = gym.make(env_id, obs_mode="flat", max_episode_steps=max_steps)
    handle = None
    started_here = not device.started
    try:
        # The first step of a process is slow (JIT and cache warm-up, ~0.5 s here, seconds
        # beside a software-rendered viewer): take it now, not on the operator's first input.
        env.reset(seed=seed)
        env.step(np.zeros(ACTION_DIM, dtype=np.float32))
        if viewer:
            handle = _open_viewer(env)
        if started_here:
            device.start()
        session = {"device": device.name, "operator": operator, "keep_all": bool(keep_all),
                   "seeds": [], "episode_ids": [], "provenance": run_provenance()}
        quit_session = False
        for i in range(n_episodes):
            ep_seed = seed + i
            obs, info = env.reset(seed=ep_seed)
            device.reset(vacuum=_suction_engaged(env))
            if handle is not None:
                handle.sync()
            say(f"episode {i + 1}/{n_episodes} (seed {ep_seed}): "
                + ("move to start; " if start_on_input else "")
                + "Enter ends, Backspace discards, Esc quits")
            randomization = dict(info.get("randomization", {}))
            observations, actions, rewards, flags = [obs], [], [], []
            terminated = truncated = False
            outcome = None
            pacer = _Pacer(realtime)
            waiting = start_on_input
            while outcome is None:
                device.poll()
                cmd = device.take_command()
                if handle is not None and not handle.is_running():
                    cmd = "quit"
                if cmd == "quit":
                    outcome, quit_session = "quit", True
                    break
                if cmd == "discard" or (cmd == "end" and not actions):
                    outcome = "discarded"
                    break
                if cmd == "end":
                    truncated, outcome = True, "ended"
                    break
                if waiting and not device.active:
                    pacer.wait()
                    continue
                waiting = False
                a = device.action()
                obs, reward, terminated, truncated, info = env.step(a)
                observations.append(obs)
                actions.append(a)
                rewards.append(reward)
                flags.append([bool(info.get(k, False)) for k in STAGE_FLAGS])
                if handle is not None:
                    handle.sync()
                if terminated:
                    outcome = "accepted"
                elif truncated:
                    outcome = "unstable" if info.get("sim_unstable") else "time_limit"
                else:
                    pacer.wait()

            T = len(actions)
            kept = outcome == "accepted" or (keep_all and outcome in ("ended", "time_limit",
                                                                      "unstable"))
            ep_id = None
            if kept:
                ep_id = next_id
                next_id += 1
                end = np.zeros(T, dtype=bool)
                end[-1] = True
                ep = EpisodeLog(
                    observations=np.stack(observations), actions=np.stack(actions),
                    rewards=np.asarray(rewards, dtype=np.float32),
                    terminated=end & bool(terminated), truncated=end & (not terminated),
                    provenance=np.full(T, "demo"), takeover_kind=np.full(T, ""),
                    episode_id=ep_id, env_id=env_id, seed=ep_seed,
                    stage_flags=np.asarray(flags, dtype=bool).reshape(T, len(STAGE_FLAGS)),
                    randomization=randomization, operator=operator,
                )
                ep.validate()
                result.episodes.append(ep)
                session["seeds"].append(ep_seed)
                session["episode_ids"].append(ep_id)
                if record_dir is not None:
                    all_eps = existing + result.episodes
                    meta = {"operator": operator, "device": device.name, "env_id": env_id,
                            "seeds": [int(e.seed) for e in all_eps],
                            "teleop_sessions": sessions + [session]}
                    result.dataset_path = save_episodes(
                        all_eps, dataset_id, env_id=env_id, obs_dim=int(ep.observations.shape[1]),
                        data_path=record_dir, metadata=meta, overwrite=True)
            result.outcomes.append(EpisodeOutcome(seed=ep_seed, steps=T, outcome=outcome,
                                                  kept=kept, episode_id=ep_id))
            say(f"  {outcome} after {T} steps ({T * STEP_DT:.1f} s)"
                + (f", kept as episode {ep_id}" if kept else ", not kept"))
            if quit_session:
                break
    finally:
        if started_here:
            device.stop()
        if handle is not None:
            handle.close()
        env.close()
    if result.dataset_path is not None:
        say(f"{len(result.episodes)} episode(s) saved to {result.dataset_id!r} under "
            f"{record_dir} ({result.dataset_path})")
    return result


def probe(device: TeleopDevice, seconds: float | None = None, out=None) -> None:
    """Print the device's action and activity at 10 Hz (check a key map or axis signs).

    Runs until the device issues ``"quit"`` (Esc) or for ``seconds``.
    """
    out = out or sys.stdout
    t_end = None if seconds is None else time.monotonic() + float(seconds)
    pacer = _Pacer(True)
    while t_end is None or time.monotonic() < t_end:
        device.poll()
        cmd = device.take_command()
        if cmd == "quit":
            break
        active = device.active
        a = device.action()
        out.write(f"{'ACTIVE' if active else 'idle  '} "
                  + " ".join(f"{v:+.2f}" for v in a) + (f"  [{cmd}]" if cmd else "") + "\n")
        out.flush()
        pacer.wait()


# ---------------------------------------------------------------------------- CLI
def _env_arg(value: str) -> str:
    import window_bench

    if value not in window_bench.ENV_IDS:
        raise argparse.ArgumentTypeError(
            f"unknown env {value!r}; registered: {', '.join(window_bench.ENV_IDS)}")
    return value


def _int_arg(lo: int, hi: int | None = None):
    def parse(value: str) -> int:
        try:
            v = int(value)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {value!r}") from None
        if v < lo or (hi is not None and v > hi):
            rng = f"in [{lo}, {hi}]" if hi is not None else f">= {lo}"
            raise argparse.ArgumentTypeError(f"must be {rng}, got {v}")
        return v
    return parse


def add_teleop_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``bench teleop`` on an ``argparse`` subparsers object; returns the parser."""
    p = subparsers.add_parser(
        "teleop", help="drive the robot with a keyboard or SpaceMouse and record demonstrations",
        description="Teleoperate the window installation in the MuJoCo viewer and record "
                    "demonstrations (provenance 'demo') as a Minari dataset. Needs a display "
                    f"and the teleop extra: {INSTALL_HINT}. See docs/teleop.md.")
    p.add_argument("--env", type=_env_arg, default="WindowInstall-A-v0", help="registered env id")
    p.add_argument("--device", choices=DEVICES, default="keyboard", help="input device")
    p.add_argument("--record", metavar="DIR",
                   help="datasets root to save the demonstrations in (appends if present)")
    p.add_argument("--episodes", type=_int_arg(1), default=1, help="episodes to teleoperate")
    p.add_argument("--seed", type=_int_arg(0), default=0, help="seed of the first episode")
    p.add_argument("--max-steps", type=_int_arg(1, MAX_STEPS), default=MAX_STEPS,
                   help=f"time limit in 10 Hz steps (1..{MAX_STEPS})")
    p.add_argument("--keep-all", action="store_true",
                   help="also keep episodes that were not accepted (ended, time limit)")
    p.add_argument("--operator", default="human", help="who is teleoperating (stored)")
    p.add_argument("--no-viewer", action="store_true", help="do not open the MuJoCo viewer")
    p.add_argument("--probe", action="store_true",
                   help="only print the device's actions at 10 Hz (Esc stops); no env")
    p.set_defaults(func=cmd_teleop)
    return p


def cmd_teleop(args) -> int:
    """``bench teleop``: returns the process exit code (2 if a device/display is missing)."""
    device = make_device(args.device)
    try:
        with device:
            if args.probe:
                probe(device)
                return 0
            result = teleop_session(args.env, device, record_dir=args.record,
                                    episodes=args.episodes, viewer=not args.no_viewer,
                                    seed=args.seed, max_steps=args.max_steps,
                                    keep_all=args.keep_all, realtime=True,
                                    operator=args.operator)
    except TeleopUnavailable as e:
        print(f"bench teleop: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("bench teleop: interrupted (episodes kept before this one are already saved)",
              file=sys.stderr)
        return 130
    accepted = sum(o.outcome == "accepted" for o in result.outcomes)
    print(f"{len(result.outcomes)} episode(s): {accepted} accepted, "
          f"{len(result.episodes)} kept")
    return 0
