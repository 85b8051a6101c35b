"""iCEM's options of the CEM, each against what it must do to the samples, the population and the warm start."""

from itertools import pairwise

import numpy as np
import pytest
import torch as th
from conftest import tiny

from sb3_poplin import POPLIN
from sb3_poplin.planning import CEM, ICEM_OPTIONS, CEMOptions, colored_noise_filter


def identity_constraint(mean: th.Tensor, var: th.Tensor) -> th.Tensor:
    return var


class Recorder:
    """An ``evaluate`` with known returns, ``-|z - target|^2``, that keeps every population it scores."""

    def __init__(self, target: th.Tensor) -> None:
        self.target = target  # [n_envs, D]
        self.populations: list[th.Tensor] = []

    def returns(self, z: th.Tensor) -> th.Tensor:
        return -(z - self.target.unsqueeze(1)).square().sum(dim=2)

    def __call__(self, z: th.Tensor) -> th.Tensor:
        self.populations.append(z.clone())
        return self.returns(z)


def run(options: CEMOptions, population: int = 20, elites: int = 4, iterations: int = 3, reuse: bool = False, **kwargs):
    target = th.tensor([[0.3, -0.2, 0.1, 0.4, -0.5, 0.2]])
    recorder = Recorder(target)
    cem = CEM(population, elites, iterations, alpha=0.1, options=options)
    mean, var = th.zeros(1, 6), th.full((1, 6), 0.25)
    result = cem.optimize(
        recorder, mean, var, identity_constraint, th.Generator().manual_seed(0), steps=3, reuse=reuse, **kwargs
    )
    return cem, recorder, result


# ------------------------------------------------------------------------------------------------ colored noise
@pytest.mark.parametrize("sampling", ["clipped", "truncated"])
@pytest.mark.parametrize("beta", [0.0, 1.0, 2.0])
def test_colored_noise_has_the_power_law_spectrum_along_the_horizon(beta, sampling):
    """The candidates' noise, per search dimension of a step block, has power ~ f^-beta over the H steps (numpy's FFT)."""
    horizon, block, population = 32, 2, 4000
    cem = CEM(population, 10, iterations=1, sampling=sampling, options=CEMOptions(noise_beta=beta))
    recorder = Recorder(th.zeros(1, horizon * block))
    mean, var = th.full((1, horizon * block), 0.5), th.full((1, horizon * block), 4.0)
    cem.optimize(recorder, mean, var, identity_constraint, th.Generator().manual_seed(1), steps=horizon)
    noise = ((recorder.populations[0][0] - 0.5) / 2.0).view(population, horizon, block).permute(0, 2, 1).double().numpy()
    power = (np.abs(np.fft.rfft(noise, axis=-1)) ** 2).mean(axis=(0, 1))  # [H / 2 + 1]
    k = np.arange(1, horizon // 2 + 1)
    slope = np.polyfit(np.log(k / horizon), np.log(power[k]), 1)[0]
    assert slope == pytest.approx(-beta, abs=0.08)
    # unit variance per step before the scale (the truncated normal's own variance, 0.774, when truncated)
    variance = noise.var(axis=(0, 1))
    expected = 1.0 if sampling == "clipped" else 0.7737
    np.testing.assert_allclose(variance, expected, rtol=0.06)


def test_colored_noise_filter_is_the_identity_for_white_noise_and_keeps_unit_variance():
    assert th.equal(colored_noise_filter(7, 0.0), th.eye(7, dtype=th.float64))
    m = colored_noise_filter(10, 2.0)
    np.testing.assert_allclose((m @ m.T).diagonal().numpy(), 1.0, rtol=1e-12)  # unit variance per step
    # stationary: the covariance of steps t and t + d depends on d only (circular along the horizon)
    cov = (m @ m.T).numpy()
    for d in range(10):
        np.testing.assert_allclose(np.array([cov[t, (t + d) % 10] for t in range(10)]), cov[0, d], atol=1e-12)
    assert cov[0, 1] > 0.5  # beta 2: neighbouring steps strongly correlated


def test_colored_noise_needs_a_horizon_axis():
    cem = CEM(10, 2, 1, options=CEMOptions(noise_beta=1.0))
    with pytest.raises(ValueError, match="noise_beta > 0 needs a search space with a horizon axis"):
        cem.optimize(Recorder(th.zeros(1, 4)), th.zeros(1, 4), th.ones(1, 4), identity_constraint, steps=1)


def test_poplin_p_uni_refuses_colored_noise_with_the_fix():
    with pytest.raises(ValueError, match=r"noise='uni' has one parameter-noise block.*noise='sep'.*'noise_beta': 0"):
        POPLIN("poplin-p", "Pendulum-v1", noise="uni", optimizer="icem")
    model = POPLIN("poplin-p", "Pendulum-v1", noise="uni", optimizer="icem", optimizer_kwargs={"noise_beta": 0})
    assert model.planner.optimizer.options == CEMOptions(**{**ICEM_OPTIONS.__dict__, "noise_beta": 0})


# ------------------------------------------------------------------------------------- kept elites, decay, mean
def test_kept_elites_are_ranked_again_in_the_next_iteration():
    cem, recorder, result = run(CEMOptions(keep_elites=0.4))  # ceil(0.4 * 4) = 2 elites kept
    assert cem.kept == 2 and [z.shape[1] for z in recorder.populations] == [20, 22, 22]
    for before, after in pairwise(recorder.populations):
        best = before[0, recorder.returns(before)[0].topk(2).indices]  # by the known returns, best first
        assert th.equal(after[0, -2:], best)
    every = th.cat(recorder.populations, dim=1)[0]
    assert th.equal(result.elites[0, 0], every[recorder.returns(every.unsqueeze(0))[0].argmax()])  # the best is never lost


def test_kept_elites_are_not_evaluated_again_when_their_return_is_exact():
    cem, recorder, result = run(CEMOptions(keep_elites=0.4), reuse=True)
    assert [z.shape[1] for z in recorder.populations] == [20, 20, 20]  # only the new samples are scored
    every = th.cat(recorder.populations, dim=1)[0]
    assert th.equal(result.elites[0, 0], every[recorder.returns(every.unsqueeze(0))[0].argmax()])
    assert cem.evaluations(reuse=True) == 60 and cem.evaluations(reuse=False) == 64


def test_reused_elites_keep_their_returns():
    """Later populations score 1000 lower: with their returns reused, the first iteration's two best stay the elites."""
    recorder = Recorder(th.tensor([[0.3, -0.2, 0.1, 0.4, -0.5, 0.2]]))

    def evaluate(z: th.Tensor) -> th.Tensor:
        return recorder(z) - (1000.0 if len(recorder.populations) > 1 else 0.0)

    cem = CEM(20, 4, 3, options=CEMOptions(keep_elites=0.5))
    result = cem.optimize(evaluate, th.zeros(1, 6), th.full((1, 6), 0.25), identity_constraint, steps=3, reuse=True)
    first = recorder.populations[0]
    assert th.equal(result.elites[0, :2], first[0, recorder.returns(first)[0].topk(2).indices])
    assert result.elite_return[0] < -500  # the other two elites come from the penalised populations


@pytest.mark.parametrize(
    ("population", "elites", "iterations", "decay", "sizes"),
    [
        (20, 4, 4, 1.25, [20, 16, 12, 10]),  # floor(20 / 1.25^i)
        (20, 8, 3, 2.0, [20, 16, 16]),  # never below 2 x elites
        (10, 8, 2, 2.0, [10, 10]),  # nor above the population
        (20, 4, 3, 1.0, [20, 20, 20]),
    ],
)
def test_population_decay_sizes(population, elites, iterations, decay, sizes):
    cem, recorder, _ = run(CEMOptions(population_decay=decay), population, elites, iterations)
    assert [z.shape[1] for z in recorder.populations] == sizes
    assert [cem.samples(i) for i in range(iterations)] == sizes and cem.evaluations(reuse=False) == sum(sizes)


def test_the_mean_is_a_candidate_of_the_last_iteration():
    alpha = 0.1
    _, recorder, _ = run(CEMOptions(add_mean=True), iterations=2)
    first, last = recorder.populations
    assert first.shape[1] == 20 and last.shape[1] == 21
    # the mean after the first iteration, by hand: momentum towards the mean of its 4 best candidates
    elites = first[0, recorder.returns(first)[0].topk(4).indices]
    expected = alpha * th.zeros(6) + (1 - alpha) * elites.mean(dim=0)
    th.testing.assert_close(last[0, -1], expected)
    assert not (last[0, :-1] == expected).all(dim=1).any()


@pytest.mark.parametrize("execute", ["mean", "best"])
def test_execute_the_final_mean_or_the_best_candidate(execute):
    _, recorder, result = run(CEMOptions(execute=execute))
    last = recorder.populations[-1][0]
    best = last[recorder.returns(last.unsqueeze(0))[0].argmax()]
    if execute == "best":
        assert th.equal(result.solution[0], best) and not th.equal(result.solution, result.mean)
    else:
        assert th.equal(result.solution, result.mean) and not th.equal(result.solution[0], best)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (
            dict(optimizer="sgd"),
            r"optimizer='sgd' is not available for the 'pets' variant; accepted values: \['cem', 'icem'\]",
        ),
        (dict(policy="rs", optimizer="icem"), r"not available for the 'rs' variant; accepted values: \['rs'\]"),
        (dict(policy="rs", optimizer_kwargs={"noise_beta": 1}), r"'rs' variant .* takes no optimizer_kwargs"),
        (dict(optimizer_kwargs={"beta": 2}), r"Unknown optimizer_kwargs \['beta'\]; accepted: \['noise_beta', "),
        (dict(optimizer_kwargs=[("noise_beta", 1)]), r"optimizer_kwargs must be a dict"),
        (dict(optimizer_kwargs={"keep_elites": 1.5}), r"keep_elites'\] must be a fraction in \[0, 1\]"),
        (dict(optimizer_kwargs={"population_decay": 0.5}), r"population_decay'\] must be >= 1"),
        (dict(optimizer_kwargs={"execute": "worst"}), r"execute.*'worst'.*\['mean', 'best'\]"),
        (dict(optimizer_kwargs={"noise_beta": -1}), r"noise_beta'\] must be a number in \[0, 8\]"),
        (dict(optimizer_kwargs={"add_mean": "yes"}), r"add_mean'\] must be True or False"),
        (dict(optimizer_kwargs={"shift_elites": True}), r"shift_elites=True .* keep_elites is 0: set keep_elites > 0"),
        (dict(optimizer="icem", optimizer_kwargs={"keep_elites": 0}), r"keep_elites is 0"),
    ],
)
def test_bad_optimizer_settings(kwargs, message):
    with pytest.raises(ValueError, match=message):
        POPLIN(**{"policy": "pets", **kwargs}, env="Pendulum-v1")


def test_icem_in_one_word_and_each_option_over_it():
    model = tiny("pets", optimizer="icem", optimizer_kwargs={"noise_beta": 0.25})
    options = model.planner.optimizer.options
    assert options == CEMOptions(
        noise_beta=0.25,
        keep_elites=0.3,
        shift_elites=True,
        population_decay=1.25,
        add_mean=True,
        execute="best",
        variance_cap=False,
    )
    assert tiny("pets").planner.optimizer.options == CEMOptions()  # plain CEM unless asked


# ------------------------------------------------------------------------------------------------ shifted elites
def shifted(rows: th.Tensor, block: int) -> th.Tensor:
    """Drop the first block of each row and append a zero block, by hand."""
    return th.cat([rows[..., block:], th.zeros_like(rows[..., :block])], dim=-1)


def test_shifted_elites_are_carried_per_env_reset_at_episode_starts_and_saved(tmp_path):
    model = tiny("pets", optimizer="icem", optimizer_kwargs={"noise_beta": 0.0})
    optimizer = model.planner.optimizer
    seen = []
    optimize = optimizer.optimize

    def spy(evaluate, mean, var, constrain, generator=None, **options):
        populations = []

        def recorded(z):
            populations.append(z.clone())
            return evaluate(z)

        result = optimize(recorded, mean, var, constrain, generator, **options)
        seen.append((options["carried"].clone(), populations, result))
        return result

    optimizer.optimize = spy
    obs = np.array([[0.3, 0.95, -1.0], [-1.0, 0.0, 2.0]], dtype=np.float32)
    dim, carried, block = model.planner.search_space.dim, optimizer.carried, 1  # Pendulum: one action per step
    assert carried == 2 and model.planner.state_dim == dim * 3
    _, state = model.predict(obs, episode_start=np.ones(2, dtype=bool))
    given, _, result = seen[-1]
    assert given.isnan().all()  # an episode start: nothing carried
    expected = th.cat([shifted(result.mean, block), shifted(result.elites[:, :carried], block).flatten(1)], dim=1)
    np.testing.assert_array_equal(state, expected.numpy())
    # the next step: env 0 continues (its shifted elites in the first population), env 1 starts a new episode
    model.predict(obs, state=state, episode_start=np.array([False, True]))
    given, populations, _ = seen[-1]
    th.testing.assert_close(given[0], th.as_tensor(state[0, dim:]).view(carried, dim), rtol=0, atol=0)
    assert given[1].isnan().all()
    first = populations[0]
    assert th.equal(first[0, -carried:], given[0]) and not first[1].isnan().any()
    # the agent's own warm start (the training rollout's), reset per env at an episode end, and saved with the agent
    model.mpc.collect(th.as_tensor(obs))
    model.mpc.collect(th.as_tensor(obs))
    warm = model.mpc.warm_start.clone()
    assert not warm.isnan().any()
    model.save(tmp_path / "agent")
    loaded = POPLIN.load(tmp_path / "agent")
    assert th.equal(loaded.mpc.warm_start, warm)
    model.mpc.episodes_ended(np.array([True, False]))
    assert model.mpc.warm_start[0, dim:].isnan().all() and not model.mpc.warm_start[0, :dim].any()
    assert th.equal(model.mpc.warm_start[1], warm[1])
    loaded.mpc.episodes_ended(np.array([True, False]))
    model.set_random_seed(5), loaded.set_random_seed(5)
    np.testing.assert_array_equal(model.predict(obs)[0], loaded.predict(obs)[0])


def test_a_state_of_the_wrong_width_names_the_fix():
    model = tiny("pets", optimizer="icem")
    with pytest.raises(ValueError, match=r"state has shape \(1, 5\) but the planner needs \(1, 15\)"):
        model.predict(np.zeros(3, dtype=np.float32), state=np.zeros((1, 5), dtype=np.float32))


def test_a_zip_loaded_with_icem_plans_afresh(tmp_path):
    """The warm start of a CEM agent has no room for carried elites: loaded with optimizer="icem" it is dropped."""
    model = tiny("pets")
    obs = np.zeros((1, 3), dtype=np.float32)
    model.mpc.collect(th.as_tensor(obs))  # the training rollout's own warm start
    model.save(tmp_path / "agent")
    loaded = POPLIN.load(tmp_path / "agent", optimizer="icem")
    assert loaded.settings.optimizer == "icem" and loaded.mpc.warm_start is None
    _, state = loaded.predict(obs)
    assert state.shape == (1, loaded.planner.state_dim) == (1, 15)
    assert POPLIN.load(tmp_path / "agent").mpc.warm_start is not None  # kept when it fits


@pytest.mark.parametrize("cap", [True, False])
def test_the_variance_cap_is_an_option(cap):
    """With the cap, PETS's 2-sigma-inside-the-bounds variance (a mean at 0.8 leaves room 0.1, std 0.1); without, 0.5."""
    seen = []
    cem = CEM(4000, 10, 1, sampling="clipped", options=CEMOptions(variance_cap=cap))

    def constrain(mean: th.Tensor, var: th.Tensor) -> th.Tensor:
        seen.append(True)
        return th.minimum(var, ((1.0 - mean) / 2.0) ** 2)

    recorder = Recorder(th.zeros(1, 2))
    cem.optimize(recorder, th.full((1, 2), 0.8), th.full((1, 2), 0.25), constrain, th.Generator().manual_seed(2))
    std = recorder.populations[0][0].std(dim=0)
    np.testing.assert_allclose(std.numpy(), 0.1 if cap else 0.5, rtol=0.05)
    assert bool(seen) == cap
