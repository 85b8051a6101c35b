"""POPLIN-A and POPLIN-P: the policy network, the search spaces, distillation and control modes."""

import copy
import itertools

import numpy as np
import pytest
import torch as th
from torch.func import functional_call

from conftest import TINY, pendulum_reward, sorted_rows

from sb3_poplin import POPLIN
from sb3_poplin.callbacks import ControlModesEvalCallback
from sb3_poplin.distillation import average_perturbation, behaviour_cloning, gan_distillation, saturated_fraction
from sb3_poplin.dynamics import ProbabilisticEnsemble
from sb3_poplin.planning import MPCPlanner, PlanResult, PolicyActionNoise, PolicyParameterNoise
from sb3_poplin.policies import Discriminator, PolicyNetwork
from sb3_poplin.variants import NAMED_CONFIGURATIONS, POLICY_VARIANTS, configuration

# every named configuration with a policy network
POLICY_CONFIGS = [name for name, config in NAMED_CONFIGURATIONS.items() if config["policy"] in POLICY_VARIANTS]


def whitened_policy(seed=0, obs_dim=3, action_dim=2, arch=(8, 6)):
    th.manual_seed(seed)
    policy = PolicyNetwork(obs_dim, action_dim, arch)
    policy.update_whitening(th.randn(50, obs_dim) * 3 + 1)
    return policy


# ---------------------------------------------------------------- policy network
@pytest.mark.parametrize("particles", [1, 3])  # one particle: shared matmul + noise product; several: per-row weights
def test_perturbed_forward_equals_a_loop_of_functional_forwards(particles: int):
    policy = whitened_policy()
    rows, w = 7, policy.num_params
    assert w == 3 * 8 + 8 + 8 * 6 + 6 + 6 * 2 + 2
    # the noise as the planner passes it: a strided view of one step's block of a longer search vector
    obs, noise = th.randn(rows, particles, 3), 0.3 * th.randn(rows, 3 * w)[:, w : 2 * w]
    batched = policy.forward_perturbed(obs, noise)
    names = [name for name, _ in policy.named_parameters()]  # weights.0, weights.1, ..., biases.0, ...
    for r in range(rows):
        params, offset = {}, 0
        for i, (d_in, d_out) in enumerate(policy.shapes):  # the flat layout: W_i row-major, then b_i
            params[f"weights.{i}"] = policy.weights[i] + noise[r, offset : offset + d_in * d_out].view(d_in, d_out)
            offset += d_in * d_out
            params[f"biases.{i}"] = policy.biases[i] + noise[r, offset : offset + d_out]
            offset += d_out
        assert sorted(params) == sorted(names)
        expected = functional_call(policy, params, (obs[r],))
        assert th.allclose(batched[r], expected, atol=1e-5)


def test_flat_parameters_and_add_to_parameters_share_one_layout():
    policy = whitened_policy()
    theta = policy.flat_parameters().clone()
    delta = th.randn(policy.num_params)
    policy.add_to_parameters(delta)
    assert th.allclose(policy.flat_parameters(), theta + delta)
    obs = th.randn(4, 1, 3)
    policy.add_to_parameters(-delta)
    assert th.allclose(policy.flat_parameters(), theta, atol=1e-6)
    # zero noise is the plain network
    assert th.allclose(policy.forward_perturbed(obs, th.zeros(4, policy.num_params)), policy(obs), atol=1e-6)


def test_whitening_update_keeps_the_function():
    policy = whitened_policy()
    obs = th.randn(20, 3) * 5
    before = policy(obs)
    policy.update_whitening(th.randn(200, 3) * 0.01 + 7.0)
    assert th.allclose(policy(obs), before, atol=1e-4)
    assert policy.obs_count.item() == 250


def test_whitening_floors_the_variance_of_a_constant_input():
    th.manual_seed(0)
    policy = PolicyNetwork(2, 1, (4,))
    states = th.stack([th.full((10,), 3.0), th.arange(10.0)], dim=1)  # the first input never changes: variance 0
    policy.update_whitening(states)
    assert policy.obs_mean.tolist() == [3.0, 4.5] and policy.obs_var.tolist() == [0.0, 8.25]
    probe = th.tensor([[3.5, 4.5], [2.0, 0.0]])
    # the constant input is divided by the floored std, sqrt(1e-2) = 0.1, not by 0
    assert th.allclose(policy.whiten(probe), th.tensor([[5.0, 0.0], [-10.0, -4.5 / 8.25**0.5]]))
    # a later update still under the floor (variance 0.0025) re-expresses the first layer with the floored stds
    before = policy(probe)
    policy.update_whitening(th.stack([th.full((10,), 3.1), th.arange(10.0)], dim=1))
    assert policy.obs_mean[0].item() == pytest.approx(3.05, abs=1e-6)
    assert policy.obs_var[0].item() == pytest.approx(0.0025, abs=1e-6)
    assert th.allclose(policy.whiten(probe)[:, 0], th.tensor([4.5, -10.5]), atol=1e-5)
    assert th.allclose(policy(probe), before, atol=1e-5)


def test_initial_policy_output_is_small_and_actions_are_clipped():
    policy = PolicyNetwork(3, 1, [32])
    assert policy(th.randn(100, 3)).abs().max() < 0.2  # normc: output layer scaled to 0.01
    with th.no_grad():
        policy.biases[-1].fill_(5.0)
    assert th.all(policy.act(th.randn(10, 3)) == 1.0)


# ---------------------------------------------------------------- search spaces
def make_planner(space_cls, **kwargs):
    th.manual_seed(0)
    model = ProbabilisticEnsemble(3, 1, ensemble_size=2, hidden_sizes=(8,))
    policy = PolicyNetwork(3, 1, [4])
    space = space_cls(horizon=4, action_dim=1, init_var=0.1, policy=policy, **kwargs)
    return space, policy, model


def test_parameter_noise_shift_semantics():
    sep, policy, _ = make_planner(PolicyParameterNoise, noise="sep")
    w = policy.num_params
    assert sep.block == w and sep.dim == 4 * w
    mean = th.arange(4 * w, dtype=th.float32).unsqueeze(0)
    shifted = sep.shift(mean)
    assert th.equal(shifted[:, : 3 * w], mean[:, w:]) and th.equal(shifted[:, 3 * w :], th.zeros(1, w))
    uni, _, _ = make_planner(PolicyParameterNoise, noise="uni")
    assert uni.dim == w
    mean = th.randn(2, w)
    assert th.equal(uni.shift(mean), mean)  # one shared block, carried over unchanged
    with pytest.raises(ValueError, match=r"Unknown noise 'both'; accepted values: \['sep', 'uni'\]"):
        make_planner(PolicyParameterNoise, noise="both")


def test_action_noise_shift_and_proposals():
    init, policy, model = make_planner(PolicyActionNoise, proposal="init")
    assert init.dim == 4
    assert th.equal(init.shift(th.tensor([[1.0, 2.0, 3.0, 4.0]])), th.tensor([[2.0, 3.0, 4.0, 0.0]]))
    planner = MPCPlanner(
        model, init, None, lambda o, a, n: -n[..., 0], None, "expectation", 1, th.tensor([-2.0]), th.tensor([2.0])
    )
    obs = th.randn(2, 3)
    refs = init.prepare(obs, planner)  # open-loop policy rollout through the mean model
    assert refs.shape == (2, 4, 1)
    with th.no_grad():
        s1, _ = model.propagate(obs.unsqueeze(1), policy.act(obs.unsqueeze(1)), "expectation")
    assert th.allclose(refs[:, 0], policy.act(obs)) and th.allclose(refs[:, 1], policy.act(s1[:, 0]))
    z = th.zeros(2, 5, 4)
    states = th.randn(2, 5, 1, 3)
    assert th.allclose(init.actions(z, 1, states, refs)[:, :, 0], refs[:, 1].unsqueeze(1).expand(2, 5, 1))
    replan, _, _ = make_planner(PolicyActionNoise, proposal="replan")
    assert replan.prepare(obs, planner) is None
    assert th.allclose(replan.actions(z + 0.1, 2, states, None), (policy.act(states) + 0.1).clamp(-1, 1))
    with pytest.raises(ValueError, match="Unknown proposal 'open'"):
        make_planner(PolicyActionNoise, proposal="open")


def test_zero_noise_executes_the_policy():
    p_space, policy, _ = make_planner(PolicyParameterNoise, noise="sep")
    obs = th.randn(3, 3)
    assert th.allclose(p_space.executed_action(th.zeros(3, p_space.dim), obs, None), policy.act(obs), atol=1e-6)
    a_space, policy, _ = make_planner(PolicyActionNoise, proposal="init")
    assert th.allclose(a_space.executed_action(th.zeros(3, a_space.dim), obs, None), policy.act(obs))


def test_poplin_p_with_vanishing_noise_acts_like_its_policy():
    model = POPLIN("poplin-p", "Pendulum-v1", seed=0, init_var=1e-12, **TINY)
    obs = np.array([[0.3, 0.95, -1.0], [-1.0, 0.0, 2.0]], dtype=np.float32)
    planned, _ = model.predict(obs, episode_start=np.ones(2, dtype=bool))
    model.control = "policy"
    direct, _ = model.predict(obs)
    np.testing.assert_allclose(planned, direct, atol=1e-4)


# ---------------------------------------------------------------- distillation
def test_average_moves_theta_by_exactly_the_mean_perturbation():
    policy = whitened_policy()
    theta = policy.flat_parameters().clone()
    omegas = th.randn(25, policy.num_params)
    average_perturbation(policy, omegas)
    assert th.allclose(policy.flat_parameters() - theta, omegas.mean(dim=0), atol=1e-6)
    average_perturbation(policy, omegas, step_size=0.25)
    expected = theta + 1.25 * omegas.double().mean(dim=0).float()
    assert th.allclose(policy.flat_parameters(), expected, atol=1e-5)


def test_saturated_fraction_counts_components_beyond_the_clip():
    policy = whitened_policy()
    states = th.randn(40, 3)
    raw = policy(states)
    expected = float((raw.abs() > 1).float().mean())
    assert saturated_fraction(policy, states) == expected
    assert th.equal(policy.biases[-1], th.zeros(2))  # whitening changes the first layer only
    with th.no_grad():
        policy.biases[-1].copy_(th.tensor([50.0, 0.0]))
    # the first output is pushed far beyond +1 for every state, the second keeps its values
    assert saturated_fraction(policy, states) == 0.5 + float((raw[:, 1].abs() > 1).float().mean()) / 2


def target_policy_data(n=600):
    gen = th.Generator().manual_seed(0)
    states = th.randn(n, 3, generator=gen)
    targets = th.tanh(states[:, :1] - 0.5 * states[:, 1:2]).repeat(1, 2) * th.tensor([0.8, -0.4])
    return states, targets


def test_behaviour_cloning_fits_a_target_policy():
    states, targets = target_policy_data()
    th.manual_seed(0)
    policy = PolicyNetwork(3, 2, (32,))
    policy.update_whitening(states)  # as the distiller does: whitened on the states it trains on
    before = th.nn.functional.mse_loss(policy(states), targets).item()
    stats = behaviour_cloning(
        policy, th.optim.Adam(policy.parameters(), lr=3e-3), states, targets, generator=th.Generator().manual_seed(0)
    )
    after = th.nn.functional.mse_loss(policy(states), targets).item()
    assert after < 0.05 * before and stats["policy_holdout_loss"] < 0.01


def test_behaviour_cloning_stops_when_the_holdout_loss_rises_and_keeps_the_best_checked_parameters():
    gen = th.Generator().manual_seed(0)
    states = th.randn(60, 3, generator=gen)
    targets = th.tanh(states[:, :2]) + th.randn(60, 2, generator=gen)  # noisy targets: the net soon overfits
    th.manual_seed(0)
    policy = PolicyNetwork(3, 2, (32, 32))
    policy.update_whitening(states)
    # every holdout evaluation (the forward passes without gradients): its rows and the parameters it saw
    evaluated: list[tuple[th.Tensor, dict[str, th.Tensor]]] = []

    def record(module: th.nn.Module, args: tuple[th.Tensor]) -> None:
        if not th.is_grad_enabled():
            evaluated.append((args[0].clone(), {k: v.clone() for k, v in module.state_dict().items()}))

    policy.register_forward_pre_hook(record)
    optimizer = th.optim.Adam(policy.parameters(), lr=1e-2)
    check_every = 2
    stats = behaviour_cloning(
        policy, optimizer, states, targets, epochs=50, batch_size=8, check_every=check_every, generator=gen
    )
    hold_states = evaluated[0][0]
    assert hold_states.shape == (12, 3) and all(th.equal(rows, hold_states) for rows, _ in evaluated)  # 20 % of 60
    hold = (hold_states.unsqueeze(1) == states).all(dim=-1).int().argmax(dim=1)
    assert th.equal(states[hold], hold_states)

    def holdout_loss(state: dict[str, th.Tensor]) -> float:  # mean squared error, computed here on a copy
        probe = PolicyNetwork(3, 2, (32, 32))
        probe.load_state_dict(state)
        with th.no_grad():
            return ((probe(states[hold]) - targets[hold]) ** 2).mean().item()

    epochs = int(stats["policy_epochs"])
    assert epochs < 50 and epochs % check_every == 0  # stopped at a check
    # before training, then at every check: falling (or flat), then up at the last one
    losses = [holdout_loss(state) for _, state in evaluated[: 1 + epochs // check_every]]
    assert all(later <= earlier for earlier, later in itertools.pairwise(losses[:-1])) and losses[-1] > losses[-2]
    assert len(losses) >= 3  # trained for at least one check before it got worse
    best = evaluated[len(losses) - 2][1]
    for name, value in policy.state_dict().items():  # the best checked parameters, not the last epoch's
        assert th.equal(value, best[name]), name
    assert stats["policy_holdout_loss"] == pytest.approx(losses[-2], rel=1e-5)
    assert stats["policy_holdout_loss"] == pytest.approx(holdout_loss(policy.state_dict()), rel=1e-5)


def test_gan_distillation_moves_the_policy_towards_the_planned_actions():
    states, targets = target_policy_data(400)
    policy = whitened_policy(arch=(32,))
    disc = Discriminator(2 + 3)
    before = th.nn.functional.mse_loss(policy(states), targets).item()
    stats = gan_distillation(
        policy,
        th.optim.Adam(policy.parameters(), lr=3e-3),
        disc,
        th.optim.Adam(disc.parameters(), lr=3e-3),
        states,
        targets,
        noise_var=1e-4,
        epochs=40,
        generator=th.Generator().manual_seed(0),
    )
    assert stats["policy_loss"] < 0.5 * before, (before, stats)


def test_only_planned_steps_are_distilled(monkeypatch):
    seen = []
    import sb3_poplin.distillation as distillation_module

    original = distillation_module.behaviour_cloning

    def spy(policy, optimizer, states, targets, **kwargs):
        seen.append(states.shape[0])
        return original(policy, optimizer, states, targets, **kwargs)

    monkeypatch.setattr(distillation_module, "behaviour_cloning", spy)
    model = POPLIN("poplin-a", "Pendulum-v1", seed=0, distill_imagined=False, distill_window=None, **TINY)
    model.learn(600)  # a random episode, then two planned ones; a fit after each
    assert seen == [200, 200]  # fit 1: nothing planned yet; fits 2 and 3: that episode's 200 planned states
    assert model.distiller.data == {}  # without a window nothing is kept between distillations (nor saved)
    seen.clear()
    model = POPLIN("poplin-a", "Pendulum-v1", seed=0, distill_imagined=False, distill_window=300, **TINY)
    model.learn(800)
    assert seen == [200, 300, 300]  # the most recent 300 planned steps
    # the executed actions (the buffer holds them after a scale round trip)
    assert th.allclose(model.distiller.data["actions"], th.as_tensor(model.replay_buffer.actions[500:800, 0]), atol=1e-6)
    model = POPLIN("poplin-a", "Pendulum-v1", seed=0, **TINY)  # BC-AI: plus the 4 elites of every planned step
    seen.clear()
    model.learn(400)
    assert seen == [200 * (1 + 4)]


def flat_policy_forward(policy: PolicyNetwork, flat: th.Tensor, obs: th.Tensor) -> th.Tensor:
    """A reference forward of unwhitened inputs (mean 0, variance 1): tanh layers read off the flat layout."""
    x, offset = obs, 0
    for i, (d_in, d_out) in enumerate(policy.shapes):
        weight = flat[offset : offset + d_in * d_out].view(d_in, d_out)
        offset += d_in * d_out
        x = x @ weight + flat[offset : offset + d_out]
        offset += d_out
        x = th.tanh(x) if i < len(policy.shapes) - 1 else x
    return x


def poplin_p_planned_episode(**kwargs) -> tuple[POPLIN, PolicyNetwork, list[tuple[th.Tensor, PlanResult]]]:
    """
    A POPLIN-P agent (distill_imagined=True) after a random and a planned episode, its policy network as it planned
    (nothing is distilled before the first planned episode) and every plan (obs, result) of that episode.
    """
    model = POPLIN("poplin-p", "Pendulum-v1", seed=0, distill_imagined=True, **kwargs, **TINY)
    planned: list[tuple[th.Tensor, PlanResult]] = []
    plan = model.planner.plan

    def recording(obs, mean, generator=None, observer=None):
        result = plan(obs, mean, generator, observer)
        planned.append((obs.clone(), result))
        return result

    model.planner.plan = recording
    before = copy.deepcopy(model.policy.actor)
    assert before.obs_count.item() == 0  # no whitening yet: the network reads raw observations
    model.learn(400)
    assert len(planned) == 200 and not any(result.fallback.any() for _, result in planned)
    return model, before, planned


def test_poplin_p_avg_distills_the_imagined_elite_blocks():
    model, before, planned = poplin_p_planned_episode()  # Avg, overwrite: theta <- mean of the perturbations
    w, k = before.num_params, TINY["num_elites"]
    # per planned step: the executed block (the solution's first W entries) and the K final elites' first blocks
    blocks = th.cat([th.cat([result.solution[:, :w], result.elites[0, :, :w]]) for _, result in planned])
    assert blocks.shape == (200 * (1 + k), w)
    assert th.allclose(model.policy.actor.flat_parameters(), blocks.mean(dim=0), atol=1e-6)


def test_poplin_p_bc_distills_the_imagined_elite_actions(monkeypatch):
    import sb3_poplin.distillation as distillation_module

    seen: list[tuple[th.Tensor, th.Tensor]] = []
    original = distillation_module.behaviour_cloning

    def spy(policy, optimizer, states, targets, **kwargs):
        seen.append((states.clone(), targets.clone()))
        return original(policy, optimizer, states, targets, **kwargs)

    monkeypatch.setattr(distillation_module, "behaviour_cloning", spy)
    model, before, planned = poplin_p_planned_episode(distillation="bc")
    assert model.settings.distill_target == "planned" and len(seen) == 1
    theta, w = before.flat_parameters().detach(), before.num_params
    rows = []  # (state, target): the planner's action, then every final elite's, of the network it planned with
    with th.no_grad():
        for obs, result in planned:
            for block in th.cat([result.solution[:, :w], result.elites[0, :, :w]]):
                rows.append(th.cat([obs[0], flat_policy_forward(before, theta + block, obs[0])]))
    expected = th.stack(rows)
    states, targets = seen[0]
    assert states.shape == (200 * (1 + TINY["num_elites"]), 3)
    received = th.cat([states, targets], dim=1).numpy()
    np.testing.assert_allclose(sorted_rows(received), sorted_rows(expected.numpy()), atol=1e-5)  # in any order


# ---------------------------------------------------------------- algorithm
@pytest.mark.parametrize("name", POLICY_CONFIGS)
def test_variant_trains_plans_and_saves(tmp_path, name):
    config = configuration(name)
    model = POPLIN(env="Pendulum-v1", seed=0, **config, **TINY)
    model.learn(400)
    assert model.policy.actor is not None
    obs = np.array([[np.cos(2.0), np.sin(2.0), 0.5], [1.0, 0.0, 0.0]], dtype=np.float32)
    path = tmp_path / "model.zip"
    model.control = "policy"
    model.save(path)
    loaded = POPLIN.load(path, device="cpu")
    assert (loaded.variant, loaded.control, loaded.settings.distillation) == (
        config["policy"],
        "policy",
        model.settings.distillation,
    )
    for (name, a), (_, b) in zip(model.policy.state_dict().items(), loaded.policy.state_dict().items(), strict=True):
        assert th.equal(a, b), name
    np.testing.assert_allclose(model.predict(obs)[0], loaded.predict(obs)[0], atol=1e-6)  # policy control
    loaded = POPLIN.load(path, device="cpu", control="mpc")
    model.control = "mpc"
    model.set_random_seed(3)
    loaded.set_random_seed(3)
    start = np.ones(2, dtype=bool)
    np.testing.assert_allclose(
        model.predict(obs, episode_start=start)[0], loaded.predict(obs, episode_start=start)[0], atol=1e-6
    )


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(policy="poplin-a", distillation="avg"), r"Unknown distillation 'avg'; accepted values: \['bc'\]"),
        (dict(policy="poplin-p", distillation="dagger"), r"accepted values: \['avg', 'bc', 'gan'\]"),
        (dict(policy="pets", distillation="bc"), "has no policy network to distill into"),
        (dict(policy="poplin-p", distill_window="latest"), r"distill_window must be .* or 'auto' .*got 'latest'"),
        (dict(policy="poplin-p", distill_window=0), r"distill_window must be an integer >= 1 \(or None\), got 0"),
        (dict(policy="pets", policy_net_arch=[8]), "leave policy_net_arch=None"),
        (dict(policy="poplin-a", proposal="closed"), r"Unknown proposal 'closed'; accepted values: \['init', 'replan'\]"),
        (dict(policy="poplin-p", noise="shared"), r"Unknown noise 'shared'; accepted values: \['sep', 'uni'\]"),
        (dict(policy="pets", control="policy"), "control='policy' is not available"),
    ],
)
def test_bad_variant_settings(kwargs, message):
    with pytest.raises(ValueError, match=message):
        POPLIN(env="Pendulum-v1", **kwargs)


def test_variant_defaults_are_the_papers():
    a = POPLIN("poplin-a", "Pendulum-v1", **TINY)
    p = POPLIN("poplin-p", "Pendulum-v1", **TINY)
    a_settings, p_settings = a.settings, p.settings
    assert (a_settings.init_var, a_settings.policy_net_arch, a_settings.distillation, a_settings.distill_imagined) == (
        0.25,
        [64, 64],
        "bc",
        True,
    )
    assert (p_settings.init_var, p_settings.policy_net_arch, p_settings.distillation, p_settings.distill_imagined) == (
        0.1,
        [32],
        "avg",
        False,
    )
    assert p.planner.search_space.dim == 5 * (3 * 32 + 32 + 32 + 1)


def test_distillation_data_and_model_target_defaults_follow_the_fidelity_ab():
    # POPLIN-P: BC-PR's planned targets of the steps since the last distillation; POPLIN-A: BC-AI's executed
    # actions from a 10 000-step window; every variant's model predicts raw targets (the README's fidelity A/B)
    a = POPLIN("poplin-a", "Pendulum-v1", **TINY)
    p = POPLIN("poplin-p", "Pendulum-v1", distillation="bc", **TINY)
    assert (a.settings.distill_target, a.settings.distill_window) == ("executed", 10_000)
    assert (p.settings.distill_target, p.settings.distill_window) == ("planned", None)
    assert p.distiller is not None and (p.distiller.target, p.distiller.window) == ("planned", None)
    auto = POPLIN("poplin-a", "Pendulum-v1", distill_window="auto", distill_target=None, **TINY)
    assert (auto.settings.distill_target, auto.settings.distill_window) == ("executed", 10_000)
    explicit = POPLIN("poplin-p", "Pendulum-v1", distill_target="executed", distill_window=500, **TINY)
    assert (explicit.settings.distill_target, explicit.settings.distill_window) == ("executed", 500)
    for model in (a, p, POPLIN("pets", "Pendulum-v1", **TINY)):
        assert model.settings.standardise_targets is False and model.policy.dynamics.standardise_targets is False


def test_training_collects_with_mpc_even_in_policy_control():
    model = POPLIN("poplin-p", "Pendulum-v1", seed=0, control="policy", **TINY)
    calls = []
    plan = model.planner.plan
    model.planner.plan = lambda *args: calls.append(1) or plan(*args)
    model.learn(300)  # train_freq is one episode: SB3 finishes the second one (200 planned steps)
    assert model.num_timesteps == 400 and len(calls) == 200 and model.control == "policy"


def test_control_modes_callback_evaluates_each_mode_under_its_control(tmp_path):
    model = POPLIN("poplin-p", "Pendulum-v1", seed=0, **TINY)
    calls: list[tuple[str, np.ndarray, np.ndarray]] = []  # every evaluation step: the control, the obs, the action
    predict = model.predict

    def recording(observation, state=None, episode_start=None, deterministic=False):
        action, new_state = predict(observation, state, episode_start, deterministic)
        # only evaluate_policy calls predict: the training rollout plans in _sample_action
        calls.append((model.control, observation.copy(), action.copy()))
        if model.control == "policy":  # the policy network's action, mapped to the torque bounds
            with th.no_grad():
                direct = 2.0 * model.policy.actor.act(th.as_tensor(observation)).numpy()
            np.testing.assert_allclose(action, direct, atol=1e-6)
        return action, new_state

    model.predict = recording
    callback = ControlModesEvalCallback(eval_freq=200, n_eval_episodes=2, log_path=str(tmp_path))
    model.learn(400, callback=callback)
    # two evaluations, each 2 MPC episodes then 2 policy episodes of 200 steps
    assert [control for control, _, _ in calls] == (["mpc"] * 400 + ["policy"] * 400) * 2
    for mode_index, mode in enumerate(("mpc", "policy")):
        data = np.load(tmp_path / f"evaluations_{mode}.npz")
        assert data["timesteps"].tolist() == [200, 400] and data["results"].shape == (2, 2)
        assert (data["ep_lengths"] == 200).all()
        for evaluation in range(2):
            start = evaluation * 800 + mode_index * 400
            for episode in range(2):
                steps = calls[start + episode * 200 : start + (episode + 1) * 200]
                observations = np.concatenate([obs for _, obs, _ in steps])
                actions = np.concatenate([action for _, _, action in steps])
                expected = float(pendulum_reward(observations, actions[:, 0]).sum())
                assert data["results"][evaluation, episode] == pytest.approx(expected, rel=1e-4), (mode, evaluation)
    assert model.control == "mpc"
    pets = POPLIN("pets", "Pendulum-v1", seed=0, **TINY)
    callback = ControlModesEvalCallback(eval_freq=200, n_eval_episodes=1, log_path=str(tmp_path / "pets"))
    pets.learn(200, callback=callback)
    assert (tmp_path / "pets" / "evaluations_mpc.npz").exists() and not (tmp_path / "pets" / "evaluations_policy.npz").exists()


def test_recorded_distillation_targets_carry_no_graph():
    model = POPLIN("poplin-a", "Pendulum-v1", seed=0, **TINY)  # BC-AI: imagined targets computed while acting
    model.learn(400)
    model._last_obs = np.array([[1.0, 0.0, 0.0]], dtype=np.float32)
    model._sample_action(learning_starts=0)  # a training rollout's step: planned and recorded
    for key, value in model.distiller.planned[-1].items():
        assert not value.requires_grad and value.grad_fn is None, key


def test_the_settings_have_one_source() -> None:
    """Settings' fields give the setting lists and the defaults; POPLIN's signature states the same defaults."""
    import inspect

    from sb3_poplin import POPLIN, variants

    signature = inspect.signature(POPLIN.__init__).parameters
    assert {name: signature[name].default for name in variants.SETTINGS} == variants.DEFAULT_SETTINGS
    assert set(variants.PLANNER_SETTINGS) < set(variants.SETTINGS) and "horizon" in variants.PLANNER_SETTINGS
    assert "model_epochs" not in variants.PLANNER_SETTINGS and "distill_window" in variants.STRING_SETTINGS
    assert "optimizer_kwargs" not in variants.STRING_SETTINGS and "horizon" not in variants.STRING_SETTINGS
    assert variants.resolve_settings("pets", variants.DEFAULT_SETTINGS).horizon == 30


def test_an_optimizer_of_ones_own_plans_through_the_protocol():
    """planning.Optimizer: any object with its budget, ``carried`` and ``optimize`` plans (and its FLOPs count)."""
    from sb3_poplin.planning import ActionSequences, Optimizer, OptimizerResult, plan_flops

    class BestOfTwo:  # scores the incoming mean and its negation; keeps the better
        population_size, iterations, carried = 2, 1, 0

        def optimize(self, evaluate, mean, var, constrain_var, generator=None, steps=1, carried=None, reuse=False):
            z = th.stack([mean, -mean], dim=1)
            returns = evaluate(z)
            best = returns.argmax(dim=1)
            solution = z[th.arange(len(z)), best]
            found = th.ones(len(z), dtype=th.bool)
            return OptimizerResult(solution, returns.max(dim=1).values, solution.unsqueeze(1), found, solution)

    optimizer: Optimizer = BestOfTwo()
    model = ProbabilisticEnsemble(3, 1, ensemble_size=2, hidden_sizes=(8,))
    space = ActionSequences(horizon=3, action_dim=1, init_var=0.25)
    planner = MPCPlanner(
        model, space, optimizer, lambda o, a, n: a[..., 0], None, "expectation", 1, th.tensor([-2.0]), th.tensor([2.0])
    )
    state = th.full((2, 3), 0.5)  # the warm start: +0.5 everywhere; the reward pays the action: +0.5 beats -0.5
    result = planner.plan(th.zeros(2, 3), state)
    assert th.allclose(result.action, th.full((2, 1), 0.5))
    # 2 candidates x 3 steps x 2 members through [4 -> 8 -> 3 mean outputs], 2 envs
    assert plan_flops(planner, th.zeros(2, 3), state) == 2 * 2 * 3 * 2 * (2 * 4 * 8 + 2 * 8 * 3)
    assert th.allclose(planner.plan(th.zeros(2, 3), -state).action, th.full((2, 1), 0.5))  # the negation wins
