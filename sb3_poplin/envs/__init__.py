"""
The POPLIN paper's extra tasks as gymnasium environments, registered under the ``sb3_poplin/`` namespace.

Importing :mod:`sb3_poplin` registers them; entry points are strings, so MuJoCo is only imported when a
MuJoCo-based one is made. Their :class:`~sb3_poplin.tasks.TaskSpec` are in :mod:`sb3_poplin.tasks.paper`,
:mod:`sb3_poplin.tasks.pets_arm` and :mod:`sb3_poplin.tasks.mbbl`.

========================================  =========================================================  =====
id                                        what                                                       steps
========================================  =========================================================  =====
``sb3_poplin/PETSCheetah-v0``             HalfCheetah-v5 with obs[0] = forward velocity (PETS)       1000
``sb3_poplin/CartPoleSwingUp-v0``         continuous cart-pole swing-up (numpy)                      200
``sb3_poplin/AcrobotSwingUp-v0``          continuous Acrobot swing-up (numpy)                        200
``sb3_poplin/FixedSwimmer-v0``            Swimmer-v5 paid the head's x velocity (last obs entry)     1000
``sb3_poplin/HopperNoTerm-v0``            Hopper-v5, shaped reward, never terminates                 1000
``sb3_poplin/Walker2dNoTerm-v0``          Walker2d-v5, shaped reward, never terminates               1000
``sb3_poplin/AntNoTerm-v0``               Ant-v5, shaped reward, never terminates                    1000
``sb3_poplin/PETSReacher3D-v0``           PETS's 7-DoF arm reaching a 3-D goal                       150
``sb3_poplin/PETSPusher-v0``              PETS's 7-DoF arm pushing a cylinder to a goal              150
``sb3_poplin/MBBLPendulum-v0``            MBBL's Pendulum (gym Pendulum-v0, MBBL reward)             201
``sb3_poplin/MBBLInvertedPendulum-v0``    MBBL's InvertedPendulum (reward -theta^2, no termination)  101
``sb3_poplin/MBBLAcrobot-v0``             MBBL's Acrobot (three torques, tip height)                 201
``sb3_poplin/MBBLCartpole-v0``            MBBL's Cartpole balance (bang-bang force, no termination)  201
========================================  =========================================================  =====
"""

from __future__ import annotations

import gymnasium as gym

NAMESPACE = "sb3_poplin"

_ENVS: dict[str, tuple[str, int]] = {
    "PETSCheetah-v0": ("sb3_poplin.envs.mujoco_variants:PETSCheetahEnv", 1000),
    "CartPoleSwingUp-v0": ("sb3_poplin.envs.cartpole_swingup:CartPoleSwingUpEnv", 200),
    "AcrobotSwingUp-v0": ("sb3_poplin.envs.acrobot_swingup:AcrobotSwingUpEnv", 200),
    "FixedSwimmer-v0": ("sb3_poplin.envs.mujoco_variants:FixedSwimmerEnv", 1000),
    "HopperNoTerm-v0": ("sb3_poplin.envs.mujoco_variants:HopperNoTermEnv", 1000),
    "Walker2dNoTerm-v0": ("sb3_poplin.envs.mujoco_variants:Walker2dNoTermEnv", 1000),
    "AntNoTerm-v0": ("sb3_poplin.envs.mujoco_variants:AntNoTermEnv", 1000),
    "PETSReacher3D-v0": ("sb3_poplin.envs.pets_arm:PETSReacher3DEnv", 150),
    "PETSPusher-v0": ("sb3_poplin.envs.pets_arm:PETSPusherEnv", 150),
    # MBBL ends an episode once its step count exceeds max_length (200, InvertedPendulum 100)
    "MBBLPendulum-v0": ("sb3_poplin.envs.mbbl_classic:MBBLPendulumEnv", 201),
    "MBBLInvertedPendulum-v0": ("sb3_poplin.envs.mujoco_variants:MBBLInvertedPendulumEnv", 101),
    "MBBLAcrobot-v0": ("sb3_poplin.envs.mbbl_classic:MBBLAcrobotEnv", 201),
    "MBBLCartpole-v0": ("sb3_poplin.envs.mbbl_classic:MBBLCartpoleEnv", 201),
}

ENV_IDS: tuple[str, ...] = tuple(f"{NAMESPACE}/{name}" for name in _ENVS)


def register_envs() -> None:
    """Register every env of this package with gymnasium (a no-op for ids already registered)."""
    for name, (entry_point, max_episode_steps) in _ENVS.items():
        env_id = f"{NAMESPACE}/{name}"
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=entry_point, max_episode_steps=max_episode_steps)


register_envs()

__all__ = ["ENV_IDS", "NAMESPACE", "register_envs"]
