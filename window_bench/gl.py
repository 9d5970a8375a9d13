"""OpenGL for ``mujoco.Renderer`` on machines with and without a display.

``mujoco`` picks its OpenGL backend from ``MUJOCO_GL`` once, when it is first imported; unset,
that is GLFW, which on a machine without a display dies in native code (a fatal error and an
abort) the first time anything renders. So ``import window_bench`` sets ``MUJOCO_GL`` when
it is unset and there is no display: EGL, else OSMesa, whichever library is installed.
Nothing is set when the user chose a backend. Finding the library, not opening a context,
keeps the import cheap. :func:`renderer` turns the remaining failure into one Python error.
"""

from __future__ import annotations

import ctypes.util
import os
import sys

# (MUJOCO_GL value, the library PyOpenGL loads for it), in order of preference.
HEADLESS = (("egl", "EGL"), ("osmesa", "OSMesa"))


class NoOpenGLError(RuntimeError):
    """Rendering needs OpenGL that this machine does not offer."""


def _has_display(environ=os.environ) -> bool:
    return sys.platform != "linux" or bool(environ.get("DISPLAY") or environ.get("WAYLAND_DISPLAY"))


def choose_headless_backend(environ=os.environ, find_library=ctypes.util.find_library):
    """Set ``environ["MUJOCO_GL"]`` to the first installed headless backend when it is
    unset and there is no display; returns the value set, or None."""
    if environ.get("MUJOCO_GL") or _has_display(environ):
        return None
    for backend, lib in HEADLESS:
        if find_library(lib):
            environ["MUJOCO_GL"] = backend
            return backend
    return None


def renderer(model, height: int, width: int):
    """``mujoco.Renderer(model, height, width)``, or :class:`NoOpenGLError` with what to do
    where it would abort the process."""
    import mujoco

    backend = getattr(getattr(mujoco, "GLContext", None), "__module__", "")  # none: disabled
    if backend.startswith("mujoco.glfw") and not _has_display():
        if os.environ.get("MUJOCO_GL") in ("egl", "osmesa"):
            why = (f"mujoco was imported before window_bench, so MUJOCO_GL="
                   f"{os.environ['MUJOCO_GL']} came too late; import window_bench first or "
                   f"set MUJOCO_GL before starting Python")
        else:
            why = ("no EGL or OSMesa library was found (Debian: apt-get install libegl1 or "
                   "libosmesa6), or set MUJOCO_GL to a backend that works here")
        raise NoOpenGLError(f"cannot render: no display (DISPLAY is unset) and {why}")
    return mujoco.Renderer(model, height, width)
