"""The ``[extra]`` install: tensorboard logging of POPLIN's own keys, and the packages the README's commands import."""

from __future__ import annotations

import importlib
import math
from pathlib import Path

import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from sb3_poplin import POPLIN

# a planner small enough for three episodes in a couple of seconds
TINY = dict(
    horizon=3,
    population_size=16,
    num_elites=4,
    cem_iterations=1,
    ensemble_size=2,
    dynamics_net_arch=(16, 16),
    model_epochs=1,
)


def read_scalars(folder: Path) -> dict[str, list[tuple[int, float]]]:
    """Every scalar of the single tensorboard run under ``folder``: tag -> [(step, value), ...]."""
    files = sorted(folder.rglob("events.out.tfevents.*"))
    assert len(files) == 1, files
    events = EventAccumulator(str(files[0]))
    events.Reload()
    return {tag: [(e.step, e.value) for e in events.Scalars(tag)] for tag in events.Tags()["scalars"]}


def test_tensorboard_log_records_the_poplin_keys(tmp_path: Path) -> None:
    model = POPLIN("poplin-p", "Pendulum-v1", seed=0, tensorboard_log=str(tmp_path), **TINY)  # type: ignore[arg-type]
    model.learn(600)  # a random episode, then two planned ones; each refit is logged at the next episode's end
    assert [path.name for path in tmp_path.iterdir()] == ["POPLIN_1"]
    scalars = read_scalars(tmp_path)
    expected = {
        "train/model_loss",
        "train/model_mse",
        "train/n_transitions",
        "plan/elite_return",
        "plan/fallbacks",
        "train/avg_step_norm",  # POPLIN-P's default Avg distillation
        "rollout/ep_rew_mean",
    }
    assert expected <= set(scalars), sorted(scalars)
    # the fits after episodes 1 and 2 saw 200 and 400 transitions
    assert scalars["train/n_transitions"] == [(400, 200.0), (600, 400.0)]
    # episodes 2 and 3 were planned, with finite elite returns and no fallback
    assert [step for step, _ in scalars["plan/elite_return"]] == [400, 600]
    assert all(math.isfinite(value) for _, value in scalars["plan/elite_return"])
    assert scalars["plan/fallbacks"] == [(400, 0.0), (600, 0.0)]
    assert all(math.isfinite(value) and value != 0.0 for _, value in scalars["train/model_loss"])


def test_tensorboard_runs_are_numbered_per_learn_call(tmp_path: Path) -> None:
    model = POPLIN("pets", "Pendulum-v1", seed=0, tensorboard_log=str(tmp_path), **TINY)  # type: ignore[arg-type]
    model.learn(200, tb_log_name="pets")
    model.learn(200, tb_log_name="pets", reset_num_timesteps=False)  # continues the same run, as in SB3
    model.learn(200, tb_log_name="pets")
    assert sorted(path.name for path in tmp_path.iterdir()) == ["pets_1", "pets_2"]


@pytest.mark.parametrize("module", ["tensorboard", "rliable.library", "pygame", "moviepy", "matplotlib", "seaborn", "scipy"])
def test_extra_installs_what_the_readme_commands_import(module: str) -> None:
    """tensorboard_log=, sb3-poplin-zoo plots (-r needs rliable), record_video (pygame, moviepy), make demo's plot."""
    importlib.import_module(module)
