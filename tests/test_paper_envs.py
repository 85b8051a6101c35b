"""The paper's PETS arm and MBBL tasks: kinematics against MuJoCo's, dynamics against gymnasium's, resets."""

import gymnasium as gym
import mujoco
import numpy as np
import pytest
import torch as th
from gymnasium.envs.classic_control.acrobot import AcrobotEnv
from gymnasium.envs.classic_control.cartpole import CartPoleEnv
from gymnasium.envs.classic_control.pendulum import PendulumEnv

from sb3_poplin.envs.mbbl_classic import MBBLAcrobotEnv, MBBLCartpoleEnv, MBBLPendulumEnv
from sb3_poplin.envs.pets_arm import PETSPusherEnv, PETSReacher3DEnv
from sb3_poplin.tasks import make_task
from sb3_poplin.tasks.pets_arm import PUSHER_GOAL, PUSHER_SHOULDER, PUSHER_TIP_LENGTH, arm_point, reacher3d_end_effector


def random_angles(env: gym.Env, rng: np.random.Generator) -> np.ndarray:
    """Seven angles inside the joint ranges (any angle for the unlimited joints)."""
    model = env.unwrapped.model  # type: ignore[attr-defined]
    low, high = model.jnt_range[:7].T.copy()
    unlimited = ~model.jnt_limited[:7].astype(bool)
    low[unlimited], high[unlimited] = -np.pi, np.pi
    return rng.uniform(low, high)


def test_reacher3d_kinematics_match_mujoco():
    env = PETSReacher3DEnv()
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    for _ in range(50):
        angles = random_angles(env, rng)
        env.data.qpos[:7] = angles
        expected = env.end_effector()  # MuJoCo's kinematics of the compiled model
        np.testing.assert_allclose(reacher3d_end_effector(th.as_tensor(angles)).numpy(), expected, atol=1e-12)
    # batched over leading dimensions, in float32
    angles = th.as_tensor(rng.uniform(-1, 1, size=(4, 3, 7)))
    batched = reacher3d_end_effector(angles.float())
    assert batched.shape == (4, 3, 3) and batched.dtype == th.float32
    np.testing.assert_allclose(batched.numpy(), reacher3d_end_effector(angles).numpy(), atol=1e-5)
    # at rest the arm points along +x from the shoulder: 0.1 + 0.4 + 0.321 + 0.16828
    np.testing.assert_allclose(reacher3d_end_effector(th.zeros(7)).numpy(), [0.98928, -0.188, 0.0], atol=1e-12)


def test_reacher3d_goal_is_observed_and_drawn_per_episode():
    env = gym.make("sb3_poplin/PETSReacher3D-v0")
    goals = []
    for episode in range(200):
        obs, _ = env.reset(seed=episode)
        np.testing.assert_array_equal(obs[:7], 0.0)  # the arm starts at rest, every angle 0
        np.testing.assert_array_equal(obs[10:], 0.0)
        goals.append(obs[7:10])
        for _ in range(3):
            action = env.action_space.sample()
            obs, reward, *_ = env.step(action)
            np.testing.assert_array_equal(obs[7:10], goals[-1])  # the goal does not move
            ee = env.unwrapped.data.site_xpos[0]  # type: ignore[attr-defined]
            expected = -np.sum((ee - goals[-1]) ** 2) - 0.01 * np.sum(np.square(action.astype(np.float64)))
            assert reward == pytest.approx(expected, abs=1e-9)
    goals = np.asarray(goals)
    # (0, 0.25, 0) + N(0, 0.1^2): 200 draws, 4 standard errors
    np.testing.assert_allclose(goals.mean(axis=0), [0.0, 0.25, 0.0], atol=4 * 0.1 / np.sqrt(200))
    np.testing.assert_allclose(goals.std(axis=0), 0.1, atol=0.025)


def test_pusher_observes_tip_and_object_of_its_state():
    env = PETSPusherEnv()
    obs, _ = env.reset(seed=0)
    np.testing.assert_allclose(env.model.body("goal").pos, PUSHER_GOAL)
    for _ in range(20):
        qpos = env.data.qpos
        tip = arm_point(th.as_tensor(qpos[:7].copy()), PUSHER_SHOULDER, PUSHER_TIP_LENGTH).numpy()
        np.testing.assert_allclose(obs[14:17], tip, atol=1e-12)
        # the object's body sits at its base + the (y, x) slide offsets
        np.testing.assert_allclose(obs[17:20], [0.45 + qpos[8], -0.05 + qpos[7], -0.275], atol=1e-12)
        np.testing.assert_array_equal(obs[:14], np.concatenate([qpos[:7], env.data.qvel[:7]]))
        obs, *_ = env.step(env.action_space.sample())
    # the tip is the centre of mass of the fingertip body (what PETS observed)
    mujoco.mj_forward(env.model, env.data)
    np.testing.assert_allclose(obs[14:17], env.data.subtree_com[env.model.body("tips_arm").id], atol=1e-12)


def test_pusher_reset_is_pets():
    env = PETSPusherEnv()
    starts = []
    for episode in range(200):
        obs, _ = env.reset(seed=episode)
        np.testing.assert_array_equal(obs[:7], 0.0)
        assert np.abs(obs[7:14]).max() <= 0.005
        starts.append(obs[17:19])
        assert (env.data.qpos[-2:] == 0).all() and (env.data.qvel[-4:] == 0).all()
    starts = np.asarray(starts)
    # object at (0.45 + 0.15, -0.05 - 0.25) + N(0, 0.025^2) each
    np.testing.assert_allclose(starts.mean(axis=0), [0.6, -0.3], atol=4 * 0.025 / np.sqrt(200))
    np.testing.assert_allclose(starts.std(axis=0), 0.025, atol=0.006)


def test_pusher_reward_is_paid_on_the_positions_before_the_step():
    env = gym.make("sb3_poplin/PETSPusher-v0")
    obs, _ = env.reset(seed=3)
    action = np.full(7, 0.5, dtype=np.float32)
    tip, obj = obs[14:17], obs[17:20]
    expected = -1.25 * np.abs(obj - PUSHER_GOAL).sum() - 0.5 * np.abs(obj - tip).sum() - 0.1 * 7 * 0.25
    next_obs, reward, *_ = env.step(action)
    assert reward == pytest.approx(expected, abs=1e-6)
    assert not np.allclose(next_obs[14:17], tip)  # the arm moved: the post-step positions would pay another reward


def test_mbbl_pendulum_steps_as_gym_pendulum():
    """Gymnasium's Pendulum-v1 has the same update while the speed stays under 8 (v1 clips before moving)."""
    ours, theirs = MBBLPendulumEnv(), PendulumEnv()
    ours.reset(seed=0)
    theirs.reset(seed=0)
    rng = np.random.default_rng(0)
    for _ in range(200):
        state = np.array([rng.uniform(-np.pi, np.pi), rng.uniform(-5, 5)])
        action = rng.uniform(-1.2, 1.2, size=1).astype(np.float32)
        ours.state, theirs.state = state.copy(), state.copy()
        obs, reward, *_ = ours.step(action)
        expected_obs, *_ = theirs.step(2.0 * np.clip(action, -1, 1))
        if abs(obs[2]) < 8.0:
            np.testing.assert_allclose(obs, expected_obs, atol=1e-5)  # gymnasium's obs are float32
        torque = 2.0 * np.clip(float(action[0]), -1, 1)
        expected = -(np.cos(state[0]) + 0.1 * abs(np.sin(state[0])) + 0.1 * state[1] ** 2 + 0.001 * torque**2)
        assert reward == pytest.approx(expected, abs=1e-12)
    # Pendulum-v0 moves with the unclipped speed, then clips it
    ours.state = np.array([0.0, 7.9])
    obs, *_ = ours.step(np.ones(1, dtype=np.float32))
    assert obs[2] == 8.0 and ours.state[0] == pytest.approx((7.9 + 3 * 2.0 * 0.05) * 0.05)
    # MBBL's reward, read literally, is best hanging down at rest: +1 - 0.001 u^2
    ours.state = np.array([np.pi, 0.0])
    assert ours.step(np.zeros(1, dtype=np.float32))[1] == pytest.approx(1.0)


def test_mbbl_cartpole_steps_as_gym_cartpole():
    ours, theirs = MBBLCartpoleEnv(), CartPoleEnv()
    ours.reset(seed=0)
    theirs.reset(seed=0)
    rng = np.random.default_rng(1)
    for _ in range(200):
        state = rng.uniform(-1, 1, size=4)
        action = rng.uniform(-1, 1, size=1).astype(np.float32)
        ours.state = state.copy()
        theirs.state = state.copy()
        theirs.steps_beyond_terminated = None
        obs, reward, terminated, *_ = ours.step(action)
        theirs.step(int(action[0] > 0))
        np.testing.assert_allclose(obs, np.asarray(theirs.state, dtype=np.float64), atol=1e-12)
        assert reward == pytest.approx(np.cos(state[2]) - 0.01 * state[0] ** 2, abs=1e-12) and not terminated
    assert ours.step(np.zeros(1, dtype=np.float32))[4]["force"] == -10.0  # a = 0 pushes left


def test_mbbl_acrobot_steps_as_gym_acrobot():
    ours, theirs = MBBLAcrobotEnv(), AcrobotEnv()
    ours.reset(seed=0)
    theirs.reset(seed=0)
    rng = np.random.default_rng(2)
    for action_value, torque_index in [(-0.9, 0), (-0.34, 0), (-0.32, 1), (0.0, 1), (0.32, 1), (0.33, 2), (1.0, 2)]:
        for _ in range(20):
            state = np.concatenate([rng.uniform(-np.pi, np.pi, size=2), rng.uniform(-3, 3, size=2)])
            ours.state, theirs.state = state.copy(), state.copy()
            obs, reward, *_ = ours.step(np.array([action_value], dtype=np.float32))
            expected_obs, *_ = theirs.step(torque_index)
            np.testing.assert_allclose(obs, expected_obs, atol=1e-5)  # gymnasium's obs are float32
            assert reward == pytest.approx(-np.cos(state[0]) - np.cos(state[0] + state[1]), abs=1e-12)
    # velocities are bounded as gym bounds them
    ours.state, theirs.state = np.array([0.0, 0.0, 30.0, 60.0]), np.array([0.0, 0.0, 30.0, 60.0])
    obs, *_ = ours.step(np.zeros(1, dtype=np.float32))
    np.testing.assert_allclose(obs, theirs.step(1)[0], atol=1e-5)
    assert np.abs(obs[4:]).tolist() == pytest.approx([4 * np.pi, 9 * np.pi])


def test_mbbl_inverted_pendulum_runs_on_after_the_pole_falls():
    env = gym.make("sb3_poplin/MBBLInvertedPendulum-v0")
    assert env.action_space.low[0] == -3.0 and env.action_space.high[0] == 3.0
    obs, _ = env.reset(seed=0)
    fallen = 0
    for _ in range(101):
        next_obs, reward, terminated, truncated, _ = env.step(np.ones(1, dtype=np.float32) * 3.0)
        assert reward == pytest.approx(-(obs[1] ** 2)) and not terminated
        fallen += abs(next_obs[1]) > 0.2  # InvertedPendulum-v5 would have terminated
        obs = next_obs
    assert truncated and fallen > 50


@pytest.mark.parametrize(
    "env_id",
    ["sb3_poplin/MBBLPendulum-v0", "sb3_poplin/MBBLAcrobot-v0", "sb3_poplin/MBBLCartpole-v0"],
)
def test_mbbl_rewards_read_the_observation_before_the_step(env_id):
    task = make_task(env_id)
    env = gym.make(env_id)
    obs, _ = env.reset(seed=0)
    action = env.action_space.sample()
    next_obs, reward, *_ = env.step(action)
    on_obs = task.reward_fn(th.as_tensor(obs[None]), th.as_tensor(action[None]), th.as_tensor(next_obs[None]))
    swapped = task.reward_fn(th.as_tensor(next_obs[None]), th.as_tensor(action[None]), th.as_tensor(obs[None]))
    assert on_obs.item() == pytest.approx(reward, abs=1e-9) and swapped.item() != pytest.approx(reward, abs=1e-9)


@pytest.mark.parametrize("env_class", [MBBLPendulumEnv, MBBLAcrobotEnv, MBBLCartpoleEnv])
def test_numpy_envs_reject_rendering(env_class):
    with pytest.raises(ValueError, match="no rendering"):
        env_class(render_mode="human")


NEW_ENVS = [
    "sb3_poplin/PETSReacher3D-v0",
    "sb3_poplin/PETSPusher-v0",
    "sb3_poplin/MBBLPendulum-v0",
    "sb3_poplin/MBBLInvertedPendulum-v0",
    "sb3_poplin/MBBLAcrobot-v0",
    "sb3_poplin/MBBLCartpole-v0",
]


@pytest.mark.parametrize("variant", ["pets", "poplin-p"])
@pytest.mark.parametrize("env_id", NEW_ENVS)
def test_poplin_runs_on_the_paper_envs_and_fits_on_every_step(env_id, variant):
    """A smoke test (a planned episode, valid actions), not a learning test; and the last fit saw every transition."""
    from sb3_poplin import POPLIN

    tiny = dict(horizon=4, population_size=16, num_elites=4, cem_iterations=1, ensemble_size=2)
    model = POPLIN(variant, env_id, seed=0, dynamics_net_arch=(16, 16), model_epochs=1, **tiny)
    episode = model.env.envs[0].spec.max_episode_steps  # type: ignore[union-attr]
    model.learn(episode + 20)  # one random episode, a model fit, then a planned episode (train_freq: 1 episode)
    assert model.num_timesteps == 2 * episode and model._n_updates == 2
    # the model's input statistics were refit on all 2 * episode transitions (none of these tasks hides an input)
    buffer = model.replay_buffer
    columns = (buffer.observations[: 2 * episode, 0], buffer.actions[: 2 * episode, 0])
    inputs = np.concatenate(columns, axis=1).astype(np.float64)
    dynamics = model.policy.dynamics
    np.testing.assert_allclose(dynamics.input_mean.numpy(), inputs.mean(axis=0), rtol=1e-4, atol=1e-5)
    spread = inputs.std(axis=0)
    constant = spread < 1e-9  # the Pusher's object height never changes: its std counts as 1
    np.testing.assert_allclose(dynamics.input_std.numpy(), np.where(constant, 1.0, spread), rtol=1e-4, atol=1e-5)
    env = gym.make(env_id)
    obs, _ = env.reset(seed=1)
    action, _ = model.predict(obs, deterministic=True)
    assert action.shape == env.action_space.shape and env.action_space.contains(action)
