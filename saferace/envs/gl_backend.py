"""Choose MuJoCo's offscreen OpenGL backend before ``mujoco`` is first imported.

MuJoCo reads ``MUJOCO_GL`` once, when it is imported. When the user has not set it,
SafeRace tries Mesa's EGL (works without a GPU), then OSMesa, each in a short-lived
subprocess so that a failing backend cannot poison this process, and exports the
first that renders (child processes, such as vector-env workers, inherit it). When
neither works, rendering raises :class:`RenderingUnavailableError` saying what to
install.

Mesa's software renderer (llvmpipe) loads LLVM: OSMesa when ``mujoco`` is imported, EGL
with the first GL context. Triton, which CUDA builds of PyTorch import (``torch._dynamo``,
so also ``torchvision``), bundles its own LLVM, whose static initialisers crash the process
(``llvm::DebugCounter``, a segmentation fault seen under gdb) when Mesa's LLVM is already
loaded; the other order works. :func:`load_llvm_users_before_mesa` therefore imports Triton
(0.12 s, without torch), where it is installed, before ``mujoco``, so that the learned
driver can be imported at any time.
"""

from __future__ import annotations

import importlib
import importlib.util
import logging
import os
import subprocess
import sys
from collections.abc import Callable, Sequence

from saferace.errors import SafeRaceError

logger = logging.getLogger(__name__)

BACKENDS = ("egl", "osmesa")
INSTALL_HINT = (
    "install Mesa's offscreen rendering libraries (Debian/Ubuntu: "
    "apt-get install libegl1 libgl1-mesa-dri libosmesa6; `make setup` does it as root), "
    "or set MUJOCO_GL to a backend that works on this machine"
)
_PROBE = (
    "import mujoco\n"
    "xml = '<mujoco><worldbody><geom size=\"1\"/></worldbody></mujoco>'\n"
    "model = mujoco.MjModel.from_xml_string(xml)\n"
    "renderer = mujoco.Renderer(model, 8, 8)\n"
    "renderer.update_scene(mujoco.MjData(model))\n"
    "renderer.render()\n"
)


class RenderingUnavailableError(SafeRaceError, RuntimeError):
    """No offscreen OpenGL backend could be started."""


def probe_backend(backend: str) -> bool:
    """Whether MuJoCo can render offscreen with ``MUJOCO_GL=backend`` (checked in a subprocess)."""
    env = {**os.environ, "MUJOCO_GL": backend}
    env.pop("PYOPENGL_PLATFORM", None)
    try:
        result = subprocess.run(
            [sys.executable, "-c", _PROBE], env=env, capture_output=True, timeout=60, check=False
        )
    except (OSError, subprocess.TimeoutExpired):
        return False
    return result.returncode == 0


def choose_backend(
    candidates: Sequence[str] = BACKENDS, probe: Callable[[str], bool] = probe_backend
) -> str | None:
    """The first backend of ``candidates`` that ``probe`` accepts, or None."""
    for backend in candidates:
        if probe(backend):
            return backend
        logger.info("MuJoCo offscreen backend %s is not available", backend)
    return None


def configure_gl_backend() -> None:
    """Set ``MUJOCO_GL`` (and PyOpenGL's platform) unless the user already chose a backend."""
    if os.environ.get("MUJOCO_GL"):
        return
    if "mujoco" in sys.modules:
        logger.warning(
            "mujoco was imported before saferace.envs with MUJOCO_GL unset; offscreen rendering "
            "may fail. Set MUJOCO_GL=egl (or osmesa) before importing mujoco."
        )
        return
    backend = choose_backend()
    if backend is None:
        os.environ["MUJOCO_GL"] = "disable"
        logger.warning("no offscreen rendering backend works (tried %s)", ", ".join(BACKENDS))
        return
    os.environ["MUJOCO_GL"] = backend
    os.environ.setdefault("PYOPENGL_PLATFORM", backend)


#: Libraries with a bundled LLVM that must be loaded before Mesa's (see the module docstring).
LLVM_BEFORE_MESA = ("triton",)


def load_llvm_users_before_mesa() -> None:
    """Import the installed :data:`LLVM_BEFORE_MESA` libraries, unless ``mujoco`` came first."""
    for name in LLVM_BEFORE_MESA:
        if name in sys.modules or importlib.util.find_spec(name) is None:
            continue
        if "mujoco" in sys.modules:
            logger.warning(
                "mujoco was imported before saferace.envs: importing PyTorch's %s (torchvision, "
                "the learned driver) after rendering with Mesa may crash this process",
                name,
            )
            return
        try:
            importlib.import_module(name)
        except Exception as exc:  # a broken install must not stop the simulator
            logger.warning(
                "could not load %s before Mesa (%s): the learned driver may crash", name, exc
            )


#: The process that made the first OpenGL context, if any (see :func:`check_gl_process`).
_GL_OWNER_PID: int | None = None


def check_gl_process() -> None:
    """Before making a renderer: refuse in a child forked from a process that rendered.

    Mesa's EGL and OSMesa do not survive ``fork`` once a context exists (the child hangs
    in its first context), which is what ``gymnasium.make_vec(..., vectorization_mode=
    "async")`` does by default on Linux; spawned children are fine. :func:`note_gl_process`
    records a process once it has a renderer.
    """
    if _GL_OWNER_PID is not None and os.getpid() != _GL_OWNER_PID:
        raise RenderingUnavailableError(
            f"this process was forked from process {_GL_OWNER_PID} after it rendered, and "
            "offscreen OpenGL does not survive a fork: start subprocesses with spawn, e.g. "
            'gymnasium.make_vec(..., vectorization_mode="async", '
            'vector_kwargs={"context": "spawn"})'
        )


def has_rendered() -> bool:
    """Whether this process (or one it was forked from) has made an OpenGL context: a child
    forked from it could not render."""
    return _GL_OWNER_PID is not None


def note_gl_process() -> None:
    """Record this process as one that has made an OpenGL context."""
    global _GL_OWNER_PID
    _GL_OWNER_PID = os.getpid()


def renderer_error(exc: BaseException) -> RenderingUnavailableError:
    """The error to raise when a MuJoCo renderer cannot be created."""
    backend = os.environ.get("MUJOCO_GL")
    if backend == "disable":
        tried = f"none of the offscreen OpenGL backends works here (tried {', '.join(BACKENDS)})"
    elif backend:
        tried = f"cannot create an offscreen renderer with MUJOCO_GL={backend} ({exc})"
    else:
        tried = (
            f"cannot create an offscreen renderer ({exc}): mujoco was imported before "
            "saferace.envs with MUJOCO_GL unset; set MUJOCO_GL=egl"
        )
    return RenderingUnavailableError(f"{tried}; {INSTALL_HINT}")
