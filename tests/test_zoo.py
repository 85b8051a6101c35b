"""rl-zoo3 integration: the sb3_poplin.zoo front end and the packaged hyperparameter files (compare: test_compare.py)."""

from __future__ import annotations

import inspect
import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import optuna
import pytest
import yaml

from sb3_poplin.experiments import presets, zoo
from sb3_poplin.tasks import env_util
from sb3_poplin.envs import ENV_IDS
from sb3_poplin.poplin import POPLIN

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
    """
    A POPLIN-P run on Pendulum-v1 through the zoo: one random episode, one planned, one MPC evaluation at its end and a
    policy-control evaluation every 200 steps (``--policy-eval-freq``).
    """
    folder = tmp_path_factory.mktemp("zoo")
    zoo_train = [sys.executable, "-m", "sb3_poplin.zoo", "train", "--algo", "poplin", "--env", "Pendulum-v1"]
    args = ["-n", "400", "--num-threads", "1", "--seed", "0", "-f", "logs", "--eval-freq", "400", "--eval-episodes", "2"]
    args += ["--policy-eval-freq", "200"]
    run([*zoo_train, *args, "-params", *TINY_POPLIN], folder)
    return folder


def test_train_writes_the_zoo_files(trained: Path) -> None:
    run_dir = trained / "logs" / "poplin" / "Pendulum-v1_1"
    assert (run_dir / "Pendulum-v1.zip").is_file()
    with np.load(run_dir / "evaluations.npz") as mpc, np.load(run_dir / "evaluations_policy.npz") as policy:
        assert mpc["timesteps"].tolist() == [400] and mpc["results"].shape == (1, 2)
        assert policy["timesteps"].tolist() == [200, 400] and policy["results"].shape == (2, 2)
    config = dict(load_yaml(run_dir / "Pendulum-v1" / "config.yml"))
    assert config["policy"] == "poplin-p" and config["horizon"] == 5 and config["train_freq"] == [1, "episode"]
    args = dict(load_yaml(run_dir / "Pendulum-v1" / "args.yml"))
    assert args["conf_file"] == str(presets.config_path("poplin"))
    assert args["policy_eval_freq"] == 200  # a setting of the run: compare finds the run by it


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
    def conf_file(algo: str, env_id: str, config: str | None = None) -> tuple[str, str | None]:
        args = SimpleNamespace(env_kwargs=None, conf_file=config)
        manager = zoo.PoplinExperimentManager(args, algo, env_id, log_folder=os.devnull, config=config)
        return manager.config, args.conf_file  # what is read, and what args.yml records

    sac = str(presets.config_path("sac"))
    assert conf_file("sac", "HalfCheetah-v5") == (sac, sac)
    assert conf_file("poplin", "MountainCarContinuous-v0") == (str(presets.config_path("poplin")),) * 2
    zoo_own, recorded = conf_file("sac", "HalfCheetah-v4")  # no packaged entry: rl-zoo3's own file, None in args.yml
    assert zoo_own.endswith(os.path.join("hyperparams", "sac.yml")) and zoo_own != sac and recorded is None
    assert conf_file("poplin", "Pendulum-v1", __file__) == (__file__, __file__)
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


def test_optimizer_and_its_options_come_from_the_yml(tmp_path: Path) -> None:
    """`optimizer: icem` and an `optimizer_kwargs` mapping in a hyperparameter file reach the planner's CEM."""
    from sb3_poplin.planning import ICEM_OPTIONS

    entry = dict(presets.load_config(presets.config_path("poplin", "cpu"))["Pendulum-v1"])
    entry.update(optimizer="icem", optimizer_kwargs={"noise_beta": 0.25, "keep_elites": 0.5})
    conf = tmp_path / "icem.yml"
    conf.write_text(yaml.safe_dump({"Pendulum-v1": entry}))
    hyperparams = zoo.read_hyperparameters("poplin", "Pendulum-v1", conf_file=str(conf))
    assert hyperparams["optimizer"] == "icem" and dict(hyperparams["optimizer_kwargs"]) == entry["optimizer_kwargs"]
    settings = {key: value for key, value in hyperparams.items() if key not in ("n_timesteps", "env_kwargs")}
    settings["train_freq"] = tuple(settings["train_freq"])
    model = POPLIN(env="Pendulum-v1", **settings)
    assert model.planner.optimizer.options == ICEM_OPTIONS.__class__(
        **{**ICEM_OPTIONS.__dict__, "noise_beta": 0.25, "keep_elites": 0.5}
    )
    # the same from the command line's -params (rl-zoo3 evaluates each value)
    overrides = zoo.read_hyperparameters("poplin", "Pendulum-v1", hyperparams={"optimizer": "icem"})
    assert overrides["optimizer"] == "icem"


# ------------------------------------------------------------------------------------------------ the train command line
class _SetUp(Exception):
    """Raised by :func:`zoo_train` in place of rl-zoo3's set-up: the manager and the hyperparameters ``train`` would use."""


@pytest.fixture
def zoo_train(monkeypatch: pytest.MonkeyPatch) -> Callable[[list[str]], tuple[zoo.PoplinExperimentManager, dict]]:
    """``sb3-poplin-zoo train ARGS`` run in this process up to its hyperparameters: nothing is created or trained."""

    def setup_experiment(self: zoo.PoplinExperimentManager) -> None:
        hyperparams, _ = self.read_hyperparameters()
        raise _SetUp(self, hyperparams)

    monkeypatch.setattr(zoo.PoplinExperimentManager, "setup_experiment", setup_experiment)

    def train(args: list[str]) -> tuple[zoo.PoplinExperimentManager, dict]:
        with pytest.raises(_SetUp) as set_up:
            zoo.main(["train", "--seed", "0", "-f", os.devnull, *args])
        return set_up.value.args

    return train


@pytest.mark.parametrize(
    "spelling",
    [["-c", "{}"], ["-conf", "{}"], ["--conf-file", "{}"], ["--conf-file={}"], ["-conf={}"], ["--conf", "{}"], ["--c", "{}"]],
)
def test_every_conf_file_spelling_is_honoured(
    spelling: list[str], tmp_path: Path, zoo_train: Callable[[list[str]], tuple[zoo.PoplinExperimentManager, dict]]
) -> None:
    """rl-zoo3's -conf, --conf-file and what argparse takes for them (-c, --conf, ...): the file's entry, not poplin.yml."""
    entry = dict(presets.load_config(presets.config_path("poplin", "cpu"))["Pendulum-v1"], horizon=7)
    entry["env_kwargs"] = {"g": 9.0}
    conf = tmp_path / "mine.yml"
    conf.write_text(yaml.safe_dump({"Pendulum-v1": entry}))
    args = [part.format(conf) for part in spelling]
    manager, hyperparams = zoo_train(["--algo", "poplin", "--env", "Pendulum-v1", *args])
    assert manager.config == str(conf) and manager.args.conf_file == str(conf)  # args.yml names the file used
    assert hyperparams["horizon"] == 7 and hyperparams["env_kwargs"] == {"g": 9.0}
    assert manager.eval_env_kwargs == {"g": 9.0}


def test_packaged_conf_files_by_name(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    zoo_train: Callable[[list[str]], tuple[zoo.PoplinExperimentManager, dict]],
) -> None:
    """Outside the repository, poplin_cpu.yml and hyperparams/poplin_cpu.yml are the packaged file; a local file wins."""
    monkeypatch.chdir(tmp_path)
    packaged = str(presets.config_path("poplin", "cpu"))
    horizon = presets.load_config(packaged)["Pendulum-v1"]["horizon"]
    for name in ("poplin_cpu.yml", "hyperparams/poplin_cpu.yml"):
        manager, hyperparams = zoo_train(["--algo", "poplin", "--env", "Pendulum-v1", "--conf-file", name])
        assert manager.config == packaged and manager.args.conf_file == packaged and hyperparams["horizon"] == horizon
        assert zoo.read_hyperparameters("poplin", "Pendulum-v1", conf_file=name)["horizon"] == horizon
    manager, _ = zoo_train(["--algo", "sac", "--env", "Pendulum-v1", "-c", "sac.yml"])
    assert manager.config == str(presets.config_path("sac"))
    # a file of that name here wins
    (tmp_path / "hyperparams").mkdir()
    entry = dict(presets.load_config(packaged)["Pendulum-v1"], horizon=7)
    (tmp_path / "hyperparams" / "poplin_cpu.yml").write_text(yaml.safe_dump({"Pendulum-v1": entry}))
    manager, hyperparams = zoo_train(["--algo", "poplin", "--env", "Pendulum-v1", "--conf-file", "hyperparams/poplin_cpu.yml"])
    assert manager.config == "hyperparams/poplin_cpu.yml" and hyperparams["horizon"] == 7
    # neither here nor packaged: the problem and the fix
    with pytest.raises(FileNotFoundError, match=r"nothere\.yml.*packaged files.*poplin_cpu\.yml"):
        zoo_train(["--algo", "poplin", "--env", "Pendulum-v1", "--conf-file", "nothere.yml"])


def test_n_envs_with_the_packaged_episodic_train_freq(tmp_path: Path) -> None:
    """-params n_envs:2 with a packaged file (train_freq: [1, episode]): refit every episode length's worth of steps."""
    zoo_train = [sys.executable, "-m", "sb3_poplin.zoo", "train", "--algo", "poplin", "--env", "Pendulum-v1"]
    args = ["-n", "800", "--num-threads", "1", "--seed", "0", "-f", "logs", "--eval-freq", "-1"]
    process = run([*zoo_train, *args, "-params", "n_envs:2", *TINY_POPLIN], tmp_path)
    assert "train_freq [1, 'episode'] with n_envs 2" in process.stdout and "[200, 'step']" in process.stdout
    run_dir = tmp_path / "logs" / "poplin" / "Pendulum-v1_1"
    assert (run_dir / "Pendulum-v1.zip").is_file()
    assert dict(load_yaml(run_dir / "Pendulum-v1" / "config.yml"))["train_freq"] == [200, "step"]


def test_n_envs_train_freq_is_adapted_or_refused() -> None:
    """The file's episodic train_freq becomes steps with several envs; an episodic one asked for on -params is refused."""
    hyperparams = zoo.read_hyperparameters("poplin", "Pendulum-v1", hyperparams={"n_envs": 2})
    assert hyperparams["train_freq"] == [200, "step"]
    hyperparams = zoo.read_hyperparameters("poplin", "Pendulum-v1", hyperparams={"n_envs": 2, "train_freq": 50})
    assert hyperparams["train_freq"] == 50
    assert zoo.read_hyperparameters("poplin", "Pendulum-v1")["train_freq"] == [1, "episode"]
    with pytest.raises(ValueError, match=r"train_freq.*one env.*train_freq:\"\(200, 'step'\)\""):
        zoo.read_hyperparameters("poplin", "Pendulum-v1", hyperparams={"n_envs": 2, "train_freq": (1, "episode")})


def test_params_take_bare_strings_for_string_settings(
    zoo_train: Callable[[list[str]], tuple[zoo.PoplinExperimentManager, dict]], capsys: pytest.CaptureFixture[str]
) -> None:
    """-params policy:poplin-a needs no nested quotes; Python values still parse as rl-zoo3 evaluates them."""
    params = ["policy:poplin-a", "proposal:replan", "propagation:ts1", "optimizer:icem", "device:cpu"]
    params += ["horizon:30", "dynamics_net_arch:[64,64]", "distillation:None", "noise:'sep'", "cem_alpha:0.2"]
    _, hyperparams = zoo_train(["--algo", "poplin", "--env", "Pendulum-v1", "-params", *params])
    assert hyperparams["policy"] == "poplin-a" and hyperparams["proposal"] == "replan" and hyperparams["device"] == "cpu"
    assert hyperparams["propagation"] == "ts1" and hyperparams["optimizer"] == "icem" and hyperparams["noise"] == "sep"
    assert hyperparams["horizon"] == 30 and hyperparams["dynamics_net_arch"] == [64, 64] and hyperparams["cem_alpha"] == 0.2
    assert hyperparams["distillation"] is None
    assert set(zoo.STRING_SETTINGS) <= set(inspect.signature(POPLIN.__init__).parameters)
    # a word where a Python value is needed: the setting, the value and the fix, not a NameError
    with pytest.raises(SystemExit):
        zoo.main(["train", "--algo", "poplin", "--env", "Pendulum-v1", "-params", "horizon:thirty"])
    error = capsys.readouterr().err
    assert "horizon:thirty" in error and "not a Python value" in error and "horizon:\"'thirty'\"" in error


def test_makefile_torch_index(tmp_path: Path) -> None:
    """make install TORCH_INDEX=URL installs torch from that index (only torch); the default install is unchanged."""
    if shutil.which("make") is None:
        pytest.skip("make is not installed")
    root = Path(__file__).resolve().parents[1]

    def install_commands(*variables: str) -> list[str]:
        dry_run = ["make", "-n", "-B", "install", f"VENV={tmp_path / 'venv'}", *variables]
        process = subprocess.run(dry_run, cwd=root, capture_output=True, text=True, check=True)
        return [line for line in process.stdout.splitlines() if "pip install" in line and "--upgrade pip" not in line]

    default = install_commands()
    assert len(default) == 2 and "torch==2.13.0" in default[0] and all("--index-url" not in line for line in default)
    cpu = "https://download.pytorch.org/whl/cpu"
    torch_line, package_line = install_commands(f"TORCH_INDEX={cpu}")
    assert f"--index-url {cpu}" in torch_line and "torch==2.13.0" in torch_line
    assert "--index-url" not in package_line and package_line == default[1]
