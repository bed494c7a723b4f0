"""Headless OpenGL for MuJoCo's rendering: EGL or OSMesa, whichever can make a context here.

Gymnasium's MuJoCo renderer reads MUJOCO_GL when it makes its first context, and PyOpenGL fixes its platform
when first imported (which that first context does), so `choose_gl_backend()` must run before the process
renders anything: the CLI calls it first, `softac.outputs.video.record` before it makes its env (a notebook that
trained an agent can then film it). dm_control picks its own backend when imported (softac.envs.dmc).
"""

from __future__ import annotations

import os
import subprocess
import sys

from softac.errors import SoftacError

GL_BACKENDS = ("egl", "osmesa")
NO_GL_MESSAGE = ("headless rendering found neither EGL nor OSMesa: install Debian's libegl1 (with a Mesa or NVIDIA "
                 "driver) or libosmesa6 (apt-get install libosmesa6), or set MUJOCO_GL")
_PROBE = ("import os, sys; os.environ['MUJOCO_GL'] = sys.argv[1]; import mujoco; "
          "ctx = mujoco.GLContext(16, 16); ctx.make_current(); ctx.free()")


def gl_backend_works(backend: str) -> bool:
    try:
        r = subprocess.run([sys.executable, "-c", _PROBE, backend], capture_output=True, timeout=60)
    except (subprocess.TimeoutExpired, OSError):
        return False
    return r.returncode == 0


def choose_gl_backend() -> str:
    """MUJOCO_GL as set by the user, else the first backend that can make a context here."""
    chosen = os.environ.get("MUJOCO_GL")
    if chosen:
        return chosen
    if "OpenGL" in sys.modules:  # PyOpenGL fixed its platform when imported: too late to choose for this process
        return "preset"
    backend = working_gl_backend()
    if backend is None:
        raise SoftacError(NO_GL_MESSAGE)
    return backend


def working_gl_backend() -> str | None:
    """The first headless backend that can make a context here (set as MUJOCO_GL, which child processes
    inherit), or None."""
    for backend in GL_BACKENDS:
        if gl_backend_works(backend):
            os.environ["MUJOCO_GL"] = backend
            os.environ.setdefault("PYOPENGL_PLATFORM", backend)
            return backend
    return None
