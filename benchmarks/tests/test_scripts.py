"""
The benchmark scripts' own logic (``benchmarks/``): the true-simulator planner of ``diagnose_mpc.py``, the posture
check, the fidelity A/B's arms and where ``results_file.py`` puts a row. The package's tests (``tests/``) import
nothing from ``benchmarks/``; ``make test`` runs both folders.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch as th
from bench_util import load_benchmark, tiny

from sb3_poplin import POPLIN
from sb3_poplin.variants import configuration


# ------------------------------------------------------------------------------------------------ diagnose_mpc.py
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
    # net turns count the first pitch to the last, whatever happened between: 1.0 - 0.0 over 2π; backwards negative
    assert posture.net_turns(pitches) == pytest.approx(1.0 / (2 * np.pi))
    assert posture.net_turns(np.array([0.5, -3.0, -6 * np.pi + 0.5])) == pytest.approx(-3.0)
    assert posture.parse_tags(["column=PETS", "run=poplin/a=b"]) == {"column": "PETS", "run": "poplin/a=b"}
    with pytest.raises(SystemExit, match=r"--tag takes KEY=VALUE, e.g. --tag column=PETS; got 'PETS'"):
        posture.parse_tags(["PETS"])
    # a seed is recorded as a number, as the lines' own seeds are; a commit of digits stays text
    assert posture.parse_tags(["seed=1", "trained_by=1234567"]) == {"seed": 1, "trained_by": "1234567"}
    with pytest.raises(SystemExit, match=r"--tag seed= takes an integer \(e.g. seed=1\); got 'one'"):
        posture.parse_tags(["seed=one"])


def test_cheetah_posture_plans_with_the_settings_it_is_given(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``--set``: the agent is loaded with those settings (its planner's population), each line records them; a
    value is typed as the constructor takes it, and a misspelt setting stops the check before any episode."""
    posture = load_benchmark("cheetah_posture")
    assert posture.parse_settings(["population_size=500", "cem_alpha=0.25", "optimizer=icem"]) == {
        "population_size": 500,
        "cem_alpha": 0.25,
        "optimizer": "icem",
    }
    with pytest.raises(SystemExit, match=r"--set takes KEY=VALUE, e.g. --set population_size=500; got 'horizon='"):
        posture.parse_settings(["horizon="])
    agent = tiny("pets", "sb3_poplin/PETSCheetah-v0")
    agent.save(tmp_path / "agent.zip")
    populations = []
    real_episode = posture.posture_episode

    def episode(model, env, seed, steps, pitch):  # the population the loaded agent plans with
        populations.append(model.mpc.planner.optimizer.population_size)
        return real_episode(model, env, seed, steps, pitch)

    monkeypatch.setattr(posture, "posture_episode", episode)
    record = tmp_path / "posture.jsonl"
    command = ["cheetah_posture.py", "--env", "sb3_poplin/PETSCheetah-v0", "--models", str(tmp_path / "agent.zip")]
    command += ["--steps", "3", "--record", str(record), "--tag", "seed=0"]
    monkeypatch.setattr("sys.argv", [*command, "--set", "population_size=7", "num_elites=2"])
    posture.main()
    monkeypatch.setattr("sys.argv", command)
    posture.main()
    assert populations == [7, agent.settings.population_size]
    lines = [json.loads(line) for line in record.read_text().splitlines()]
    assert [line["settings"] for line in lines] == [{"population_size": 7, "num_elites": 2}, {}]
    monkeypatch.setattr("sys.argv", [*command, "--set", "num_elite=2"])
    with pytest.raises(TypeError, match=r"'num_elite' \(did you mean 'num_elites'\?\)"):
        posture.main()
    assert len(record.read_text().splitlines()) == 2


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


# ------------------------------------------------------------------------------------------------ fidelity_ab.py
def test_fidelity_ab_pairs_arms_seed_by_seed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    ab = load_benchmark("fidelity_ab")
    monkeypatch.setattr(ab, "OUTPUT", tmp_path)
    # reference v0.3 on seeds 0-2; "original" on seeds 1-3: only seeds 1 and 2 are shared
    values = {
        "v0.3": {0: (10.0, -5.0), 1: (20.0, -7.0), 2: (30.0, 1.0)},
        "original": {1: (25.0, -8.0), 2: (29.0, 4.0), 3: (0, 0)},
    }
    for arm, seeds in values.items():
        for seed, (mpc, policy) in seeds.items():
            path = ab.run_path("Pendulum-v1", "poplin-p/sep/bc", arm, seed)
            path.parent.mkdir(parents=True, exist_ok=True)
            record = dict(task="Pendulum-v1", configuration="poplin-p/sep/bc", arm=arm, seed=seed, train_returns=[-1.0])
            # two episodes each, whose mean is the value above
            record.update(mpc_returns=[mpc - 1.0, mpc + 1.0], policy_returns=[policy - 2.0, policy + 2.0])
            path.write_text(json.dumps(record))
    table = ab.paired("v0.3").splitlines()
    assert len(table) == 3  # header, rule, one row
    # MPC: +5 (seed 1), -1 (seed 2) -> higher on 1 / 2, mean +2; policy: -1, +3 -> 1 / 2, mean +1
    assert table[2] == "| Pendulum-v1 | poplin-p/sep/bc | original | v0.3 | 2 | 1 / 2 | +2 | 1 / 2 | +1 |"
    assert ab.paired("whitening").splitlines()[2:] == []  # no run of the reference arm: no rows


def test_fidelity_ab_leave_one_out_arms_change_exactly_one_original_setting() -> None:
    ab = load_benchmark("fidelity_ab")
    for policy in ("poplin-p", "poplin-a"):
        original = ab.arm_settings("original", policy)
        for name in ab.LEFT_OUT:
            arm = ab.arm_settings(f"original-without-{name}", policy)
            changed = {key for key in original if arm[key] != original[key]}
            # POPLIN-A's original already clones the executed actions: leaving out the planned target changes nothing
            expected = set() if (policy, name) == ("poplin-a", "planned-target") else set(ab.ARMS[name])
            assert changed == expected, (policy, name, changed)
            assert all(arm[key] == ab.V0_3[key] for key in ab.ARMS[name])
    assert ab.arm_settings("original-without-raw-targets", "poplin-p")["standardise_targets"] is True
    assert ab.uses_pets_hooks("sb3_poplin/PETSCheetah-v0", "original-without-latest-window")
    combined = ab.arm_settings("v0.3+planned-latest", "poplin-p")
    assert combined == {**ab.V0_3, "distill_target": "planned", "distill_window": None}


@pytest.mark.parametrize(
    ("config", "arm"),
    [
        ("poplin-p/sep/bc", "original-without-whitening-plain"),
        ("poplin-p/uni/gan", "original-without-whitening-plain"),
        ("poplin-p/sep/avg", "original-without-whitening-plain"),
        ("poplin-a/init", "v0.3+raw-targets"),
        ("pets", "v0.3+raw-targets"),
    ],
)
def test_the_defaults_are_the_ab_arms_they_were_chosen_from(config: str, arm: str) -> None:
    # the README's claim: POPLIN-P's defaults are the fidelity A/B's `original-without-whitening-plain` arm (the
    # original's settings with the function-preserving whitening); the others' are the earlier defaults with raw
    # model targets (POPLIN-A keeps its 10 000-step window of executed actions)
    ab = load_benchmark("fidelity_ab")
    kwargs = configuration(config)
    policy = kwargs.pop("policy")
    settings = {**ab.V0_2, **ab.arm_settings(arm, policy)}
    by_default, explicit = tiny(policy, **kwargs), tiny(policy, **kwargs, **settings)
    assert {key: getattr(by_default.settings, key) for key in settings} == {
        key: getattr(explicit.settings, key) for key in settings
    }


# ------------------------------------------------------------------------------------------------ beside_paper.py
def test_beside_paper_welch_test_is_scipys_from_the_same_statistics() -> None:
    """Welch's test of our seeds against a published mean ± std: scipy's ``ttest_ind_from_stats`` on the same numbers
    (our sample std, the paper's std as a sample one), and the Welch-Satterthwaite degrees of freedom by hand."""
    from scipy import stats

    beside = load_benchmark("beside_paper")
    ours = [3318.5, 2778.9, 3700.5, 2900.0]
    result = beside.welch_from_stats(ours, 4205.0, 789.0, 4)
    expected = stats.ttest_ind_from_stats(np.mean(ours), np.std(ours, ddof=1), 4, 4205.0, 789.0, 4, equal_var=False)
    assert result["t"] == pytest.approx(expected.statistic, rel=1e-12)
    assert result["p"] == pytest.approx(expected.pvalue, rel=1e-9)
    a, b = np.var(ours, ddof=1) / 4, 789.0**2 / 4
    assert result["df"] == pytest.approx((a + b) ** 2 / (a**2 / 3 + b**2 / 3), rel=1e-12)
    with pytest.raises(ValueError, match="at least 2 values a side; got 1 here"):
        beside.welch_from_stats([1.0], 0.0, 1.0, 4)


def test_beside_paper_permutation_test_is_exact() -> None:
    """The exact permutation test: scipy's exhaustive one on equal groups (where its two-sided p and the share of
    splits at least as extreme in magnitude agree), a small case by hand, and the floor of 4 seeds a side."""
    from scipy import stats

    beside = load_benchmark("beside_paper")
    first, second = [16705.0, 14287.0, 3100.0, 9000.0], [3319.0, 2779.0, 3700.0, 4100.0]

    def difference(x, y, axis):
        return np.mean(x, axis=axis) - np.mean(y, axis=axis)

    exhaustive = stats.permutation_test((first, second), difference, permutation_type="independent", n_resamples=np.inf)
    assert beside.permutation_p(first, second) == pytest.approx(exhaustive.pvalue, rel=1e-12)
    # [3] against [1, 2]: the splits {3}|{1,2} (1.5), {1}|{2,3} (-1.5), {2}|{1,3} (0): 2 of 3 as extreme
    assert beside.permutation_p([3.0], [1.0, 2.0]) == pytest.approx(2 / 3)
    # every one of 4 above every one of 4: only the observed split and its mirror are as extreme
    assert beside.permutation_p([10.0, 11.0, 12.0, 13.0], [1.0, 2.0, 3.0, 4.0]) == pytest.approx(2 / 70)
    with pytest.raises(ValueError, match="values on both sides"):
        beside.permutation_p([], [1.0])


def test_beside_paper_writes_its_section_once_with_the_numbers(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``--write``: the section replaces an earlier one in results.md (text after it stays), its numbers go into
    results.json; a paper column not run here says so; posture lines at other settings are left out, a re-checked
    agent counts once (its latest line); a misspelt --paper is a clear error."""
    beside = load_benchmark("beside_paper")
    protocol = {
        "step": 50000,
        "window": 3000,
        "labels": {
            "PETS": {"seeds": [0, 1], "values": [3000.0, 4000.0]},
            "POPLIN-P": {"seeds": [0, 1], "values": [15000.0, 17000.0]},
        },
    }
    report = tmp_path / "report"
    report.mkdir()
    (report / "results.json").write_text(json.dumps({"tasks": [{"env": "T-v0", "paper_protocol": protocol}]}))
    (report / "results.md").write_text("# Report\n\n## Table\n\nrows\n")
    posture = tmp_path / "posture.jsonl"
    lines = [
        {"column": "PETS", "seed": 0, "run": "a", "return": 2000.0, "upside_down": 0.5, "settings": {}},
        {"column": "PETS", "seed": 0, "run": "a", "return": 2100.0, "upside_down": 0.4, "turns": 3.0, "settings": {}},
        {"column": "PETS", "seed": 0, "run": "a", "return": 9999.0, "upside_down": 0.0, "settings": {"population_size": 500}},
        {"column": "POPLIN-P", "seed": 1, "run": "b", "return": 18000.0, "upside_down": 0.42, "turns": 133.0},
    ]
    posture.write_text("\n".join(json.dumps(line) for line in lines) + "\n")
    command = ["beside_paper.py", "--report", str(report), "--paper", "POPLIN-P=12228,5653", "PETS=4205,789"]
    command += ["SAC=1746,839", "--paper-seeds", "4", "--ratio", "POPLIN-P", "PETS", "--posture", str(posture)]
    monkeypatch.setattr("sys.argv", [*command, "--write", "--note", "first"])
    beside.main()
    monkeypatch.setattr("sys.argv", [*command, "--write", "--note", "second"])
    beside.main()
    text = (report / "results.md").read_text()
    assert text.count("## Beside the paper") == 1 and "second" in text and "first" not in text
    assert text.startswith("# Report\n\n## Table\n\nrows\n\n## Beside the paper")
    assert "| PETS | 4205 ± 789 | 3500 ± 500 (2 seeds) | s0: 3000, s1: 4000 | -705 (-17%) |" in text
    assert "| SAC | 1746 ± 839 | not run here | — | — | — |" in text
    assert "POPLIN-P / PETS: 4.57x here (2 and 2 seeds), 2.91x in the paper" in text
    assert "in 4 of 4 pairs" in text and "two-sided p = 0.333" in text  # 2 of the 6 splits of 4 values
    assert "| PETS | 0 | — | 2100 | 40.0% | 3.0 |" in text and "9999" not in text and "2000 |" not in text
    numbers = json.loads((report / "results.json").read_text())["beside_paper"]
    assert numbers["columns"]["POPLIN-P"]["mean"] == 16000.0 and numbers["ratio"]["pairs_above"] == 4
    assert numbers["columns"]["PETS"]["welch"]["t"] == pytest.approx(-705 / np.sqrt(500_000 / 2 + 789.0**2 / 4))
    assert [line["return"] for line in numbers["posture"]] == [2100.0, 18000.0]
    monkeypatch.setattr("sys.argv", ["beside_paper.py", "--report", str(report), "--paper", "PETS:4205", "--paper-seeds", "4"])
    with pytest.raises(SystemExit, match=r"--paper takes LABEL=MEAN,STD, e.g. --paper PETS=4205,789; got 'PETS:4205'"):
        beside.main()


# ------------------------------------------------------------------------------------------------ results_file.py
def test_a_row_goes_below_the_table_not_below_the_text_after_it(tmp_path: Path) -> None:
    results = load_benchmark("results_file")
    path = tmp_path / "RESULTS.md"
    path.write_text(
        "# Benchmark results\n\n## Speed\n\nintro\n\n| a | b |\n|---|---|\n| 1 | 2 |\n\nReading of the rows above.\n\n"
        "## Other\n\ntext\n"
    )
    results.append_row("Speed", "intro", ["a", "b"], ["3", "4"], path=str(path))
    assert "| 1 | 2 |\n| 3 | 4 |\n\nReading of the rows above.\n\n## Other" in path.read_text()
    # a new section: heading, intro, header, rule, row at the end
    results.append_row("New", "what it measures", ["x"], ["5"], path=str(path))
    assert path.read_text().endswith("## New\n\nwhat it measures\n\n| x |\n|---|\n| 5 |\n")
    # a section without its table (the header changed): the row goes to the section's end, before the next heading
    results.append_row("Speed", "intro", ["a", "b", "c"], ["6", "7", "8"], path=str(path))
    assert "Reading of the rows above.\n| 6 | 7 | 8 |\n\n## Other" in path.read_text()


def test_code_version_marks_changed_code_not_changed_data(tmp_path: Path) -> None:
    """A record's ``code``: ``+changes`` for an edited or staged Python, package or build file; a synced run's data
    files (csv, json, config.yml outside the package) and RESULTS.md leave it the bare commit."""
    import subprocess

    results = load_benchmark("results_file")
    repo = tmp_path / "repo"
    (repo / "sb3_poplin" / "hyperparams").mkdir(parents=True)
    (repo / "benchmarks" / "suite" / "zoo").mkdir(parents=True)
    files = {
        "benchmarks/compare.py": "x = 1\n",
        "sb3_poplin/hyperparams/poplin.yml": "a: 1\n",
        "setup.cfg": "[metadata]\n",
        "benchmarks/suite/zoo/config.yml": "seed: 0\n",
        "benchmarks/suite/zoo/monitor.csv": "r,l\n",
        "benchmarks/RESULTS.md": "# results\n",
    }
    for name, text in files.items():
        (repo / name).write_text(text)

    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=repo, check=True, capture_output=True, text=True).stdout.strip()

    git("init", "-q")
    git("add", ".")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "start")
    commit = git("rev-parse", "--short", "HEAD")
    where = str(repo / "benchmarks")
    assert results.code_version(where) == commit
    for data in ("benchmarks/suite/zoo/config.yml", "benchmarks/suite/zoo/monitor.csv", "benchmarks/RESULTS.md"):
        (repo / data).write_text(files[data] + "more\n")
    assert results.code_version(where) == commit  # data changed only
    for code in ("benchmarks/compare.py", "sb3_poplin/hyperparams/poplin.yml", "setup.cfg"):
        (repo / code).write_text(files[code] + "# edited\n")
        assert results.code_version(where) == commit + "+changes", code
        git("add", code)  # staged, not committed: still a change
        assert results.code_version(where) == commit + "+changes", code
        git("checkout", "HEAD", "--", code)
    assert results.code_version(where) == commit
    assert results.code_version(str(tmp_path)) == "unknown"  # not a checkout
