"""``make demo`` (sb3_poplin.demo): settings from the packaged CPU file, both control modes, the files it writes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sb3_poplin import POPLIN
from sb3_poplin.experiments.demo import CPU_SETTINGS, SIZE_KEYS, cpu_config, main, random_policy_returns, warmup_episodes
from sb3_poplin.experiments.presets import ZOO_KEYS
from sb3_poplin.experiments.presets import config_path, load_config

# a planner small enough for two episodes and three evaluation episodes in a few seconds
TINY = ["horizon:3", "population_size:16", "num_elites:4", "cem_iterations:1", "ensemble_size:2", "dynamics_net_arch:[16]"]


def pendulum_entry() -> dict:
    path = config_path("poplin", "cpu")
    assert path is not None
    return load_config(path)["Pendulum-v1"]


def run_demo(tmp_path: Path, *extra: str) -> dict:
    args = ["--steps", "400", "--eval-episodes", "1", "--curve-episodes", "1", "--out", str(tmp_path), *extra]
    return main([*args, "--params", *TINY, "model_epochs:1"])


def test_settings_are_the_packaged_pendulum_entry() -> None:
    entry = pendulum_entry()
    config = cpu_config()
    assert config.variant == entry["policy"] == "poplin-p"
    assert set(config.kwargs) == set(entry) - set(ZOO_KEYS) - {"policy"}
    for key, value in config.kwargs.items():
        assert (list(value) if isinstance(value, tuple) else value) == entry[key], key
    assert config.kwargs["train_freq"] == (1, "episode")  # SB3 needs the tuple
    assert config.n_timesteps == entry["n_timesteps"]
    assert CPU_SETTINGS == {key: tuple(entry[key]) if isinstance(entry[key], list) else entry[key] for key in SIZE_KEYS}


def test_variant_and_params_replace_the_entry_settings() -> None:
    config = cpu_config(variant="pets", overrides={"horizon": 5, "model_epochs": 2})
    assert config.variant == "pets"
    assert config.kwargs["horizon"] == 5 and config.kwargs["model_epochs"] == 2
    assert config.kwargs["population_size"] == pendulum_entry()["population_size"]


def test_settings_poplin_does_not_take_are_rejected() -> None:
    with pytest.raises(ValueError, match=r"POPLIN does not take \['normalize'\]"):
        cpu_config(overrides={"normalize": True})
    with pytest.raises(ValueError, match="has no entry for 'CartPole-v1'"):
        cpu_config("CartPole-v1")
    with pytest.raises(ValueError, match="KEY:VALUE"):
        main(["--params", "horizon"])


def test_warmup_episodes_are_those_before_the_first_fit() -> None:
    assert warmup_episodes([200, 400, 600], learning_starts=0) == 1
    assert warmup_episodes([200, 400, 600], learning_starts=300) == 2
    assert warmup_episodes([200], learning_starts=1000) == 1
    assert warmup_episodes([], learning_starts=0) == 0


def test_demo_trains_saves_and_evaluates_both_modes_next_to_random(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    summary = run_demo(tmp_path)
    out = capsys.readouterr().out
    assert "MPC control" in out and "policy control" in out and "uniform random actions" in out
    assert summary["variant"] == "poplin-p" and summary["settings"]["horizon"] == 3
    assert summary["training_episodes"]["steps"] == [200, 400] and summary["training_episodes"]["random_warmup"] == 1
    assert summary["policy_control_curve"]["steps"] == [200, 400]
    assert set(summary["evaluation"]) == {"mpc", "policy", "random"}
    for stats in summary["evaluation"].values():
        assert len(stats["returns"]) == 1 and np.isfinite(stats["mean"])
    # the random policy plays the agents' start states (reset seeds 1000, 1001, ...)
    assert summary["evaluation"]["random"]["returns"] == random_policy_returns("Pendulum-v1", 1, seed=1000)
    assert json.loads((tmp_path / "summary.json").read_text()) == summary
    assert (tmp_path / "learning_curve.png").stat().st_size > 0
    loaded = POPLIN.load(tmp_path / "poplin-p_Pendulum-v1.zip")
    assert loaded.variant == "poplin-p" and loaded.settings.horizon == 3


def test_demo_keeps_pets_reachable(tmp_path: Path) -> None:
    summary = run_demo(tmp_path, "--variant", "pets")
    assert summary["variant"] == "pets"
    assert set(summary["evaluation"]) == {"mpc", "random"}  # PETS has no policy network
    assert summary["policy_control_curve"] is None
    assert (tmp_path / "pets_Pendulum-v1.zip").is_file()
