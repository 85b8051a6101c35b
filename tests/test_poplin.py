"""The POPLIN algorithm through the SB3 API: input checks, predict, save/load, logging, variants."""

import csv
import os

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import configure

from conftest import TINY, sorted_rows, tiny

from sb3_poplin import POPLIN


# ---------------------------------------------------------------- bad input
def test_discrete_action_space_is_rejected():
    with pytest.raises(ValueError, match=r"Box action space.*Discrete"):
        POPLIN("pets", "CartPole-v1")


def test_unknown_variant_is_rejected():
    with pytest.raises(ValueError, match=r"Unknown POPLIN variant 'petz'; accepted values: \['pets', 'rs'"):
        POPLIN("petz", "Pendulum-v1")


def test_more_elites_than_population_is_rejected():
    with pytest.raises(ValueError, match=r"num_elites must be between 1 and population_size \(10\), got 11"):
        POPLIN("pets", "Pendulum-v1", population_size=10, num_elites=11)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(horizon=0), "horizon must be an integer >= 1"),
        (dict(cem_alpha=1.0), r"cem_alpha must be in \[0, 1\)"),
        (dict(init_var=0.0), "init_var must be > 0"),
        (dict(propagation="mean"), r"Unknown propagation 'mean'; accepted values: \['expectation'"),
        (dict(propagation="tsinf", num_particles=7), "multiple of ensemble_size"),
        (dict(cem_sampling="uniform"), "Unknown cem_sampling"),
    ],
)
def test_bad_settings_are_rejected(kwargs, message):
    with pytest.raises(ValueError, match=message):
        POPLIN("pets", "Pendulum-v1", **kwargs)


def test_policy_control_needs_a_policy_network():
    model = tiny()
    with pytest.raises(ValueError, match="no policy network"):
        model.control = "policy"
    with pytest.raises(ValueError, match="Unknown control 'plan'"):
        model.control = "plan"


def test_wrong_observation_shape_is_rejected():
    model = tiny()
    with pytest.raises(ValueError, match="observation"):
        model.predict(np.zeros(5, dtype=np.float32))


# ---------------------------------------------------------------- acting
def test_predict_single_and_batched_in_one_plan():
    model = tiny()
    calls = []
    plan = model.planner.plan

    def counting_plan(obs, mean, generator=None):
        calls.append(obs.shape[0])
        return plan(obs, mean, generator)

    model.planner.plan = counting_plan
    action, state = model.predict(np.zeros(3, dtype=np.float32))
    assert action.shape == (1,) and state.shape == (1, 5)
    vec_env = make_vec_env("Pendulum-v1", n_envs=2, seed=0)
    obs = vec_env.reset()
    actions, state = model.predict(obs, episode_start=np.ones(2, dtype=bool))
    assert actions.shape == (2, 1) and calls == [1, 2]  # the two envs were planned in one call
    assert np.all(np.abs(actions) <= 2.0)
    assert state.shape == (2, 5)
    # the returned warm start is the shifted mean: its last step is the action-space centre
    assert isinstance(state, np.ndarray) and np.all(state[:, -1] == 0)  # SB3's type for a state


def test_episode_start_resets_only_that_envs_warm_start():
    model = tiny()
    obs = np.zeros((2, 3), dtype=np.float32)
    state = th.full((2, 5), 0.7)
    seen = {}
    plan = model.planner.plan

    def spy(obs, mean, generator=None):
        seen["mean"] = mean.clone()
        return plan(obs, mean, generator)

    model.planner.plan = spy
    model.predict(obs, state=state, episode_start=np.array([True, False]))
    assert th.equal(seen["mean"][0], th.zeros(5)) and th.equal(seen["mean"][1], th.full((5,), 0.7))
    with pytest.raises(ValueError, match="state has shape"):
        model.predict(obs, state=th.zeros(3, 5))


# ---------------------------------------------------------------- training, logging, variants
def test_random_warmup_then_planning_and_logger_keys(tmp_path):
    model = tiny()
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(600)
    assert model._model_fitted and model._n_updates == 3  # fit after each of the 3 episodes
    with open(os.path.join(tmp_path, "progress.csv")) as file:
        rows = list(csv.DictReader(file))
    keys = set(rows[-1])
    for key in ("train/model_loss", "train/model_mse", "plan/elite_return", "rollout/ep_rew_mean"):
        assert key in keys
    assert float(rows[-1]["train/n_transitions"]) == 600 - 200  # fitted before the last episode was collected


class TransitionRecorder(gym.Wrapper):
    """Every transition the env steps through, as one row: obs, action (env units), next obs."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.rows: list[np.ndarray] = []
        self.obs: np.ndarray | None = None

    def reset(self, **kwargs):
        self.obs, info = self.env.reset(**kwargs)
        return self.obs, info

    def step(self, action):
        next_obs, reward, terminated, truncated, info = self.env.step(action)
        self.rows.append(np.concatenate([self.obs, action, next_obs]))
        self.obs = next_obs
        return next_obs, reward, terminated, truncated, info


def test_a_wrapped_replay_buffer_fits_on_its_newest_transitions_only():
    recorder = TransitionRecorder(gym.make("Pendulum-v1"))
    model = POPLIN("pets", recorder, seed=0, buffer_size=150, **TINY)  # wraps during the first 200-step episode
    fits: list[np.ndarray] = []
    dynamics = model.policy.dynamics
    fit = dynamics.fit

    def spy(obs, actions, next_obs, *args, **kwargs):
        fits.append(th.cat([obs, actions, next_obs], dim=1).numpy().copy())
        return fit(obs, actions, next_obs, *args, **kwargs)

    dynamics.fit = spy
    model.learn(400)  # fits after 200 steps (buffer position 50) and after 400 (position 100)
    collected = np.array(recorder.rows)
    assert len(fits) == 2 and len(collected) == 400
    for fitted, steps in zip(fits, (200, 400), strict=True):
        newest = collected[steps - 150 : steps].copy()
        newest[:, 3] /= 2.0  # the buffer holds the actions scaled to [-1, 1] (Pendulum's torque bound is 2)
        assert fitted.shape == (150, 7)  # no stale row, no duplicate: each newest transition once, obs to its next obs
        np.testing.assert_allclose(sorted_rows(fitted), sorted_rows(newest), atol=1e-6)


def test_progress_bar_and_verbose_output(capsys):
    model = tiny(verbose=1)
    model.learn(400, progress_bar=True)
    out = capsys.readouterr().out
    assert "model_loss" in out and "elite_return" in out  # verbose=1 prints the logger table
    assert model.num_timesteps == 400


def one_step_error(model, obs, actions, next_obs):
    """Mean squared error of the mean model's next observations (``actions`` scaled)."""
    with th.no_grad():
        predicted, _ = model.policy.dynamics.propagate(obs.unsqueeze(1), actions.unsqueeze(1), "expectation")
    return float(((predicted[:, 0] - next_obs) ** 2).mean())


def spy_on_rollouts(planner, seen):
    """Keep every rollout's candidates and returns in ``seen`` (lists under "z" and "returns")."""
    rollout = planner.rollout

    def spy(obs, z, context, generator=None):
        returns = rollout(obs, z, context, generator)
        seen.setdefault("z", []).append(z.clone())
        seen.setdefault("returns", []).append(returns.clone())
        return returns

    planner.rollout = spy


def test_random_shooting_trains_and_plans():
    model = tiny("rs", population_size=64)
    model.learn(400)
    assert model._model_fitted and model._n_updates == 2
    # trained (twice, two epochs each): on the 400 transitions it saw, it predicts better than the untrained model
    buffer = model.replay_buffer
    obs, next_obs = (th.as_tensor(a[:400, 0]) for a in (buffer.observations, buffer.next_observations))
    actions = th.as_tensor(buffer.actions[:400, 0])
    untrained = tiny("rs", population_size=64)
    assert one_step_error(model, obs, actions, next_obs) < 0.9 * one_step_error(untrained, obs, actions, next_obs)
    # plans: the executed action is the first action of the candidate with the best return, in env units (bounds +-2),
    # and the warm start is the rest of it
    seen = {}
    spy_on_rollouts(model.planner, seen)
    action, state = model.predict(np.array([1.0, 0.0, 0.0], dtype=np.float32))
    (z,), (returns,) = seen["z"], seen["returns"]
    assert returns.std() > 0  # the model tells the candidates apart
    best = z[0, returns[0].argmax()]  # [H]
    np.testing.assert_allclose(action, [2.0 * best[0].item()], atol=1e-6)
    np.testing.assert_allclose(state[0], [*best[1:].tolist(), 0.0], atol=1e-7)


def test_inverted_pendulum_with_termination_and_vec_env():
    env = make_vec_env("InvertedPendulum-v5", n_envs=2, seed=0)
    model = POPLIN("pets", env, seed=0, **{**TINY, "horizon": 8})
    assert model.task_id == "InvertedPendulum-v5"
    # one episode length in steps: SB3 counts episodes with one env only
    assert (model.train_freq.frequency, model.train_freq.unit.value) == (1000, "step")
    model.learn(300)
    model.train(1, 1)  # refit on the 300 transitions now (the first refit would come at 1000 steps)
    # the returns of the planner's rollout count the steps before the first predicted fall (|angle| > 0.2 pays 0 and
    # ends the imagined episode), here against the mean model stepped by hand
    obs = th.tensor([[0.0, 0.15, 0.0, 0.5], [0.0, -0.1, 0.3, -0.8]])
    z = th.rand(2, 60, 8, generator=th.Generator().manual_seed(0)) * 2 - 1
    with th.inference_mode():
        returns = model.planner.rollout(obs, z, None)
        states = obs.repeat_interleave(60, dim=0).unsqueeze(1)  # [120, 1, 4]
        masked, unmasked, alive = th.zeros(120), th.zeros(120), th.ones(120, dtype=th.bool)
        for t in range(8):
            states, _ = model.policy.dynamics.propagate(states, z.reshape(120, 1, 8)[:, :, t : t + 1], "expectation")
            fallen = states[:, 0, 1].abs() > 0.2
            unmasked += (~fallen).float()
            alive &= ~fallen
            masked += alive.float()
    assert th.equal(returns.reshape(-1), masked)
    assert masked.min() < 8 and masked.max() > masked.min()  # some imagined poles fall, at different steps
    assert (unmasked > masked).any()  # some rise again after falling: what comes after a fall must not count
    # both envs are planned in one batch; each executes the first planned action clipped to the bounds (+-3) and keeps
    # the rest of its plan as its warm start
    plans = []
    plan = model.planner.plan

    def spy(obs, mean, generator=None):
        plans.append(plan(obs, mean, generator))
        return plans[-1]

    model.planner.plan = spy
    actions, state = model.predict(env.reset())
    (result,) = plans
    solution = result.solution.numpy()  # [2, 8]
    assert actions.shape == (2, 1) and np.abs(solution[:, 0]).max() > 0
    np.testing.assert_allclose(actions[:, 0], 3.0 * np.clip(solution[:, 0], -1.0, 1.0), atol=1e-6)
    np.testing.assert_array_equal(state, np.concatenate([solution[:, 1:], np.zeros((2, 1))], axis=1))


def test_learned_reward_fallback_warns_for_unknown_envs():
    env = gym.make("MountainCarContinuous-v0")
    with pytest.warns(UserWarning, match="learns the reward.*termination_fn="):
        model = POPLIN("pets", env, seed=0, train_freq=(60, "step"), **TINY)  # a fit every 60 steps
    assert model.settings.learned_reward and model.planner.reward_fn is None
    seen = {}
    spy_on_rollouts(model.planner, seen)
    model.learn(120, reset_num_timesteps=True)
    assert model._n_updates == 2 and len(seen["z"]) == 60 * TINY["cem_iterations"]  # planned the 60 steps after the first fit
    # the planner scores candidates with the learned reward: the reward head's output summed along the mean model
    # (the members' average prediction), here computed with the model's plain forward
    dynamics = model.policy.dynamics
    obs = th.tensor([[-0.5, 0.0], [-0.9, 0.03]])
    z = th.rand(2, 10, TINY["horizon"], generator=th.Generator().manual_seed(0)) * 2 - 1
    with th.inference_mode():
        returns = model.planner.rollout(obs, z, None)
        states, expected = obs.repeat_interleave(10, dim=0), th.zeros(20)
        for t in range(TINY["horizon"]):
            x = (th.cat([states, z.reshape(20, -1)[:, t : t + 1]], dim=1) - dynamics.input_mean) / dynamics.input_std
            mean, _ = dynamics(x.expand(dynamics.ensemble_size, -1, -1))
            prediction = mean.mean(dim=0) * dynamics.target_std + dynamics.target_mean  # [20, delta (2) + reward]
            states, expected = states + prediction[:, :2], expected + prediction[:, 2]
    assert expected.std() > 0  # the reward head tells the candidates apart
    assert th.allclose(returns.reshape(-1), expected, atol=1e-5)


# ---------------------------------------------------------------- save / load
@pytest.mark.parametrize("variant", ["pets", "rs"])
def test_save_load_without_env_gives_the_same_actions(tmp_path, variant):
    model = tiny(variant)
    model.learn(400)
    path = tmp_path / "model.zip"
    model.save(path)
    loaded = POPLIN.load(path, device="cpu")
    assert loaded.variant == variant and loaded.task_id == "Pendulum-v1" and loaded._model_fitted
    for (name, a), (_, b) in zip(model.policy.state_dict().items(), loaded.policy.state_dict().items(), strict=True):
        assert th.equal(a, b), name
    obs = np.array([[np.cos(2.0), np.sin(2.0), 0.5], [1.0, 0.0, 0.0]], dtype=np.float32)
    model.set_random_seed(7)
    loaded.set_random_seed(7)
    start = np.ones(2, dtype=bool)
    a1, s1 = model.predict(obs, episode_start=start)
    a2, s2 = loaded.predict(obs, episode_start=start)
    np.testing.assert_allclose(a1, a2, atol=1e-6)
    np.testing.assert_allclose(s1, s2, atol=1e-6)
    # and it keeps learning
    loaded.set_env(make_vec_env("Pendulum-v1", n_envs=1, seed=1))
    loaded.learn(200, reset_num_timesteps=False)
    assert loaded.num_timesteps == 600
