"""Indoor path-following environments built on MuJoCo and labmaze, for TorchRL.

Importing :mod:`envs` selects a headless OpenGL back-end (``MUJOCO_GL``) before
MuJoCo opens any context; see :func:`envs.render.select_gl_backend`.
"""
from __future__ import annotations

from envs.render import select_gl_backend

select_gl_backend()
