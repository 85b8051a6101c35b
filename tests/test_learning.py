"""End-to-end learning on Pendulum-v1 from scratch on a CPU budget: PETS in the default run; POPLIN-A with its distilled
policy, the other seeds and iCEM in the slow set (`make test-slow`)."""

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.evaluation import evaluate_policy

from sb3_poplin import POPLIN
from sb3_poplin.experiments.demo import CPU_SETTINGS, random_policy_returns

RANDOM_PENDULUM = -1200  # uniform random actions score about -1200 per 200-step episode


def evaluate(model: POPLIN, episodes: int = 10) -> list[float]:
    returns, _ = evaluate_policy(model, model.get_env(), n_eval_episodes=episodes, return_episode_rewards=True)
    return [float(r) for r in returns]


def test_random_pendulum_reference():
    assert np.mean(random_policy_returns("Pendulum-v1", 10, seed=0)) < -900


def test_pets_learns_pendulum_within_1400_steps():
    """
    The default run's end-to-end learning check: seven episodes, the first random. Seeds 0-3 scored -193, -149, -174
    and -191 over 5 episodes (random actions: about -1200); the bar, -400, is 800 above random and 200 below the
    weakest of them.
    """
    model = POPLIN("pets", "Pendulum-v1", seed=0, **CPU_SETTINGS)
    model.learn(1400)
    returns = evaluate(model, episodes=5)
    print(f"PETS Pendulum-v1 after 1400 steps: {np.mean(returns):.1f} ± {np.std(returns):.1f} ({np.round(returns).tolist()})")
    assert np.mean(returns) >= -400, returns


@pytest.mark.slow  # the longer version of the check above
def test_pets_learns_pendulum_within_3000_steps():
    model = POPLIN("pets", "Pendulum-v1", seed=0, **CPU_SETTINGS)
    model.learn(3000)
    returns, _ = evaluate_policy(model, model.get_env(), n_eval_episodes=10, return_episode_rewards=True)
    mean = float(np.mean(returns))
    print(f"PETS Pendulum-v1 after 3000 steps: {mean:.1f} ± {np.std(returns):.1f} ({np.round(returns).tolist()})")
    assert mean >= -250, returns


@pytest.mark.slow  # 355 s on an idle 2-core CI machine: the default run would pass 15 minutes with it
def test_poplin_a_and_its_distilled_policy_learn_pendulum():
    """
    POPLIN-A at its defaults (Init proposals, BC distillation): MPC swings up, and the policy network distilled from
    the planner's actions is far above random on its own (it does not swing up every start at 3k steps: the CPU
    suite's 4 seeds scored -650 to -850 with policy control, and MPC -130 to -400, against -1170 for random actions).
    """
    model = POPLIN("poplin-a", "Pendulum-v1", seed=0, **CPU_SETTINGS)
    model.learn(3000)
    mpc = evaluate(model)
    model.control = "policy"
    policy = evaluate(model)
    print(f"POPLIN-A Pendulum-v1 after 3000 steps: MPC {np.mean(mpc):.1f} {np.round(mpc).tolist()}")
    print(f"  policy control {np.mean(policy):.1f} {np.round(policy).tolist()}")
    assert np.mean(mpc) >= -500, mpc  # seed 0 here: -251 (one start of ten not swung up)
    assert np.mean(policy) >= -1000, policy  # seed 0 here: -554


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


@pytest.mark.slow
@pytest.mark.parametrize("variant", ["pets", "poplin-p"])
def test_icem_learns_pendulum_with_a_quarter_of_the_population(variant):
    """
    optimizer="icem" (iCEM's defaults: colored noise beta 2, 30 % of the elites kept and shifted, decay 1.25, the mean
    added, the best executed, no variance cap) at population 50 and 10 elites, a quarter of the CEM tests': 126
    candidates per step against CEM's 600. Seed 0 measured -125.6 (PETS) and -124.7 (POPLIN-P Sep + Avg) over 10
    episodes.
    """
    settings = {**CPU_SETTINGS, "population_size": CPU_SETTINGS["population_size"] // 4, "num_elites": 10}
    model = POPLIN(variant, "Pendulum-v1", seed=0, optimizer="icem", **settings)
    assert model.planner.optimizer.evaluations(reuse=True) == 50 + 40 + 32 + 3 + 1
    model.learn(3000)
    returns = evaluate(model)
    print(f"{variant} iCEM Pendulum-v1 after 3000 steps: {np.mean(returns):.1f} {np.round(returns).tolist()}")
    assert np.mean(returns) >= -250, returns
