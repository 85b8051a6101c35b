"""
Gymnasium v5 MuJoCo tasks.

Formulas and default weights are those of the ``gymnasium`` 1.4 ``*_v5.py`` environments. The
locomotion tasks whose reward is a forward velocity (HalfCheetah, Hopper, Walker2d, Swimmer, Ant)
are made with ``exclude_current_positions_from_observation=False``, so the observation starts with
the root position and the velocity is ``(x' - x) / dt`` between two observations; the dynamics model
and the policy do not see those positions as inputs (``model_input_exclude``).
"""

from __future__ import annotations


import torch as th

from sb3_poplin.tasks import TaskSpec, register_task, squared_norm
from sb3_poplin.tasks.hooks import LocomotionHooks

KEEP_POSITIONS = {"exclude_current_positions_from_observation": False}


def _not_finite(next_obs: th.Tensor) -> th.Tensor:
    """:return: True where some entry of ``next_obs`` is NaN or infinite"""
    return ~th.isfinite(next_obs).all(dim=-1)


# ---------------------------------------------------------------------------------------------------------------------
# InvertedPendulum-v5: obs = [cart x, pole angle, cart velocity, pole angular velocity], action in [-3, 3]
INVERTED_PENDULUM_ANGLE = 1
INVERTED_PENDULUM_MAX_ANGLE = 0.2


def inverted_pendulum_termination(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    """InvertedPendulum-v5 terminates when the next obs is not finite or ``|pole angle| > 0.2``."""
    return _not_finite(next_obs) | (next_obs[..., INVERTED_PENDULUM_ANGLE].abs() > INVERTED_PENDULUM_MAX_ANGLE)


def inverted_pendulum_reward(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    """InvertedPendulum-v5 pays 1 per step that does not terminate (0 on the terminating step)."""
    return (~inverted_pendulum_termination(obs, action, next_obs)).to(next_obs.dtype)


# ---------------------------------------------------------------------------------------------------------------------
# HalfCheetah-v5 with x kept: obs = [qpos (9): x, z, angle, 6 joints; qvel (9)], dt = 0.01 * 5
HALF_CHEETAH_X = 0
HALF_CHEETAH_DT = 0.05
HALF_CHEETAH_CTRL_COST = 0.1


def half_cheetah_reward(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    """HalfCheetah-v5: ``(x' - x) / dt - 0.1 |a|^2``."""
    forward = (next_obs[..., HALF_CHEETAH_X] - obs[..., HALF_CHEETAH_X]) / HALF_CHEETAH_DT
    return forward - HALF_CHEETAH_CTRL_COST * squared_norm(action)


# ---------------------------------------------------------------------------------------------------------------------
# Hopper-v5 with x kept: obs = [qpos (6): x, z, angle, thigh, leg, foot; clip(qvel, -10, 10) (6)], dt = 0.002 * 4
HOPPER_X, HOPPER_Z, HOPPER_ANGLE = 0, 1, 2
HOPPER_DT = 0.008
HOPPER_CTRL_COST = 1e-3
HOPPER_MIN_Z = 0.7
HOPPER_MAX_ANGLE = 0.2
HOPPER_MAX_STATE = 100.0
# The env checks ``state_vector()[2:]`` = qpos[2:] and the *unclipped* qvel, i.e. obs[2:] of this layout.
HOPPER_STATE_START = 2


def hopper_healthy(next_obs: th.Tensor) -> th.Tensor:
    """
    Hopper-v5 ``is_healthy``: ``z > 0.7``, ``|angle| < 0.2`` and every entry of ``state_vector()[2:]``
    strictly inside (-100, 100). The env checks the unclipped qvel while the observation clips it to
    [-10, 10], so only a joint velocity above 100 (never seen in practice) could be missed.
    """
    z, angle = next_obs[..., HOPPER_Z], next_obs[..., HOPPER_ANGLE]
    state_ok = (next_obs[..., HOPPER_STATE_START:].abs() < HOPPER_MAX_STATE).all(dim=-1)
    return (z > HOPPER_MIN_Z) & (angle.abs() < HOPPER_MAX_ANGLE) & state_ok


def hopper_termination(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    """Hopper-v5 terminates when the next state is not healthy (see :func:`hopper_healthy`)."""
    return ~hopper_healthy(next_obs)


def hopper_reward(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    """Hopper-v5: ``(x' - x) / dt + 1[healthy'] - 0.001 |a|^2``."""
    forward = (next_obs[..., HOPPER_X] - obs[..., HOPPER_X]) / HOPPER_DT
    healthy = hopper_healthy(next_obs).to(next_obs.dtype)
    return forward + healthy - HOPPER_CTRL_COST * squared_norm(action)


# ---------------------------------------------------------------------------------------------------------------------
# Walker2d-v5 with x kept: obs = [qpos (9): x, z, angle, 6 joints; clip(qvel, -10, 10) (9)], dt = 0.002 * 4
WALKER_X, WALKER_Z, WALKER_ANGLE = 0, 1, 2
WALKER_DT = 0.008
WALKER_CTRL_COST = 1e-3
WALKER_Z_RANGE = (0.8, 2.0)
WALKER_MAX_ANGLE = 1.0


def walker2d_healthy(next_obs: th.Tensor) -> th.Tensor:
    """Walker2d-v5 ``is_healthy``: ``0.8 < z < 2`` and ``-1 < angle < 1`` (no state-range check in v5)."""
    z, angle = next_obs[..., WALKER_Z], next_obs[..., WALKER_ANGLE]
    return (z > WALKER_Z_RANGE[0]) & (z < WALKER_Z_RANGE[1]) & (angle.abs() < WALKER_MAX_ANGLE)


def walker2d_termination(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    """Walker2d-v5 terminates when the next state is not healthy (see :func:`walker2d_healthy`)."""
    return ~walker2d_healthy(next_obs)


def walker2d_reward(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    """Walker2d-v5: ``(x' - x) / dt + 1[healthy'] - 0.001 |a|^2``."""
    forward = (next_obs[..., WALKER_X] - obs[..., WALKER_X]) / WALKER_DT
    healthy = walker2d_healthy(next_obs).to(next_obs.dtype)
    return forward + healthy - WALKER_CTRL_COST * squared_norm(action)


# ---------------------------------------------------------------------------------------------------------------------
# Swimmer-v5 with x, y kept: obs = [qpos (5): x, y, angle, 2 joints; qvel (5)], dt = 0.01 * 4
SWIMMER_X, SWIMMER_Y = 0, 1
SWIMMER_DT = 0.04
SWIMMER_CTRL_COST = 1e-4


def swimmer_reward(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    """Swimmer-v5: ``(x' - x) / dt - 1e-4 |a|^2``."""
    forward = (next_obs[..., SWIMMER_X] - obs[..., SWIMMER_X]) / SWIMMER_DT
    return forward - SWIMMER_CTRL_COST * squared_norm(action)


# ---------------------------------------------------------------------------------------------------------------------
# Ant-v5 with x, y kept: obs = [qpos (15): x, y, z, quaternion (4), 8 joints; qvel (14);
#                               clip(cfrc_ext[1:], -1, 1) (13 bodies x 6)], dt = 0.01 * 5
ANT_X, ANT_Y, ANT_Z = 0, 1, 2
ANT_STATE_END = 29  # obs[:29] = qpos, qvel (the env's state_vector())
ANT_CONTACT_START = 29
ANT_DT = 0.05
ANT_CTRL_COST = 0.5
ANT_CONTACT_COST = 5e-4
ANT_Z_RANGE = (0.2, 1.0)


def ant_healthy(next_obs: th.Tensor) -> th.Tensor:
    """Ant-v5 ``is_healthy``: ``qpos, qvel`` all finite and ``0.2 <= z <= 1`` (bounds included)."""
    finite = th.isfinite(next_obs[..., :ANT_STATE_END]).all(dim=-1)
    z = next_obs[..., ANT_Z]
    return finite & (z >= ANT_Z_RANGE[0]) & (z <= ANT_Z_RANGE[1])


def ant_termination(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    """Ant-v5 terminates when the next state is not healthy (see :func:`ant_healthy`)."""
    return ~ant_healthy(next_obs)


def ant_reward(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    """
    Ant-v5: ``(x' - x) / dt + 1[healthy'] - 0.5 |a|^2 - 5e-4 |clip(cfrc_ext', -1, 1)|^2``.

    The contact forces are the clipped ``cfrc_ext[1:]`` the default observation carries (the world
    body's entry is always zero). The env measures x on the torso's ``xpos``, which MuJoCo last
    updated at the start of the final substep, so its velocity lags the ``qpos``-based one used here
    by one substep (``tests/test_tasks.py`` bounds the difference).
    """
    forward = (next_obs[..., ANT_X] - obs[..., ANT_X]) / ANT_DT
    healthy = ant_healthy(next_obs).to(next_obs.dtype)
    contact = (next_obs[..., ANT_CONTACT_START:] ** 2).sum(dim=-1)
    return forward + healthy - ANT_CTRL_COST * squared_norm(action) - ANT_CONTACT_COST * contact


# ---------------------------------------------------------------------------------------------------------------------
# InvertedDoublePendulum-v5: obs = [cart x, sin q1, sin q2, cos q1, cos q2, clip(qvel, -10, 10) (3),
#                                   clip(qfrc_constraint[0], -10, 10)], action in [-1, 1]
# q1 is the first pole's angle from vertical, q2 the second pole's angle relative to the first; both
# poles are 0.6 long, so the tip is at x + 0.6 (sin q1 + sin(q1 + q2)), height 0.6 (cos q1 + cos(q1 + q2)).
IDP_X, IDP_SIN1, IDP_SIN2, IDP_COS1, IDP_COS2, IDP_V1, IDP_V2 = 0, 1, 2, 3, 4, 6, 7
IDP_POLE_LENGTH = 0.6
IDP_MIN_TIP_HEIGHT = 1.0
IDP_ALIVE_BONUS = 10.0


def _idp_tip(next_obs: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
    """:return: the tip's ``(x, height)`` by forward kinematics from the observation"""
    sin1, sin2 = next_obs[..., IDP_SIN1], next_obs[..., IDP_SIN2]
    cos1, cos2 = next_obs[..., IDP_COS1], next_obs[..., IDP_COS2]
    sin12 = sin1 * cos2 + cos1 * sin2
    cos12 = cos1 * cos2 - sin1 * sin2
    tip_x = next_obs[..., IDP_X] + IDP_POLE_LENGTH * (sin1 + sin12)
    tip_height = IDP_POLE_LENGTH * (cos1 + cos12)
    return tip_x, tip_height


def inverted_double_pendulum_termination(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    """InvertedDoublePendulum-v5 terminates when the tip height ``y <= 1``."""
    return _idp_tip(next_obs)[1] <= IDP_MIN_TIP_HEIGHT


def inverted_double_pendulum_reward(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    """
    InvertedDoublePendulum-v5: ``10 * 1[y > 1] - 0.01 x_tip^2 - (y - 2)^2 - 0.001 v1^2 - 0.005 v2^2``.

    The env reads the tip from ``site_xpos`` (one substep behind ``qpos``) and the unclipped joint
    velocities; this uses the observation's forward kinematics and its velocities clipped to
    [-10, 10], so it is close but not exact (``tests/test_tasks.py`` bounds the difference).
    """
    tip_x, tip_height = _idp_tip(next_obs)
    alive = IDP_ALIVE_BONUS * (tip_height > IDP_MIN_TIP_HEIGHT).to(next_obs.dtype)
    distance_penalty = 0.01 * tip_x**2 + (tip_height - 2.0) ** 2
    velocity_penalty = 0.001 * next_obs[..., IDP_V1] ** 2 + 0.005 * next_obs[..., IDP_V2] ** 2
    return alive - distance_penalty - velocity_penalty


# ---------------------------------------------------------------------------------------------------------------------
# Reacher-v5: obs = [cos q (2), sin q (2), target x, y, joint velocities (2), (fingertip - target)[:2]]
REACHER_DELTA = slice(8, 10)


def reacher_reward(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    """
    Reacher-v5: ``-|fingertip' - target| - |a|^2``, on the state *after* the step (v5 changed this
    from v4). Fingertip and target are both at height 0.01, so the planar offset in the obs is enough.
    """
    return -th.linalg.vector_norm(next_obs[..., REACHER_DELTA], dim=-1) - squared_norm(action)


# ---------------------------------------------------------------------------------------------------------------------
# Pusher-v5: obs = [qpos[:7], qvel[:7], tips_arm com (3), object com (3), goal com (3)], action in [-2, 2]
PUSHER_TIP, PUSHER_OBJECT, PUSHER_GOAL = slice(14, 17), slice(17, 20), slice(20, 23)


def pusher_reward(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    """Pusher-v5: ``-0.5 |object' - tip'| - |object' - goal'| - 0.1 |a|^2``, on the state after the step."""
    near = th.linalg.vector_norm(next_obs[..., PUSHER_OBJECT] - next_obs[..., PUSHER_TIP], dim=-1)
    dist = th.linalg.vector_norm(next_obs[..., PUSHER_OBJECT] - next_obs[..., PUSHER_GOAL], dim=-1)
    return -0.5 * near - dist - 0.1 * squared_norm(action)


# ---------------------------------------------------------------------------------------------------------------------
# Candidate model hooks of the locomotion tasks (benchmarks: `python -m sb3_poplin.analysis model-quality --hooks`):
# "raw" is what the registered specs did up to 0.3.0 (root positions hidden, every change predicted as a delta);
# "sincos" feeds a wrapping root angle as its sine and cosine; "progress" predicts the root's change as a velocity,
# (x' - x) / dt; "bounded" squashes the velocity inputs the env does not clip (10 tanh(v / 10)); "all" combines them
HOOK_CANDIDATES: dict[str, dict[str, LocomotionHooks]] = {}


def _candidates(
    obs_dim: int,
    positions: tuple[int, ...],
    dt: float,
    angles: tuple[int, ...] = (),
    velocities: tuple[int, ...] = (),
) -> dict[str, LocomotionHooks]:
    """:param velocities: unclipped velocity entries of the observation (a "bounded" candidate where there are any)"""
    candidates = dict(
        raw=LocomotionHooks(obs_dim, exclude=positions),
        progress=LocomotionHooks(obs_dim, exclude=positions, rates=positions, dt=dt),
    )
    if angles:
        candidates["sincos"] = LocomotionHooks(obs_dim, exclude=positions, angles=angles)
        candidates["sincos+progress"] = LocomotionHooks(obs_dim, exclude=positions, angles=angles, rates=positions, dt=dt)
    if velocities:
        candidates["bounded"] = LocomotionHooks(obs_dim, exclude=positions, bounded=velocities)
        candidates["all"] = LocomotionHooks(
            obs_dim, exclude=positions, angles=angles, rates=positions, dt=dt, bounded=velocities
        )
    return candidates


HOOK_CANDIDATES["HalfCheetah-v5"] = _candidates(
    18, (HALF_CHEETAH_X,), HALF_CHEETAH_DT, angles=(2,), velocities=tuple(range(9, 18))
)
HOOK_CANDIDATES["Hopper-v5"] = _candidates(12, (HOPPER_X,), HOPPER_DT)  # qvel clipped to [-10, 10] by the env
HOOK_CANDIDATES["Walker2d-v5"] = _candidates(18, (WALKER_X,), WALKER_DT)  # the same
HOOK_CANDIDATES["Swimmer-v5"] = _candidates(
    10, (SWIMMER_X, SWIMMER_Y), SWIMMER_DT, angles=(2,), velocities=tuple(range(5, 10))
)
HOOK_CANDIDATES["Ant-v5"] = _candidates(107, (ANT_X, ANT_Y), ANT_DT, velocities=tuple(range(15, ANT_STATE_END)))


# HalfCheetah-v5: the pitch as sine and cosine, to the model and the policy (a flipped cheetah is one posture);
# Swimmer-v5: the body angle as sine and cosine to the model only. How they were chosen: docs/results.md
HALF_CHEETAH_HOOKS = "sincos"
HALF_CHEETAH_POLICY_FEATURES = True
SWIMMER_HOOKS = "sincos"


for _spec in (
    TaskSpec(
        env_id="InvertedPendulum-v5",
        reward_fn=inverted_pendulum_reward,
        termination_fn=inverted_pendulum_termination,
        description="reward 1 while |angle| <= 0.2; terminates when |next angle| > 0.2 or non-finite",
    ),
    TaskSpec(
        env_id="HalfCheetah-v5",
        reward_fn=half_cheetah_reward,
        env_kwargs=dict(KEEP_POSITIONS),
        **HOOK_CANDIDATES["HalfCheetah-v5"][HALF_CHEETAH_HOOKS].model_hooks(policy=HALF_CHEETAH_POLICY_FEATURES),
        description="x kept in obs[0] for the forward reward, hidden from the networks; the pitch as its sine and "
        "cosine to the model and the policy; never terminates",
    ),
    TaskSpec(
        env_id="Hopper-v5",
        reward_fn=hopper_reward,
        termination_fn=hopper_termination,
        env_kwargs=dict(KEEP_POSITIONS),
        model_input_exclude=(HOPPER_X,),
        description="x kept in obs[0]; terminates when z <= 0.7, |angle| >= 0.2 or |obs[2:]| >= 100",
    ),
    TaskSpec(
        env_id="Walker2d-v5",
        reward_fn=walker2d_reward,
        termination_fn=walker2d_termination,
        env_kwargs=dict(KEEP_POSITIONS),
        model_input_exclude=(WALKER_X,),
        description="x kept in obs[0]; terminates when z not in (0.8, 2) or |angle| >= 1",
    ),
    TaskSpec(
        env_id="Swimmer-v5",
        reward_fn=swimmer_reward,
        env_kwargs=dict(KEEP_POSITIONS),
        **HOOK_CANDIDATES["Swimmer-v5"][SWIMMER_HOOKS].model_hooks(policy=False),
        description="x, y kept in obs[0:2], hidden from the networks; the body angle as its sine and cosine to the "
        "model; never terminates",
    ),
    TaskSpec(
        env_id="Ant-v5",
        reward_fn=ant_reward,
        termination_fn=ant_termination,
        env_kwargs=dict(KEEP_POSITIONS),
        model_input_exclude=(ANT_X, ANT_Y),
        description="x, y kept in obs[0:2]; contact cost from obs[29:]; terminates when z not in [0.2, 1] or non-finite",
    ),
    TaskSpec(
        env_id="InvertedDoublePendulum-v5",
        reward_fn=inverted_double_pendulum_reward,
        termination_fn=inverted_double_pendulum_termination,
        description="tip by forward kinematics from sin/cos; terminates when the tip height <= 1",
    ),
    TaskSpec(
        env_id="Reacher-v5",
        reward_fn=reacher_reward,
        description="reward from the post-step fingertip-target offset obs[8:10]; never terminates",
    ),
    TaskSpec(
        env_id="Pusher-v5",
        reward_fn=pusher_reward,
        description="reward from the post-step body positions obs[14:23]; never terminates",
    ),
):
    register_task(_spec)
