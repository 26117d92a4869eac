"""MuJoCo scenes, the racing tasks and their registry.

Importing this package chooses MuJoCo's offscreen OpenGL backend (see
:mod:`saferace.envs.gl_backend`) before ``mujoco`` is imported.
"""

from saferace.envs.gl_backend import configure_gl_backend

configure_gl_backend()
