"""MuJoCo scenes, the racing tasks and their registry.

Importing this package chooses MuJoCo's offscreen OpenGL backend, and loads the libraries
whose LLVM must come before Mesa's (see :mod:`saferace.envs.gl_backend`), before ``mujoco``
is imported.
"""

from saferace.envs.gl_backend import configure_gl_backend, load_llvm_users_before_mesa

configure_gl_backend()
load_llvm_users_before_mesa()
