"""End-to-end learning: PETS must solve Pendulum-v1 from scratch on a CPU budget."""

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.evaluation import evaluate_policy

from sb3_poplin import POPLIN
from sb3_poplin.demo import CPU_SETTINGS, random_policy_returns

RANDOM_PENDULUM = -1200  # uniform random actions score about -1200 per 200-step episode


def test_random_pendulum_reference():
    assert np.mean(random_policy_returns("Pendulum-v1", 10, seed=0)) < -900


def test_pets_learns_pendulum_within_3000_steps():
    model = POPLIN("pets", "Pendulum-v1", seed=0, **CPU_SETTINGS)
    model.learn(3000)
    returns, _ = evaluate_policy(model, model.get_env(), n_eval_episodes=10, return_episode_rewards=True)
    mean = float(np.mean(returns))
    print(f"PETS Pendulum-v1 after 3000 steps: {mean:.1f} ± {np.std(returns):.1f} ({np.round(returns).tolist()})")
    assert mean >= -250, returns


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2])
def test_pets_learns_pendulum_other_seeds(seed):
    model = POPLIN("pets", "Pendulum-v1", seed=seed, **CPU_SETTINGS)
    model.learn(3000)
    returns, _ = evaluate_policy(model, model.get_env(), n_eval_episodes=10, return_episode_rewards=True)
    assert np.mean(returns) >= -250, returns


@pytest.mark.slow
def test_random_shooting_beats_random_on_pendulum():
    model = POPLIN("rs", "Pendulum-v1", seed=0, **{**CPU_SETTINGS, "population_size": 500})
    model.learn(2000)
    returns, _ = evaluate_policy(model, model.get_env(), n_eval_episodes=5, return_episode_rewards=True)
    assert np.mean(returns) >= RANDOM_PENDULUM / 2, returns


@pytest.mark.slow
def test_learned_reward_learns_pendulum():
    model = POPLIN("pets", "Pendulum-v1", seed=0, learned_reward=True, **CPU_SETTINGS)
    assert model.planner.reward_fn is None  # the planner scores with the model's reward head
    model.learn(3000)
    returns, _ = evaluate_policy(model, model.get_env(), n_eval_episodes=10, return_episode_rewards=True)
    assert np.mean(returns) >= -400, returns


@pytest.mark.slow
def test_poplin_p_sep_avg_learns_pendulum():
    """The packaged POPLIN-P (Sep noise, Avg distillation): MPC and an unsaturated policy network."""
    model = POPLIN("poplin-p", "Pendulum-v1", seed=0, noise="sep", distillation="avg", **CPU_SETTINGS)
    model.learn(3000)
    returns, _ = evaluate_policy(model, model.get_env(), n_eval_episodes=10, return_episode_rewards=True)
    assert np.mean(returns) >= -300, returns
    states = th.as_tensor(model.replay_buffer.observations[: model.replay_buffer.pos, 0])
    with th.no_grad():
        raw = model.policy.actor(states.to(model.device))
    assert (raw.abs() > 1).float().mean() < 0.5, "Avg drove the policy output into saturation"
