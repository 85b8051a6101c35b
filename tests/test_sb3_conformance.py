"""
What SB3's own generic tests (save/load, predict, spaces, train/eval mode) expect of an algorithm, checked on every
POPLIN variant and both control modes: ``predict(deterministic=True)`` is a function of its inputs, parameters are
parameters, a policy saves and loads alone, the action space's shape and dtype come back, a Gym-API mix-up is
explained, and the SB3 idioms that POPLIN does not take (``policy_kwargs``) name what to use instead.
"""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy

from conftest import TINY, tiny
from sb3_poplin import POPLIN
from sb3_poplin.policies import POPLINPolicy

DEVICES = ["cpu", *(["cuda"] if th.cuda.is_available() else [])]
# every variant under each control mode it has
CASES = [("pets", "mpc"), ("rs", "mpc"), ("poplin-a", "mpc"), ("poplin-a", "policy"), ("poplin-p", "mpc")]
CASES += [("poplin-p", "policy")]
OBS = np.array([[0.6, 0.8, -0.4], [-0.2, 0.98, 1.5]], dtype=np.float32)


@pytest.fixture(scope="module")
def trained() -> dict[str, POPLIN]:
    """One agent per variant after one random and one planned episode (model fitted, policy distilled)."""
    agents = {}
    for variant in ("pets", "rs", "poplin-a", "poplin-p"):
        agent = tiny(variant)
        agent.learn(400)
        agents[variant] = agent
    return agents


def agent_in(trained: dict[str, POPLIN], variant: str, control: str) -> POPLIN:
    agent = trained[variant]
    agent.control = control
    return agent


# ------------------------------------------------------------------------------------ deterministic predict
@pytest.mark.parametrize(("variant", "control"), CASES)
def test_deterministic_predict_is_a_function_of_its_inputs(trained, tmp_path: Path, variant: str, control: str) -> None:
    agent = agent_in(trained, variant, control)
    first, state = agent.predict(OBS, deterministic=True)
    again, state_again = agent.predict(OBS, deterministic=True)
    np.testing.assert_array_equal(first, again)
    if control == "mpc":
        np.testing.assert_array_equal(state, state_again)
        # with a state passed back: the same state gives the same plan
        from_state, _ = agent.predict(OBS, state=state, episode_start=np.zeros(2, dtype=bool), deterministic=True)
        np.testing.assert_array_equal(
            from_state, agent.predict(OBS, state=state, episode_start=np.zeros(2, dtype=bool), deterministic=True)[0]
        )
    agent.save(tmp_path / "agent")
    for device in DEVICES:
        loaded = POPLIN.load(tmp_path / "agent", device=device)
        assert loaded.control == control
        np.testing.assert_allclose(loaded.predict(OBS, deterministic=True)[0], first, atol=1e-5 if device != "cpu" else 0)
    agent.control = "mpc"


@pytest.mark.parametrize(("variant", "control"), CASES)
def test_evaluate_policy_deterministic_gives_identical_returns_also_after_load(
    trained, tmp_path: Path, variant: str, control: str
) -> None:
    """The acceptance check: twice in a row, and again after save/load, on an env seeded the same way."""
    agent = agent_in(trained, variant, control)

    def returns(model: POPLIN) -> list[float]:
        env = make_vec_env("Pendulum-v1", n_envs=1, seed=7)
        episode_returns, _ = evaluate_policy(model, env, n_eval_episodes=1, deterministic=True, return_episode_rewards=True)
        return list(episode_returns)  # type: ignore[arg-type]

    first = returns(agent)
    assert returns(agent) == first
    agent.save(tmp_path / "agent")
    assert returns(POPLIN.load(tmp_path / "agent")) == first
    agent.control = "mpc"


@pytest.mark.parametrize("variant", ["pets", "poplin-p"])
def test_stochastic_predict_draws_and_predict_leaves_the_training_rollout_alone(trained, variant: str) -> None:
    agent = agent_in(trained, variant, "mpc")
    own = None if agent.mpc.warm_start is None else agent.mpc.warm_start.clone()
    generator = agent.mpc.generator.get_state()
    actions = {tuple(agent.predict(OBS)[0].ravel()) for _ in range(3)}
    assert len(actions) == 3  # fresh draws from the planner's generator
    agent.mpc.generator.set_state(generator)
    deterministic = agent.predict(OBS, deterministic=True)[0]
    assert th.equal(agent.mpc.generator.get_state(), generator)  # deterministic=True draws nothing from it
    assert not np.array_equal(deterministic, agent.predict(OBS)[0])
    # the training rollout's own warm start is not predict's: no call above changed it
    assert (own is None and agent.mpc.warm_start is None) or th.equal(agent.mpc.warm_start, own)


def test_deterministic_planning_depends_on_the_seed() -> None:
    obs = OBS[0]
    actions = [POPLIN("pets", "Pendulum-v1", seed=seed, **TINY).predict(obs, deterministic=True)[0] for seed in (0, 0, 1)]
    np.testing.assert_array_equal(actions[0], actions[1])
    assert not np.array_equal(actions[0], actions[2])


# ------------------------------------------------------------------------------------ parameters
@pytest.mark.parametrize("variant", ["pets", "rs", "poplin-a", "poplin-p"])
def test_get_parameters_holds_parameters_only_and_round_trips_perturbed(trained, variant: str) -> None:
    agent = trained[variant]
    params = agent.get_parameters()
    optimizers = set(agent.policy.optimizer_names())
    assert set(params) == {"policy", *optimizers}
    for key, value in params["policy"].items():
        assert isinstance(value, th.Tensor) and value.is_floating_point(), key
    # SB3's test: perturb every parameter, set them, get them back equal
    perturbed = {key: value + 0.5 * th.rand_like(value) for key, value in params["policy"].items()}
    agent.set_parameters({"policy": perturbed}, exact_match=False)
    for key, value in agent.get_parameters()["policy"].items():
        th.testing.assert_close(value, perturbed[key], rtol=0, atol=0)
    agent.set_parameters(params)  # exact match: every parameter and optimizer
    for key, value in agent.get_parameters()["policy"].items():
        th.testing.assert_close(value, params["policy"][key], rtol=0, atol=0)
    with pytest.raises(ValueError, match="Names of parameters do not match"):
        agent.set_parameters({"policy": params["policy"]}, exact_match=True)
    with pytest.raises(ValueError, match="invalid object name"):
        agent.set_parameters({"not_a_module": {}}, exact_match=False)


def test_the_planner_state_is_saved_beside_the_parameters_and_resumes_exactly(tmp_path: Path) -> None:
    agent = tiny("poplin-p")
    agent.learn(200)  # the random episode, then the model's first fit
    agent._last_obs = OBS[:1]
    for _ in range(3):  # three steps of a training rollout, planned and recorded, not yet distilled
        agent._sample_action(learning_starts=0)
    agent.save(tmp_path / "agent")
    loaded = POPLIN.load(tmp_path / "agent", env="Pendulum-v1")
    assert th.equal(loaded.mpc.generator.get_state(), agent.mpc.generator.get_state())
    assert th.equal(loaded.mpc.warm_start, agent.mpc.warm_start)
    assert len(loaded.distiller.planned) == len(agent.distiller.planned) == 3
    # set_parameters from the zip restores it too (SB3's in-place load)
    other = POPLIN("poplin-p", "Pendulum-v1", seed=5, **TINY)
    other.set_parameters(str(tmp_path / "agent.zip"))
    assert th.equal(other.mpc.generator.get_state(), agent.mpc.generator.get_state())
    assert len(other.distiller.planned) == 3
    with pytest.raises(ValueError, match=r"uint8 tensor of torch\.Generator\.get_state"):
        other.mpc.load_state_dict({"generator": th.rand(10), "warm_start": None})
    with pytest.warns(UserWarning, match="does not fit this device's generator"):
        other.mpc.load_state_dict({"generator": th.zeros(16, dtype=th.uint8), "warm_start": None})
    assert th.equal(other.mpc.generator.get_state(), agent.mpc.generator.get_state())  # kept as it was
    with pytest.raises(ValueError, match="no policy network to distill into"):
        tiny("pets").set_parameters({**tiny("pets").get_parameters(), "distiller": agent.distiller.state_dict()})


# ------------------------------------------------------------------------------------ the policy alone
@pytest.mark.parametrize("variant", ["pets", "rs", "poplin-a", "poplin-p"])
def test_the_policy_saves_and_loads_alone(trained, tmp_path: Path, variant: str) -> None:
    agent = trained[variant]
    agent.policy.save(str(tmp_path / "policy.pth"))
    policy = POPLINPolicy.load(str(tmp_path / "policy.pth"))
    for key, value in agent.policy.state_dict().items():
        th.testing.assert_close(policy.state_dict()[key], value, rtol=0, atol=0)
    if agent.policy.actor is not None:  # policy control without the algorithm
        np.testing.assert_array_equal(policy.predict(OBS, deterministic=True)[0], agent.policy.predict(OBS)[0])
    else:
        with pytest.raises(ValueError, match="no policy network"):
            policy.predict(OBS)


# ------------------------------------------------------------------------------------ spaces
class BoxEnv(gym.Env):
    """A linear system with actions of any shape and dtype, and a reward the planner is told."""

    def __init__(self, shape: tuple[int, ...] = (2,), dtype: type = np.float32) -> None:
        size = int(np.prod(shape))
        self.action_space = spaces.Box(-1.0, 1.0, shape=shape, dtype=dtype)
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(size,), dtype=np.float32)
        self.state = np.zeros(size, dtype=np.float32)
        self.steps = 0

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        self.state = self.np_random.uniform(-1, 1, self.observation_space.shape).astype(np.float32)
        self.steps = 0
        return self.state.copy(), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        assert action.shape == self.action_space.shape
        self.state = (self.state + 0.1 * np.asarray(action, dtype=np.float32).reshape(-1)).astype(np.float32)
        self.steps += 1
        return self.state.copy(), float(-np.sum(self.state**2)), False, self.steps >= 50, {}


def box_reward(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    return -(next_obs**2).sum(-1)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("variant", ["pets", "poplin-p"])
def test_actions_come_back_in_the_action_space_shape_and_dtype(variant: str, dtype: type) -> None:
    env = BoxEnv(shape=(2, 2), dtype=dtype)
    agent = POPLIN(variant, env, seed=0, reward_fn=box_reward, **TINY)
    agent.learn(100)  # one random and one planned episode, actions of shape (2, 2)
    obs, _ = env.reset(seed=0)
    controls = ["mpc", "policy"] if variant == "poplin-p" else ["mpc"]
    for control in controls:
        agent.control = control
        action, _ = agent.predict(obs, deterministic=True)
        assert action.shape == (2, 2) and action.dtype == dtype, control
        assert env.action_space.contains(action)
        batch, _ = agent.predict(np.stack([obs, obs]), deterministic=True)
        assert batch.shape == (2, 2, 2) and batch.dtype == dtype, control
    # the planner's flat actions map onto the space element by element: with a reward of the action alone, CEM finds
    # a target whose entries have bounds and signs of their own
    target = np.array([[0.5, -1.5], [2.0, -3.0]])
    bounded = BoxEnv(shape=(2, 2), dtype=dtype)
    bound = np.array([[1.0, 2.0], [3.0, 4.0]], dtype=dtype)
    bounded.action_space = spaces.Box(-bound, bound, dtype=dtype)
    flat_target = th.as_tensor(target.reshape(-1), dtype=th.float32)

    def action_reward(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
        return -((action - flat_target) ** 2).sum(-1)

    wide = {**TINY, "population_size": 200, "num_elites": 20, "cem_iterations": 5, "horizon": 1}
    planner = POPLIN("pets", bounded, seed=0, reward_fn=action_reward, **wide)
    action, _ = planner.predict(np.zeros(4, dtype=np.float32), deterministic=True)
    assert action.shape == (2, 2) and bounded.action_space.contains(action)
    np.testing.assert_allclose(action, target, atol=0.5)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_mpc_returns_the_action_space_dtype(dtype: type) -> None:
    env = BoxEnv(shape=(2,), dtype=dtype)
    obs, _ = env.reset(seed=0)
    agent = POPLIN("pets", env, seed=0, reward_fn=box_reward, **TINY)
    for deterministic in (True, False):
        assert agent.predict(obs, deterministic=deterministic)[0].dtype == dtype
    assert agent.predict(np.stack([obs, obs]))[0].dtype == dtype


def test_predict_explains_the_gym_api_mix_up() -> None:
    agent = tiny("pets")
    env = gym.make("Pendulum-v1")
    for control, variant in (("mpc", "pets"), ("policy", "poplin-p")):
        agent = tiny(variant, control=control)
        with pytest.raises(ValueError, match=r"tuple|Tuple"):
            agent.predict(env.reset(seed=0))  # (obs, info), not obs


# ------------------------------------------------------------------------------------ construction and loading
def test_policy_kwargs_names_the_settings_to_use() -> None:
    with pytest.raises(TypeError, match=r"policy_net_arch.*dynamics_net_arch"):
        POPLIN("poplin-p", "Pendulum-v1", policy_kwargs=dict(net_arch=[64, 64]))


def test_named_configurations_are_policies() -> None:
    agent = tiny("poplin-p/uni/bc")
    assert agent.variant == "poplin-p" and agent.settings.noise == "uni" and agent.settings.distillation == "bc"
    replan = tiny("poplin-a/replan")
    assert replan.variant == "poplin-a" and replan.settings.proposal == "replan"
    with pytest.raises(ValueError, match="policy='poplin-p/sep/bc' sets noise='sep', but noise='uni' was given"):
        POPLIN("poplin-p/sep/bc", "Pendulum-v1", noise="uni", **TINY)
    with pytest.raises(ValueError, match=r"Unknown POPLIN variant 'poplin-q'.*poplin-p/sep/avg"):
        POPLIN("poplin-q", "Pendulum-v1")


def test_load_takes_an_env_id(tmp_path: Path) -> None:
    agent = tiny("pets")
    agent.save(tmp_path / "agent")
    loaded = POPLIN.load(tmp_path / "agent", env="Pendulum-v1")
    assert loaded.get_env() is not None and loaded.get_env().num_envs == 1
    loaded.learn(10)  # trains on the env made from the id
