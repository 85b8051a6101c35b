"""
The original code's behaviours and the options around them (issue 19): the policy's first whitening update, Avg's
overwrite, GAN's real and fake in one space, planned-action targets, PETS's model hooks, unstandardised targets, and
agents of earlier releases keeping their behaviour.
"""

import math
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th
import torch.nn.functional as F

from conftest import tiny
from sb3_poplin import POPLIN
from sb3_poplin.distillation import Distiller, average_perturbation, clip_straight_through, gan_distillation
from sb3_poplin.dynamics import ProbabilisticEnsemble
from sb3_poplin.planning import PlanResult, PolicyActionNoise, PolicyParameterNoise
from sb3_poplin.policies import Discriminator, POPLINPolicy, PolicyNetwork
from sb3_poplin.tasks.hooks import LocomotionHooks
from sb3_poplin.tasks import TaskSpec, make_env, make_task, registered_tasks
from sb3_poplin.variants import ORIGINAL_CODE_SETTINGS, original_code_settings
from sb3_poplin.tasks.paper import (
    pets_cheetah_obs_postproc,
    pets_cheetah_obs_preproc,
    pets_cheetah_reward,
    pets_cheetah_targ_proc,
)

DATA = Path(__file__).resolve().parent / "data"
CHEETAH = "sb3_poplin/PETSCheetah-v0"


def cheetah_like_states(n: int = 2000, seed: int = 0) -> th.Tensor:
    """Observations with HalfCheetah-like scales: positions near 0.1-1, velocities up to 10."""
    gen = th.Generator().manual_seed(seed)
    scales = th.tensor([0.1, 0.3, 1.0] * 3 + [2.0, 5.0, 10.0] * 3)[:17]
    return th.randn(n, 17, generator=gen) * scales + 0.5 * th.randn(17, generator=gen)


# ---------------------------------------------------------------- whitening
def first_layer_preactivation_std(policy: PolicyNetwork, states: th.Tensor) -> th.Tensor:
    with th.no_grad():
        return (policy.whiten(states) @ policy.weights[0] + policy.biases[0]).std(dim=0)


def test_after_the_first_whitening_update_the_normc_layer_sees_unit_scale_inputs():
    states = cheetah_like_states()
    th.manual_seed(0)
    policy = PolicyNetwork(17, 6, (32,))
    policy.update_whitening(states)  # the default: "function"
    std = first_layer_preactivation_std(policy, states)
    # whitened inputs of variance 1 through unit-norm columns: pre-activations of std ~ 1
    assert 0.85 < float(std.mean()) < 1.15 and float(std.max()) < 1.6, std
    # 0.2.0 kept the initial network's function of raw observations: pre-activations at the raw scale
    th.manual_seed(0)
    raw = PolicyNetwork(17, 6, (32,))
    raw.update_whitening(states, "function_from_raw")
    assert float(first_layer_preactivation_std(raw, states).mean()) > 3.0


def test_later_whitening_updates_keep_the_function_unless_plain():
    states = cheetah_like_states()
    more = cheetah_like_states(500, seed=1) * 2 + 1
    for mode, same in (("function", True), ("function_from_raw", True), ("plain", False)):
        th.manual_seed(0)
        policy = PolicyNetwork(17, 6, (32,))
        policy.update_whitening(states, mode)
        before = policy(more)
        policy.update_whitening(more, mode)
        assert th.allclose(policy(more), before, atol=1e-4) == same, mode
        # the statistics are the same in every mode: those of all states seen
        all_states = th.cat([states, more])
        assert th.allclose(policy.obs_mean, all_states.mean(dim=0), atol=1e-4)
        assert th.allclose(policy.obs_var, all_states.var(dim=0, unbiased=False), rtol=1e-4)


@pytest.mark.parametrize(
    ("method", "space_kind"),
    [("bc", "action noise"), ("bc", "parameter noise"), ("gan", "parameter noise"), ("avg", "parameter noise")],
)
def test_whitening_over_distillations_with_a_window_and_imagined_data_counts_each_real_state_once(method, space_kind):
    """
    Three distillations of 10 real steps each (2 envs x 5 steps), with a window of 6 steps and 3 imagined elites per
    step: the whitening statistics are numpy's over the 30 real states recorded, neither the window (states distilled
    again) nor the imagined copies of a state count (issue 48).
    """
    th.manual_seed(0)
    obs_space, action_space = gym.spaces.Box(-np.inf, np.inf, (3,)), gym.spaces.Box(-1, 1, (2,))
    networks = POPLINPolicy(
        obs_space, action_space, ensemble_size=1, dynamics_net_arch=(4,), policy_net_arch=[8],
        discriminator_net_arch=[8] if method == "gan" else None,
    )  # fmt: skip
    policy = networks.actor
    assert policy is not None
    if space_kind == "action noise":
        space: PolicyActionNoise | PolicyParameterNoise = PolicyActionNoise(2, 2, 0.1, policy, "replan")
    else:
        space = PolicyParameterNoise(2, 2, 0.1, policy, "sep")
    distiller = Distiller(
        method, space, networks, imagined=True, window=6, avg_step_size=1.0, epochs=2, batch_size=8, noise_var=0.1,
        avg_update="add",
    )  # fmt: skip
    gen = th.Generator().manual_seed(1)
    scale, shift = th.tensor([1.0, 3.0, 0.5]), th.tensor([1.4, -2.0, 0.3])
    seen: list[np.ndarray] = []
    for _ in range(3):
        for _ in range(5):
            obs = th.randn(2, 3, generator=gen) * scale + shift
            elites = th.randn(2, 3, space.dim, generator=gen) * 0.1
            action, no_fallback = th.rand(2, 2, generator=gen) * 2 - 1, th.zeros(2, dtype=th.bool)
            plan = PlanResult(action, th.zeros(2, 2), th.zeros(2), elites[:, 0], elites, no_fallback, elites.mean(dim=1))
            distiller.record(obs, plan)
            seen.append(obs.numpy())
        distiller.distill(th.Generator().manual_seed(2))
        states = np.concatenate(seen).astype(np.float64)
        assert float(policy.obs_count) == len(states)
        np.testing.assert_allclose(policy.obs_mean.numpy(), states.mean(axis=0), rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(policy.obs_var.numpy(), states.var(axis=0), rtol=1e-5, atol=1e-6)
    if method != "avg":
        assert len(distiller.data["states"]) == 6 and distiller.data["imagined"].shape == (6, 3, 2)  # the window was used


# ---------------------------------------------------------------- Avg
def parameter_noise_distiller(policy: PolicyNetwork, **kwargs) -> tuple[Distiller, PolicyParameterNoise]:
    space = PolicyParameterNoise(3, 1, 0.1, policy, "sep")
    networks = POPLINPolicy(gym.spaces.Box(-1, 1, (3,)), gym.spaces.Box(-1, 1, (1,)), policy_net_arch=[8])
    networks.actor = policy
    return Distiller("avg", space, networks, False, None, 0.1, 10, 64, 0.1, **kwargs), space


def fake_plan(space: PolicyParameterNoise, n_envs: int, gen: th.Generator, failed: bool = False) -> PlanResult:
    solution = th.randn(n_envs, space.dim, generator=gen)
    fallback = th.full((n_envs,), failed)
    return PlanResult(th.zeros(n_envs, 1), solution, th.zeros(n_envs), solution, solution.unsqueeze(1), fallback, solution)


@pytest.mark.parametrize("whitening", ["function", "plain"])
def test_avg_overwrite_leaves_theta_equal_to_the_mean_recorded_perturbation(whitening):
    th.manual_seed(0)
    policy = PolicyNetwork(3, 1, (8,))
    distiller, space = parameter_noise_distiller(policy, avg_update="overwrite", whitening=whitening)
    gen = th.Generator().manual_seed(1)
    plans = [fake_plan(space, 2, gen) for _ in range(5)] + [fake_plan(space, 2, gen, failed=True)]
    for plan in plans:
        distiller.record(th.randn(2, 3, generator=gen) * 3, plan)
    expected = th.cat([p.solution[:, : policy.num_params] for p in plans[:-1]]).mean(dim=0)  # failed plan dropped
    distiller.distill(None)  # the first whitening update: statistics only, in both modes
    assert th.allclose(policy.flat_parameters(), expected, atol=1e-6)


def test_avg_add_moves_theta_by_the_step_times_the_mean():
    th.manual_seed(0)
    policy = PolicyNetwork(3, 1, (8,))
    theta = policy.flat_parameters().clone()
    omega = th.randn(7, policy.num_params)
    stats = average_perturbation(policy, omega, step_size=0.25, update="add")
    assert th.allclose(policy.flat_parameters(), theta + 0.25 * omega.mean(dim=0), atol=1e-6)
    assert stats["avg_step_norm"] == pytest.approx(float((0.25 * omega.mean(dim=0)).norm()), rel=1e-4)


# ---------------------------------------------------------------- GAN and the targets
class SpyDiscriminator(Discriminator):
    """Records the action columns of every input."""

    def __init__(self, input_dim: int, action_dim: int) -> None:
        super().__init__(input_dim)
        self.action_dim, self.seen = action_dim, []

    def forward(self, x: th.Tensor) -> th.Tensor:
        self.seen.append(x[:, : self.action_dim].detach().clone())
        return super().forward(x)


@pytest.mark.parametrize("clip", [True, False])
def test_gan_real_and_fake_go_through_the_same_clip(clip):
    th.manual_seed(0)
    policy = PolicyNetwork(3, 2, (16,))
    with th.no_grad():
        policy.weights[-1].mul_(500.0)  # outputs well beyond [-1, 1]
    states = th.randn(128, 3)
    targets = 3.0 * th.randn(128, 2)  # planned (unclipped) actions beyond the bounds too
    disc = SpyDiscriminator(2 + 3, 2)
    gan_distillation(
        policy, th.optim.Adam(policy.parameters()), disc, th.optim.Adam(disc.parameters()), states, targets,
        noise_var=0.01, epochs=1, clip=clip, generator=th.Generator().manual_seed(0),
    )  # fmt: skip
    real, fake = disc.seen[0], disc.seen[1]  # per minibatch: real, fake (D step), fake (G step)
    if clip:
        assert all(float(a.abs().max()) <= 1.0 for a in disc.seen)
    else:  # neither clipped: both sides beyond the bounds
        assert float(real.abs().max()) > 1.5 and float(fake.abs().max()) > 1.5


def test_clipped_fake_actions_still_pass_the_gradient():
    raw = th.tensor([-3.0, -0.5, 0.2, 2.5], requires_grad=True)
    clipped = clip_straight_through(raw)
    assert th.equal(clipped, th.tensor([-1.0, -0.5, 0.2, 1.0]))
    (clipped * th.tensor([1.0, 2.0, 3.0, 4.0])).sum().backward()
    assert th.equal(raw.grad, th.tensor([1.0, 2.0, 3.0, 4.0]))  # a plain clamp gives 0 at -3.0 and 2.5
    # a policy whose every output is saturated still learns from the generator's loss
    th.manual_seed(0)
    policy = PolicyNetwork(3, 2, (16,))
    with th.no_grad():
        policy.weights[-1].mul_(500.0)
        policy.biases[-1].fill_(50.0)
    states = th.randn(64, 3)
    assert bool((policy(states).abs() > 1.0).all())
    before = policy.flat_parameters().clone()
    disc = Discriminator(2 + 3, (8,))
    gan_distillation(
        policy, th.optim.Adam(policy.parameters()), disc, th.optim.Adam(disc.parameters()), states,
        th.rand(64, 2) * 2 - 1, noise_var=1e-6, epochs=1, clip=True, generator=th.Generator().manual_seed(0),
    )  # fmt: skip
    assert not th.equal(policy.flat_parameters(), before)


def test_the_discriminator_starts_as_the_original_normc():
    disc = Discriminator(9, (64, 64))
    for layer in disc.layers:
        assert th.allclose(layer.weight.norm(dim=1), th.ones(layer.out_features), atol=1e-5)
        assert th.equal(layer.bias, th.zeros_like(layer.bias))


def test_planned_targets_are_the_unclipped_outputs_the_planner_chose():
    th.manual_seed(0)
    policy = PolicyNetwork(3, 1, (8,))
    with th.no_grad():
        policy.weights[-1].mul_(300.0)
    space = PolicyParameterNoise(3, 1, 0.1, policy, "sep")
    gen = th.Generator().manual_seed(1)
    plan, obs = fake_plan(space, 4, gen), th.randn(4, 3, generator=gen)
    with th.no_grad():
        planned = policy.forward_perturbed(obs.unsqueeze(1), plan.solution[:, : policy.num_params])[:, 0]
    assert float(planned.abs().max()) > 1.0  # the clip matters here
    assert th.allclose(space.executed_action(plan.solution, obs, None), planned.clamp(-1, 1))
    for target, expected in (("planned", planned), ("executed", plan.action)):
        distiller, _ = parameter_noise_distiller(policy, target=target)
        distiller.method = "bc"
        distiller.record(obs, plan)
        assert th.allclose(distiller.planned[0]["actions"], expected, atol=1e-6), target


def test_original_settings_run_end_to_end_and_are_kept_by_save_load(tmp_path):
    settings = original_code_settings("poplin-p")
    assert settings == ORIGINAL_CODE_SETTINGS
    model = tiny("poplin-p", distillation="bc", policy_epochs=5, **settings).learn(450)
    assert model.policy.dynamics.standardise_targets is False
    assert th.equal(model.policy.dynamics.target_std, th.ones_like(model.policy.dynamics.target_std))
    model.save(tmp_path / "agent")
    loaded = POPLIN.load(tmp_path / "agent")
    for key, value in settings.items():
        assert getattr(loaded.settings, key) == value, key
    assert loaded.distiller.target == "planned" and loaded.distiller.whitening == "plain"
    obs = np.array([[0.3, 0.95, -1.0]], dtype=np.float32)
    start = np.ones(1, dtype=bool)
    model.set_random_seed(3), loaded.set_random_seed(3)
    np.testing.assert_array_equal(model.predict(obs, episode_start=start)[0], loaded.predict(obs, episode_start=start)[0])


def test_the_original_poplin_a_clones_the_executed_actions():
    """The original's POPLIN-A (BC-AR/BC-AI) regressed onto clip(pi(s) + delta); only POPLIN-P's BC-PR was unclipped."""
    settings = original_code_settings("poplin-a")
    assert settings == {**ORIGINAL_CODE_SETTINGS, "distill_target": "executed"}
    model = tiny("poplin-a", policy_epochs=5, **settings).learn(450)
    assert model.distiller.target == "executed" and model.distiller.window is None
    with pytest.raises(ValueError, match=r"Unknown policy 'sac'"):
        original_code_settings("sac")


def test_bad_fidelity_settings_name_the_choices():
    for key, value in (("whitening", "raw"), ("avg_update", "replace"), ("distill_target", "clipped")):
        with pytest.raises(ValueError, match=f"{key}.*{value}"):
            tiny("poplin-p", **{key: value})


# ---------------------------------------------------------------- PETS's model hooks
@pytest.mark.parametrize("task_id", registered_tasks())
def test_obs_postproc_inverts_targ_proc_for_every_registered_task(task_id):
    env = make_env(task_id)
    env.reset(seed=0)
    obs = th.as_tensor(np.stack([env.observation_space.sample() for _ in range(16)]), dtype=th.float32)
    nxt = th.as_tensor(np.stack([env.observation_space.sample() for _ in range(16)]), dtype=th.float32)
    obs, nxt = th.nan_to_num(obs.clamp(-50, 50)), th.nan_to_num(nxt.clamp(-50, 50))
    spec = make_task(task_id)
    hooks = spec.hooks.network_kwargs()
    # the policy sees the observation without the root positions, or (HalfCheetah-v5 since 0.4.1) the model's features
    policy_exclude, policy_preproc = hooks.pop("policy_input_exclude"), hooks.pop("policy_obs_preproc")
    if task_id in POLICY_ON_MODEL_FEATURES:
        assert policy_exclude == [] and policy_preproc == spec.obs_preproc is not None
        moved = obs.clone()
        moved[:, EXCLUDED_INPUTS[task_id]] += 7.0  # the root position is not among the features
        assert th.equal(policy_preproc(moved), policy_preproc(obs))
    else:
        assert policy_exclude == list(EXCLUDED_INPUTS.get(task_id, ())) and policy_preproc is None
    model = ProbabilisticEnsemble(
        obs.shape[1], 1, ensemble_size=1, hidden_sizes=(4,), input_exclude=hooks.pop("model_input_exclude"), **hooks
    )
    assert th.allclose(model.obs_postproc(obs, model.targ_proc(obs, nxt)), nxt, atol=1e-5)
    if spec.obs_preproc is None:  # the observation without the excluded indices (PETSCheetah's own: by hand below)
        kept = [i for i in range(obs.shape[1]) if i not in spec.model_input_exclude]
        assert th.equal(model.obs_preproc(obs), obs[:, kept])


# the tasks whose policy network sees the model's input features
POLICY_ON_MODEL_FEATURES = ("HalfCheetah-v5",)

# the root positions the tasks hide from the networks (test_tasks checks that they are the qpos coordinates)
EXCLUDED_INPUTS = {
    "Ant-v5": (0, 1),
    "HalfCheetah-v5": (0,),
    "Hopper-v5": (0,),
    "Swimmer-v5": (0, 1),
    "Walker2d-v5": (0,),
    "sb3_poplin/AntNoTerm-v0": (0, 1),
    "sb3_poplin/HopperNoTerm-v0": (0,),
    "sb3_poplin/Walker2dNoTerm-v0": (0,),
}


def hidden_positions(spec) -> tuple[int, ...]:
    """The root positions a task hides from its model: by ``model_input_exclude`` or inside its locomotion hooks."""
    hooks = getattr(spec.obs_preproc, "__self__", None)
    return hooks.exclude if isinstance(hooks, LocomotionHooks) else spec.model_input_exclude


def test_the_tasks_that_hide_positions_are_the_listed_ones():
    hiding = {task_id: hidden_positions(make_task(task_id)) for task_id in registered_tasks()}
    assert {task_id: excluded for task_id, excluded in hiding.items() if excluded} == EXCLUDED_INPUTS


@pytest.mark.parametrize("task_id", sorted(EXCLUDED_INPUTS))
def test_excluded_positions_are_hidden_from_the_networks_and_their_delta_is_predicted(task_id):
    agent = tiny("poplin-a", task_id)
    dynamics, actor = agent.policy.dynamics, agent.policy.actor
    excluded = list(EXCLUDED_INPUTS[task_id])
    env = make_env(task_id)
    env.action_space.seed(0)
    obs, _ = env.reset(seed=0)
    transitions = []  # a few real (obs, scaled action, next obs)
    for _ in range(16):
        action = env.action_space.sample()
        next_obs, *_ = env.step(action)
        transitions.append((obs, agent.policy.scale_action(action), next_obs))
        obs = next_obs
    o, a, n = (th.as_tensor(np.stack(column), dtype=th.float32) for column in zip(*transitions, strict=True))
    assert (n[:, excluded] != o[:, excluded]).any()  # the positions move
    kept = [i for i in range(o.shape[1]) if i not in excluded]
    moved = o.clone()
    moved[:, excluded] += 100.0
    # the model's input: the observation without the positions (or the task's features of it: HalfCheetah's by hand
    # below), then the action; the policy's: without them too
    features = o[:, kept] if make_task(task_id).obs_preproc is None else make_task(task_id).obs_preproc(o)
    assert th.equal(dynamics.raw_input(o, a), th.cat([features, a], dim=1))
    assert th.equal(dynamics.raw_input(moved, a), dynamics.raw_input(o, a))
    with th.no_grad():
        assert th.equal(actor(moved), actor(o))
    # the target: every coordinate's change, the positions' included
    assert dynamics.out_dim == o.shape[1] and th.equal(dynamics.training_target(o, n), n - o)
    dynamics.fit(o, a, n, agent.policy.dynamics_optimizer, epochs=1, generator=th.Generator().manual_seed(0))
    with th.no_grad():
        mean, _ = dynamics(dynamics.model_input(o, a).expand(dynamics.ensemble_size, -1, -1))
        delta = mean.mean(dim=0) * dynamics.target_std + dynamics.target_mean  # the members' mean change, env units
        predicted, _ = dynamics.propagate(o.unsqueeze(1), a.unsqueeze(1), "expectation")
        from_moved, _ = dynamics.propagate(moved.unsqueeze(1), a.unsqueeze(1), "expectation")
    assert (delta[:, excluded] != 0).all()
    assert th.allclose(predicted[:, 0], o + delta, atol=1e-5)  # the positions move by their predicted delta
    shift = th.zeros_like(o)
    shift[:, excluded] = 100.0
    assert th.allclose(from_moved[:, 0] - predicted[:, 0], shift, atol=1e-4)  # from wherever they are


def test_half_cheetah_v5_networks_see_sin_cos_of_the_pitch_and_not_x():
    model = tiny("poplin-p", "HalfCheetah-v5")
    dynamics, actor = model.policy.dynamics, model.policy.actor
    assert dynamics.in_dim == 17 + 1 + 6 and dynamics.out_dim == 18  # x dropped, pitch as two features
    obs = th.randn(5, 18) * 3
    action = th.rand(5, 6) * 2 - 1
    features = th.cat([obs[:, 1:2], obs[:, 3:], th.sin(obs[:, 2:3]), th.cos(obs[:, 2:3])], dim=1)
    assert th.equal(dynamics.raw_input(obs, action), th.cat([features, action], dim=1))
    turned = obs.clone()
    turned[:, 2] += 2 * math.pi  # a full turn of the pitch is the same posture to both networks
    assert th.allclose(dynamics.raw_input(turned, action), th.cat([features, action], dim=1), atol=1e-5)
    assert dynamics.training_target(obs, turned).equal(turned - obs)  # the change itself is predicted as a delta
    assert actor.in_dim == 18  # the policy: the model's features (since 0.4.1)
    with th.no_grad():
        assert th.allclose(actor(turned), actor(obs), atol=1e-5)
        moved = obs.clone()
        moved[:, 0] += 100.0  # x is hidden from the policy too
        assert th.equal(actor(moved), actor(obs))
    hooks = make_task("HalfCheetah-v5").hooks  # what a new agent gets; zips keep theirs (tests/test_save_load.py)
    assert hooks.obs_preproc is not None and hooks.policy_obs_preproc == hooks.obs_preproc


def test_swimmer_v5_model_sees_sin_cos_of_the_body_angle_and_not_x_y():
    model = tiny("poplin-p", "Swimmer-v5")
    dynamics, actor = model.policy.dynamics, model.policy.actor
    assert dynamics.in_dim == 7 + 2 + 2 and dynamics.out_dim == 10  # x, y dropped, the angle as two features
    obs = th.randn(5, 10) * 3
    action = th.rand(5, 2) * 2 - 1
    features = th.cat([obs[:, 3:], th.sin(obs[:, 2:3]), th.cos(obs[:, 2:3])], dim=1)
    assert th.equal(dynamics.raw_input(obs, action), th.cat([features, action], dim=1))
    turned = obs.clone()
    turned[:, 2] += 2 * math.pi
    assert th.allclose(dynamics.raw_input(turned, action), th.cat([features, action], dim=1), atol=1e-5)
    assert dynamics.training_target(obs, turned).equal(turned - obs)
    assert actor.in_dim == 8  # the policy: the observation without x, y (unchanged in 0.4.2)
    with th.no_grad():
        moved = obs.clone()
        moved[:, :2] += 100.0
        assert th.equal(actor(moved), actor(obs))
    hooks = make_task("Swimmer-v5").hooks  # what a new agent gets; zips keep theirs (tests/test_save_load.py)
    assert hooks.obs_preproc is not None and hooks.policy_exclude == (0, 1) and hooks.policy_obs_preproc is None


def test_pets_cheetah_model_sees_sin_cos_of_the_angle_and_not_the_velocity():
    model = tiny("pets", CHEETAH)
    dynamics = model.policy.dynamics
    assert dynamics.in_dim == 18 + 6 and dynamics.out_dim == 18
    obs = th.randn(5, 18)
    action = th.rand(5, 6) * 2 - 1
    expected = th.cat([obs[:, 1:2], th.sin(obs[:, 2:3]), th.cos(obs[:, 2:3]), obs[:, 3:], action], dim=1)
    assert th.equal(dynamics.raw_input(obs, action), expected)
    # the velocity is not an input: changing it changes nothing the network sees
    moved = obs.clone()
    moved[:, 0] += 10.0
    assert th.equal(dynamics.raw_input(moved, action), expected)
    target = dynamics.targ_proc(obs, moved)
    assert th.equal(target[:, 0], moved[:, 0]) and th.equal(target[:, 1:], th.zeros(5, 17))  # velocity absolute


def test_predictions_through_the_hooks_equal_a_hand_computation():
    th.manual_seed(0)
    model = ProbabilisticEnsemble(
        18,
        6,
        ensemble_size=1,
        hidden_sizes=(8,),
        obs_preproc=pets_cheetah_obs_preproc,
        targ_proc=pets_cheetah_targ_proc,
        obs_postproc=pets_cheetah_obs_postproc,
        standardise_targets=True,  # the hand computation covers the target scaler too; raw targets: the test below
    )
    obs, actions, nxt = th.randn(64, 18), th.rand(64, 6) * 2 - 1, th.randn(64, 18)
    model.fit(obs, actions, nxt, th.optim.Adam(model.parameters()), epochs=1, generator=th.Generator().manual_seed(0))
    s, a = obs[:3], actions[:3]
    # by hand, one member, one step
    features = th.cat([s[:, 1:2], th.sin(s[:, 2:3]), th.cos(s[:, 2:3]), s[:, 3:], a], dim=1)
    x = (features - model.input_mean) / model.input_std
    hidden = F.silu(x @ model.hidden[0].weight[0] + model.hidden[0].bias[0])
    mean = (hidden @ model.output.weight[0] + model.output.bias[0])[:, :18]
    prediction = mean * model.target_std + model.target_mean
    by_hand = th.cat([prediction[:, :1], s[:, 1:] + prediction[:, 1:]], dim=1)
    with th.no_grad():
        through_hooks, _ = model.propagate(s.unsqueeze(1), a.unsqueeze(1), "expectation")
    assert th.allclose(through_hooks[:, 0], by_hand, atol=1e-5)
    # the targets it was fitted on: the velocity absolute, the rest as deltas
    targets = pets_cheetah_targ_proc(obs, nxt)
    assert th.allclose(model.target_mean, targets.mean(dim=0), atol=1e-5)


def test_unstandardised_targets_keep_unit_scaling():
    th.manual_seed(0)
    model = ProbabilisticEnsemble(3, 1, ensemble_size=2, hidden_sizes=(8,), standardise_targets=False)
    obs = th.randn(100, 3)
    model.fit(obs, th.rand(100, 1), obs * 10, th.optim.Adam(model.parameters()), epochs=1)
    assert th.equal(model.target_mean, th.zeros(3)) and th.equal(model.target_std, th.ones(3))
    assert not th.equal(model.input_std, th.ones(4))  # inputs are still standardised


def test_hooks_must_come_in_pairs_and_not_with_exclusions():
    with pytest.raises(ValueError, match="targ_proc and obs_postproc come together"):
        ProbabilisticEnsemble(18, 6, targ_proc=pets_cheetah_targ_proc)
    with pytest.raises(ValueError, match="either input_exclude or obs_preproc"):
        ProbabilisticEnsemble(18, 6, input_exclude=(0,), obs_preproc=pets_cheetah_obs_preproc)
    with pytest.raises(ValueError, match="TaskSpec 'x-v0': targ_proc and obs_postproc come together"):
        TaskSpec(env_id="x-v0", reward_fn=pets_cheetah_reward, targ_proc=pets_cheetah_targ_proc)
    with pytest.raises(ValueError, match="TaskSpec 'x-v0': Pass either input_exclude or obs_preproc"):
        TaskSpec(env_id="x-v0", reward_fn=pets_cheetah_reward, model_input_exclude=(0,), obs_preproc=pets_cheetah_obs_preproc)


# ---------------------------------------------------------------- the A/B's report
