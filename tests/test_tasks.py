"""Each TaskSpec's reward and termination against the real env's, over random rollouts."""

import gymnasium as gym
import numpy as np
import pytest
import torch as th

from sb3_poplin.tasks import TaskSpec, make_task, register_task, registered_tasks

STEPS = 1500


def random_transitions(env_id: str, steps: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Uniform random actions with resets; every (obs, action, next_obs, reward, terminated)."""
    task = make_task(env_id)
    env = gym.make(env_id, **task.env_kwargs)
    env.action_space.seed(seed)
    obs, _ = env.reset(seed=seed)
    rows: dict[str, list] = {"obs": [], "action": [], "next_obs": [], "reward": [], "terminated": []}
    for _ in range(steps):
        action = env.action_space.sample()
        next_obs, reward, terminated, truncated, _ = env.step(action)
        for key, value in zip(rows, (obs, action, next_obs, reward, terminated), strict=True):
            rows[key].append(value)
        obs = next_obs
        if terminated or truncated:
            obs, _ = env.reset()
    env.close()
    return {key: np.asarray(value, dtype=np.float64) for key, value in rows.items()}


@pytest.mark.parametrize("env_id", ["Pendulum-v1", "InvertedPendulum-v5"])
def test_reward_and_termination_match_env(env_id):
    data = random_transitions(env_id, STEPS)
    task = make_task(env_id)
    obs, action, next_obs = (th.as_tensor(data[k]) for k in ("obs", "action", "next_obs"))
    reward = task.reward_fn(obs, action, next_obs).numpy()
    assert reward.shape == (STEPS,)
    assert np.max(np.abs(reward - data["reward"])) <= 1e-5
    terminated = data["terminated"].astype(bool)
    if task.termination_fn is None:
        assert not terminated.any()
    else:
        predicted = task.termination_fn(obs, action, next_obs).numpy()
        assert predicted.dtype == bool
        np.testing.assert_array_equal(predicted, terminated)
        assert terminated.sum() > 10  # the check saw real terminations


def test_pendulum_reward_clips_torque_and_normalises_angle():
    task = make_task("Pendulum-v1")
    theta, theta_dot = np.pi - 0.1, 3.0
    obs = th.tensor([[np.cos(theta), np.sin(theta), theta_dot]], dtype=th.float64)
    expected = -((np.pi - 0.1) ** 2 + 0.1 * theta_dot**2 + 0.001 * 2.0**2)
    assert task.reward_fn(obs, th.tensor([[5.0]], dtype=th.float64), obs).item() == pytest.approx(expected, abs=1e-12)


def test_unknown_task_and_registration():
    with pytest.raises(ValueError, match=r"No task is registered for 'NoSuchEnv-v0'.*reward_fn="):
        make_task("NoSuchEnv-v0")
    spec = TaskSpec("MyTask-v0", reward_fn=lambda o, a, n: -(n[..., 0] ** 2))
    register_task(spec)
    assert "MyTask-v0" in registered_tasks() and make_task("MyTask-v0") is spec
    with pytest.raises(ValueError, match="already registered"):
        register_task(spec)
    register_task(spec, overwrite=True)
