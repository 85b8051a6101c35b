"""
The head-to-head command ``sb3-poplin-zoo compare`` (``sb3_poplin.experiments.compare``): planning the runs, the report, local
and Ray execution, and resuming: complete runs are reused, killed runs continue from their last checkpoint.
"""

from __future__ import annotations

import fcntl
import io
import json
import os
import signal
import subprocess
import sys
import time
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch as th
import yaml

from sb3_poplin.experiments import compare as compare_module
from sb3_poplin.experiments import checkpoints as resume
from test_zoo import TINY_POPLIN, run


# ------------------------------------------------------------------------------------------------ compare.py
def compare(tmp_path: Path, *extra: str) -> tuple[dict, str]:
    params = [f"poplin:{setting}" for setting in TINY_POPLIN]
    args = ["--algos", "poplin", "sac", "--envs", "Pendulum-v1", "-n", "400", "--n-evals", "2", "--eval-episodes", "2"]
    args += ["--log-folder", str(tmp_path / "logs"), "--output", str(tmp_path / "report"), "--params", *params, *extra]
    process = run([sys.executable, "-m", "sb3_poplin.zoo", "compare", *args], tmp_path, timeout=900)
    assert (tmp_path / "report" / "curves_Pendulum-v1.png").stat().st_size > 0
    table = (tmp_path / "report" / "results.md").read_text()
    assert "| Pendulum-v1 | 400 |" in table and "POPLIN-P (policy)" in table and "SAC" in table
    return json.loads((tmp_path / "report" / "results.json").read_text()), process.stdout


@pytest.mark.slow
@pytest.mark.timeout(2 * 900 + 120)  # two compare calls, each up to its 900 s limit
def test_compare_locally(tmp_path: Path) -> None:
    results, output = compare(tmp_path, "--seeds", "0", "1", "--jobs", "2")
    assert output.count("[done]") == 4
    labels = results["tasks"][0]["labels"]
    assert sorted(labels) == ["POPLIN-P (MPC)", "POPLIN-P (policy)", "SAC"]
    assert all(len(entry["final"]) == 2 for entry in labels.values())
    # a second call finds the complete runs and trains nothing
    again, output = compare(tmp_path, "--seeds", "0", "1", "--jobs", "2")
    assert output.count("[reused]") == 4 and again["tasks"] == results["tasks"]


def test_compare_through_local_ray(tmp_path: Path) -> None:
    results, output = compare(tmp_path, "--seeds", "0", "--jobs", "2", "--ray-address", "local")
    assert output.count("[done]") == 2
    assert all(run["returncode"] == 0 and run["run_dir"] for run in results["runs"])


def test_local_ray_workers_run_at_the_callers_priority(monkeypatch: pytest.MonkeyPatch) -> None:
    # Ray's workers default to niceness 15: on a loaded machine the runs of --ray-address local starved (a 600 s timeout)
    ray = pytest.importorskip("ray")
    from sb3_poplin.experiments.compare.execution import RAY_NICENESS, start_local_ray

    def worker_niceness() -> int:
        return os.nice(0)

    for given, expected in [(None, os.nice(0)), ("7", os.nice(0) + 7)]:
        if given is None:
            monkeypatch.delenv(RAY_NICENESS, raising=False)
        else:
            monkeypatch.setenv(RAY_NICENESS, given)
        start_local_ray(ray, 1)
        try:
            assert ray.get(ray.remote(worker_niceness).remote()) == expected
        finally:
            ray.shutdown()
        assert os.environ.get(RAY_NICENESS) == given  # the caller's environment as it was


def test_compare_runs_poplin_variants_by_name(tmp_path: Path) -> None:
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
    # Pendulum-v1's 200-step episodes: 10 evaluation episodes by default (the rule for short episodes)
    assert jobs["pets"].eval_episodes == 10
    args = {"algo": "poplin", "env": "Pendulum-v1", "seed": 0, "n_timesteps": 400, "eval_freq": 40, "eval_episodes": 10}
    args |= {"conf_file": jobs["pets"].conf_file, "hyperparams": {"policy": "pets", "horizon": 5}}
    assert jobs["pets"].matches(args) and not jobs["poplin-a"].matches(args)
    assert not jobs["pets"].matches(args | {"hyperparams": {"policy": "pets", "horizon": 5, "seed": 1}})  # one more setting
    # rl-zoo3 adds use_sde to a policy_kwargs dict it was given: still the run of that job, unless a value differs
    kwargs = {**args, "hyperparams": {"policy_kwargs": {"net_arch": [16, 16], "use_sde": False}}}
    sac = compare_module.Job("sac", "Pendulum-v1", 0, 400, 40, 10, None, ["policy_kwargs:dict(net_arch=[16, 16])"], "", "")
    assert sac.matches(kwargs | {"algo": "sac", "conf_file": None})
    other = {**kwargs, "algo": "sac", "conf_file": None, "hyperparams": {"policy_kwargs": {"net_arch": [8], "use_sde": False}}}
    assert not sac.matches(other)
    # a run committed from another checkout (its args.yml names that checkout's packaged file) is the same run
    moved = str(
        Path("/elsewhere/checkout") / Path(jobs["pets"].conf_file).relative_to(Path(jobs["pets"].conf_file).parents[2])
    )
    assert jobs["pets"].matches(args | {"conf_file": moved})
    assert not jobs["pets"].matches(args | {"conf_file": "/elsewhere/checkout/sb3_poplin/hyperparams/other.yml"})


def test_policy_control_is_evaluated_at_its_own_period_and_seeds_run_paired(tmp_path: Path) -> None:
    """
    ``--policy-eval-freq`` reaches the POPLIN runs' command and identifies their runs (a run made without it, or with
    another period, is another run); runs start seed by seed, every algorithm of a seed together.
    """
    args = ["--algos", "pets", "poplin-p", "sac", "--envs", "Pendulum-v1", "--seeds", "0", "1", "-n", "4000"]
    options = compare_module.parse_args([*args, "--eval-freq", "2000", "--policy-eval-freq", "500", "--log-folder", "x"])
    jobs = compare_module.plan_jobs(options)
    poplin_p = next(job for job in jobs if job.algo == "poplin-p")
    command = poplin_p.command()
    assert command[command.index("--policy-eval-freq") + 1] == "500"
    assert command[command.index("--eval-freq") + 1] == "2000"
    sac = next(job for job in jobs if job.algo == "sac")
    assert sac.policy_eval_freq is None and "--policy-eval-freq" not in sac.command()
    recorded = {"algo": "poplin", "env": "Pendulum-v1", "seed": 0, "n_timesteps": 4000, "eval_freq": 2000}
    recorded |= {"eval_episodes": 10, "conf_file": poplin_p.conf_file, "hyperparams": {"policy": "poplin-p"}}
    assert poplin_p.matches(recorded | {"policy_eval_freq": 500})
    assert not poplin_p.matches(recorded) and not poplin_p.matches(recorded | {"policy_eval_freq": 1000})
    order = [(jobs[index].algo, jobs[index].seed) for index in compare_module.execution_order(jobs)]
    assert order == [("pets", 0), ("poplin-p", 0), ("sac", 0), ("pets", 1), ("poplin-p", 1), ("sac", 1)]
    with pytest.raises(SystemExit):
        compare_module.parse_args([*args, "--policy-eval-freq", "0"])


def write_fake_run(job, run_dir: Path, eval_returns: list[float], train_returns: list[float], episode: int) -> None:
    """A run folder as the zoo and compare.py leave it (no model zip): args, config, evaluations, monitor, marker."""
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
    table = compare_module.write_report(results, options.tasks(), "cpu", tmp_path / "report", reference="PETS (MPC)")
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
    # the paper's protocol along training (--protocol-steps): the window means by hand; PETS ended at 3000
    assert compare_module.parse_args([*common, "--protocol-steps", "3000", "6000", "9000"]).protocol_steps == [
        3000,
        6000,
        9000,
    ]
    steps = [3000, 4000, 6000, 9000]
    table = compare_module.write_report(results, options.tasks(), "cpu", tmp_path / "along", protocol_steps=steps)
    task = json.loads((tmp_path / "along" / "results.json").read_text())["tasks"][0]
    along = {entry["step"]: entry["labels"] for entry in task["paper_protocol_at"]}
    assert along[3000]["PETS"]["values"] == pytest.approx([-200, -440 / 3])
    assert along[6000]["SAC"]["values"] == pytest.approx([-150, -200]) and "PETS" not in along[6000]
    # past the end of PETS's runs (3000 steps) they have no value, though their last episodes are in the window
    assert along[4000]["SAC"]["values"] == pytest.approx([-250, -280]) and "PETS" not in along[4000]
    assert along[9000]["SAC"] == {"seeds": [0, 1], "values": [0.0, -80.0], "mean": -40.0, "std": 40.0}
    # the training figure's thick line: the mean over seeds of the window means (SAC at 6000: -150 and -200)
    sac = [compare_module.load_training(result) for result in results if result.job.algo == "sac"]
    curve = compare_module.training_curve(sac, np.array([1000, 6000, 9000]), 3000)
    assert curve == pytest.approx([(-350 - 360) / 2, -175, -40])
    assert (tmp_path / "along" / "training_Pendulum-v1.png").stat().st_size > 0
    text = table.read_text()
    assert "| Pendulum-v1 | 6000 | — | -175.0 ± 25.0 (s0: -150, s1: -200) |" in text
    assert "| Pendulum-v1 | 9000 | — | -40.0 ± 40.0 (s0: 0, s1: -80) |" in text
    with pytest.raises(SystemExit):
        compare_module.parse_args([*common, "--protocol-steps", "0"])
    # a run folder without the marker and without the model zip is an unfinished run
    for path in tmp_path.glob(f"*/*/{compare_module.COMPLETE_FILE}"):
        path.unlink()
    assert compare_module.find_run(jobs[0]) is None
    with pytest.raises(SystemExit, match=r"--steps-scale takes ALGO:FACTOR .* got 'td3:3'"):
        compare_module.plan_jobs(compare_module.parse_args([*common, "--steps-scale", "td3:3"]))
    with pytest.raises(SystemExit, match=r"got 'sac:three'"):
        compare_module.plan_jobs(compare_module.parse_args([*common, "--steps-scale", "sac:three"]))


def test_report_only_labels_runs_not_made_yet_missing_and_not_failed(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Seeds 0-1 finished, seed 2 never started: ``--report-only`` reports two seeds and one missing run."""
    common = ["--algos", "pets", "--envs", "Pendulum-v1", "-n", "2000", "--n-evals", "2", "--log-folder", str(tmp_path)]
    for job in compare_module.plan_jobs(compare_module.parse_args([*common, "--seeds", "0", "1"])):
        run_dir = tmp_path / job.zoo_algo / f"Pendulum-v1_{job.seed + 1}_{job.algo}"
        write_fake_run(job, run_dir, [-100.0, 10.0 * (job.seed + 1)], [-300.0, -200.0], 1000)
    argv = [*common, "--seeds", "0", "1", "2", "--report-only", "--output", str(tmp_path / "report")]
    assert compare_module.main(argv) == 1
    output = capsys.readouterr().out
    assert "1 of 3 runs are missing" in output and "failed" not in output
    table = (tmp_path / "report" / "results.md").read_text()
    assert "| Pendulum-v1 | 2000 | 15.0 ± 5.0 (2 seeds, 1 missing) |" in table and "failed" not in table
    task = json.loads((tmp_path / "report" / "results.json").read_text())["tasks"][0]
    assert task["missing"] == {"pets": 1} and task["failed"] == {}
    # a run that was started and failed is still a failure
    job = compare_module.plan_jobs(compare_module.parse_args([*common, "--seeds", "2"]))[0]
    protocol = compare_module.ProtocolSummary(2000, 3000)
    summary = compare_module.TaskSummary("Pendulum-v1", 0, {}, {"pets": 1}, {"pets": 1}, {}, protocol)
    assert compare_module.format_cell(summary, "PETS (MPC)", job.column) == "failed (1/1)"
    summary = compare_module.TaskSummary("Pendulum-v1", 0, {}, {}, {"pets": 1}, {"pets": 1}, protocol)
    assert compare_module.format_cell(summary, "PETS (MPC)", job.column) == "missing (1/1)"


def test_report_only_includes_unfinished_runs_as_far_as_they_got(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Seeds 0-1 finished at 2000 steps; seed 2 was interrupted at 2000, seed 3 after its first episode."""
    common = ["--algos", "pets", "--envs", "Pendulum-v1", "-n", "2000", "--n-evals", "2", "--log-folder", str(tmp_path)]
    seeds = ["--seeds", "0", "1", "2", "3"]
    for job in compare_module.plan_jobs(compare_module.parse_args([*common, *seeds])):
        run_dir = tmp_path / job.zoo_algo / f"Pendulum-v1_{job.seed + 1}_{job.algo}"
        if job.seed < 3:
            write_fake_run(job, run_dir, [-100.0, 10.0 * (job.seed + 1)], [-300.0, -200.0 + 50 * (job.seed == 2)], 1000)
        else:
            write_fake_run(job, run_dir, [-50.0], [-250.0], 1000)
        if job.seed >= 2:
            (run_dir / compare_module.COMPLETE_FILE).unlink()  # interrupted
    report = tmp_path / "report"
    argv = [*common, *seeds, "--report-only", "--output", str(report)]
    assert compare_module.main([*argv, "--include-unfinished"]) == 0
    assert "2 of 4 runs are unfinished" in capsys.readouterr().out
    table = (report / "results.md").read_text()
    # the matched step is the complete runs' (2000): seed 2 reached it (30), seed 3 did not and has no value there
    assert "| Pendulum-v1 | 2000 | 20.0 ± 8.2 (3 seeds, 1 unfinished, 1 not at 2000 yet) |" in table
    assert "| Pendulum-v1 | PETS | 2 | 2000 |" in table and "| Pendulum-v1 | PETS | 3 | 1000 |" in table
    results = json.loads((report / "results.json").read_text())
    task = results["tasks"][0]
    assert task["unfinished"] == {"PETS (MPC)": 1} and task["short"] == {"PETS (MPC)": 1}
    assert task["interrupted"] == {"pets": 2}
    assert [run.get("unfinished", False) for run in results["runs"]] == [False, False, True, True]
    # the paper's protocol at the budget (2000) leaves out seed 3, which stopped at 1000 steps
    assert task["paper_protocol"]["labels"]["PETS"]["seeds"] == [0, 1, 2]
    assert task["paper_protocol"]["labels"]["PETS"]["values"] == pytest.approx([-250, -250, -225])
    # without the option the interrupted runs are missing
    assert compare_module.main(argv) == 1
    assert "2 of 4 runs are missing" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        compare_module.parse_args([*common, "--include-unfinished"])


def test_the_report_counts_each_runs_time_without_its_interruptions(tmp_path: Path) -> None:
    """The run time of a resumed run: its monitor keeps its start, so the time it was stopped is inside one episode,
    which counts at the run's median; an uninterrupted run's time is its monitor's last time."""
    common = ["--algos", "pets", "--envs", "Pendulum-v1", "--seeds", "0", "1", "-n", "5000", "--n-evals", "5"]
    jobs = compare_module.plan_jobs(compare_module.parse_args([*common, "--log-folder", str(tmp_path)]))
    end_times = {0: [100.0, 210.0, 300.0, 7500.0, 7600.0], 1: [90.0, 200.0, 310.0, 420.0, 530.0]}
    results = []
    for job in jobs:
        run_dir = tmp_path / job.zoo_algo / f"Pendulum-v1_{job.seed + 1}_{job.algo}"
        write_fake_run(job, run_dir, [0.0] * 5, [-100.0] * 5, 1000)
        lines = ["#" + json.dumps({"t_start": 0, "env_id": job.env}), "r,l,t"]
        lines += [f"-100.0,1000,{t}" for t in end_times[job.seed]]
        (run_dir / "0.monitor.csv").write_text("\n".join(lines) + "\n")
        results.append(compare_module.JobResult(job, 0, str(run_dir.relative_to(tmp_path)), reused=True))
    episodes = compare_module.load_training(results[0])
    # durations 100, 110, 90, 7200 (stopped inside), 100: median 100; 7200 > 3 x 100 counts as 100
    assert episodes.run_time() == (pytest.approx(500.0), 1)
    assert episodes.run_time(gap=100.0) == (pytest.approx(7600.0), 0)
    table = compare_module.write_report(results, ["Pendulum-v1"], "cpu", tmp_path / "report").read_text()
    assert "| Pendulum-v1 | PETS | 0 | 5 | 0.14 | 1 | 2.11 |" in table
    assert "| Pendulum-v1 | PETS | 1 | 5 | 0.15 | 0 | 0.15 |" in table
    assert "All 2 runs: 0.29 hours of run time." in table
    runs = json.loads((tmp_path / "report" / "results.json").read_text())["runs"]
    assert [(run["run_time_s"], run["interrupted_episodes"]) for run in runs] == [(500.0, 1), (530.0, 0)]


def test_the_interrupted_run_to_continue_is_the_furthest_one(tmp_path: Path) -> None:
    """The newest checkpoint wins; without checkpoints (a synced copy) the most training episodes, then the newest."""
    import os

    common = ["--algos", "pets", "--envs", "Pendulum-v1", "-n", "5000", "--seeds", "0", "--log-folder", str(tmp_path)]
    job = compare_module.plan_jobs(compare_module.parse_args(common))[0]
    runs = {}
    for name, episodes, mtime in (("ahead", 4, 100.0), ("behind", 2, 200.0)):
        run_dir = tmp_path / job.zoo_algo / f"Pendulum-v1_{name}"
        write_fake_run(job, run_dir, [-100.0], [-300.0] * episodes, 1000)
        (run_dir / compare_module.COMPLETE_FILE).unlink()
        os.utime(run_dir / job.env / "args.yml", (mtime, mtime))
        os.utime(run_dir, (mtime, mtime))
        runs[name] = str(run_dir.relative_to(tmp_path))
    assert compare_module.find_interrupted(job) == runs["ahead"]  # 4 episodes against 2, though older
    step = tmp_path / runs["behind"] / "checkpoints" / "step-2000"
    step.mkdir(parents=True)
    for name in ("model.zip", "replay_buffer.npz", "state.pt"):
        (step / name).write_bytes(b"x")
    assert compare_module.find_interrupted(job) == runs["behind"]  # a checkpoint to resume from beats none


def test_the_reach_tables_last_step_is_the_last_one_the_mean_covers() -> None:
    """With a seed that stopped at 2000 steps, the mean over seeds is undefined after it: "not by" says 2000."""
    curve = compare_module.Curve("PETS (MPC)", 0, np.array([1000, 2000]), np.array([10.0, 20.0]))
    done = compare_module.TrainingEpisodes(
        "PETS", 0, np.array([1000, 2000, 3000, 4000]), np.array([-40.0, -30, -20, -10]), 4000
    )
    stopped = compare_module.TrainingEpisodes("PETS", 1, np.array([1000, 2000]), np.array([-40.0, -30]), 2000)
    summary = compare_module.summarize(
        "Pendulum-v1", [curve], {}, {}, [done, stopped], budget_step=4000, reference="PETS (MPC)"
    )
    assert summary.reach is not None and summary.reach.paper_target == pytest.approx(-20)  # seed 0 alone at 4000
    entry = summary.reach.paper_protocol["PETS"]  # the mean: -40, -35, then undefined
    assert entry.step is None and entry.last_step == 2000 and entry.per_seed == {"0": 4000, "1": None}
    # seed 1 did not reach it by 2000, where it stopped: not "never"
    assert entry.short == {"1": 2000} and entry.to_json()["short"] == {"1": 2000}
    assert compare_module.report._reach_cell(entry) == "not by 2000 (s0: 4000, s1: not by 2000)"
    assert "short" not in summary.reach.evaluation["PETS (MPC)"].to_json()  # one seed: none shorter
    # one seed has no spread to show; the cell of a column whose one unfinished run is short of the matched step
    protocol = summary.paper_protocol.labels["PETS"]
    assert protocol.seeds == [0] and compare_module.report._mean_cell(protocol) == "-20.0 (1 seed)"
    assert compare_module.report._seeds_cell(protocol) == "-20.0 (s0: -20)"
    # (seed 1 interrupted before its first evaluation: it has no curve at all)
    summary = compare_module.summarize("Pendulum-v1", [curve], {}, {"pets": 4}, missing={"pets": 2}, interrupted={"pets": 1})
    assert summary.matched_step == 2000 and summary.short("PETS (MPC)") == 1
    assert compare_module.format_cell(summary, "PETS (MPC)", "pets") == "20.0 (1 seed, 2 missing, 1 not at 2000 yet)"
    assert summary.to_json()["short"] == {"PETS (MPC)": 1}


def test_an_unfinished_run_does_not_lower_the_matched_step() -> None:
    """An unfinished run's early policy evaluations do not move the matched step below the complete runs' schedule."""
    complete = [
        compare_module.Curve("PETS (MPC)", 0, np.array([25000, 50000]), np.array([100.0, 200.0])),
        compare_module.Curve("POPLIN-P (MPC)", 0, np.array([25000, 50000]), np.array([300.0, 400.0])),
    ]
    early = compare_module.Curve("POPLIN-P (policy)", 1, np.array([5000, 10000]), np.array([-1.0, -2.0]), unfinished=True)
    summary = compare_module.summarize("Pendulum-v1", [*complete, early], {}, {}, reference="POPLIN-P (MPC)")
    assert summary.matched_step == 50000
    assert summary.labels["PETS (MPC)"].values == [200.0] and "POPLIN-P (policy)" not in summary.labels
    assert summary.unfinished == {}
    assert compare_module.format_cell(summary, "POPLIN-P (MPC)", "poplin-p") == "400.0 (1 seed)"


def test_compare_plans_and_reports_the_paper_suite(tmp_path: Path) -> None:
    from sb3_poplin.tasks.paper_suite import PAPER_TASKS

    common = ["--algos", "poplin", "sac", "--seeds", "0", "-n", "400", "--log-folder", str(tmp_path)]
    options = compare_module.parse_args(["--suite", "paper", *common])
    jobs = compare_module.plan_jobs(options)
    assert options.tasks() == [task.env_id for task in PAPER_TASKS.values()] and options.envs is None  # not mutated
    assert [job.env for job in jobs[::2]] == options.tasks() and {job.algo for job in jobs} == {"poplin", "sac"}
    assert options.paper_names["sb3_poplin/MBBLCartpole-v0"] == "Cartpole"
    # a report of runs that do not exist: every cell is a failure, the columns are the paper's names in its order
    results = [compare_module.JobResult(job, 1) for job in jobs]
    table = compare_module.write_report(results, options.tasks(), "cpu", tmp_path / "report", options.paper_names)
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
@pytest.mark.timeout(3600 + 120)  # the compare call's own limit
def test_compare_runs_the_paper_suite(tmp_path: Path) -> None:
    from sb3_poplin.tasks.paper_suite import PAPER_TASKS

    params = [f"poplin:{setting}" for setting in TINY_POPLIN]
    args = ["--suite", "paper", "--algos", "poplin", "sac", "--seeds", "0", "-n", "400", "--n-evals", "1"]
    args += ["--eval-episodes", "2", "--log-folder", str(tmp_path / "logs"), "--output", str(tmp_path / "report")]
    run([sys.executable, "-m", "sb3_poplin.zoo", "compare", *args, "--params", *params], tmp_path, timeout=3600)
    table = (tmp_path / "report" / "results.md").read_text()
    assert "| | " + " | ".join(PAPER_TASKS) + " |" in table and "failed" not in table
    assert "| SAC |" in table and "| POPLIN-P (MPC) |" in table
    results = json.loads((tmp_path / "report" / "results.json").read_text())
    assert results["suite"] == "paper" and [task["name"] for task in results["tasks"]] == list(PAPER_TASKS)


def test_evaluation_episodes_follow_the_short_episode_rule(capsys: pytest.CaptureFixture[str]) -> None:
    assert compare_module.evaluation_episodes("Pendulum-v1", None, "cpu") == 10  # 200-step episodes
    assert compare_module.evaluation_episodes("HalfCheetah-v5", None, "cpu") == 3  # 1000-step episodes
    assert compare_module.evaluation_episodes("HalfCheetah-v5", None, "paper") == 5
    assert capsys.readouterr().out == ""
    assert compare_module.evaluation_episodes("Pendulum-v1", 2, "cpu") == 2  # given: kept, with a warning
    assert "use --eval-episodes 10 or more" in capsys.readouterr().out
    assert compare_module.evaluation_episodes("HalfCheetah-v5", 2, "cpu") == 2
    assert capsys.readouterr().out == ""


# ------------------------------------------------------------------------------------------------ killed and resumed
RESUME_PARAMS = {
    "poplin-p": [f"poplin-p:{setting}" for setting in TINY_POPLIN if not setting.startswith("cem_iterations")],
    "sac": ["sac:learning_starts:100", "sac:buffer_size:1000", "sac:policy_kwargs:dict(net_arch=[16, 16])"],
}


def resume_command(folder: Path, algo: str) -> list[str]:
    """A tiny comparison of one run (3 episodes of Pendulum-v1, an evaluation after each), logs in ``folder``."""
    args = ["--algos", algo, "--envs", "Pendulum-v1", "--seeds", "0", "-n", "600", "--eval-freq", "200"]
    args += ["--eval-episodes", "2", "--jobs", "1", "--log-folder", str(folder / "logs"), "--output", str(folder / "report")]
    return [sys.executable, "-m", "sb3_poplin.zoo", "compare", *args, "--params", *RESUME_PARAMS[algo]]


def run_folders(folder: Path, algo: str) -> list[Path]:
    return sorted((folder / "logs" / ("sac" if algo == "sac" else "poplin")).glob("Pendulum-v1_*"))


def kill_when(folder: Path, algo: str, ready: str, delay: float) -> bool:
    """
    Start the comparison, wait for ``ready`` (``"started"``: the comparison would find the run to continue, its settings
    ``args.yml`` complete; ``"checkpoint"``: its first checkpoint exists), ``delay`` seconds more, then ``kill -9`` the
    comparison (only its process: its run must die with it).

    :return: whether the kill came where asked: ``"started"`` needs a run killed before its first checkpoint, which a
        loaded machine can miss by starting the poll late (the caller then tries again)
    """
    (job,) = compare_module.plan_jobs(compare_module.parse_args(resume_command(folder, algo)[4:]))
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    process = subprocess.Popen(resume_command(folder, algo), env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and process.poll() is None:
        runs = run_folders(folder, algo)
        # not the mere existence of args.yml: rl-zoo3 creates it empty and fills it a few milliseconds later, and a run
        # killed in between cannot be found again (its comparison starts a new folder)
        if runs and (resume.latest_checkpoint(runs[0]) if ready == "checkpoint" else compare_module.job_runs(job)):
            break
        time.sleep(0.02)
    time.sleep(delay)
    assert process.poll() is None, "the run finished before it could be killed"
    os.kill(process.pid, signal.SIGKILL)
    process.wait()
    (run_dir,) = run_folders(folder, algo)
    assert not (run_dir / compare_module.COMPLETE_FILE).exists() and not (run_dir / "Pendulum-v1.zip").exists()
    # the run's own process died with the comparison: its folder's lock is free at once
    deadline = time.monotonic() + 10
    while True:
        with open(run_dir / resume.LOCK_FILE, "a+") as lock:
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except OSError:
                assert time.monotonic() < deadline, "the killed comparison left its run training"
        time.sleep(0.1)
    return ready == "checkpoint" or resume.latest_checkpoint(run_dir) is None


def run_files(run_dir: Path) -> dict[str, object]:
    """What a finished run recorded: evaluations (both control modes), training episodes (no wall times), networks."""
    files: dict[str, object] = {}
    for path in sorted(run_dir.glob("evaluations*.npz")):
        with np.load(path) as data:
            files |= {f"{path.name}:{key}": data[key].tolist() for key in data.files}
    rows = (run_dir / "0.monitor.csv").read_text().splitlines()
    files["monitor"] = [row.rsplit(",", 1)[0] for row in rows[1:]]  # r, l (t is wall time)
    with zipfile.ZipFile(run_dir / "Pendulum-v1.zip") as archive:
        for member in sorted(name for name in archive.namelist() if name.endswith(".pth")):  # networks, optimizers
            state = th.load(io.BytesIO(archive.read(member)), weights_only=False)
            files[member] = {key: value.tolist() for key, value in flat_tensors(state).items()}
    return files


def flat_tensors(state: object, prefix: str = "") -> dict[str, th.Tensor]:
    if isinstance(state, th.Tensor):
        return {prefix: state}
    items = state.items() if isinstance(state, dict) else enumerate(state) if isinstance(state, (list, tuple)) else []
    found: dict[str, th.Tensor] = {}
    for key, value in items:
        found |= flat_tensors(value, f"{prefix}/{key}")
    return found


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory: pytest.TempPathFactory) -> Callable[[str], dict[str, object]]:
    """The files of an uninterrupted run of an algorithm (made once per module)."""
    made: dict[str, dict[str, object]] = {}

    def files_of(algo: str) -> dict[str, object]:
        if algo not in made:
            folder = tmp_path_factory.mktemp(f"uninterrupted-{algo}")
            run(resume_command(folder, algo), folder, timeout=600)
            (run_dir,) = run_folders(folder, algo)
            assert not (run_dir / resume.CHECKPOINT_FOLDER).exists()  # a finished run drops its checkpoints
            made[algo] = run_files(run_dir)
            assert len(made[algo]["monitor"]) == 1 + 3 and len(made[algo]["evaluations.npz:timesteps"]) == 3
        return made[algo]

    return files_of


@pytest.mark.parametrize(
    ("algo", "ready", "delay"), [("poplin-p", "checkpoint", 0.4), ("poplin-p", "started", 0.0), ("sac", "checkpoint", 0.3)]
)
def test_a_killed_run_resumes_to_the_files_of_an_uninterrupted_one(
    uninterrupted: Callable[[str], dict[str, object]], tmp_path: Path, algo: str, ready: str, delay: float
) -> None:
    """
    ``kill -9`` in the second episode (after the first checkpoint), or before any checkpoint; the same command then
    continues the run in its folder and finishes it with exactly the uninterrupted run's evaluations, training
    episodes, networks and optimizers: nothing recorded twice, nothing lost. POPLIN-P (planner, distiller) and SAC.
    """
    for attempt in range(3):  # a run killed after its first checkpoint when asked for one killed before: again
        folder = tmp_path / f"attempt-{attempt}"
        if kill_when(folder, algo, ready, delay):
            break
    else:
        pytest.fail("the run reached its first checkpoint before it could be killed, three times")
    (run_dir,) = run_folders(folder, algo)
    settings = run_dir / "Pendulum-v1" / "args.yml"
    written = settings.stat().st_mtime_ns
    checkpoint = resume.latest_checkpoint(run_dir)
    assert (checkpoint is not None) == (ready == "checkpoint")
    process = run(resume_command(folder, algo), folder, timeout=600)
    assert f"[resumed] {algo}_Pendulum-v1_seed0" in process.stdout
    assert run_folders(folder, algo) == [run_dir]  # continued in place, no second folder
    log = (folder / "logs" / "compare_logs" / f"{algo}_Pendulum-v1_seed0.log").read_text()
    if checkpoint is not None:
        assert f"from {checkpoint.name}" in log
    else:
        assert "it has no checkpoint" in log
    assert run_files(run_dir) == uninterrupted(algo)
    assert not (run_dir / resume.CHECKPOINT_FOLDER).exists()
    assert settings.stat().st_mtime_ns == written  # the run's identity is never rewritten (a kill could truncate it)


def test_a_checkpoint_counts_only_once_complete_and_a_finished_run_stays_finished(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    step = tmp_path / resume.CHECKPOINT_FOLDER / "step-200"
    step.mkdir(parents=True)
    (step / "state.pt").write_bytes(b"")
    assert resume.latest_checkpoint(tmp_path) is None  # killed while its files were written or deleted
    for name in ("model.zip", "replay_buffer.npz"):
        (step / name).write_bytes(b"")
    (tmp_path / resume.CHECKPOINT_FOLDER / "step-400.tmp").mkdir()
    assert resume.latest_checkpoint(tmp_path) == step
    (tmp_path / "Pendulum-v1.zip").write_bytes(b"")
    np.savez(tmp_path / "evaluations.npz", timesteps=[200])
    assert not compare_module.is_complete(tmp_path, "Pendulum-v1")  # model saved, checkpoints still there

    def killed(*args: object, **kwargs: object) -> None:
        raise RuntimeError("killed while deleting the checkpoints")

    monkeypatch.setattr(resume.shutil, "rmtree", killed)
    with pytest.raises(RuntimeError, match="killed"):
        resume.drop_checkpoints(tmp_path)
    assert compare_module.is_complete(tmp_path, "Pendulum-v1")  # finished, whatever was left of the checkpoints
    monkeypatch.undo()
    resume.drop_checkpoints(tmp_path)
    assert sorted(path.name for path in tmp_path.iterdir()) == ["Pendulum-v1.zip", "checkpoints.finished", "evaluations.npz"]


def test_checkpoints_follow_episodes_that_end_a_rollout(tmp_path: Path) -> None:
    callback = resume.EpisodeCheckpointCallback(tmp_path, [])
    for dones, ended in [([False], False), ([True], True), ([False], False), ([True], True)]:
        callback.locals = {"dones": np.array(dones)}
        callback._on_step()
        assert callback._episode_ended is ended  # a rollout that ran past an episode's end is mid-episode
    callback.locals = {"dones": np.array([False])}
    callback._on_step()
    callback._on_rollout_start()  # mid-episode: nothing saved (no model to save would raise)
    assert not (tmp_path / resume.CHECKPOINT_FOLDER).exists()


def test_a_finished_run_is_marked_when_reused_and_unreadable_settings_are_skipped(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    options = compare_module.parse_args(["--algos", "pets", "--envs", "Pendulum-v1", "--seeds", "0", "-n", "400"])
    options.log_folder = str(tmp_path)
    (job,) = compare_module.plan_jobs(options)
    run_dir = tmp_path / "poplin" / "Pendulum-v1_1_done"
    write_fake_run(job, run_dir, [-500.0], [-900.0, -700.0], 200)
    (run_dir / compare_module.COMPLETE_FILE).unlink()  # finished (its model saved), the comparison killed before marking
    (run_dir / "Pendulum-v1.zip").write_bytes(b"")
    broken = tmp_path / "poplin" / "Pendulum-v1_2_broken" / "Pendulum-v1"
    broken.mkdir(parents=True)
    (broken / "args.yml").write_text("algo: [poplin\n")  # cut by a kill
    result = compare_module.execute(job)
    assert result.reused and result.run_dir == "poplin/Pendulum-v1_1_done"
    assert json.loads((run_dir / compare_module.COMPLETE_FILE).read_text())["job"] == job.name
    assert "Pendulum-v1_2_broken/Pendulum-v1/args.yml is unreadable" in capsys.readouterr().out


def test_checkpoints_are_refused_with_the_reason_where_runs_cannot_continue_exactly() -> None:
    from stable_baselines3 import PPO, SAC
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import VecNormalize

    env = make_vec_env("Pendulum-v1", n_envs=1)
    assert resume.unsupported_reason(SAC("MlpPolicy", env, buffer_size=10), env) is None
    assert "on-policy" in str(resume.unsupported_reason(PPO("MlpPolicy", env, n_steps=64), env))
    two = make_vec_env("Pendulum-v1", n_envs=2)
    assert "2 envs" in str(resume.unsupported_reason(SAC("MlpPolicy", two, buffer_size=10), two))
    normalized = VecNormalize(env)
    assert "VecNormalize" in str(resume.unsupported_reason(SAC("MlpPolicy", normalized, buffer_size=10), normalized))
    assert "gSDE" in str(resume.unsupported_reason(SAC("MlpPolicy", env, buffer_size=10, use_sde=True), env))
    no_timeouts = {"handle_timeout_termination": False}
    compact = SAC("MlpPolicy", env, buffer_size=10, optimize_memory_usage=True, replay_buffer_kwargs=no_timeouts)
    assert "optimize_memory_usage" in str(resume.unsupported_reason(compact, env))


def test_a_run_folder_in_use_is_refused(tmp_path: Path) -> None:
    held = resume.RunLock(tmp_path)
    held.acquire()
    with pytest.raises(RuntimeError, match=f"in use by another training process \\(pid {os.getpid()}\\)"):
        resume.RunLock(tmp_path).acquire()
    held.release()
    again = resume.RunLock(tmp_path)
    again.acquire()
    again.release()
