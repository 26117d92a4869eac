"""Offscreen rendering: EGL by default, OSMesa as fallback, clear advice when neither works."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from saferace.envs.gl_backend import INSTALL_HINT, choose_backend, renderer_error

RENDER_ONE_FRAME = (
    "import saferace.envs, os, gymnasium as gym, saferace\n"
    "env = gym.make('saferace/CenterLine-v0', track='oval')\n"
    "obs, _ = env.reset(seed=0)\n"
    "print(os.environ['MUJOCO_GL'], int(obs['image'].mean()))\n"
    "env.close()\n"
)


def run_python(code: str, *args: str, **env_changes: str | None) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    for key, value in env_changes.items():
        if value is None:
            env.pop(key, None)
        else:
            env[key] = value
    return subprocess.run(
        [sys.executable, "-c", code, *args], env=env, capture_output=True, text=True, check=False
    )


def test_egl_is_chosen_when_unset():
    result = run_python(RENDER_ONE_FRAME, MUJOCO_GL=None, PYOPENGL_PLATFORM=None)
    assert result.returncode == 0, result.stderr
    backend, mean = result.stdout.split()
    assert backend == "egl"
    assert 40 < int(mean) < 220


def test_falls_back_to_osmesa_when_egl_is_broken():
    result = run_python(
        RENDER_ONE_FRAME,
        MUJOCO_GL=None,
        PYOPENGL_PLATFORM=None,
        __EGL_VENDOR_LIBRARY_FILENAMES="/nonexistent/egl_vendor.json",
    )
    assert result.returncode == 0, result.stderr
    backend, mean = result.stdout.split()
    assert backend == "osmesa"
    assert 40 < int(mean) < 220


SAVE_ONE_FRAME = (
    "import sys, numpy as np, gymnasium as gym, saferace\n"
    "env = gym.make('saferace/CenterLine-v0', track='oval')\n"
    "obs, _ = env.reset(seed=0)\n"
    "np.save(sys.argv[1], obs['image'])\n"
    "env.close()\n"
)


def test_egl_and_osmesa_render_the_same_scene(tmp_path):
    """Pixel by pixel (both are Mesa's rasteriser here, and agree exactly; a GPU's EGL may
    differ by a level or two at edges), not by the mean brightness, which a moved camera or
    a missing texture can keep."""
    images = {}
    for backend in ("egl", "osmesa"):
        path = tmp_path / f"{backend}.npy"
        result = run_python(SAVE_ONE_FRAME, str(path), MUJOCO_GL=backend, PYOPENGL_PLATFORM=None)
        assert result.returncode == 0, result.stderr
        images[backend] = np.load(path).astype(int)
    assert images["egl"].std() > 20  # a scene, not a blank frame
    difference = np.abs(images["egl"] - images["osmesa"])
    assert difference.mean() < 1.0 and np.mean(difference <= 8) > 0.99


def test_choose_backend_order_and_none():
    tried = []

    def probe(backend: str) -> bool:
        tried.append(backend)
        return backend == "osmesa"

    assert choose_backend(probe=probe) == "osmesa"
    assert tried == ["egl", "osmesa"]
    assert choose_backend(probe=lambda backend: False) is None


def test_without_any_backend_the_error_says_what_to_install():
    error = renderer_error(RuntimeError("no display"))
    assert "libegl1" in str(error) and "libosmesa6" in str(error)
    assert INSTALL_HINT in str(error)


def test_a_machine_without_backends_gets_the_advice_from_the_env():
    """A bogus Gallium driver breaks both Mesa backends (OSMesa even crashes its probe)."""
    code = (
        "import saferace.envs, gymnasium as gym, saferace\n"
        "env = gym.make('saferace/CenterLine-v0', track='oval')\n"
        "env.reset()\n"
    )
    result = run_python(code, MUJOCO_GL=None, PYOPENGL_PLATFORM=None, GALLIUM_DRIVER="bogus")
    assert result.returncode == 1
    assert "RenderingUnavailableError: none of the offscreen OpenGL backends works" in result.stderr
    assert "apt-get install libegl1 libgl1-mesa-dri libosmesa6" in result.stderr


@pytest.mark.parametrize("variable", ["MUJOCO_GL"])
def test_user_choice_is_respected(variable: str):
    result = run_python(
        "import saferace.envs, os; print(os.environ['MUJOCO_GL'])", **{variable: "osmesa"}
    )
    assert result.stdout.strip() == "osmesa"


@pytest.mark.parametrize("backend", ["egl", "osmesa"])
def test_learned_driver_can_be_imported_after_rendering(backend: str):
    """Mesa's LLVM is loaded with the first context; Triton's (CUDA PyTorch) must come first."""
    code = RENDER_ONE_FRAME + "import torchvision\nprint('imported')\n"
    result = run_python(code, MUJOCO_GL=backend, PYOPENGL_PLATFORM=None)
    assert result.returncode == 0, f"exit {result.returncode}: {result.stderr[-2000:]}"
    assert result.stdout.split()[-1] == "imported"
