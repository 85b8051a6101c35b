"""Datasets of recorded transitions, the locomotion model hooks and the model-quality report (issue 34)."""

import json
import math

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from conftest import TINY, pendulum_reward, tiny

from sb3_poplin.experiments.analysis import main as analysis_main
from sb3_poplin.analysis.model_quality import (
    EnsembleUnderTest,
    TransitionDataset,
    dataset_from_agent,
    evaluate,
    fit_after_every_episode,
    model_quality,
    record,
)
from sb3_poplin.tasks import make_env, make_task
from sb3_poplin.tasks.hooks import LocomotionHooks
from sb3_poplin.tasks.mujoco import HALF_CHEETAH_HOOKS, HOOK_CANDIDATES


# ------------------------------------------------------------------------------------------------ hooks
def test_locomotion_hooks_by_hand():
    hooks = LocomotionHooks(6, exclude=(0,), angles=(2,), rates=(0, 1), dt=0.5)
    obs = th.tensor([[10.0, 1.0, 0.3, 4.0, 5.0, 6.0]])
    nxt = th.tensor([[11.0, 0.5, 0.1, 4.5, 5.0, 7.0]])
    # plain entries 1, 3, 4, 5, then sin and cos of entry 2
    expected = [1.0, 4.0, 5.0, 6.0, math.sin(0.3), math.cos(0.3)]
    assert th.allclose(hooks.obs_preproc(obs), th.tensor([expected]))
    assert hooks.feature_dim == 6
    # entries 0 and 1 as rates: (x' - x) / dt; the others as deltas
    assert th.allclose(hooks.targ_proc(obs, nxt), th.tensor([[2.0, -1.0, -0.2, 0.5, 0.0, 1.0]]))
    assert th.allclose(hooks.obs_postproc(obs, hooks.targ_proc(obs, nxt)), nxt)
    # without rates, no target hooks: the model keeps its default delta
    assert LocomotionHooks(6, exclude=(0,)).model_hooks()["targ_proc"] is None


def test_bounded_inputs_are_squashed_and_their_targets_are_not():
    hooks = LocomotionHooks(4, exclude=(0,), bounded=(2, 3), bound=2.0)
    obs = th.tensor([[7.0, 1.5, 0.1, -40.0]])
    nxt = th.tensor([[8.0, 1.0, 30.0, -39.0]])
    expected = [1.5, 2.0 * math.tanh(0.1 / 2.0), 2.0 * math.tanh(-40.0 / 2.0)]
    assert th.allclose(hooks.obs_preproc(obs), th.tensor([expected]))
    assert hooks.obs_preproc(obs)[0, 2] >= -2.0  # within the bound however large the velocity
    assert th.allclose(hooks.targ_proc(obs, nxt), nxt - obs)  # the change is predicted unsquashed
    assert th.allclose(hooks.obs_postproc(obs, hooks.targ_proc(obs, nxt)), nxt)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(exclude=(6,)), "exclude must hold distinct indices in \\[0, 6\\)"),
        (dict(angles=(1, 1)), "angles must hold distinct indices"),
        (dict(exclude=(2,), angles=(2,)), "both excluded and fed as sine and cosine"),
        (dict(rates=(0,), dt=0.0), "dt must be > 0"),
        (dict(exclude=(1,), bounded=(1,)), "bounded and also excluded"),
        (dict(angles=(2,), bounded=(2, 3)), "bounded and also excluded or fed as sine"),
        (dict(bounded=(3,), bound=0.0), "bound must be > 0"),
    ],
)
def test_locomotion_hooks_refuse_bad_layouts(kwargs, message):
    with pytest.raises(ValueError, match=message):
        LocomotionHooks(6, **kwargs)


@pytest.mark.parametrize("env_id", sorted(HOOK_CANDIDATES))
def test_every_candidate_round_trips_on_real_transitions_and_keeps_the_reward_exact(env_id):
    env = make_env(env_id)
    task = make_task(env_id)
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=0)
    rows = []
    for _ in range(40):
        action = rng.uniform(env.action_space.low, env.action_space.high).astype(np.float32)
        nxt, reward, terminated, _, _ = env.step(action)
        rows.append((obs, action, nxt, reward))
        obs = nxt if not terminated else env.reset(seed=1)[0]
    o, a, n, r = (th.as_tensor(np.array(column), dtype=th.float64) for column in zip(*rows, strict=True))
    for name, hooks in HOOK_CANDIDATES[env_id].items():
        assert hooks.obs_dim == o.shape[1], name
        rebuilt = hooks.obs_postproc(o, hooks.targ_proc(o, n))
        assert th.allclose(rebuilt, n, rtol=0, atol=1e-9), name
        # the planner's reward on the rebuilt next observation is the env's
        assert th.allclose(task.reward_fn(o, a, rebuilt), r, atol=1e-6 if env_id != "Ant-v5" else 0.2), name
        # the root positions are no input, every other entry is
        features = hooks.obs_preproc(o)
        assert features.shape[1] == hooks.feature_dim
        moved = o.clone()
        moved[:, list(hooks.exclude)] += 100.0
        assert th.equal(hooks.obs_preproc(moved), features), name


def test_sincos_sees_a_full_turn_of_the_pitch_as_the_same_posture():
    hooks = HOOK_CANDIDATES["HalfCheetah-v5"]["sincos"]
    obs = th.randn(4, 18, dtype=th.float64)
    turned = obs.clone()
    turned[:, 2] += 2 * math.pi
    assert th.allclose(hooks.obs_preproc(obs), hooks.obs_preproc(turned))
    assert not th.allclose(
        HOOK_CANDIDATES["HalfCheetah-v5"]["raw"].obs_preproc(obs), HOOK_CANDIDATES["HalfCheetah-v5"]["raw"].obs_preproc(turned)
    )


def test_progress_predicts_the_forward_velocity_the_reward_pays():
    hooks = HOOK_CANDIDATES["HalfCheetah-v5"]["progress"]
    obs, nxt = th.zeros(1, 18), th.zeros(1, 18)
    nxt[0, 0] = 0.25  # 0.25 m in one 0.05 s step
    assert th.allclose(hooks.targ_proc(obs, nxt)[0, 0], th.tensor(5.0))
    assert th.allclose(make_task("HalfCheetah-v5").reward_fn(obs, th.zeros(1, 6), nxt), th.tensor([5.0]))


# ------------------------------------------------------------------------------------------------ datasets
@pytest.fixture(scope="module")
def pendulum_data():
    # a preset buffer of exactly the steps recorded: record makes room for them without a wrap-around
    return record("Pendulum-v1", "pets", 600, 0, **{**TINY, "ensemble_size": 2, "buffer_size": 600})


def test_record_keeps_whole_episodes_in_env_units(pendulum_data, tmp_path):
    data = pendulum_data
    assert data.env_id == "Pendulum-v1" and len(data.obs) == 600 and data.num_episodes == 3
    assert data.episode_bounds() == [(0, 200), (200, 400), (400, 600)]
    same_episode = np.diff(data.episode) == 0
    assert np.array_equal(data.next_obs[:-1][same_episode], data.obs[1:][same_episode])
    # the recorded rewards are Pendulum's for the recorded actions in env units ([-2, 2]: the buffer stores [-1, 1])
    assert np.allclose(data.rewards, pendulum_reward(data.obs, data.actions[:, 0]), atol=1e-4)
    assert np.abs(data.actions).max() > 1.0
    assert not data.terminated.any()
    assert data.meta["variant"] == "pets" and len(data.meta["training_returns"]) == 3
    data.save(str(tmp_path / "d.npz"))
    loaded = TransitionDataset.load(str(tmp_path / "d.npz"))
    for name in ("obs", "actions", "rewards", "next_obs", "terminated", "episode"):
        assert np.array_equal(getattr(loaded, name), getattr(data, name)), name
    assert loaded.meta == json.loads(json.dumps(data.meta))


def test_dataset_slices(pendulum_data):
    first = pendulum_data.first_steps(400)
    assert first.num_episodes == 2 and np.array_equal(first.obs, pendulum_data.obs[:400])
    later = pendulum_data.episodes(1, 3)
    assert np.array_equal(later.obs, pendulum_data.obs[200:]) and later.episode[0] == 0 and later.num_episodes == 2
    with pytest.raises(
        ValueError,
        match="300 steps end inside an episode of this dataset: pass an episode end, the nearest are 200 and 400",
    ):
        pendulum_data.first_steps(300)
    with pytest.raises(ValueError, match=r"the nearest are 600\.$"):
        pendulum_data.first_steps(700)
    with pytest.raises(ValueError, match=r"Episodes 2\.\.3 asked of a dataset of 3 episodes"):
        pendulum_data.episodes(2, 4)
    with pytest.raises(ValueError, match="episode must count"):
        TransitionDataset("x", *(np.zeros((2, 1)) for _ in range(5)), episode=np.array([0, 2]))


def test_terminations_are_recorded_and_time_limits_are_not():
    agent = tiny("pets", "InvertedPendulum-v5", buffer_size=400)
    agent.learn(300)
    data = dataset_from_agent(agent)
    fell = np.abs(data.next_obs[:, 1]) > 0.2
    assert data.terminated.any()
    assert np.array_equal(data.terminated, fell)
    ends = [stop - 1 for _, stop in data.episode_bounds()]
    assert data.terminated[ends].all() and data.terminated.sum() == len(ends)


def test_a_checkpoint_replay_buffer_gives_the_same_dataset(tmp_path):
    from sb3_poplin.experiments.checkpoints import replay_buffer_arrays

    agent = tiny(buffer_size=1000)
    agent.learn(400)
    arrays = replay_buffer_arrays(agent.replay_buffer)
    # as if saved 50 steps into a third episode, which the dataset leaves out
    arrays = {name: np.concatenate([rows, rows[:50]]) if rows.ndim else rows for name, rows in arrays.items()}
    arrays["dones"][400:] = 0.0
    np.savez(tmp_path / "replay_buffer.npz", **{**arrays, "pos": np.array(450)})
    analysis_main(["record", "--env", "Pendulum-v1", "--from-checkpoint", str(tmp_path), "--output", str(tmp_path)])
    loaded = TransitionDataset.load(str(tmp_path / "Pendulum-v1-pets-400-seed0.npz"))
    direct = dataset_from_agent(agent)
    assert loaded.num_episodes == 2 and loaded.meta["checkpoint"].endswith("replay_buffer.npz")
    for name in ("obs", "actions", "rewards", "next_obs", "terminated", "episode"):
        np.testing.assert_allclose(getattr(loaded, name), getattr(direct, name), rtol=0, atol=1e-6, err_msg=name)
    with pytest.raises(SystemExit, match=r"--steps .* or --from-checkpoint"):
        analysis_main(["record", "--env", "Pendulum-v1", "--output", str(tmp_path)])


def test_dataset_from_agent_refuses_a_wrapped_buffer():
    agent = tiny(buffer_size=100)
    agent.learn(200)
    with pytest.raises(ValueError, match="1 envs and is full"):
        dataset_from_agent(agent)


# ------------------------------------------------------------------------------------------------ fitting and evaluation
def test_the_fit_schedule_refits_after_every_episode(pendulum_data):
    seen = []
    fit_after_every_episode(lambda data: seen.append(len(data.obs)), pendulum_data)
    assert seen == [200, 400, 600]


class Lookup:
    """A perfect model of a dataset: the recorded next state of every recorded (state, action)."""

    def __init__(self, data, scale=0.0):
        self.table = {tuple(o.tolist()): n for o, n in zip(data.obs, data.next_obs, strict=True)}
        self.scale = scale

    def one_step(self, obs, actions, next_obs, rewards):
        return 0.0, 0.0

    def step(self, states, actions):
        out = th.stack([th.as_tensor(self.table[tuple(s.tolist())]) for s in states.float()])
        return out + self.scale  # a constant error on every entry


class NoChange:
    def one_step(self, obs, actions, next_obs, rewards):
        return 1.0, 2.0

    def step(self, states, actions):
        return states.clone()


def test_a_perfect_model_has_no_error(pendulum_data):
    task = make_task("Pendulum-v1")
    report = evaluate(Lookup(pendulum_data), pendulum_data, task.reward_fn, ks=(1, 5), return_horizons=(5, 10))
    assert report["state_error"] == {1: 0.0, 5: 0.0}
    assert report["return_error"][5] < 1e-3 and report["return_error"][10] < 1e-3
    assert report["return_correlation"][10] == pytest.approx(1.0)
    assert report["starts"] == 3 * len(range(0, 200 - 10 + 1, 5))


def test_errors_of_a_model_that_predicts_no_change_by_hand(pendulum_data):
    task = make_task("Pendulum-v1")
    data = pendulum_data.episodes(2, 3)
    report = evaluate(NoChange(), data, task.reward_fn, ks=(1, 3), return_horizons=(3,), stride=7)
    obs, actions, rewards = data.obs.astype(np.float64), data.actions[:, 0].astype(np.float64), data.rewards
    states = np.concatenate([obs, data.next_obs[-1:]])
    std = obs.std(axis=0, ddof=1)
    starts = np.arange(0, 200 - 3 + 1, 7)
    for k in (1, 3):
        error = (states[starts] - states[starts + k]) / std
        assert report["state_error"][k] == pytest.approx(np.sqrt((error**2).mean()), rel=1e-5)
    # the predicted state never moves: Pendulum's reward of the start state, under each recorded action
    predicted = sum(pendulum_reward(obs[starts], actions[starts + j]) for j in range(3))
    real = np.array([rewards[s : s + 3].sum() for s in starts])
    assert report["return_error"][3] == pytest.approx(np.abs(predicted - real).mean(), rel=1e-4)
    assert report["return_correlation"][3] == pytest.approx(np.corrcoef(predicted, real)[0, 1], rel=1e-4)
    assert (report["nll"], report["mse"]) == (1.0, 2.0)


def test_a_predicted_termination_ends_the_predicted_return():
    data = TransitionDataset(
        "x",
        obs=np.zeros((4, 1), np.float32),
        actions=np.zeros((4, 1), np.float32),
        rewards=np.ones(4, np.float32),
        next_obs=np.zeros((4, 1), np.float32),
        terminated=np.zeros(4, bool),
        episode=np.zeros(4, np.int64),
    )

    class Counter:
        def one_step(self, *args):
            return 0.0, 0.0

        def step(self, states, actions):
            return states + 1.0

    def reward(obs, action, nxt):
        return th.ones(len(obs))

    def terminates_at_two(obs, action, nxt):
        return nxt[:, 0] >= 2.0

    report = evaluate(Counter(), data, reward, terminates_at_two, ks=(1,), return_horizons=(4,), stride=1)
    # predicted return: steps 1 and 2 count (the terminating step too), steps 3 and 4 do not; the real return is 4
    assert report["return_error"][4] == pytest.approx(2.0)


def test_one_step_nll_against_an_independent_computation():
    agent = tiny(standardise_targets=True)
    agent.learn(400)
    data = dataset_from_agent(agent)
    model = EnsembleUnderTest(agent)
    obs, actions, nxt, rewards = (
        th.as_tensor(a, dtype=th.float32) for a in (data.obs, data.actions, data.next_obs, data.rewards)
    )
    nll, mse = model.one_step(obs, actions, nxt, rewards)
    dynamics = agent.policy.dynamics
    with th.no_grad():
        x = dynamics.model_input(obs, actions / 2.0)  # Pendulum's torque bound is 2
        mean, logvar = dynamics(x.unsqueeze(0).expand(dynamics.ensemble_size, -1, -1))
        std = dynamics.target_std
        mu, sigma = mean * std + dynamics.target_mean, (0.5 * logvar).exp() * std
        target = nxt - obs
        hand = -th.distributions.Normal(mu, sigma).log_prob(target).mean()
    assert dynamics.target_std.min() < 0.5  # the conversion to target units matters here
    assert nll == pytest.approx(float(hand), rel=1e-4)
    assert mse == pytest.approx(float(((target - mu) ** 2).mean()), rel=1e-4)


def half_cheetah_dataset(episodes=3, steps=60, seed=0):
    """Random-action episodes of HalfCheetah-v5 (x kept), cut to ``steps`` steps each."""
    env = gym.wrappers.TimeLimit(make_env("HalfCheetah-v5").unwrapped, steps)
    rng = np.random.default_rng(seed)
    columns = {k: [] for k in ("obs", "actions", "rewards", "next_obs", "terminated", "episode")}
    for e in range(episodes):
        obs, _ = env.reset(seed=seed + e)
        done = False
        while not done:
            action = rng.uniform(-1, 1, 6).astype(np.float32)
            nxt, reward, terminated, truncated, _ = env.step(action)
            for key, value in zip(columns, (obs, action, reward, nxt, terminated, e), strict=True):
                columns[key].append(value)
            obs, done = nxt, terminated or truncated
    return TransitionDataset("HalfCheetah-v5", **{k: np.array(v) for k, v in columns.items()})


def test_the_chosen_candidate_is_the_registered_task_and_the_registry_is_untouched():
    data = half_cheetah_dataset()
    settings = dict(ensemble_size=2, dynamics_net_arch=(16, 16), model_epochs=2)
    kwargs = dict(ks=(1, 5), return_horizons=(5,), stride=10)
    candidates = HOOK_CANDIDATES["HalfCheetah-v5"]
    registered = make_task("HalfCheetah-v5")
    task = model_quality(data, 2, 1, settings, None, 0, **kwargs)
    chosen = model_quality(data, 2, 1, settings, candidates[HALF_CHEETAH_HOOKS].hooks(), 0, **kwargs)
    raw = model_quality(data, 2, 1, settings, candidates["raw"].hooks(), 0, **kwargs)
    assert make_task("HalfCheetah-v5") is registered  # the hooks go to the agent, not into the registry
    for key in ("state_error", "return_error", "nll", "mse"):
        assert task[key] == chosen[key], key
    assert raw["return_error"] != chosen["return_error"]  # other inputs: another model


def test_commands_record_and_measure(tmp_path):
    small = ["population_size:20", "num_elites:4", "horizon:5", "ensemble_size:2", "dynamics_net_arch:[16,16]"]
    analysis_main(["record", "--env", "Pendulum-v1", "--steps", "600", "--output", str(tmp_path), "--params", *small])
    path = tmp_path / "Pendulum-v1-pets-600-seed0.npz"
    assert TransitionDataset.load(str(path)).meta["overrides"]["dynamics_net_arch"] == [16, 16]
    analysis_main(
        [
            *["model-quality", "--data", str(path), "--train-episodes", "2", "--output", str(tmp_path), "--seeds", "0", "1"],
            *["--params", "ensemble_size:2", "dynamics_net_arch:[16,16]", "model_epochs:2"],
        ]
    )
    results = json.loads((tmp_path / "model_quality_Pendulum-v1-pets-600-seed0.json").read_text())
    assert [(r["hooks"], r["seed"]) for r in results] == [("task", 0), ("task", 1)]
    assert results[0]["state_error"] != results[1]["state_error"]  # two seeds, two fits
    assert "| task | 1 |" in (tmp_path / "model_quality_Pendulum-v1-pets-600-seed0.md").read_text()
    with pytest.raises(SystemExit, match="has the candidates \\['task'\\]"):
        analysis_main(["model-quality", "--data", str(path), "--hooks", "sincos", "--output", str(tmp_path)])
    with pytest.raises(ValueError, match="KEY:VALUE"):
        analysis_main(["model-quality", "--data", str(path), "--params", "model_epochs", "--output", str(tmp_path)])


# ------------------------------------------------------------------------------------------------ hooks as agent state
def test_model_hooks_are_an_argument_and_checked():
    from sb3_poplin import POPLIN
    from sb3_poplin.tasks import ModelHooks

    new = HOOK_CANDIDATES["HalfCheetah-v5"]["sincos+progress"]
    agent = POPLIN("poplin-p", "HalfCheetah-v5", seed=0, model_hooks=new.hooks(), **TINY)
    assert agent.model_hooks == new.hooks() and agent.policy.dynamics.hooks[0] == new.obs_preproc
    assert agent.policy.actor.in_dim == 17  # policy=False: the raw observation without x
    assert POPLIN("pets", "HalfCheetah-v5", seed=0, **TINY).model_hooks == make_task("HalfCheetah-v5").hooks
    raw = ModelHooks(model_input_exclude=(0,))
    agent = POPLIN("poplin-p", "HalfCheetah-v5", seed=0, model_hooks=raw, **TINY)
    assert agent.policy.dynamics.hooks[0] is None and agent.policy.dynamics.in_dim == 17 + 6
    assert agent.policy.actor.in_dim == 17 and raw.policy_exclude == (0,)
    with pytest.raises(
        TypeError, match=r"model_hooks must be a sb3_poplin.tasks.ModelHooks, got LocomotionHooks.*hooks\(policy=True\)"
    ):
        POPLIN("pets", "HalfCheetah-v5", model_hooks=new, **TINY)
    with pytest.raises(ValueError, match="Pass either input_exclude or obs_preproc"):
        ModelHooks(model_input_exclude=(0,), obs_preproc=new.obs_preproc)
    with pytest.raises(ValueError, match="targ_proc and obs_postproc come together"):
        ModelHooks(targ_proc=new.targ_proc)
    with pytest.raises(ValueError, match=r"the policy takes either policy_input_exclude .* or policy_obs_preproc"):
        ModelHooks(model_input_exclude=(0,), policy_obs_preproc=new.obs_preproc)
    with pytest.raises(ValueError, match=r"TaskSpec 'HalfCheetah-v5': the policy takes either"):
        from dataclasses import replace

        replace(make_task("HalfCheetah-v5"), policy_obs_preproc=new.obs_preproc, policy_input_exclude=(0,))


def test_the_policy_can_see_the_model_features(monkeypatch):

    from sb3_poplin import POPLIN
    from sb3_poplin.policies import PolicyNetwork

    hooks = HOOK_CANDIDATES["HalfCheetah-v5"]["sincos"]
    agent = POPLIN("poplin-p", "HalfCheetah-v5", seed=0, model_hooks=hooks.hooks(policy=True), **TINY)
    actor = agent.policy.actor
    assert actor.in_dim == hooks.feature_dim == 18
    obs = th.randn(7, 18)
    obs[:, 2] += 6.0  # a cheetah that turned once: the same features as without the turn
    turned = obs.clone()
    turned[:, 2] -= 2 * math.pi
    assert th.allclose(actor.features(obs), hooks.obs_preproc(obs)) and th.allclose(actor(obs), actor(turned), atol=1e-5)
    actor.update_whitening(obs)
    assert th.allclose(actor.obs_mean, hooks.obs_preproc(obs).mean(dim=0))
    with pytest.raises(ValueError, match="either input_exclude or input_preproc"):
        PolicyNetwork(18, 6, (8,), input_exclude=(0,), input_preproc=hooks.obs_preproc)


def test_a_zip_keeps_the_hooks_it_was_trained_with(tmp_path, monkeypatch):
    from dataclasses import replace

    import sb3_poplin.tasks as tasks
    from sb3_poplin import POPLIN

    agent = POPLIN("poplin-p", "HalfCheetah-v5", seed=0, **TINY)
    agent.save(tmp_path / "agent.zip")
    obs = th.as_tensor(make_env("HalfCheetah-v5").reset(seed=0)[0], dtype=th.float32).repeat(3, 1)
    actions = th.zeros(3, 6)
    before, _ = agent.policy.dynamics.propagate(obs.unsqueeze(1), actions.unsqueeze(1), "expectation")
    # a later release gives the task other hooks (the progress target, the raw policy input): only its spec changes,
    # and zips of this release keep theirs
    progress = HOOK_CANDIDATES["HalfCheetah-v5"]["sincos+progress"].model_hooks(policy=False)
    monkeypatch.setitem(tasks._REGISTRY, "HalfCheetah-v5", replace(make_task("HalfCheetah-v5"), **progress))
    assert make_task("HalfCheetah-v5").hooks != agent.model_hooks
    loaded = POPLIN.load(tmp_path / "agent.zip")
    after, _ = loaded.policy.dynamics.propagate(obs.unsqueeze(1), actions.unsqueeze(1), "expectation")
    assert loaded.model_hooks == agent.model_hooks and loaded.policy.model_hooks["targ_proc"] is None
    assert th.equal(before, after) and loaded.policy.actor.in_dim == agent.policy.actor.in_dim == 18
    fresh = POPLIN("poplin-p", "HalfCheetah-v5", seed=0, **TINY)  # a new agent takes the task's new hooks
    fresh.policy.dynamics.load_state_dict(agent.policy.dynamics.state_dict())
    moved, _ = fresh.policy.dynamics.propagate(obs.unsqueeze(1), actions.unsqueeze(1), "expectation")
    assert fresh.policy.actor.in_dim == 17 and not th.allclose(moved[..., 0], before[..., 0])  # x read as a velocity
    other = HOOK_CANDIDATES["HalfCheetah-v5"]["sincos+progress"].hooks(policy=True)  # the same network shapes
    given = POPLIN.load(tmp_path / "agent.zip", model_hooks=other)  # load(model_hooks=) replaces the saved ones
    assert given.model_hooks == other and given.policy.model_hooks["targ_proc"] == other.targ_proc
