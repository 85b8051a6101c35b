"""
The POPLIN paper's benchmark (Wang & Ba 2019, table 1, plus Swimmer-v0): its task names -> this package's env ids.

One table, :data:`PAPER_TASKS`, gives each of the 13 tasks its gymnasium id, the paper's training budget and the
planning horizon of the original code (25 for Reacher3D and Pusher, else 30). ``hyperparams/poplin.yml`` and the
baseline files hold an entry with the same budget for each id, and ``benchmarks/compare.py --suite paper`` runs the
13 under these names (``tests/test_zoo.py`` checks both).

This module imports nothing beyond the standard library.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class PaperTask:
    """
    One task of the paper's table.

    :param name: the paper's name, e.g. ``"Cheetah-v0"``
    :param env_id: the gymnasium id that defines it here
    :param n_timesteps: the paper's training steps
    :param horizon: the planning horizon of the original code
    :param origin: where the task's definition comes from (PETS, MBBL's ``gym_*`` wrapper)
    """

    name: str
    env_id: str
    n_timesteps: int
    horizon: int
    origin: str


# In the paper's table order (first row of tasks, second row, then Swimmer-v0).
PAPER_TASKS: dict[str, PaperTask] = {
    task.name: task
    for task in (
        PaperTask("Cheetah", "sb3_poplin/PETSCheetah-v0", 50_000, 30, "PETS halfcheetah"),
        PaperTask("Ant", "sb3_poplin/AntNoTerm-v0", 200_000, 30, "MBBL gym_ant"),
        PaperTask("Hopper", "sb3_poplin/HopperNoTerm-v0", 200_000, 30, "MBBL gym_hopper"),
        PaperTask("Swimmer", "sb3_poplin/FixedSwimmer-v0", 50_000, 30, "MBBL gym_fswimmer"),
        PaperTask("Cheetah-v0", "HalfCheetah-v5", 200_000, 30, "MBBL gym_cheetah"),
        PaperTask("Walker2d", "sb3_poplin/Walker2dNoTerm-v0", 200_000, 30, "MBBL gym_walker2d"),
        PaperTask("Reacher3D", "sb3_poplin/PETSReacher3D-v0", 50_000, 25, "PETS reacher"),
        PaperTask("Pusher", "sb3_poplin/PETSPusher-v0", 50_000, 25, "PETS pusher"),
        PaperTask("Pendulum", "sb3_poplin/MBBLPendulum-v0", 50_000, 30, "MBBL gym_pendulum"),
        PaperTask("InvertedPendulum", "sb3_poplin/MBBLInvertedPendulum-v0", 50_000, 30, "MBBL gym_invertedPendulum"),
        PaperTask("Acrobot", "sb3_poplin/MBBLAcrobot-v0", 50_000, 30, "MBBL gym_acrobot"),
        PaperTask("Cartpole", "sb3_poplin/MBBLCartpole-v0", 50_000, 30, "MBBL gym_cartpole"),
        # Not in the table we have; its budget is taken to be Swimmer's.
        PaperTask("Swimmer-v0", "Swimmer-v5", 50_000, 30, "MBBL gym_swimmer"),
    )
}


def paper_task(name: str) -> PaperTask:
    """
    :param name: a task name of the paper, e.g. ``"Reacher3D"``
    :return: its entry
    :raises ValueError: for a name the paper does not use
    """
    try:
        return PAPER_TASKS[name]
    except KeyError:
        raise ValueError(f"{name!r} is not a task of the POPLIN paper; its tasks are {list(PAPER_TASKS)}.") from None


def paper_name(env_id: str) -> str | None:
    """
    :param env_id: a gymnasium id
    :return: the paper's name of the task it defines, or ``None``
    """
    return next((task.name for task in PAPER_TASKS.values() if task.env_id == env_id), None)


__all__ = ["PAPER_TASKS", "PaperTask", "paper_name", "paper_task"]
