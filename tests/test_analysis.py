"""The paper's analyses: PCA round trip, grid returns against the planner's own, roughness, and the commands."""

import json

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from conftest import TINY, pendulum_reward

from sb3_poplin import POPLIN
from sb3_poplin.experiments.analysis import main
from sb3_poplin.analysis.model_error import Episode, model_error
from sb3_poplin.analysis.popsize import population_sweep
from sb3_poplin.analysis.surface import PCA2, grid_returns, record_search, roughness
from sb3_poplin.variants import replanner


def test_pca_round_trip_on_vectors_in_a_plane():
    generator = th.Generator().manual_seed(0)
    origin, basis = th.randn(20, generator=generator), th.randn(2, 20, generator=generator)
    coords = th.randn(50, 2, generator=generator) * th.tensor([3.0, 0.5])
    vectors = origin + coords @ basis  # 50 points of a 2-D plane in 20-D
    pca = PCA2.fit(vectors)
    assert th.allclose(pca.inverse_transform(pca.transform(vectors)), vectors, atol=1e-4)
    assert sum(pca.explained_variance_ratio) == pytest.approx(1.0, abs=1e-6)
    assert pca.explained_variance_ratio[0] > pca.explained_variance_ratio[1]
    # off the plane the inverse transform is the projection onto it: transforming it again changes nothing
    other = th.randn(7, 20, generator=generator)
    projected = pca.inverse_transform(pca.transform(other))
    assert th.allclose(pca.transform(projected), pca.transform(other), atol=1e-4)
    assert th.allclose(pca.components @ pca.components.T, th.eye(2), atol=1e-5)


@pytest.fixture(scope="module")
def agent(tmp_path_factory):
    model = POPLIN("poplin-p", "Pendulum-v1", seed=0, **{**TINY, "horizon": 2})
    model.learn(400)  # fitted twice: a model that predicts something
    path = tmp_path_factory.mktemp("analysis") / "agent.zip"
    model.save(path)
    return model, path


def test_a_grid_point_returns_what_the_planner_returned_for_that_vector(agent):
    model, _ = agent
    controller = replanner(model, "pets", seed=0)  # Pendulum, horizon 2: two-dimensional search vectors
    obs = th.tensor([0.3, 0.95, -1.0])
    record = record_search(controller, obs)
    candidates, returns = th.cat(record.candidates), th.cat(record.returns)
    assert candidates.shape == (2 * 20, 2) and len(record.candidates) == TINY["cem_iterations"]
    pca = PCA2.fit(candidates)  # the plane is the whole 2-D space: every candidate lies on it
    coords = pca.transform(candidates).numpy()
    for i in (0, 7, 25, 39):
        grid = grid_returns(controller, obs, pca, coords[i, :1], coords[i, 1:])
        assert grid.shape == (1, 1)
        assert grid[0, 0] == pytest.approx(returns[i].item(), rel=1e-4, abs=1e-4)


def test_roughness_is_zero_on_a_plane_and_grows_with_noise():
    x, y = np.meshgrid(np.linspace(-1, 1, 25), np.linspace(-2, 2, 25))
    plane = 3.0 * x - 0.5 * y + 7.0
    assert roughness(plane)["roughness"] == pytest.approx(0.0, abs=1e-12)
    assert roughness(1000.0 * plane)["roughness"] == pytest.approx(0.0, abs=1e-12)  # scale-free
    rng = np.random.default_rng(0)
    noise = rng.standard_normal(plane.shape)
    values = [roughness(plane + scale * noise)["roughness"] for scale in (0.01, 0.1, 1.0)]
    assert 0 < values[0] < values[1] < values[2]
    assert roughness(1000.0 * (plane + noise))["roughness"] == pytest.approx(values[2])
    bowl = -(x**2) - y**2
    assert roughness(bowl)["local_maxima"] == 1 and roughness(bowl + noise)["local_maxima"] > 10


def reference_roughness(values: np.ndarray) -> float:
    """The roughness's definition, cell by cell: mean |second difference| along both axes over the range (finite only)."""
    rows, cols = values.shape
    seconds = [values[i - 1, j] - 2 * values[i, j] + values[i + 1, j] for i in range(1, rows - 1) for j in range(cols)]
    seconds += [values[i, j - 1] - 2 * values[i, j] + values[i, j + 1] for i in range(rows) for j in range(1, cols - 1)]
    finite = [abs(s) for s in seconds if np.isfinite(s)]
    return sum(finite) / len(finite) / (np.nanmax(values) - np.nanmin(values))


def test_roughness_and_local_maxima_of_surfaces_known_by_hand():
    # 4 x^2 on 5 columns (x = 0, 0.25, ..., 1) and 4 rows: second differences 4 * 2 * 0.25^2 = 0.5 along x (12 of
    # them), 0 along y (10), over the range 4
    parabola = np.tile(4.0 * np.linspace(0.0, 1.0, 5) ** 2, (4, 1))
    assert roughness(parabola)["roughness"] == pytest.approx(12 * 0.5 / 22 / 4, rel=1e-12)
    # a missing cell drops the second differences through it (one along x, one along y), not the range
    parabola[0, 4] = np.nan
    assert roughness(parabola)["roughness"] == pytest.approx(11 * 0.5 / 20 / 4, rel=1e-12)
    assert reference_roughness(parabola) == pytest.approx(11 * 0.5 / 20 / 4, rel=1e-12)
    # three interior cells strictly above their 8 neighbours (one next to a missing cell); a plateau of two is none
    spikes = np.zeros((6, 6))
    spikes[1, 1], spikes[4, 4], spikes[1, 4], spikes[2, 4] = 1.0, 2.0, 0.5, np.nan
    spikes[4, 1] = spikes[4, 2] = 3.0
    assert roughness(spikes)["local_maxima"] == 3


def still_agent() -> POPLIN:
    """A PETS agent on Pendulum whose ensemble predicts no change: a zero output layer (targets unstandardised)."""
    model = POPLIN("pets", "Pendulum-v1", seed=0, **TINY)
    with th.no_grad():
        model.policy.dynamics.output.weight.zero_()
        model.policy.dynamics.output.bias.zero_()
    return model


def test_model_error_of_a_model_that_predicts_no_change():
    # an episode that moves by the same step every time: obs_t = obs_0 + t v
    steps, horizon, stride = 10, 3, 2
    velocity = np.array([-0.05, 0.03, 0.2])
    obs = np.array([0.6, 0.8, -1.0]) + np.arange(steps + 1)[:, None] * velocity
    actions = np.linspace(-2.5, 2.5, steps)[:, None]  # some beyond the torque bound
    rewards = -0.5 * np.arange(steps)
    errors = model_error(still_agent(), Episode(obs, actions, rewards), stride=stride, horizon=horizon)
    # k steps ahead the prediction is still obs_s: off by k v, k / std(0..10) in each dimension's std units
    sigma = np.std(np.arange(steps + 1), ddof=1)
    np.testing.assert_allclose(errors["state_rmse"], [k / sigma for k in (1, 2, 3)], rtol=1e-5)
    starts = np.arange(0, steps - horizon + 1, stride)  # 0, 2, 4, 6
    # the predicted k-step return pays the reward of obs_s at every step; the real one is the episode's
    predicted = np.cumsum([pendulum_reward(obs[starts], actions[starts + j, 0]) for j in range(horizon)], axis=0)
    real = np.cumsum([rewards[starts + j] for j in range(horizon)], axis=0)
    np.testing.assert_allclose(errors["return_abs_error"], np.abs(predicted - real).mean(axis=1), rtol=1e-5)
    np.testing.assert_allclose(errors["real_return_abs"], np.abs(real).mean(axis=1), rtol=1e-6)
    with pytest.raises(ValueError, match="The episode has 10 steps, fewer than the 11 prediction steps"):
        model_error(still_agent(), Episode(obs, actions, rewards), horizon=11)


class EpisodeRecorder(gym.Wrapper):
    """Per episode: the reset seed, the observations before every step and the rewards."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.episodes: list[dict] = []

    def reset(self, *, seed=None, options=None):
        obs, info = self.env.reset(seed=seed, options=options)
        self.episodes.append({"seed": seed, "obs": [obs], "rewards": []})
        return obs, info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.episodes[-1]["obs"].append(obs)
        self.episodes[-1]["rewards"].append(float(reward))
        return obs, reward, terminated, truncated, info


def test_population_sweep_on_a_model_that_predicts_no_change():
    env = EpisodeRecorder(gym.make("Pendulum-v1"))
    rows = population_sweep(still_agent(), env, ["pets", "rs"], [10, 40], episodes=2, steps=3, seed=5)
    # the agent's elite fraction, 4 of 20
    assert [(r["method"], r["population"], r["elites"]) for r in rows] == [
        ("pets", 10, 2),
        ("pets", 40, 8),
        ("rs", 10, 2),
        ("rs", 40, 8),
    ]
    assert [episode["seed"] for episode in env.episodes] == [5, 6] * 4  # the same two start states for every row
    horizon = TINY["horizon"]
    for i, r in enumerate(rows):
        episodes = env.episodes[2 * i : 2 * i + 2]
        real = [sum(episode["rewards"]) for episode in episodes]
        assert r["real_returns"] == pytest.approx(real, rel=1e-6) and r["real_return"] == pytest.approx(np.mean(real))
        assert r["planned_return"] == pytest.approx(np.mean(r["planned_returns"]))
        # every plan's state stays put in the model: horizon x its reward, less at most 0.001 * 2^2 per step of torque
        for planned, episode in zip(r["planned_returns"], episodes, strict=True):
            best = horizon * pendulum_reward(np.array(episode["obs"][:3]), np.zeros(3)).mean()
            assert best - horizon * 0.004 - 1e-4 <= planned <= best + 1e-4, (r["method"], r["population"])
    one = population_sweep(still_agent(), env, ["pets"], [10], steps=1, elite_fraction=0.5)
    assert one[0]["elites"] == 5


def test_commands_write_tables_and_figures(agent, tmp_path):
    _, path = agent
    out = tmp_path / "out"
    main(["surface", "--model", str(path), "--env", "Pendulum-v1", "--output", str(out), "--grid", "6"])
    surface = json.loads((out / "surface.json").read_text())
    assert set(surface) == {"pets", "poplin-a", "poplin-p"}
    for method, stats in surface.items():
        assert (out / f"surface_{method}.png").stat().st_size > 1000
        returns = np.array(stats["returns"])
        assert returns.shape == (6, 6) and stats["roughness"] == pytest.approx(reference_roughness(returns), rel=1e-9)
    assert "| pets |" in (out / "surface.md").read_text()
    main(
        [
            "popsize",
            "--model",
            str(path),
            "--env",
            "Pendulum-v1",
            "--output",
            str(out),
            "--populations",
            "10",
            "30",
            "--methods",
            "pets",
            "poplin-p",
            "--steps",
            "5",
        ]
    )
    rows = json.loads((out / "popsize.json").read_text())
    assert [(r["method"], r["population"]) for r in rows] == [("pets", 10), ("pets", 30), ("poplin-p", 10), ("poplin-p", 30)]
    assert [r["elites"] for r in rows] == [2, 6, 2, 6]  # the agent's fraction: 4 of 20
    for r in rows:
        assert len(r["real_returns"]) == 1 and r["real_return"] == r["real_returns"][0] < 0  # Pendulum pays < 0 off the top
    assert (out / "popsize.png").exists()
    main(["model-error", "--model", str(path), "--env", "Pendulum-v1", "--output", str(out), "--steps", "20"])
    errors = json.loads((out / "model_error.json").read_text())
    assert set(errors) == {"episode_return", "state_rmse", "return_abs_error", "real_return_abs"}
    assert [len(errors[key]) for key in ("state_rmse", "return_abs_error", "real_return_abs")] == [2, 2, 2]  # horizon 2


def test_control_curves_from_zoo_runs(tmp_path):
    runs = (("Pendulum-v1_1", 0.0), ("Pendulum-v1_2_3f2a-9c", 10.0), ("Acrobot-v1_1", 99.0), ("Pendulum-v1_x", 5.0))
    for run, offset in runs:
        folder = tmp_path / "logs" / "poplin" / run
        folder.mkdir(parents=True)
        timesteps = np.array([200, 400, 600])
        for name, base in (("evaluations.npz", -1000.0), ("evaluations_policy.npz", -1500.0)):
            results = base + offset + np.arange(3)[:, None] * 100.0 + np.array([[-1.0, 1.0]])  # 2 episodes each
            np.savez(folder / name, timesteps=timesteps, results=results, ep_lengths=np.full((3, 2), 200))
    out = tmp_path / "out"
    main(["control", "--log-folder", str(tmp_path / "logs"), "--env", "Pendulum-v1", "--output", str(out)])
    data = json.loads((out / "control.json").read_text())
    assert data["mpc"]["runs"] == ["Pendulum-v1_1", "Pendulum-v1_2_3f2a-9c"]  # zoo run folders of this env only
    np.testing.assert_allclose(data["mpc"]["returns"], [[-1000, -900, -800], [-990, -890, -790]])
    np.testing.assert_allclose(np.mean(data["policy"]["returns"], axis=0), [-1495, -1395, -1295])
    assert (out / "control.png").exists()
    with pytest.raises(FileNotFoundError, match="No rl-zoo3 run of HalfCheetah-v5"):
        main(["control", "--log-folder", str(tmp_path / "logs"), "--env", "HalfCheetah-v5", "--output", str(out)])
