"""
The planner's rollout and plans through a model with known dynamics: termination masking, a learned reward, POPLIN-P's
parameter blocks, and the warm starts of a batch of envs.

The model is a real :class:`ProbabilisticEnsemble` whose weights are set so that every member predicts an exact linear
function of ``[obs, scaled action]`` (see :func:`linear_ensemble`), so returns can be computed by hand.
"""

from collections.abc import Sequence

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env

from conftest import tiny

from sb3_poplin.dynamics import ProbabilisticEnsemble
from sb3_poplin.planning import (
    CEM,
    ActionSequences,
    MPCController,
    MPCPlanner,
    PolicyActionNoise,
    PolicyParameterNoise,
    SearchSpace,
)
from sb3_poplin.policies import PolicyNetwork
from sb3_poplin.tasks import RewardFn, TerminationFn


def linear_ensemble(maps: Sequence[th.Tensor], learned_reward: bool = False) -> ProbabilisticEnsemble:
    """
    An ensemble whose member ``e`` predicts the target ``[obs, scaled action] @ maps[e]`` (``[in, out]``: the state
    delta, then the reward under ``learned_reward``) with a vanishing variance (std ~1e-22); its normalisers stay at
    mean 0 and std 1. Its one hidden layer holds ``u = x @ maps[e]`` and ``-u``, and the output takes
    ``silu(u) - silu(-u)``, which is ``u`` (up to float rounding).
    """
    in_dim, out_dim = maps[0].shape
    obs_dim = out_dim - int(learned_reward)
    model = ProbabilisticEnsemble(
        obs_dim, in_dim - obs_dim, ensemble_size=len(maps), hidden_sizes=(2 * out_dim,), learned_reward=learned_reward
    )
    eye = th.eye(out_dim)
    with th.no_grad():
        for member, weights in enumerate(maps):
            model.hidden[0].weight[member] = th.cat([weights, -weights], dim=1)
            model.output.weight[member] = th.cat([th.cat([eye, -eye]), th.zeros(2 * out_dim, out_dim)], dim=1)
        model.hidden[0].bias.zero_()
        model.output.bias.zero_()
        model.output.bias[..., out_dim:] = -100.0  # the log-variance half
        model.min_logvar.fill_(-100.0)
    return model


def slopes_ensemble(slopes: Sequence[float], reward_row: Sequence[float] | None = None) -> ProbabilisticEnsemble:
    """
    One-dimensional states: member ``e`` moves ``s' = s + slopes[e] * a``; with ``reward_row = (c_s, c_a)`` it also
    predicts the reward ``c_s * s + c_a * a`` (``a`` scaled).
    """
    maps = []
    for slope in slopes:
        delta = th.tensor([[0.0], [slope]])
        maps.append(delta if reward_row is None else th.cat([delta, th.tensor(reward_row).view(2, 1)], dim=1))
    return linear_ensemble(maps, learned_reward=reward_row is not None)


def make_planner(
    model: ProbabilisticEnsemble,
    space: SearchSpace,
    reward_fn: RewardFn | None,
    termination_fn: TerminationFn | None = None,
    propagation: str = "expectation",
    num_particles: int = 1,
    bound: float = 1.0,
    max_batch_rows: int | None = None,
) -> MPCPlanner:
    """A planner of one-dimensional actions in ``[-bound, bound]`` with a small CEM (32 candidates, 4 elites, 4 iterations)."""
    cem = CEM(population_size=32, num_elites=4, iterations=4, alpha=0.1)
    low, high = th.tensor([-bound]), th.tensor([bound])
    return MPCPlanner(
        model, space, cem, reward_fn, termination_fn, propagation, num_particles, low, high, max_batch_rows=max_batch_rows
    )


def next_state_reward(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    return next_obs[..., 0]


def beyond_one(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    return next_obs[..., 0] > 1.0


# four action sequences (scaled; 1.5 is clamped to 1) from s0 = 0.125
CANDIDATES = th.tensor(
    [
        [0.375, 0.375, 0.375, 0.375],
        [0.25, -0.25, 0.25, 0.25],
        [1.5, 0.25, -1.0, 0.0],
        [0.25, 0.875, -0.875, 0.5],
    ]
).unsqueeze(0)  # [n_envs = 1, N = 4, D = H = 4]


# ---------------------------------------------------------------- termination
@pytest.mark.parametrize(
    "propagation, particles, max_batch_rows, expected",
    [
        # mean of the members' slopes (0.5, 1.5): s' = s + a. Reward s', terminated once s' > 1 (its own reward counts):
        # A: 0.5, 0.875, 1.25 | 1.625        -> 2.625 (4.25 unmasked)
        # B: 0.375, 0.125, 0.375, 0.625      -> 1.5
        # C: 1.125 | 1.375, 0.375, 0.375     -> 1.125 (3.25 unmasked)
        # D: 0.375, 1.25 | 0.375, 0.875      -> 1.625 (back below 1 after terminating: still masked)
        ("expectation", 1, None, [2.625, 1.5, 1.125, 1.625]),
        # particle 0 on member 0 (slope 0.5), particle 1 on member 1 (slope 1.5); the mean over particles:
        # A: 0.3125, 0.5, 0.6875, 0.875 -> 2.375   and 0.6875, 1.25 | 1.8125, 2.375 -> 1.9375   -> 2.15625
        # B: 0.25, 0.125, 0.25, 0.375   -> 1.0     and 0.5, 0.125, 0.5, 0.875        -> 2.0      -> 1.5
        # C: 0.625, 0.75, 0.25, 0.25    -> 1.875   and 1.625 | 1.875, 0.375, 0.375   -> 1.625    -> 1.75
        # D: 0.25, 0.6875, 0.25, 0.5    -> 1.6875  and 0.5, 1.8125 | 0.5, 1.25       -> 2.3125   -> 2.0
        ("tsinf", 2, 2, [2.15625, 1.5, 1.75, 2.0]),  # and one candidate per chunk
    ],
)
def test_rewards_after_a_predicted_termination_do_not_count(
    propagation: str, particles: int, max_batch_rows: int | None, expected: list[float]
) -> None:
    model = slopes_ensemble([0.5, 1.5])
    space = ActionSequences(horizon=4, action_dim=1, init_var=0.25)
    planner = make_planner(model, space, next_state_reward, beyond_one, propagation, particles, max_batch_rows=max_batch_rows)
    with th.inference_mode():
        returns = planner.rollout(th.tensor([[0.125]]), CANDIDATES, None, th.Generator().manual_seed(0))
    assert th.allclose(returns, th.tensor([expected]), atol=1e-5)


# ---------------------------------------------------------------- learned reward
# the reward head predicts r = -0.25 s - a (scaled a), the state moves by slope * a: the best plan is a = -1 throughout
LEARNED_REWARD = (-0.25, -1.0)


@pytest.mark.parametrize("propagation, particles", [("expectation", 1), ("ts1", 2)])
def test_rollout_and_plan_use_the_learned_reward(propagation: str, particles: int) -> None:
    # members of slopes 0.5 and 1.5: the mean slope is 1, and with ts1 each step sends one of the two particles through
    # each member, so the particles' mean state, and so their mean return (linear in the states), is that of slope 1
    model = slopes_ensemble([0.5, 1.5], reward_row=LEARNED_REWARD)
    space = ActionSequences(horizon=4, action_dim=1, init_var=0.25)
    planner = make_planner(model, space, None, propagation=propagation, num_particles=particles, bound=2.0)
    obs = th.tensor([[1.0], [-2.0]])
    z = th.tensor([[0.5, 0.5, 0.5, 0.5], [-1.0, -1.0, -1.0, -1.0], [1.5, 0.0, -0.5, 0.0]]).expand(2, 3, 4)
    # r_t = -0.25 s_t - a_t along s_{t+1} = s_t + a_t:
    # s0 = 1:  s = 1, 1.5, 2, 2.5 -> -3.75;  s = 1, 0, -1, -2 -> 4.5;    s = 1, 2, 2, 1.5 (a0 clamped to 1) -> -2.125
    # s0 = -2: s = -2, -1.5, -1, -0.5 -> -0.75;  s = -2, -3, -4, -5 -> 7.5;  s = -2, -1, -1, -1.5 -> 0.875
    expected = th.tensor([[-3.75, 4.5, -2.125], [-0.75, 7.5, 0.875]])
    with th.inference_mode():
        returns = planner.rollout(obs, z, None, th.Generator().manual_seed(0))
    assert th.allclose(returns, expected, atol=1e-5)
    # every action's term in the return is negative (-1 - 0.25 * the steps it moves the state): the plan pushes a0
    # towards -1, and its elites return more than halfway from the zero plan's (-1, 2) to the best (4.5, 7.5)
    plan = planner.plan(obs, space.initial_mean(2, obs.device), th.Generator().manual_seed(1))
    assert (plan.action < -0.5).all(), plan.action
    assert (plan.elite_return > th.tensor([1.75, 4.75])).all(), plan.elite_return


# ---------------------------------------------------------------- POPLIN-P's parameter blocks
def output_bias_policy() -> tuple[PolicyNetwork, int]:
    """
    A policy network with every parameter 0: a perturbation that moves only the output bias (the last entry of a
    block) to ``c`` makes it act ``c``.

    :return: the network and its number of parameters W
    """
    th.manual_seed(0)
    policy = PolicyNetwork(1, 1, [2])
    policy.set_parameters(th.zeros(policy.num_params))
    return policy, policy.num_params


def bias_blocks(biases: th.Tensor, w: int) -> th.Tensor:
    """Search vectors ``[1, N, H * W]`` whose block t perturbs the output bias by ``biases[n, t]`` only."""
    z = th.zeros(*biases.shape, w)
    z[..., -1] = biases
    return z.flatten(1).unsqueeze(0)


def recording_reward(seen: list[th.Tensor]) -> RewardFn:
    """A zero reward that keeps the actions (env units) of every imagined step."""

    def reward(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
        seen.append(action[:, 0].clone())
        return th.zeros(obs.shape[0])

    return reward


@pytest.mark.parametrize("noise", ["sep", "uni"])
def test_parameter_noise_drives_each_step_with_its_block(noise: str) -> None:
    policy, w = output_bias_policy()
    space = PolicyParameterNoise(horizon=3, action_dim=1, init_var=0.1, policy=policy, noise=noise)
    seen: list[th.Tensor] = []
    planner = make_planner(slopes_ensemble([1.0]), space, recording_reward(seen))
    if noise == "sep":  # one block per step: step t plays its block's bias (clamped)
        biases = th.tensor([[0.1, 0.2, 0.3], [-0.5, 1.5, 0.0]])  # [N = 2, H = 3]
        expected = [[0.1, -0.5], [0.2, 1.0], [0.3, 0.0]]
    else:  # one block shared by every step
        biases = th.tensor([[0.4], [-0.7]])
        expected = [[0.4, -0.7]] * 3
    z = bias_blocks(biases, w)
    assert z.shape == (1, 2, space.dim)
    with th.inference_mode():
        planner.rollout(th.tensor([[0.3]]), z, None)
    assert len(seen) == 3
    assert th.allclose(th.stack(seen), th.tensor(expected), atol=1e-6)


@pytest.mark.parametrize("noise", ["sep", "uni"])
def test_parameter_noise_plan_executes_the_first_block_and_warm_starts(noise: str) -> None:
    th.manual_seed(0)
    policy = PolicyNetwork(1, 1, [4])
    w = policy.num_params
    space = PolicyParameterNoise(horizon=3, action_dim=1, init_var=0.5, policy=policy, noise=noise)
    # the reward prefers the state near 0.5 (s' = s + a): candidates must differ to move the mean
    planner = make_planner(slopes_ensemble([1.0]), space, lambda o, a, n: -((n[..., 0] - 0.5) ** 2))
    obs = th.tensor([[-0.2], [0.6]])
    plan = planner.plan(obs, space.initial_mean(2, obs.device), th.Generator().manual_seed(2))
    solution = plan.solution
    assert solution.shape == (2, space.dim) and solution.abs().min() > 0
    # the executed action: the network with its parameters moved by the first block (sep) or the one block (uni), run
    # on the real observation through its plain forward
    for env in range(2):
        moved = PolicyNetwork(1, 1, [4])
        moved.load_state_dict(policy.state_dict())
        moved.add_to_parameters(solution[env, :w])
        assert th.allclose(plan.action[env], moved(obs[env]).clamp(-1.0, 1.0), atol=1e-6)
    if noise == "sep":  # the next step's blocks move up, a zero block comes last
        assert th.equal(plan.next_state, th.cat([solution[:, w:], th.zeros(2, w)], dim=1))
    else:  # the one block is carried over unchanged
        assert th.equal(plan.next_state, solution)


@pytest.mark.parametrize("proposal", ["init", "replan"])
def test_action_noise_plan_executes_the_policy_action_plus_the_first_noise(proposal: str) -> None:
    th.manual_seed(0)
    policy = PolicyNetwork(1, 1, [4])
    with th.no_grad():
        policy.biases[-1].fill_(0.3)  # the policy alone acts about 0.3
    space = PolicyActionNoise(horizon=3, action_dim=1, init_var=0.25, policy=policy, proposal=proposal)
    # the reward prefers the state near -0.5 (s' = s + a): the plan moves the policy's actions down
    planner = make_planner(slopes_ensemble([1.0]), space, lambda o, a, n: -((n[..., 0] + 0.5) ** 2))
    obs = th.tensor([[0.0], [0.4]])
    plan = planner.plan(obs, space.initial_mean(2, obs.device), th.Generator().manual_seed(3))
    solution = plan.solution
    assert (solution[:, 0] < -0.1).all()  # the noise of the executed step is far from zero
    with th.no_grad():
        expected = (policy(obs).clamp(-1.0, 1.0) + solution[:, :1]).clamp(-1.0, 1.0)
    assert th.allclose(plan.action, expected, atol=1e-6)
    assert th.equal(plan.next_state, th.cat([solution[:, 1:], th.zeros(2, 1)], dim=1))


# ---------------------------------------------------------------- warm starts of a batch of envs
def test_episodes_ended_resets_the_own_warm_start_of_those_envs_only() -> None:
    space = ActionSequences(horizon=3, action_dim=1, init_var=0.25)
    controller = MPCController(make_planner(slopes_ensemble([1.0]), space, next_state_reward), "cpu")
    controller.episodes_ended(np.array([True, False, True]))  # no warm start yet: nothing to reset
    assert controller.warm_start is None
    controller.warm_start = th.tensor([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]])
    controller.episodes_ended(np.array([False, False, False]))
    assert th.equal(controller.warm_start, th.tensor([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]]))
    controller.episodes_ended(np.array([False, True, False]))
    expected = th.tensor([[1.0, 2.0, 3.0], [0.0, 0.0, 0.0], [7.0, 8.0, 9.0]])
    assert th.equal(controller.warm_start, expected)
    # the training rollout's next step of the three envs plans from that warm start and keeps the new one
    seen = {}
    plan = controller.planner.plan

    def spy(observations: th.Tensor, mean: th.Tensor, generator: th.Generator | None = None):
        seen["mean"] = mean.clone()
        seen["plan"] = plan(observations, mean, generator)
        return seen["plan"]

    controller.planner.plan = spy  # type: ignore[method-assign]
    step = controller.collect(th.tensor([[0.1], [0.2], [0.3]]))
    assert th.equal(seen["mean"], expected)
    assert th.equal(controller.warm_start, seen["plan"].next_state)
    np.testing.assert_array_equal(step.state, seen["plan"].next_state.numpy())
    # a step from a given state (predict) plans from it, with a given generator, and leaves the own warm start alone
    own = controller.warm_start.clone()
    given = th.full((3, 3), 0.5)
    generator = th.Generator().manual_seed(3)
    controller.step(th.tensor([[0.1], [0.2], [0.3]]), given.numpy(), None, generator)
    assert th.equal(seen["mean"], given) and th.equal(controller.warm_start, own)
    controller.step(th.tensor([[0.1], [0.2], [0.3]]))  # no state: a fresh start
    assert th.equal(seen["mean"], th.zeros(3, 3)) and th.equal(controller.warm_start, own)


@pytest.mark.parametrize("variant", ["pets", "poplin-p"])
def test_episode_start_in_a_vec_env_resets_only_the_ended_env(variant: str) -> None:
    model = tiny(variant)
    env = make_vec_env("Pendulum-v1", n_envs=3, seed=0)
    obs = env.reset()
    means = []
    plan = model.planner.plan

    def spy(observations: th.Tensor, mean: th.Tensor, generator: th.Generator | None = None):
        means.append(mean.clone())
        return plan(observations, mean, generator)

    model.planner.plan = spy  # type: ignore[method-assign]
    actions, state = model.predict(obs, episode_start=np.ones(3, dtype=bool))
    dim = model.planner.search_space.dim
    assert state.shape == (3, dim) and np.abs(state[:, 0]).min() > 0  # every env has its own warm start
    obs, _, _, _ = env.step(actions)
    model.predict(obs, state=state, episode_start=np.array([False, True, False]))
    assert th.equal(means[0], th.zeros(3, dim))
    expected = state.copy()
    expected[1] = 0.0  # the initial mean of every search space
    np.testing.assert_array_equal(means[1].numpy(), expected)


# ---------------------------------------------------------------- a model without hidden layers
@pytest.mark.parametrize("learned_reward", [False, True])  # with the reward, the input and output widths are equal (4)
def test_expectation_propagation_of_a_model_without_hidden_layers(learned_reward: bool) -> None:
    """A linear ensemble (``dynamics_net_arch=()``): the planner's mean-model step is the members' average output."""
    th.manual_seed(0)
    model = ProbabilisticEnsemble(3, 1, ensemble_size=2, hidden_sizes=(), learned_reward=learned_reward)
    obs, actions = th.randn(6, 1, 3), th.rand(6, 1, 1) * 2 - 1
    with th.inference_mode():  # the planner's no-gradient path (fewer rows than the fused forward takes)
        next_obs, reward = model.propagate(obs, actions, "expectation")
    x = th.cat([obs[:, 0], actions[:, 0]], dim=1)  # the normalisers are at mean 0, std 1
    weight, bias = model.output.weight[:, :, : model.out_dim], model.output.bias[:, :, : model.out_dim]
    expected = (x @ weight + bias).mean(dim=0).detach()  # [6, out]
    assert th.allclose(next_obs[:, 0], obs[:, 0] + expected[:, :3], atol=1e-6)
    if learned_reward:
        assert th.allclose(reward[:, 0], expected[:, 3], atol=1e-6)
