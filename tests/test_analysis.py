"""The paper's analyses: PCA round trip, grid returns against the planner's own, roughness, and the commands."""

import json

import numpy as np
import pytest
import torch as th
from conftest import TINY, load_benchmark

from sb3_poplin import POPLIN
from sb3_poplin.analysis.__main__ import main
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


def test_commands_write_tables_and_figures(agent, tmp_path):
    _, path = agent
    out = tmp_path / "out"
    main(["surface", "--model", str(path), "--env", "Pendulum-v1", "--output", str(out), "--grid", "6"])
    surface = json.loads((out / "surface.json").read_text())
    assert set(surface) == {"pets", "poplin-a", "poplin-p"}
    for method, stats in surface.items():
        assert (out / f"surface_{method}.png").stat().st_size > 1000
        assert np.array(stats["returns"]).shape == (6, 6) and stats["roughness"] >= 0
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
    assert all(np.isfinite(r["real_return"]) and len(r["real_returns"]) == 1 for r in rows)
    assert (out / "popsize.png").exists()
    main(["model-error", "--model", str(path), "--env", "Pendulum-v1", "--output", str(out), "--steps", "20"])
    errors = json.loads((out / "model_error.json").read_text())
    assert len(errors["state_rmse"]) == 2 and errors["state_rmse"][0] >= 0  # one value per prediction step


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


def load_diagnose_mpc():
    return load_benchmark("diagnose_mpc")


@pytest.mark.parametrize("env_id", ["sb3_poplin/PETSCheetah-v0", "HalfCheetah-v5"])
def test_true_simulator_planner_scores_what_the_env_pays(env_id):
    """diagnose_mpc.py's true-simulator candidates: their returns equal stepping the env with the same actions."""
    import gymnasium as gym
    import mujoco

    diagnose = load_diagnose_mpc()
    kwargs = {} if env_id.startswith("sb3_poplin") else {"exclude_current_positions_from_observation": False}
    env = gym.make(env_id, **kwargs)
    model = POPLIN("pets", gym.make(env_id, **kwargs), horizon=4, population_size=6, num_elites=2, seed=0)
    planner = diagnose.TrueModelPlanner(env, model)
    env.reset(seed=3)
    for _ in range(3):  # PETSCheetah: the first observation entry is a velocity from here on
        env.step(env.action_space.sample())
    unwrapped = env.unwrapped
    state = np.empty(mujoco.mj_stateSize(unwrapped.model, planner.spec))
    mujoco.mj_getState(unwrapped.model, unwrapped.data, state, planner.spec)
    z = th.rand(1, 6, 4 * 6, generator=th.Generator().manual_seed(0)) * 2.2 - 1.1  # some beyond the bounds
    scored = planner.evaluate(state, z)[0].numpy()
    x_before = getattr(unwrapped, "_x_before", None)
    for i in range(6):
        mujoco.mj_setState(unwrapped.model, unwrapped.data, state, planner.spec)
        mujoco.mj_forward(unwrapped.model, unwrapped.data)
        if x_before is not None:
            unwrapped._x_before = x_before
        actions = model.planner.to_env_units(z[0, i].clamp(-1, 1).view(4, 6)).double().numpy()
        paid = sum(float(unwrapped.step(action)[1]) for action in actions)
        assert scored[i] == pytest.approx(paid, rel=1e-4, abs=1e-4), i


@pytest.mark.parametrize(
    "env_id, kwargs", [("Hopper-v5", {"exclude_current_positions_from_observation": False}), ("HalfCheetah-v5", {})]
)
def test_true_simulator_planner_refuses_envs_whose_observation_it_cannot_rebuild(env_id, kwargs):
    """Hopper clips its velocities and terminates; HalfCheetah without x is not [qpos, qvel]: both raise, naming the fix."""
    import gymnasium as gym

    diagnose = load_diagnose_mpc()
    model = POPLIN("pets", gym.make(env_id, **kwargs), horizon=2, population_size=4, num_elites=2, seed=0)
    with pytest.raises(ValueError, match=r"observation shape .* is not one of them.*--true-steps 0"):
        diagnose.TrueModelPlanner(gym.make(env_id, **kwargs), model)


def test_true_simulator_planner_takes_another_budget():
    """--true-budget: the true-simulator CEM plans at the given horizon/population/elites/iterations, not the agent's."""
    import gymnasium as gym

    diagnose = load_diagnose_mpc()
    env_id = "sb3_poplin/PETSCheetah-v0"
    model = POPLIN("pets", gym.make(env_id), horizon=3, population_size=6, num_elites=2, seed=0)
    planner = diagnose.TrueModelPlanner(gym.make(env_id), model, (5, 8, 3, 2))
    assert planner.horizon == 5 and planner.space.horizon == 5
    assert (planner.cem.population_size, planner.cem.num_elites, planner.cem.iterations) == (8, 3, 2)
    assert planner.mean.shape[-1] == 5 * 6  # the warm-start mean covers the new horizon
    env = gym.make(env_id)
    env.reset(seed=1)
    planner.env = env.unwrapped
    action = planner.act()
    assert action.shape == (6,) and np.all(np.abs(action) <= 1.0)
    with pytest.raises(ValueError, match=r"four positive integers \(horizon, population, elites, iterations\)"):
        diagnose.TrueModelPlanner(gym.make(env_id), model, (5, 0, 3, 2))


def test_cheetah_posture_counts_upside_down_pitches_over_full_turns():
    """cheetah_posture.py: a pitch beyond ±90° is upside down, also after whole turns (the joint angle accumulates)."""
    posture = load_benchmark("cheetah_posture")
    pitches = np.array([0.0, 1.5, 1.7, -3.0, 2 * np.pi + 0.1, 2 * np.pi + 3.0, -4 * np.pi - 2.0, 1.0])
    assert posture.upside_down_share(pitches) == pytest.approx(4 / 8)  # 1.7, -3.0, 2π+3.0, -4π-2.0


@pytest.mark.parametrize(
    "env_id, kwargs, index",
    [
        ("sb3_poplin/PETSCheetah-v0", {}, 2),
        ("HalfCheetah-v5", {}, 1),
        ("HalfCheetah-v5", {"exclude_current_positions_from_observation": False}, 2),
    ],
)
def test_cheetah_posture_finds_the_pitch_in_the_observation(env_id, kwargs, index):
    """The pitch index is derived from the observation layout and equals qpos[2] after a step; no pitch joint raises."""
    import gymnasium as gym

    posture = load_benchmark("cheetah_posture")
    env = gym.make(env_id, **kwargs)
    assert posture.pitch_index(env) == index
    obs, *_ = env.step(env.action_space.sample())
    assert obs[index] == env.unwrapped.data.qpos[2]
    with pytest.raises(ValueError, match="joint 2 is not 'rooty'"):
        posture.pitch_index(gym.make("Swimmer-v5"))
