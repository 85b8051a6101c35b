"""The CEM core, random shooting and the action-sequence search space, on problems with known answers."""

import itertools
import math

import pytest
import torch as th

from sb3_poplin import kernels
from sb3_poplin.planning import CEM, ActionSequences, RandomShooting
from sb3_poplin.sampling import truncated_normal


def identity_constraint(mean, var):
    return var


def quadratic(target):
    """Return = -||z - target||^2, maximal (0) at the target."""

    def evaluate(z):  # z: [n_envs, N, D], target: [n_envs, D]
        return -((z - target.unsqueeze(1)) ** 2).sum(dim=-1)

    return evaluate


@pytest.mark.parametrize("sampling", ["truncated", "clipped"])
def test_cem_finds_the_optimum_of_a_quadratic(sampling):
    gen = th.Generator().manual_seed(0)
    target = th.tensor([[0.3, -0.5, 0.8, 0.0, -0.2, 0.6], [-0.7, 0.1, 0.0, 0.4, 0.5, -0.3]])  # 2 envs
    cem = CEM(population_size=400, num_elites=40, iterations=10, alpha=0.1, sampling=sampling)
    mean, var = th.zeros(2, 6), th.full((2, 6), 0.25)
    result = cem.optimize(quadratic(target), mean, var, identity_constraint, gen)
    assert result.solution.shape == (2, 6)
    assert th.allclose(result.solution, target, atol=0.02)
    assert (result.elite_return > -1e-3).all()


def test_cem_update_is_momentum_on_elite_statistics():
    """One iteration with alpha: new mean = alpha * old + (1 - alpha) * elite mean (biased elite variance)."""
    pop, k, alpha = 50, 5, 0.3
    seen = {}

    def evaluate(z):
        seen["z"] = z.clone()
        return -(z**2).sum(-1)

    gen = th.Generator().manual_seed(1)
    mean, var = th.full((1, 3), 0.5), th.full((1, 3), 0.2)
    result = CEM(pop, k, iterations=1, alpha=alpha).optimize(evaluate, mean, var, identity_constraint, gen)
    z = seen["z"][0]
    elites = z[(-(z**2).sum(-1)).argsort(descending=True)[:k]]
    expected = alpha * 0.5 + (1 - alpha) * elites.mean(0)
    assert th.allclose(result.solution[0], expected, atol=1e-6)


def test_non_finite_returns_are_never_elites():
    """NaN and +inf candidates must rank last even though +inf compares highest."""

    def evaluate(z):
        ret = -((z - 1.0) ** 2).sum(-1)
        ret = th.where(z[..., 0] > 0.0, th.full_like(ret, math.inf), ret)  # every candidate with z0 > 0 "diverges"
        return th.where(z[..., 1] > 0.0, th.full_like(ret, math.nan), ret)

    gen = th.Generator().manual_seed(2)
    cem = CEM(300, 30, iterations=8, alpha=0.0)
    result = cem.optimize(evaluate, th.zeros(1, 2), th.full((1, 2), 0.25), identity_constraint, gen)
    # the best finite region is z0 <= 0, z1 <= 0, as close to (1, 1) as possible: near (0, 0)
    assert (result.solution <= 0.05).all()
    assert th.isfinite(result.elite_return).all()


def test_cem_keeps_the_distribution_when_nothing_is_finite():
    gen = th.Generator().manual_seed(3)
    mean = th.tensor([[0.2, -0.1]])
    result = CEM(20, 5, iterations=3).optimize(
        lambda z: th.full(z.shape[:2], math.nan), mean, th.full((1, 2), 0.1), identity_constraint, gen
    )
    assert th.equal(result.solution, mean)


def test_random_shooting_returns_its_best_sample():
    gen = th.Generator().manual_seed(4)
    target = th.tensor([[0.5, -0.5, 0.25]])
    seen = {}

    def evaluate(z):
        seen["z"] = z.clone()
        return quadratic(target)(z)

    result = RandomShooting(2000).optimize(evaluate, th.zeros(1, 3), th.ones(1, 3), identity_constraint, gen)
    z = seen["z"][0]
    best = z[quadratic(target)(z.unsqueeze(0))[0].argmax()]
    assert th.equal(result.solution[0], best)
    assert (z.abs() <= 1.0).all() and z.min() < -0.9 and z.max() > 0.9  # uniform over the whole box


def test_truncated_normal_bounds_and_moments():
    x = truncated_normal((200_000,), th.device("cpu"), th.Generator().manual_seed(5))
    assert x.abs().max() <= 2.0
    assert abs(x.mean().item()) < 0.01
    # variance of a standard normal truncated at +-2
    phi2 = math.exp(-2.0) / math.sqrt(2 * math.pi)
    z = math.erf(2 / math.sqrt(2))
    assert x.var().item() == pytest.approx(1 - 4 * phi2 / z, abs=0.01)
    # the CDF against the exact truncated normal CDF (Kolmogorov-Smirnov distance, 200k samples: ~0.003)
    points = th.linspace(-1.95, 1.95, 79, dtype=th.float64)
    exact = (th.special.ndtr(points) - th.special.ndtr(th.tensor(-2.0))) / z
    empirical = (x.double().unsqueeze(0) <= points.unsqueeze(1)).double().mean(dim=1)
    assert (empirical - exact).abs().max().item() < 0.006
    assert truncated_normal((7, 3), th.device("cpu")).shape == (7, 3)


def test_truncated_normal_outermost_levels_and_cem_scaling():
    # 4M draws hit both outermost of the 65,536 levels (miss probability e^-61): they stay inside [-2, 2]
    x = truncated_normal((4_000_000,), th.device("cpu"), th.Generator().manual_seed(6))
    assert 1.9998 < x.max().item() <= 2.0 and -2.0 <= x.min().item() < -1.9998
    # CEM folds the sqrt(2) of the inverse CDF into its std: candidates are mean + std * truncated normal
    seen = {}

    def evaluate(z):
        seen["z"] = z.clone()
        return -z.pow(2).sum(dim=-1)

    cem = CEM(population_size=20_000, num_elites=10, iterations=1, sampling="truncated")
    mean, var = th.tensor([[1.0, -3.0]]), th.tensor([[0.25, 4.0]])
    cem.optimize(evaluate, mean, var, identity_constraint, th.Generator().manual_seed(7))
    z = seen["z"][0]  # [N, 2]
    std = var[0].sqrt()
    assert (z >= mean[0] - 2 * std - 1e-5).all() and (z <= mean[0] + 2 * std + 1e-5).all()
    phi2 = math.exp(-2.0) / math.sqrt(2 * math.pi)
    truncated_var = 1 - 4 * phi2 / math.erf(2 / math.sqrt(2))
    assert th.allclose(z.mean(dim=0), mean[0], atol=0.03 * std.max().item())
    assert th.allclose(z.var(dim=0), var[0] * truncated_var, rtol=0.04)


def test_action_sequences_shift_cap_and_decode():
    space = ActionSequences(horizon=3, action_dim=2, init_var=0.25)
    assert space.dim == 6
    mean = th.tensor([[0.1, 0.2, 0.3, 0.4, 0.5, 0.6]])
    assert th.equal(space.shift(mean), th.tensor([[0.3, 0.4, 0.5, 0.6, 0.0, 0.0]]))
    capped = space.constrain_var(th.tensor([[0.0, 0.8, -1.0]]), th.full((1, 3), 0.25))
    assert th.allclose(capped, th.tensor([[0.25, 0.01, 0.0]]))  # 2 sigma stays inside [-1, 1]
    z = th.tensor([[[1.5, -0.5, 0.0, 0.0, 0.0, 0.0]]])  # [n_envs=1, N=1, D]
    states = th.zeros(1, 1, 4, 3)  # 4 particles
    actions = space.actions(z, 0, states, None)
    assert actions.shape == (1, 1, 4, 2) and th.equal(actions[0, 0, 0], th.tensor([1.0, -0.5]))
    assert th.equal(space.executed_action(mean, th.zeros(1, 3), None), th.tensor([[0.1, 0.2]]))


def test_cem_candidates_do_not_depend_on_the_thread_count():
    # a wide search (POPLIN-P-like): 9 rows per chunk of 2^18 samples, 8 chunks shared among the threads
    dim, pop = 29_000, 64
    mean, var = th.linspace(-1.0, 1.0, dim).unsqueeze(0), th.full((1, dim), 0.09)
    draws = {}
    threads = th.get_num_threads()
    try:
        for count in (1, 2, 3):
            th.set_num_threads(count)
            seen: list[th.Tensor] = []

            def evaluate(z, seen=seen):
                seen.append(z.clone())
                return -z[..., :3].pow(2).sum(dim=-1)

            cem = CEM(pop, 8, iterations=2)
            result = cem.optimize(evaluate, mean, var, identity_constraint, th.Generator().manual_seed(3))
            draws[count] = (th.stack(seen), result.solution)
    finally:
        th.set_num_threads(threads)
    for count in (2, 3):
        assert th.equal(draws[count][0], draws[1][0]) and th.equal(draws[count][1], draws[1][1])
    z = draws[1][0][0, 0]  # first iteration [N, D]
    noise = (z - mean) / var.sqrt()  # truncated standard normal
    # every chunk is its own stream: no two rows repeat, and rows of different chunks are uncorrelated
    assert th.unique(noise[:, :100], dim=0).shape[0] == pop
    corr = th.corrcoef(noise[::9])  # one row from each chunk
    assert (corr - th.eye(corr.shape[0])).abs().max().item() < 0.05
    phi2 = math.exp(-2.0) / math.sqrt(2 * math.pi)
    assert noise.abs().max().item() <= 2.0 + 1e-4
    assert noise.mean().item() == pytest.approx(0.0, abs=0.003)
    assert noise.var().item() == pytest.approx(1 - 4 * phi2 / math.erf(2 / math.sqrt(2)), abs=0.005)


def test_run_shares_runs_every_share_and_raises_their_errors():
    from sb3_poplin import sampling

    out = th.zeros(4)
    with th.inference_mode():
        tasks = [lambda i=i: out[i].fill_(th.is_inference_mode_enabled() + i) for i in range(4)]
        sampling.run_shares(tasks)
    assert out.tolist() == [1.0, 2.0, 3.0, 4.0]  # every share ran, in the caller's inference mode

    def fails():
        raise RuntimeError("share 1 failed")

    threads = th.get_num_threads()
    with pytest.raises(RuntimeError, match="share 1 failed"):
        sampling.run_shares([lambda: None, fails])
    assert th.get_num_threads() == threads  # the caller's intra-op thread count is restored
    assert sampling.split_range(10, 3) == [(0, 3), (3, 7), (7, 10)]
    assert sampling.split_range(2, 4) == [(0, 1), (1, 2)]


def test_cem_variance_update_weights_only_finite_elites():
    """With fewer finite candidates than elites, the update uses the finite ones only (biased variance)."""
    pop, k, alpha = 40, 8, 0.25
    seen = {}

    def evaluate(z):
        if "z" not in seen:
            seen["z"] = z.clone()
        ret = -(z**2).sum(-1)
        finite = th.zeros_like(ret, dtype=th.bool)
        finite[:, :5] = True  # five finite candidates, three of the eight elites are not
        return th.where(finite, ret, th.full_like(ret, math.nan))

    seen_means, variances = [], []

    def spy(mean, var):  # called with the current distribution at every iteration
        seen_means.append(mean.clone())
        variances.append(var.clone())
        return var

    mean, var = th.tensor([[0.5, -0.2, 0.1]]), th.tensor([[0.2, 0.3, 0.4]])
    CEM(pop, k, iterations=2, alpha=alpha).optimize(evaluate, mean, var, spy, th.Generator().manual_seed(5))
    finite = seen["z"][0, :5].double()  # the first iteration's finite candidates
    expected_mean = alpha * mean[0].double() + (1 - alpha) * finite.mean(0)
    expected_var = alpha * var[0].double() + (1 - alpha) * finite.var(0, unbiased=False)
    assert th.allclose(seen_means[1][0].double(), expected_mean, atol=1e-6)
    assert th.allclose(variances[1][0].double(), expected_var, atol=1e-6)


def analytic_plan_flops(model, n_envs: int) -> int:
    """
    One plan's FLOPs from the settings alone (2 per multiply-add of the matrix products): every CEM iteration pushes
    each candidate's rows through the ensemble (expectation: E members on the mean half of the output layer; particles:
    one member a particle, both halves) and, where the variant re-queries the policy on imagined states, through the
    policy (POPLIN-P's perturbed network of one particle as two products a layer, ``x theta + x omega``); POPLIN-A Init
    rolls the policy open-loop through the mean model once a plan; with a policy, the executed and the fallback action
    are one row each; CEM refits to its elites with two products an iteration and colors
    its noise with one a sample.
    """
    planner, dynamics, actor = model.planner, model.policy.dynamics, model.policy.actor
    widths = [dynamics.in_dim, *dynamics.hidden_sizes]
    hidden = sum(2 * a * b for a, b in itertools.pairwise(widths))
    mean_row = hidden + 2 * widths[-1] * dynamics.out_dim
    expectation = planner.propagation == "expectation"
    if expectation:
        model_rows = dynamics.ensemble_size * mean_row
    else:
        model_rows = planner.num_particles * (hidden + 2 * widths[-1] * 2 * dynamics.out_dim)
    policy_row = 0 if actor is None else sum(2 * a * b for a, b in actor.shapes)
    init = getattr(planner.search_space, "proposal", None) == "init"  # POPLIN-A Init
    perturbed = hasattr(planner.search_space, "noise")  # POPLIN-P
    # POPLIN-P's network of one row and one particle computes x theta + x omega: two products a layer
    perturbed_row = 2 * policy_row if planner.num_particles == 1 else planner.num_particles * policy_row
    if actor is None or init:
        step_policy = 0
    else:
        step_policy = perturbed_row if perturbed else planner.num_particles * policy_row
    candidates = planner.optimizer.evaluations(reuse=expectation)
    horizon = planner.search_space.horizon
    flops = candidates * horizon * (model_rows + step_policy)
    flops += horizon * (dynamics.ensemble_size * mean_row + policy_row) if init else 0
    flops += (2 * policy_row if perturbed else policy_row) + policy_row  # the executed (one row) and fallback action
    optimizer, space = planner.optimizer, planner.search_space
    if isinstance(optimizer, CEM):  # the elites' weighted mean and variance: two [1, K] x [K, D] products an iteration
        flops += optimizer.iterations * 2 * 2 * optimizer.num_elites * space.dim
        if optimizer.options.noise_beta > 0:  # colored noise: an [H, H] filter on every sample's [H, block]
            sampled = sum(optimizer.samples(i) for i in range(optimizer.iterations)) + optimizer.carried
            flops += sampled * 2 * space.steps**2 * space.block
    return n_envs * flops


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(policy="pets"),
        dict(policy="pets", propagation="tsinf", num_particles=4),
        dict(policy="poplin-a", proposal="init"),
        dict(policy="poplin-a", proposal="replan", propagation="ts1", num_particles=4),
        dict(policy="poplin-p", noise="sep"),
        dict(policy="poplin-p", noise="uni", propagation="tsinf", num_particles=4),
        # iCEM: decayed populations, the carried, kept (reused under expectation) and mean candidates
        dict(policy="pets", optimizer="icem"),
        dict(policy="poplin-a", proposal="replan", propagation="ts1", num_particles=4, optimizer="icem"),
        dict(policy="poplin-p", noise="sep", optimizer="icem", optimizer_kwargs=dict(keep_elites=0.6, execute="mean")),
        dict(policy="rs"),
        dict(policy="poplin-p", noise="sep", planning_dtype="bfloat16"),  # products under autocast count the same
    ],
)
def test_plan_flops_count_the_products_of_one_real_plan(kwargs):
    """``plan_flops`` (counted by torch while a plan runs) against the analytic count from the settings."""
    from conftest import TINY

    from sb3_poplin import POPLIN
    from sb3_poplin.planning import plan_flops

    model = POPLIN(env="Pendulum-v1", seed=0, **{**TINY, "dynamics_net_arch": (16, 24), **kwargs})
    obs = th.tensor([[0.3, 0.95, -1.0], [-1.0, 0.0, 2.0]])
    assert plan_flops(model.planner, obs) == analytic_plan_flops(model, n_envs=2) > 0


def test_plan_flops_leave_out_the_forward_path_probe(monkeypatch, tmp_path):
    """A host's first forward of a size times the paths (a probe): that work is not the plan's, and is not counted."""
    from conftest import TINY

    from sb3_poplin import POPLIN
    from sb3_poplin.planning import plan_flops

    monkeypatch.delenv(kernels.PATH_ENV, raising=False)
    monkeypatch.setenv(kernels.CACHE_ENV, str(tmp_path))
    monkeypatch.setattr(kernels, "PROBE_MIN_ROWS", 1)  # the tiny model's forwards are probed too
    monkeypatch.setattr(kernels.PathChoice, "chosen", {})
    monkeypatch.setattr(kernels.PathChoice, "loaded", False)
    model = POPLIN(env="Pendulum-v1", seed=0, **{**TINY, "dynamics_net_arch": (16, 24), "policy": "pets"})
    obs = th.tensor([[0.3, 0.95, -1.0]])
    assert plan_flops(model.planner, obs) == analytic_plan_flops(model, n_envs=1)
    assert kernels.PathChoice.chosen  # the probe ran (in the uncounted plan)


@pytest.mark.parametrize("path", kernels.PATHS)
def test_plan_flops_on_every_forward_path(path, monkeypatch):
    """Each of the ensemble's forward paths (oneDNN's fused linear too) is counted, and the count does not depend on it."""
    from conftest import TINY

    from sb3_poplin import POPLIN
    from sb3_poplin.planning import plan_flops

    if path == "fused" and not kernels.fused_available(th.float32):
        pytest.skip("this torch build has no oneDNN fused linear")
    monkeypatch.setenv(kernels.PATH_ENV, path)
    model = POPLIN(env="Pendulum-v1", seed=0, **{**TINY, "dynamics_net_arch": (16, 24), "policy": "pets"})
    obs = th.tensor([[0.3, 0.95, -1.0]])
    assert plan_flops(model.planner, obs) == analytic_plan_flops(model, n_envs=1) > 0
