"""rl-zoo3 integration: the sb3_poplin.zoo front end, the packaged hyperparameter files and benchmarks/compare.py."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import optuna
import pytest
import yaml

from conftest import load_benchmark
from sb3_poplin import presets, zoo
from sb3_poplin.tasks import env_util
from sb3_poplin.envs import ENV_IDS
from sb3_poplin.poplin import POPLIN

REPO = Path(__file__).resolve().parent.parent
TASKS = [
    "Pendulum-v1",
    "InvertedPendulum-v5",
    "InvertedDoublePendulum-v5",
    "HalfCheetah-v5",
    "Hopper-v5",
    "Walker2d-v5",
    "Ant-v5",
    "Swimmer-v5",
    "Reacher-v5",
    "Pusher-v5",
    *ENV_IDS,  # the package's own sb3_poplin/... tasks
]
MODEL_FREE = ["sac", "td3", "ppo", "crossq", "tqc"]
# a planner small enough for a few hundred steps in a test
TINY_POPLIN = [
    "horizon:5",
    "population_size:20",
    "num_elites:4",
    "cem_iterations:1",
    "ensemble_size:2",
    "dynamics_net_arch:[16,16]",
    "model_epochs:1",
    "buffer_size:1000",
]


def run(args: list[str], cwd: Path, timeout: int = 300) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    process = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout, check=False)
    assert process.returncode == 0, process.stdout[-3000:] + process.stderr[-3000:]
    return process


def load_yaml(path: Path) -> dict:
    with open(path) as file:
        return yaml.load(file, Loader=yaml.UnsafeLoader)  # the zoo writes OrderedDicts


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A POPLIN-P run on Pendulum-v1 through the zoo: one random episode, one planned, one evaluation."""
    folder = tmp_path_factory.mktemp("zoo")
    zoo_train = [sys.executable, "-m", "sb3_poplin.zoo", "train", "--algo", "poplin", "--env", "Pendulum-v1"]
    args = ["-n", "400", "--num-threads", "1", "--seed", "0", "-f", "logs", "--eval-freq", "400", "--eval-episodes", "2"]
    run([*zoo_train, *args, "-params", *TINY_POPLIN], folder)
    return folder


def test_train_writes_the_zoo_files(trained: Path) -> None:
    run_dir = trained / "logs" / "poplin" / "Pendulum-v1_1"
    assert (run_dir / "Pendulum-v1.zip").is_file()
    with np.load(run_dir / "evaluations.npz") as mpc, np.load(run_dir / "evaluations_policy.npz") as policy:
        assert mpc["timesteps"].tolist() == [400] and mpc["results"].shape == (1, 2)
        assert policy["timesteps"].tolist() == [400] and policy["results"].shape == (1, 2)
    config = dict(load_yaml(run_dir / "Pendulum-v1" / "config.yml"))
    assert config["policy"] == "poplin-p" and config["horizon"] == 5 and config["train_freq"] == [1, "episode"]
    args = dict(load_yaml(run_dir / "Pendulum-v1" / "args.yml"))
    assert args["conf_file"] == str(presets.config_path("poplin"))


def test_enjoy_loads_and_plays(trained: Path) -> None:
    zoo_enjoy = [sys.executable, "-m", "sb3_poplin.zoo", "enjoy", "--algo", "poplin", "--env", "Pendulum-v1"]
    process = run([*zoo_enjoy, "-f", "logs", "--no-render", "-n", "50", "--num-threads", "1"], trained)
    assert "Loading logs/poplin/Pendulum-v1_1/Pendulum-v1.zip" in process.stdout


def test_played_poplin_has_no_big_replay_buffer(trained: Path) -> None:
    path = trained / "logs" / "poplin" / "Pendulum-v1_1" / "Pendulum-v1.zip"
    model = zoo.PlayedPOPLIN.load(path)
    assert model.replay_buffer is not None and model.replay_buffer.buffer_size == 1
    assert POPLIN.load(path).buffer_size == 1000


def test_plots_writes_png(trained: Path, tmp_path: Path) -> None:
    pytest.importorskip("seaborn")
    pytest.importorskip("scipy")
    args = ["plot_train", "-a", "poplin", "-e", "Pendulum-v1", "-f", str(trained / "logs"), "-w", "1"]
    zoo.main(["plots", *args, "--output-dir", str(tmp_path)])
    assert (tmp_path / "plot_train_Training_Episodic_Reward.png").stat().st_size > 0


@pytest.mark.parametrize("algo", MODEL_FREE)
def test_packaged_v5_settings_are_used(algo: str, capsys: pytest.CaptureFixture[str]) -> None:
    budgets = presets.load_config(presets.config_path("poplin"))
    for env_id in TASKS:
        hyperparams = zoo.read_hyperparameters(algo, env_id)
        assert hyperparams["n_timesteps"] == budgets[env_id]["n_timesteps"]
    output = capsys.readouterr().out
    assert "Using 'default' hyperparameters" not in output
    assert f"Loading hyperparameters from: {presets.config_path(algo)}" in output


def test_hyperparameter_files_share_tasks_and_budgets() -> None:
    paper = presets.load_config(presets.config_path("poplin"))
    assert sorted(paper) == sorted(TASKS)
    assert sorted(presets.load_config(presets.config_path("poplin", "cpu"))) == sorted(TASKS)
    for algo in MODEL_FREE:
        config = presets.load_config(presets.config_path(algo))
        assert sorted(config) == sorted(TASKS), algo
        assert {env: entry["n_timesteps"] for env, entry in config.items()} == {
            env: entry["n_timesteps"] for env, entry in paper.items()
        }, algo


@pytest.mark.parametrize("budget", presets.BUDGETS)
def test_poplin_entries_build_and_keep_the_task_env_kwargs(budget: str) -> None:
    from sb3_poplin.tasks import has_task, make_task

    for env_id, entry in presets.load_config(presets.config_path("poplin", budget)).items():
        assert entry["policy"] in POPLIN.policy_aliases and entry["train_freq"] == [1, "episode"]
        if has_task(env_id):
            assert make_task(env_id).env_kwargs.items() <= entry.get("env_kwargs", {}).items(), env_id
    settings = dict(presets.load_config(presets.config_path("poplin", budget))["Pendulum-v1"])
    del settings["n_timesteps"]
    settings["train_freq"] = tuple(settings["train_freq"])  # as the zoo passes it
    for variant in POPLIN.policy_aliases:  # a valid set of POPLIN arguments, and one override switches the variant
        POPLIN(env="Pendulum-v1", **{**settings, "policy": variant})


def test_env_kwargs_reach_the_eval_env_and_args() -> None:
    manager = zoo.PoplinExperimentManager(
        SimpleNamespace(env_kwargs=None),
        "poplin",
        "HalfCheetah-v5",
        log_folder=os.devnull,
        config=zoo.default_config("poplin", "HalfCheetah-v5"),
    )
    hyperparams, _ = manager.read_hyperparameters()
    expected = {"exclude_current_positions_from_observation": False}
    assert hyperparams["env_kwargs"] == expected
    assert manager.eval_env_kwargs == expected and manager.args.env_kwargs == expected


def test_task_env_kwargs_are_added(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(env_util, "has_task", lambda env_id: True)
    monkeypatch.setattr(env_util, "make_task", lambda env_id: SimpleNamespace(env_kwargs={"keep_x": True}))
    assert env_util.task_env_kwargs("Any-v0", None) == {"keep_x": True}
    assert env_util.task_env_kwargs("Any-v0", {"other": 1}) == {"other": 1, "keep_x": True}
    with pytest.warns(UserWarning, match="reward function assumes"):
        assert env_util.task_env_kwargs("Any-v0", {"keep_x": False}) == {"keep_x": False}


def test_default_conf_file() -> None:
    sac = str(presets.config_path("sac"))
    assert zoo.train_args(["--algo", "sac", "--env", "HalfCheetah-v5"])[-2:] == ["--conf-file", sac]
    assert zoo.train_args(["--algo=poplin", "--env=Foo-v0"])[-1] == str(presets.config_path("poplin"))
    assert zoo.train_args(["--algo", "sac", "--env", "HalfCheetah-v4"]) == ["--algo", "sac", "--env", "HalfCheetah-v4"]
    given = ["--algo", "poplin", "--env", "Pendulum-v1", "-conf", "mine.yml"]
    assert zoo.train_args(given) == given
    with pytest.raises(ValueError, match="budget"):
        presets.config_path("poplin", "gpu")


@pytest.mark.parametrize("variant", [*POPLIN.policy_aliases, None])
def test_optuna_sampler(variant: str | None) -> None:
    zoo.register()
    from rl_zoo3.hyperparams_opt import HYPERPARAMS_CONVERTER, HYPERPARAMS_SAMPLER

    assert "poplin" in HYPERPARAMS_SAMPLER and HYPERPARAMS_CONVERTER["poplin"] is zoo.convert_poplin_params
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0))
    for _ in range(5):
        trial = study.ask()
        params = zoo.sample_poplin_params(trial, 1, 1, {}, variant=variant)
        assert params == zoo.convert_poplin_params(trial.params)  # a stored trial converts to the same settings
        chosen = variant or params["policy"]
        if chosen != "rs":
            assert 1 <= params["num_elites"] <= params["population_size"]
        assert ("noise" in params) == (chosen == "poplin-p") and ("proposal" in params) == (chosen == "poplin-a")


def test_unknown_command() -> None:
    with pytest.raises(SystemExit, match="Unknown command"):
        zoo.main(["fly"])
    with pytest.raises(SystemExit, match="plots needs"):
        zoo.main(["plots", "nothing"])


# ------------------------------------------------------------------------------------------------ compare.py
def compare(tmp_path: Path, *extra: str) -> tuple[dict, str]:
    params = [f"poplin:{setting}" for setting in TINY_POPLIN]
    args = ["--algos", "poplin", "sac", "--envs", "Pendulum-v1", "-n", "400", "--n-evals", "2", "--eval-episodes", "2"]
    args += ["--log-folder", str(tmp_path / "logs"), "--output", str(tmp_path / "report"), "--params", *params, *extra]
    process = run([sys.executable, str(REPO / "benchmarks" / "compare.py"), *args], tmp_path, timeout=900)
    assert (tmp_path / "report" / "curves_Pendulum-v1.png").stat().st_size > 0
    table = (tmp_path / "report" / "results.md").read_text()
    assert "| Pendulum-v1 | 400 |" in table and "POPLIN-P (policy)" in table and "SAC" in table
    return json.loads((tmp_path / "report" / "results.json").read_text()), process.stdout


@pytest.mark.slow
def test_compare_locally(tmp_path: Path) -> None:
    results, output = compare(tmp_path, "--seeds", "0", "1", "--jobs", "2")
    assert output.count("[done]") == 4
    labels = results["tasks"][0]["labels"]
    assert sorted(labels) == ["POPLIN-P (MPC)", "POPLIN-P (policy)", "SAC"]
    assert all(len(entry["final"]) == 2 for entry in labels.values())
    # a second call finds the complete runs and trains nothing
    again, output = compare(tmp_path, "--seeds", "0", "1", "--jobs", "2")
    assert output.count("[reused]") == 4 and again["tasks"] == results["tasks"]


@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec("ray") is None, reason="Ray is not installed (pip install 'sb3_poplin[ray]')")
def test_compare_through_local_ray(tmp_path: Path) -> None:
    results, output = compare(tmp_path, "--seeds", "0", "--jobs", "2", "--ray-address", "local")
    assert output.count("[done]") == 2
    assert all(run["returncode"] == 0 and run["run_dir"] for run in results["runs"])


def load_compare():
    return load_benchmark("compare")


def test_compare_runs_poplin_variants_by_name(tmp_path: Path) -> None:
    compare_module = load_compare()
    algos = ["--algos", "pets", "poplin-a", "poplin", "sac", "rs", "--envs", "Pendulum-v1"]
    options = compare_module.parse_args(
        [*algos, "--seeds", "0", "-n", "400", "--log-folder", str(tmp_path), "--params", "pets:horizon:5"]
    )
    jobs = {job.algo: job for job in compare_module.plan_jobs(options)}
    assert [job.zoo_algo for job in jobs.values()] == ["poplin", "poplin", "poplin", "sac", "poplin"]
    assert jobs["pets"].params == ["policy:'pets'", "horizon:5"]
    assert jobs["poplin-a"].params == ["policy:'poplin-a'"]
    # random shooting evaluates as many candidates per step as CEM: poplin_cpu.yml's 200 x 3, the paper file's 500 x 5
    assert jobs["rs"].params == ["policy:'rs'", "population_size:600"]
    paper = compare_module.parse_args(
        ["--algos", "rs", "--envs", "Pendulum-v1", "--budget", "paper", "--log-folder", str(tmp_path)]
    )
    assert compare_module.plan_jobs(paper)[0].params == ["policy:'rs'", "population_size:2500"]
    given = compare_module.parse_args(
        ["--algos", "rs", "--envs", "Pendulum-v1", "--params", "rs:population_size:50", "--log-folder", str(tmp_path)]
    )
    assert compare_module.plan_jobs(given)[0].params == ["policy:'rs'", "population_size:50"]
    assert jobs["pets"].command()[3:8] == ["train", "--algo", "poplin", "--env", "Pendulum-v1"]
    # report columns: the variant that runs (poplin alone: the file's variant)
    assert [job.column for job in jobs.values()] == ["pets", "poplin-a", "poplin-p", "sac", "rs"]
    assert jobs["pets"].name != jobs["poplin-a"].name  # separate log files
    assert compare_module.label_algo("PETS (MPC)") == "pets"
    assert compare_module.label_algo("POPLIN-A (policy)") == "poplin-a"
    assert compare_module.label_algo("SAC") == "sac"
    # a run's args.yml only matches the job of its own variant
    args = {"algo": "poplin", "env": "Pendulum-v1", "seed": 0, "n_timesteps": 400, "eval_freq": 40, "eval_episodes": 3}
    args |= {"conf_file": jobs["pets"].conf_file, "hyperparams": {"policy": "pets", "horizon": 5}}
    assert jobs["pets"].matches(args) and not jobs["poplin-a"].matches(args)
    # a run committed from another checkout (its args.yml names that checkout's packaged file) is the same run
    moved = str(
        Path("/elsewhere/checkout") / Path(jobs["pets"].conf_file).relative_to(Path(jobs["pets"].conf_file).parents[2])
    )
    assert jobs["pets"].matches(args | {"conf_file": moved})
    assert not jobs["pets"].matches(args | {"conf_file": "/elsewhere/checkout/sb3_poplin/hyperparams/other.yml"})


def write_fake_run(job, run_dir: Path, eval_returns: list[float], train_returns: list[float], episode: int) -> None:
    """A run folder as the zoo and compare.py leave it (no model zip): args, config, evaluations, monitor, marker."""
    compare_module = sys.modules["compare"]
    folder = run_dir / job.env
    folder.mkdir(parents=True)
    hyperparams = {key.split(":", 1)[0]: compare_module.parse_value(key.split(":", 1)[1]) for key in job.params}
    args = {"algo": job.zoo_algo, "env": job.env, "seed": job.seed, "n_timesteps": job.n_timesteps}
    args |= {"eval_freq": job.eval_freq, "eval_episodes": job.eval_episodes, "conf_file": job.conf_file}
    (folder / "args.yml").write_text(yaml.dump({**args, "hyperparams": hyperparams}))
    (folder / "config.yml").write_text(yaml.dump(hyperparams))
    steps = job.eval_freq * np.arange(1, len(eval_returns) + 1)
    results = np.repeat(np.asarray(eval_returns)[:, None], 2, axis=1)  # two evaluation episodes, same return
    np.savez(run_dir / "evaluations.npz", timesteps=steps, results=results)
    lines = ["#" + json.dumps({"t_start": 0, "env_id": job.env}), "r,l,t"]
    lines += [f"{ret},{episode},{k + 1.0}" for k, ret in enumerate(train_returns)]
    (run_dir / "0.monitor.csv").write_text("\n".join(lines) + "\n")
    (run_dir / compare_module.COMPLETE_FILE).write_text("{}")


def test_compare_reports_the_paper_protocol_and_steps_to_reach(tmp_path: Path) -> None:
    """SAC trains 3x as long; the tables' numbers equal a hand computation from the fake runs' files."""
    compare_module = load_compare()
    common = ["--algos", "pets", "sac", "--envs", "Pendulum-v1", "--seeds", "0", "1", "-n", "3000", "--n-evals", "3"]
    options = compare_module.parse_args([*common, "--steps-scale", "sac:3", "--log-folder", str(tmp_path)])
    jobs = compare_module.plan_jobs(options)
    assert {(job.algo, job.n_timesteps, job.eval_freq) for job in jobs} == {("pets", 3000, 1000), ("sac", 9000, 1000)}
    # the warm-up rule looks at the matched budget: the zoo's 10000 warm-up steps on HalfCheetah are cut to a tenth of
    # 10000 for the matched run and for the one trained 3 x as long alike (its first 10000 steps are the matched run's);
    # a matched budget of more than 20000 keeps them
    cheetah = ["--algos", "sac", "td3", "--envs", "HalfCheetah-v5", "--seeds", "0"]
    cheetah_jobs = compare_module.plan_jobs(compare_module.parse_args([*cheetah, "-n", "10000", "--steps-scale", "sac:3"]))
    assert {job.algo: (job.n_timesteps, job.params) for job in cheetah_jobs} == {
        "sac": (30000, ["learning_starts:1000"]),
        "td3": (10000, ["learning_starts:1000"]),
    }
    long_jobs = compare_module.plan_jobs(compare_module.parse_args([*cheetah, "-n", "30000", "--steps-scale", "sac:3"]))
    assert {job.algo: (job.n_timesteps, job.params) for job in long_jobs} == {"sac": (90000, []), "td3": (30000, [])}
    evaluations = {
        ("pets", 0): [-100, -50, 10],
        ("pets", 1): [-90, -30, 30],  # final mean 20
        ("sac", 0): [-200, -150, -100, -50, 0, 25, 30, 40, 50],  # reaches 20 at 6000
        ("sac", 1): [-200, -180, -160, -140, -120, -100, 25, 30, 40],  # at 7000; the mean curve at 7000 (27.5)
    }
    training = {
        ("pets", 0): [-300, -200, -100],  # the last 3000 steps: -200
        ("pets", 1): [-250, -150, -40],  # -146.67; target -173.33
        ("sac", 0): [-400 + 50 * k for k in range(1, 10)],  # window means -400 + 50 (k - 1): -150 at 6000
        ("sac", 1): [-400 + 40 * k for k in range(1, 10)],  # -400 + 40 (k - 1): -160 at 7000; mean -130 at 7000
    }
    results = []
    for job in jobs:
        run_dir = tmp_path / job.zoo_algo / f"Pendulum-v1_{job.seed + 1}_{job.algo}"
        write_fake_run(job, run_dir, evaluations[job.algo, job.seed], training[job.algo, job.seed], 1000)
        found = compare_module.find_run(job)  # complete without a model zip: the marker
        assert found == str(run_dir.relative_to(tmp_path))
        results.append(compare_module.JobResult(job, 0, found, reused=True))
    table = compare_module.write_report(results, options.envs, "cpu", tmp_path / "report", reference="PETS (MPC)")
    task = json.loads((tmp_path / "report" / "results.json").read_text())["tasks"][0]
    assert task["matched_step"] == 3000 and task["labels"]["SAC"]["final"] == [-100, -160]
    paper = task["paper_protocol"]
    assert paper["step"] == 3000 and paper["window"] == 3000
    assert paper["labels"]["PETS"]["values"] == pytest.approx([-200, -440 / 3])
    assert paper["labels"]["SAC"]["values"] == pytest.approx([-300, -320])
    reach = task["reach"]
    assert reach["target"] == pytest.approx(20) and reach["paper_target"] == pytest.approx(-520 / 3)
    assert reach["evaluation"]["SAC"] == {"step": 7000, "per_seed": {"0": 6000, "1": 7000}, "last_step": 9000}
    assert reach["evaluation"]["PETS (MPC)"]["step"] == 3000
    assert reach["paper_protocol"]["SAC"] == {"step": 7000, "per_seed": {"0": 6000, "1": 7000}, "last_step": 9000}
    assert reach["paper_protocol"]["PETS"]["step"] == 3000
    text = table.read_text()
    assert "| Pendulum-v1 | 3000 | -173.3 ± 26.7 (2 seeds) | -310.0 ± 10.0 (2 seeds) |" in text
    assert "| Pendulum-v1 | SAC | 20.0 (PETS (MPC)) | 7000 (s0: 6000, s1: 7000) | -173.3 | 7000 (s0: 6000, s1: 7000) |" in text
    # a run folder without the marker and without the model zip is an unfinished run
    for path in tmp_path.glob(f"*/*/{compare_module.COMPLETE_FILE}"):
        path.unlink()
    assert compare_module.find_run(jobs[0]) is None
    with pytest.raises(SystemExit, match=r"--steps-scale takes ALGO:FACTOR .* got 'td3:3'"):
        compare_module.plan_jobs(compare_module.parse_args([*common, "--steps-scale", "td3:3"]))
    with pytest.raises(SystemExit, match=r"got 'sac:three'"):
        compare_module.plan_jobs(compare_module.parse_args([*common, "--steps-scale", "sac:three"]))


# ------------------------------------------------------------------------------------------------ the paper suite
def test_paper_suite_is_in_every_hyperparameter_file() -> None:
    from sb3_poplin.tasks import has_task
    from sb3_poplin.tasks.paper_suite import PAPER_TASKS, paper_name, paper_task

    assert len(PAPER_TASKS) == 13 and len({task.env_id for task in PAPER_TASKS.values()}) == 13
    paper, cpu = zoo.load_config(zoo.config_path("poplin")), zoo.load_config(zoo.config_path("poplin", "cpu"))
    for name, task in PAPER_TASKS.items():
        assert has_task(task.env_id) and paper_name(task.env_id) == name and paper_task(name) is task
        assert paper[task.env_id]["n_timesteps"] == task.n_timesteps, name
        assert paper[task.env_id]["horizon"] == task.horizon == (25 if name in ("Reacher3D", "Pusher") else 30), name
        assert task.env_id in cpu
        for algo in MODEL_FREE:  # the baselines train as long (test_hyperparameter_files_share_tasks_and_budgets)
            assert zoo.load_config(zoo.config_path(algo))[task.env_id]["n_timesteps"] == task.n_timesteps
    assert {task.n_timesteps for task in PAPER_TASKS.values()} == {50_000, 200_000}
    assert paper_name("Pendulum-v1") is None
    with pytest.raises(ValueError, match=r"'Reacher' is not a task of the POPLIN paper; its tasks are \['Cheetah'"):
        paper_task("Reacher")


def test_compare_plans_and_reports_the_paper_suite(tmp_path: Path) -> None:
    from sb3_poplin.tasks.paper_suite import PAPER_TASKS

    compare_module = load_compare()
    common = ["--algos", "poplin", "sac", "--seeds", "0", "-n", "400", "--log-folder", str(tmp_path)]
    options = compare_module.parse_args(["--suite", "paper", *common])
    jobs = compare_module.plan_jobs(options)
    assert options.envs == [task.env_id for task in PAPER_TASKS.values()]
    assert [job.env for job in jobs[::2]] == options.envs and {job.algo for job in jobs} == {"poplin", "sac"}
    assert options.paper_names["sb3_poplin/MBBLCartpole-v0"] == "Cartpole"
    # a report of runs that do not exist: every cell is a failure, the columns are the paper's names in its order
    results = [compare_module.JobResult(job, 1) for job in jobs]
    table = compare_module.write_report(results, options.envs, "cpu", tmp_path / "report", options.paper_names)
    lines = table.read_text().splitlines()
    header = next(line for line in lines if line.startswith("| |"))
    assert header == "| | " + " | ".join(PAPER_TASKS) + " |"
    assert any(line.startswith("| POPLIN-P | failed (1/1) |") for line in lines)
    assert any(line.startswith("| SAC | failed (1/1) |") for line in lines)
    assert "| env id | `sb3_poplin/PETSCheetah-v0` | `sb3_poplin/AntNoTerm-v0` |" in table.read_text()
    # --envs picks among the paper's tasks by name or id, in the paper's order
    options = compare_module.parse_args(["--suite", "paper", "--envs", "Cartpole", "sb3_poplin/PETSPusher-v0", *common])
    compare_module.plan_jobs(options)
    assert options.paper_names == {"sb3_poplin/PETSPusher-v0": "Pusher", "sb3_poplin/MBBLCartpole-v0": "Cartpole"}
    with pytest.raises(SystemExit, match=r"\['Pendulum-v1'\] are not paper tasks"):
        compare_module.plan_jobs(compare_module.parse_args(["--suite", "paper", "--envs", "Pendulum-v1", *common]))


@pytest.mark.slow
def test_compare_runs_the_paper_suite(tmp_path: Path) -> None:
    from sb3_poplin.tasks.paper_suite import PAPER_TASKS

    params = [f"poplin:{setting}" for setting in TINY_POPLIN]
    args = ["--suite", "paper", "--algos", "poplin", "sac", "--seeds", "0", "-n", "400", "--n-evals", "1"]
    args += ["--eval-episodes", "2", "--log-folder", str(tmp_path / "logs"), "--output", str(tmp_path / "report")]
    run([sys.executable, str(REPO / "benchmarks" / "compare.py"), *args, "--params", *params], tmp_path, timeout=3600)
    table = (tmp_path / "report" / "results.md").read_text()
    assert "| | " + " | ".join(PAPER_TASKS) + " |" in table and "failed" not in table
    assert "| SAC |" in table and "| POPLIN-P (MPC) |" in table
    results = json.loads((tmp_path / "report" / "results.json").read_text())
    assert results["suite"] == "paper" and [task["name"] for task in results["tasks"]] == list(PAPER_TASKS)


def test_zoo_trains_enjoys_and_records_a_paper_env(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    env_id = "sb3_poplin/PETSReacher3D-v0"
    zoo_cli = [sys.executable, "-m", "sb3_poplin.zoo"]
    train = ["train", "--algo", "poplin", "--env", env_id, "-n", "150", "--num-threads", "1", "--seed", "0", "-f", "logs"]
    run([*zoo_cli, *train, "--eval-freq", "150", "--eval-episodes", "2", "-params", *TINY_POPLIN], tmp_path)
    run_dir = tmp_path / "logs" / "poplin" / "sb3_poplin-PETSReacher3D-v0_1"
    with np.load(run_dir / "evaluations.npz") as evaluations:
        assert evaluations["timesteps"].tolist() == [150] and evaluations["results"].shape == (1, 2)
    play = ["--algo", "poplin", "--env", env_id, "-f", "logs", "-n", "20"]
    process = run([*zoo_cli, "enjoy", *play, "--no-render", "--num-threads", "1"], tmp_path)
    assert "sb3_poplin-PETSReacher3D-v0.zip" in process.stdout
    probe = "import gymnasium as gym, sb3_poplin; e = gym.make('sb3_poplin/PETSReacher3D-v0', render_mode='rgb_array'); "
    probe += "e.reset(seed=0); e.render()"
    monkeypatch.setenv("MUJOCO_GL", os.environ.get("MUJOCO_GL", "egl"))  # offscreen rendering for the runs below
    if subprocess.run([sys.executable, "-c", probe], capture_output=True, check=False).returncode != 0:
        pytest.skip(f"no offscreen OpenGL for MuJoCo (MUJOCO_GL={os.environ['MUJOCO_GL']}): record_video not tested")
    run([*zoo_cli, "record_video", *play, "-o", "videos"], tmp_path)
    assert len(list((tmp_path / "videos").glob("*.mp4"))) == 1
