"""Reliability: clear errors for bad input, NaN-safe planning, exact save/load/resume, determinism, interruptions."""

import functools
import io
import warnings
import zipfile
from collections import deque
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from stable_baselines3 import SAC
from stable_baselines3.common.callbacks import (
    BaseCallback,
    ConvertCallback,
    EvalCallback,
    EveryNTimesteps,
    StopTrainingOnMaxEpisodes,
    StopTrainingOnNoModelImprovement,
)
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import configure
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv

from conftest import TINY, tiny

from sb3_poplin import POPLIN
from sb3_poplin.experiments import checkpoints as resume
from sb3_poplin.callbacks import ControlModesEvalCallback
from sb3_poplin.policies import PolicyNetwork


class SpaceEnv(gym.Env):
    """A do-nothing env with the given spaces."""

    def __init__(self, observation_space, action_space):
        self.observation_space, self.action_space = observation_space, action_space

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return self.observation_space.sample(), {}

    def step(self, action):
        return self.observation_space.sample(), 0.0, False, False, {}


BOX1 = spaces.Box(-1.0, 1.0, (1,))


@pytest.mark.parametrize(
    "observation_space, action_space, message",
    [
        (spaces.Box(-1.0, 1.0, (3,)), spaces.Box(-np.inf, np.inf, (1,)), "finite action bounds.*RescaleAction"),
        (spaces.Dict({"a": spaces.Box(-1.0, 1.0, (2,))}), BOX1, "flat 1-D Box observation space.*FlattenObservation"),
        (spaces.Box(0, 255, (8, 8, 3), dtype=np.uint8), BOX1, r"has shape \(8, 8, 3\).*flat 1-D Box"),
        (spaces.Box(-1.0, 1.0, (3,)), spaces.MultiDiscrete([3, 3]), "Box action space"),
    ],
)
def test_unsupported_spaces_are_rejected(observation_space, action_space, message):
    with pytest.raises(ValueError, match=message):
        POPLIN("pets", SpaceEnv(observation_space, action_space))


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(num_elites=0), "num_elites must be between 1 and population_size"),
        (dict(population_size=0), "population_size must be an integer >= 1"),
        (dict(cem_iterations=0), "cem_iterations must be an integer >= 1"),
        (dict(ensemble_size=0), "ensemble_size must be an integer >= 1"),
        (dict(cem_alpha=-0.1), r"cem_alpha must be in \[0, 1\)"),
        (dict(init_var=-1.0), "init_var must be > 0"),
        (dict(policy_epochs=0), "policy_epochs must be an integer >= 1"),
        (dict(avg_step_size=0.0), r"avg_step_size must be in \(0, 1\]"),
        (dict(avg_step_size=1.5), r"avg_step_size must be in \(0, 1\]"),
    ],
)
def test_out_of_range_settings_are_rejected(kwargs, message):
    with pytest.raises(ValueError, match=message):
        POPLIN("poplin-p", "Pendulum-v1", **kwargs)


# ---------------------------------------------------------------- loading bad files
@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    folder = tmp_path_factory.mktemp("saved")
    POPLIN("pets", "Pendulum-v1", seed=0, **TINY).save(folder / "ok.zip")
    SAC("MlpPolicy", "Pendulum-v1", policy_kwargs=dict(net_arch=[8])).save(folder / "sac.zip")
    return folder


def test_loading_what_is_not_a_poplin_zip(saved):
    (saved / "text.zip").write_text("not a zip")
    with pytest.raises(ValueError, match="not a readable POPLIN zip"):
        POPLIN.load(saved / "text.zip")
    data = (saved / "ok.zip").read_bytes()
    (saved / "truncated.zip").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="truncated or corrupted"):
        POPLIN.load(saved / "truncated.zip")
    with pytest.raises(ValueError, match=r"not saved by POPLIN.*stable_baselines3.sac.policies"):
        POPLIN.load(saved / "sac.zip")
    with pytest.raises(FileNotFoundError, match="No saved agent at"):
        POPLIN.load(saved / "missing.zip")
    # loading by name without the suffix, and from a file object, still work
    assert POPLIN.load(saved / "ok").variant == "pets"
    assert POPLIN.load(io.BytesIO(data)).variant == "pets"


def test_loading_a_zip_with_a_corrupted_member(saved):
    with zipfile.ZipFile(saved / "ok.zip") as archive:
        members = {name: archive.read(name) for name in archive.namelist()}
    with zipfile.ZipFile(saved / "bad_crc.zip", "w", compression=zipfile.ZIP_STORED) as archive:
        for name, content in members.items():
            archive.writestr(name, content)
    raw = bytearray((saved / "bad_crc.zip").read_bytes())
    weights = members["policy.pth"]
    middle = len(weights) // 2
    offset = raw.find(weights[middle : middle + 64])  # stored uncompressed: flip a byte in the middle of the weights
    assert offset > 0 and raw.count(weights[middle : middle + 64]) == 1
    raw[offset + 10] ^= 0xFF
    (saved / "bad_crc.zip").write_bytes(bytes(raw))
    with pytest.raises(ValueError, match=r"'policy\.pth' fails the CRC check"):
        POPLIN.load(saved / "bad_crc.zip")


# zips of earlier releases: tests/test_save_load.py


def test_new_zips_hold_the_mpc_and_distiller_state(tmp_path):
    model = POPLIN("poplin-p", "Pendulum-v1", seed=0, distillation="bc", distill_window=150, **TINY)
    model.learn(1000, callback=StopAt(500))  # two fits with distillation, then 100 planned steps not yet distilled
    model.save(tmp_path / "agent")
    with zipfile.ZipFile(tmp_path / "agent.zip") as archive:
        assert {"mpc.pth", "distiller.pth"} <= set(archive.namelist())
    loaded = POPLIN.load(tmp_path / "agent")
    assert model.distiller.data.keys() == loaded.distiller.data.keys() and len(model.distiller.data["states"]) == 150
    for key, value in model.distiller.data.items():
        assert th.equal(value, loaded.distiller.data[key]), key
    assert len(loaded.distiller.planned) == 100
    pets = POPLIN("pets", "Pendulum-v1", seed=0, **TINY)
    pets.save(tmp_path / "pets")
    with zipfile.ZipFile(tmp_path / "pets.zip") as archive:
        assert "mpc.pth" in archive.namelist() and "distiller.pth" not in archive.namelist()


# ---------------------------------------------------------------- NaN-safe planning
def nan_model(model, fraction):
    """Make the dynamics produce NaN for a fraction of the rows of every forward pass."""
    dynamics = model.policy.dynamics
    forward, shared_input_mean = dynamics.forward, dynamics.shared_input_mean

    def with_nan_rows(mean):
        rows = int(mean.shape[1] * fraction)
        mean = mean.clone()
        mean[:, :rows] = float("nan")
        return mean

    def broken(x):
        mean, logvar = forward(x)
        return with_nan_rows(mean), logvar

    dynamics.forward = broken  # training, sampling propagations
    dynamics.shared_input_mean = lambda x: with_nan_rows(shared_input_mean(x))  # expectation planning


def test_diverged_candidates_rank_last():
    model = POPLIN("pets", "Pendulum-v1", seed=0, **{**TINY, "population_size": 40, "num_elites": 5})
    nan_model(model, 0.5)  # the first half of the candidates always diverges
    z_seen = {}
    optimize = model.planner.optimizer.optimize

    def spy(evaluate, mean, var, constrain, generator=None, **options):
        def wrapped(z):
            returns = evaluate(z)
            z_seen.setdefault("returns", returns)
            return returns

        return optimize(wrapped, mean, var, constrain, generator, **options)

    model.planner.optimizer.optimize = spy
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no fallback warning: finite candidates existed
        action, _ = model.predict(np.array([1.0, 0.0, 0.0], dtype=np.float32))
    assert th.isnan(z_seen["returns"][0, :20]).all() and th.isfinite(z_seen["returns"][0, 20:]).all()
    assert np.isfinite(action).all()


@pytest.mark.parametrize("variant", ["pets", "rs", "poplin-a", "poplin-p"])
def test_all_diverged_falls_back_warns_once_and_counts(variant, tmp_path):
    model = POPLIN(variant, "Pendulum-v1", seed=0, **TINY)
    nan_model(model, 1.0)
    obs = np.array([[0.6, 0.8, -1.0], [1.0, 0.0, 0.0]], dtype=np.float32)
    with pytest.warns(UserWarning, match="No planned candidate had a finite return"):
        action, state = model.predict(obs)
    if variant.startswith("poplin"):
        model.control = "policy"
        np.testing.assert_allclose(action, model.predict(obs)[0], atol=1e-6)  # the policy's action
        model.control = "mpc"
    else:
        np.testing.assert_array_equal(action, np.zeros((2, 1)))  # the action-space centre
    assert isinstance(state, np.ndarray) and not state.any()  # the failed plan is not carried over
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # warned once only
        model.predict(obs)
    assert model.mpc.pop_statistics() == {}  # predict's plans are not the training rollout's statistics
    for _ in range(2):  # two steps of the training rollout's plans, two envs each: counted
        model.mpc.collect(th.as_tensor(obs))
    model.set_logger(configure(str(tmp_path), ["csv"]))
    for key, value in model.mpc.pop_statistics().items():
        model.logger.record(key, value)
    assert model.logger.name_to_value["plan/fallbacks"] == 4


@functools.cache
def fitted_inverted_pendulum_dynamics():
    """A dynamics model (2 members, one hidden layer of 8) fitted once on 300 random InvertedPendulum-v5 steps."""
    model = POPLIN("pets", "InvertedPendulum-v5", seed=0, ensemble_size=2, dynamics_net_arch=(8,), train_freq=(300, "step"))
    model.learn(300)
    assert model._n_updates == 1
    return model.policy.dynamics.state_dict()


def first_planned_action(model, obs, solution):
    """The first action (scaled, before the clip) that a plan's solution stands for, from each variant's definition."""
    actor = model.policy.actor
    if model.variant in ("pets", "rs"):  # the action sequence itself
        return solution[:, :1]
    if model.variant == "poplin-a":  # noise on the clipped policy action
        return actor(obs).clamp(-1.0, 1.0) + solution[:, :1]
    moved = PolicyNetwork(4, 1, model.settings.policy_net_arch)  # POPLIN-P: the network with its parameters moved by block 0
    moved.load_state_dict(actor.state_dict())
    moved.add_to_parameters(solution[0, : actor.num_params])
    return moved(obs)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    variant=st.sampled_from(["pets", "rs", "poplin-a", "poplin-p"]),
    noise=st.sampled_from(["sep", "uni"]),
    horizon=st.integers(1, 4),
    population=st.integers(2, 12),
    elite_fraction=st.floats(0.01, 1.0),
    iterations=st.integers(1, 3),
    alpha=st.floats(0.0, 0.99),
    init_var=st.floats(1e-4, 4.0),
    propagation=st.sampled_from(["expectation", "ts1", "tsinf", "ds"]),
    # half the observations finite (the plans are checked), half with NaN or +-inf entries most of the time
    obs=st.lists(st.floats(-1e6, 1e6), min_size=4, max_size=4)
    | st.lists(st.floats(-1e6, 1e6) | st.sampled_from([np.nan, np.inf, -np.inf]), min_size=4, max_size=4),
    seed=st.integers(0, 2**16),
)
def test_predict_is_always_finite_and_in_bounds(
    variant, noise, horizon, population, elite_fraction, iterations, alpha, init_var, propagation, obs, seed
):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = POPLIN(
            variant,
            "InvertedPendulum-v5",  # action bounds +-3
            seed=seed,
            noise=noise,
            horizon=horizon,
            population_size=population,
            num_elites=max(1, int(population * elite_fraction)),
            cem_iterations=iterations,
            cem_alpha=alpha,
            init_var=init_var,
            propagation=propagation,
            num_particles=2,
            ensemble_size=2,
            dynamics_net_arch=(8,),
        )
        model.policy.dynamics.load_state_dict(fitted_inverted_pendulum_dynamics())
        plans = []
        plan = model.planner.plan

        def spy(obs, mean, generator=None):
            plans.append((obs, plan(obs, mean, generator)))
            return plans[-1][1]

        model.planner.plan = spy
        action, state = model.predict(np.array(obs, dtype=np.float32))
    assert np.isfinite(action).all() and np.all(np.abs(action) <= 3.0)
    # from a finite observation every return is finite (InvertedPendulum pays 0 or 1), so no plan falls back: the action
    # is the plan's first planned action clipped to the bounds, and the warm start is the plan moved on by one step
    # (with an infinite observation, POPLIN-P's perturbed network may give inf - inf, so the action-space centre, where
    # the network with the perturbation added is finite)
    if not np.isfinite(obs).all():
        return
    ((obs_tensor, result),) = plans
    assert not result.fallback.item()
    with th.no_grad():
        expected = first_planned_action(model, obs_tensor, result.solution).clamp(-1.0, 1.0)
    block = model.policy.actor.num_params if variant == "poplin-p" else 1
    if variant == "poplin-p" and noise == "uni":
        expected_state = result.solution
    else:
        expected_state = th.cat([result.solution[:, block:], th.zeros(1, block)], dim=1)
    np.testing.assert_allclose(action, 3.0 * expected[0].numpy(), atol=1e-5)
    np.testing.assert_array_equal(state, expected_state.numpy())


# ---------------------------------------------------------------- save / load / resume, determinism
def parameters(model):
    return {k: v.clone() for k, v in model.policy.state_dict().items()}


def assert_same_parameters(a, b):
    assert a.keys() == b.keys()
    for key in a:
        assert th.equal(a[key], b[key]), key


def test_save_load_restores_everything(tmp_path):
    model = POPLIN("poplin-p", "Pendulum-v1", seed=0, distillation="gan", **TINY)
    model.learn(400)
    obs = np.array([0.6, 0.8, -1.0], dtype=np.float32)
    model.predict(obs)  # a warm start exists now
    model.save(tmp_path / "agent")
    loaded = POPLIN.load(tmp_path / "agent")
    assert_same_parameters(parameters(model), parameters(loaded))
    for name in ("dynamics_optimizer", "actor_optimizer", "discriminator_optimizer"):
        a, b = getattr(model.policy, name).state_dict(), getattr(loaded.policy, name).state_dict()
        for key in a["state"]:
            for tensor_name, tensor in a["state"][key].items():
                assert th.equal(tensor, b["state"][key][tensor_name]), (name, key, tensor_name)
    assert th.equal(model.mpc.warm_start, loaded.mpc.warm_start)
    assert th.equal(model.mpc.generator.get_state(), loaded.mpc.generator.get_state())
    # same warm start and same random state: the next plan is identical without reseeding
    np.testing.assert_array_equal(model.predict(obs)[0], loaded.predict(obs)[0])


def test_resume_equals_an_uninterrupted_run(tmp_path):
    """2N steps == N steps, save (agent + replay buffer), load, N more steps; N a whole number of episodes."""
    first_steps = 400

    def fresh_env():
        return make_vec_env("Pendulum-v1", n_envs=1, seed=0)

    straight = POPLIN("poplin-a", fresh_env(), seed=0, **TINY)
    straight.learn(800)

    env = fresh_env()
    first = POPLIN("poplin-a", env, seed=0, **TINY)
    first.learn(first_steps)
    first.save(tmp_path / "agent")
    first.save_replay_buffer(tmp_path / "buffer")
    # The env object continues where it was (its RNG state). force_reset=False keeps the saved last observation
    # (the auto-reset one after step 400); SB3's default would reset the env once more and draw another start state.
    resumed = POPLIN.load(tmp_path / "agent", env=env, force_reset=False)
    resumed.load_replay_buffer(tmp_path / "buffer")
    resumed.learn(800 - first_steps, reset_num_timesteps=False)

    assert resumed.num_timesteps == straight.num_timesteps == 800
    assert_same_parameters(parameters(straight), parameters(resumed))
    np.testing.assert_array_equal(straight.replay_buffer.actions[:800], resumed.replay_buffer.actions[:800])


def test_two_seeded_runs_are_identical():
    runs = []
    for _ in range(2):
        model = POPLIN("poplin-p", "Pendulum-v1", seed=3, distillation="bc", **TINY)
        model.learn(600)
        returns = [info["r"] for info in model.ep_info_buffer]
        runs.append((parameters(model), returns, model.replay_buffer.actions[:600].copy()))
    assert_same_parameters(runs[0][0], runs[1][0])
    assert runs[0][1] == runs[1][1]
    np.testing.assert_array_equal(runs[0][2], runs[1][2])


# ---------------------------------------------------------------- interruptions
class StopAt(BaseCallback):
    def __init__(self, step, error=False):
        super().__init__()
        self.step, self.error = step, error

    def _on_step(self):
        if self.num_timesteps >= self.step:
            if self.error:
                raise RuntimeError("interrupted")
            return False
        return True


@pytest.mark.parametrize("error", [False, True])
def test_interrupted_training_leaves_a_usable_model(tmp_path, error):
    model = POPLIN("poplin-p", "Pendulum-v1", seed=0, **TINY)
    if error:
        with pytest.raises(RuntimeError, match="interrupted"):
            model.learn(1000, callback=StopAt(300, error=True))
    else:
        model.learn(1000, callback=StopAt(300))
    assert model.num_timesteps == 300
    model.control = "policy"  # predict follows the control mode: the interruption left no rollout state behind
    np.testing.assert_allclose(
        model.predict(np.array([1.0, 0.0, 0.0], dtype=np.float32))[0],
        2.0 * model.policy.actor.act(th.tensor([[1.0, 0.0, 0.0]])).detach().numpy()[0],
        atol=1e-6,
    )
    model.control = "mpc"
    action, _ = model.predict(np.array([1.0, 0.0, 0.0], dtype=np.float32))
    assert np.isfinite(action).all()
    model.save(tmp_path / "agent")
    # stopped in mid-episode: the planned steps since the last distillation are saved, not dropped
    loaded = POPLIN.load(tmp_path / "agent")
    assert len(model.distiller.planned) == len(loaded.distiller.planned) == 100  # steps 201-300, recorded when planned
    for record, restored in zip(model.distiller.planned, loaded.distiller.planned, strict=True):
        assert record.keys() == restored.keys()
        assert all(th.equal(record[key], restored[key]) for key in record)
    model.learn(300, reset_num_timesteps=False)
    assert model.num_timesteps >= 600


@pytest.mark.parametrize("kwargs", [dict(noise="sep"), dict(noise="uni"), dict(noise="sep", distill_imagined=True)])
def test_planned_steps_hold_their_blocks_not_the_search_vectors(tmp_path, kwargs):
    """POPLIN-P Avg keeps the first block of each plan: in memory and in a zip saved in mid-episode, not all H blocks."""
    model = POPLIN("poplin-p", "Pendulum-v1", seed=0, **{**TINY, "distillation": "avg", **kwargs})
    model.learn(1000, callback=StopAt(300))
    block = model.planner.search_space.block
    for record in model.distiller.planned:
        for key in ("blocks", "elite_blocks"):
            if key in record:
                assert record[key].shape[-1] == block
                assert record[key].untyped_storage().nbytes() == record[key].numel() * record[key].element_size(), key
    model.save(tmp_path / "agent")
    with zipfile.ZipFile(tmp_path / "agent.zip") as archive:
        saved = archive.getinfo("distiller.pth").file_size
    per_step = sum(value.numel() * value.element_size() for value in model.distiller.planned[0].values())
    assert saved < 2 * len(model.distiller.planned) * per_step + 100_000  # the records' bytes, plus pickling overhead
    loaded = POPLIN.load(tmp_path / "agent")
    for record, restored in zip(model.distiller.planned, loaded.distiller.planned, strict=True):
        assert all(th.equal(record[key], restored[key]) for key in record)


# ---------------------------------------------------------------- checkpoints: the callbacks' schedule
EPISODE = 50  # Pendulum-v1 cut to 50 steps: a checkpoint every 50 steps


def short_pendulum(seed: int) -> DummyVecEnv:
    env = DummyVecEnv([lambda: Monitor(gym.make("Pendulum-v1", max_episode_steps=EPISODE))])
    env.seed(seed)
    return env


def periodic_callbacks(log_path: Path) -> list[BaseCallback]:
    """SB3's and the package's callbacks, with periods that do not divide the checkpoint steps (multiples of 50)."""
    return [
        EvalCallback(
            short_pendulum(1), eval_freq=30, n_eval_episodes=1, log_path=str(log_path), verbose=0,
            callback_after_eval=StopTrainingOnNoModelImprovement(max_no_improvement_evals=1000),
        ),
        ControlModesEvalCallback(short_pendulum(2), eval_freq=45, n_eval_episodes=1, log_path=str(log_path), modes=("mpc",)),
        EveryNTimesteps(35, ConvertCallback(lambda _locals, _globals: True)),
        StopTrainingOnMaxEpisodes(max_episodes=1000),
    ]  # fmt: skip


def train_with_checkpoints(run_dir: Path, kill_at: int | None = None, resume_from: Path | None = None) -> list[BaseCallback]:
    """150 steps of tiny PETS with a checkpoint after every episode, killed at ``kill_at`` or resumed from a checkpoint."""
    env = short_pendulum(0)
    resume.record_resets(env)
    callbacks = periodic_callbacks(run_dir)
    if resume_from is None:
        model = POPLIN("pets", env, seed=0, **TINY)
    else:
        model = resume.restore_checkpoint(resume_from, POPLIN, env, callbacks)
    every = [*callbacks, resume.EpisodeCheckpointCallback(run_dir, callbacks)]
    if kill_at is not None:
        every.append(StopAt(kill_at, error=True))
    model.learn(150 - model.num_timesteps, callback=every, reset_num_timesteps=resume_from is None)
    return callbacks


def numbers_only(value: Any) -> bool:
    """Whether a value holds numbers only (a counter, an evaluation list), not a path, an env or the model."""
    if isinstance(value, (bool, int, float, np.number, np.bool_)):
        return True
    if isinstance(value, np.ndarray):
        return value.dtype.kind in "biuf"
    if isinstance(value, (list, tuple, deque)):
        return all(numbers_only(item) for item in value)
    if isinstance(value, dict):
        return all(numbers_only(item) for item in value.values())
    return False


def progress(callback: BaseCallback) -> dict[str, Any]:
    """Every attribute of a callback that holds numbers only, arrays as lists (comparable with ``==``)."""

    def plain(value: Any) -> Any:
        if isinstance(value, np.ndarray):
            return value.tolist()
        if isinstance(value, (list, tuple, deque)):
            return [plain(item) for item in value]
        if isinstance(value, dict):
            return {key: plain(item) for key, item in value.items()}
        return value

    return {name: plain(value) for name, value in vars(callback).items() if numbers_only(value)}


def test_a_resumed_run_keeps_the_callbacks_schedule_and_counters(tmp_path):
    """
    Killed at step 120 (after the checkpoint of step 100) and resumed: evaluations every 30 and 45 steps, which do not
    divide 100, fall on the same steps with the same results as in an uninterrupted run, and every counter of every
    callback (nested ones too) ends as there (issue 48: a callback's ``n_calls`` not restored moved them).
    """
    straight = train_with_checkpoints(tmp_path / "straight")
    with pytest.raises(RuntimeError, match="interrupted"):
        train_with_checkpoints(tmp_path / "killed", kill_at=120)
    checkpoint = resume.latest_checkpoint(tmp_path / "killed")
    assert checkpoint is not None and checkpoint.name == "step-100"
    resumed = train_with_checkpoints(tmp_path / "killed", resume_from=checkpoint)

    assert straight[0].evaluations_timesteps == [30, 60, 90, 120, 150] and straight[1].timesteps == [45, 90, 135]
    for name in ("evaluations.npz", "evaluations_mpc.npz"):
        with np.load(tmp_path / "straight" / name) as expected, np.load(tmp_path / "killed" / name) as written:
            assert expected.files == written.files
            for key in expected.files:
                np.testing.assert_array_equal(written[key], expected[key], err_msg=f"{name}: {key}")
    pairs = list(zip(resume.iter_callbacks(straight), resume.iter_callbacks(resumed), strict=True))
    assert len(pairs) == 6  # the four callbacks, the evaluation's child, EveryNTimesteps's child
    for a, b in pairs:
        expected, found = progress(a), progress(b)
        differing = sorted(key for key in expected.keys() | found.keys() if expected.get(key) != found.get(key))
        assert not differing, f"{type(a).__name__}: {[(key, expected.get(key), found.get(key)) for key in differing]}"


def test_checkpoints_refuse_other_releases_of_the_private_state_they_use(tmp_path, monkeypatch):
    import stable_baselines3

    resume.check_private_state_releases()  # the pinned releases
    monkeypatch.setattr(stable_baselines3, "__version__", "2.10.0")
    with pytest.raises(RuntimeError, match=r"private state of stable_baselines3 2\.9\.x.*2\.10\.0 is installed"):
        resume.save_checkpoint(tmp_path, tiny(), [])
    monkeypatch.setattr(stable_baselines3, "__version__", "2.9.7")
    monkeypatch.setattr(gym, "__version__", "1.5.0")
    with pytest.raises(RuntimeError, match=r"gymnasium 1\.4\.x.*install gymnasium==1\.4\.\*"):
        resume.restore_checkpoint(tmp_path, POPLIN, None, [])
