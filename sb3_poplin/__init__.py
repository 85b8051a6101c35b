"""sb3_poplin: POPLIN, PETS and random shooting for Stable-Baselines3."""

import os

from sb3_poplin import envs  # noqa: F401  (registers the sb3_poplin/... gymnasium ids)
from sb3_poplin.poplin import POPLIN
from sb3_poplin.tasks import TaskSpec, make_task, register_task

with open(os.path.join(os.path.dirname(__file__), "version.txt")) as _file:
    __version__ = _file.read().strip()

__all__ = ["POPLIN", "TaskSpec", "__version__", "make_task", "register_task"]
