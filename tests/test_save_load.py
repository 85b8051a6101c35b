"""
Saved agents across releases: every zip that ``tests/data/manifest.json`` lists loads, predicts and plans as the
release that wrote it did (the policy in ``sb3_poplin/compat.py``), its networks are built from the hooks it saved,
and a zip of this release records its hooks, so that a task's hooks can change without any entry here.

SB3's generic save/load checks on every variant (parameters and deterministic actions after load, ``set_parameters``,
``load(env=)``, ``device=``, the policy alone) are in ``tests/test_sb3_conformance.py``.
"""

from __future__ import annotations

import json
import sys
import zipfile
from pathlib import Path
from typing import Any

import cloudpickle
import gymnasium as gym
import numpy as np
import pytest
import torch as th

from conftest import TINY, tiny
import sb3_poplin
from sb3_poplin import POPLIN
from sb3_poplin.compat import SETTINGS_BEFORE_0_3
from sb3_poplin.tasks import ModelHooks, make_task
from sb3_poplin.tasks.mujoco import HOOK_CANDIDATES

DATA = Path(__file__).resolve().parent / "data"
MANIFEST = json.loads((DATA / "manifest.json").read_text())["zips"]
# the observations 0.1.0's recorded plans are for (tests/data/make_legacy_zips.py)
LEGACY_OBS = np.array([[0.3, 0.95, -1.0], [-1.0, 0.0, 2.0]], dtype=np.float32)


def saved_data(path: Path) -> dict[str, Any]:
    """The ``data`` of a zip, read as JSON without our loader."""
    with zipfile.ZipFile(path) as archive:
        return json.loads(archive.read("data"))


def rewrite_data(source: Path, target: Path, change: Any) -> None:
    """Copy the zip ``source`` to ``target`` with ``change(data)`` applied to its ``data``."""
    with zipfile.ZipFile(source) as archive:
        members = {name: archive.read(name) for name in archive.namelist()}
    data = json.loads(members["data"])
    change(data)
    members["data"] = json.dumps(data).encode()
    with zipfile.ZipFile(target, "w") as archive:
        for name, content in members.items():
            archive.writestr(name, content)


def load_entry(entry: dict[str, Any], path: Path | None = None) -> POPLIN:
    env = gym.make(entry["env"]) if entry["release"] == "0.1.0" else None  # 0.1.0's tests gave the env
    return POPLIN.load(path or DATA / entry["file"], env=env)


def predicted(agent: POPLIN, obs: np.ndarray, actions: np.ndarray) -> np.ndarray:
    with th.no_grad():
        out, _ = agent.policy.dynamics.propagate(
            th.as_tensor(obs).unsqueeze(1), th.as_tensor(actions).unsqueeze(1), "expectation"
        )
    return out.squeeze(1).numpy()


def test_the_manifest_lists_every_zip_of_the_data_folder() -> None:
    listed = {entry["file"] for entry in MANIFEST}
    assert listed == {path.name for path in DATA.glob("*.zip")}
    for entry in MANIFEST:
        assert (DATA / entry["recorded"]).is_file() and (DATA / entry["made_by"]).is_file(), entry["file"]
    assert {entry["release"] for entry in MANIFEST if entry["published"]} == {"0.1.0", "0.2.0", "0.3.0", "0.5.0"}


@pytest.mark.parametrize("entry", MANIFEST, ids=[entry["file"] for entry in MANIFEST])
def test_a_zip_of_an_earlier_release_loads_and_plans_as_it_did(entry: dict[str, Any], tmp_path: Path) -> None:
    loaded = load_entry(entry)
    assert loaded.sb3_poplin_version == entry["release"]  # recorded, or inferred for 0.1.0 and 0.2.0
    # the networks are built from the hooks the zip saved (its policy_kwargs), whatever the task's hooks are now
    dynamics, actor = loaded.policy.dynamics, loaded.policy.actor
    assert dynamics.in_dim == entry["model_input_dim"] and (dynamics.hooks[0] is not None) == entry["model_features"]
    assert (None if actor is None else actor.in_dim) == entry["policy_input_dim"]
    assert not {"model_hooks_release", "task_model_hooks", "_collecting"} & set(vars(loaded))
    if entry["recorded"].endswith(".npy"):
        # the plan 0.1.0 made right after loading its own zip: generator and networks restored. To float32 rounding,
        # not bit for bit (other hosts and kernels round the small matmuls differently); an unrestored generator or
        # network moves the actions by far more than 1e-6
        planned = loaded.predict(LEGACY_OBS, episode_start=np.ones(2, dtype=bool))[0]
        np.testing.assert_allclose(planned, np.load(DATA / entry["recorded"]), rtol=0, atol=1e-6)
        recorded = None
    else:
        recorded = np.load(DATA / entry["recorded"])
        prediction = predicted(loaded, recorded["obs"], recorded["actions"])
        np.testing.assert_allclose(prediction, recorded["predicted"], rtol=1e-5, atol=1e-5)
        planned = loaded.predict(recorded["obs"], episode_start=np.ones(len(recorded["obs"]), dtype=bool))[0]
        np.testing.assert_allclose(planned, recorded["planned"], rtol=0, atol=1e-5)
        if "policy_actions" in recorded:
            loaded.control = "policy"
            np.testing.assert_allclose(loaded.predict(recorded["obs"])[0], recorded["policy_actions"], rtol=0, atol=1e-6)
    # saved again by this release: it records its hooks and this release, and loads to the same networks
    loaded.save(tmp_path / "resaved.zip")
    data = saved_data(tmp_path / "resaved.zip")
    assert data["sb3_poplin_version"] == sb3_poplin.__version__ and "model_hooks" in data
    resaved = POPLIN.load(tmp_path / "resaved.zip")
    assert resaved.model_hooks == loaded.model_hooks and resaved.sb3_poplin_version == sb3_poplin.__version__
    if recorded is not None:
        np.testing.assert_array_equal(predicted(resaved, recorded["obs"], recorded["actions"]), prediction)


@pytest.mark.parametrize("variant", ["pets", "poplin-p"])
def test_zips_of_release_0_1_0_keep_their_state_and_training_goes_on(tmp_path: Path, variant: str) -> None:
    path = DATA / f"legacy-0.1.0-{variant}.zip"
    with zipfile.ZipFile(path) as archive:
        assert "mpc.pth" not in archive.namelist() and "whitening" not in json.loads(archive.read("data"))
    loaded = POPLIN.load(path, env=gym.make("Pendulum-v1"))
    for key, value in SETTINGS_BEFORE_0_3.items():  # the settings added in 0.3.0 keep 0.1.0's behaviour
        assert getattr(loaded.settings, key) == value, key
    assert loaded.policy.dynamics.standardise_targets
    if variant == "poplin-p":  # saved in mid-episode: the 100 planned steps since the last distillation
        assert loaded.distiller.whitening == "function_from_raw"
        assert len(loaded.distiller.planned) == 100 and all(r["keep"].all() for r in loaded.distiller.planned)
    loaded.learn(200, reset_num_timesteps=False)
    loaded.save(tmp_path / "resaved")
    with zipfile.ZipFile(tmp_path / "resaved.zip") as archive:
        assert "mpc.pth" in archive.namelist()
        data = json.loads(archive.read("data"))
        assert data.get("_saved_planner_state") is None
    assert loaded.sb3_poplin_version == "0.1.0"  # still the release of the zip it was loaded from
    resaved = POPLIN.load(tmp_path / "resaved")
    assert resaved.num_timesteps == loaded.num_timesteps and resaved.sb3_poplin_version == sb3_poplin.__version__


def test_a_zip_without_any_planner_state_names_the_versions(tmp_path: Path) -> None:
    rewrite_data(DATA / "legacy-0.1.0-pets.zip", tmp_path / "stripped.zip", lambda data: data.pop("_saved_planner_state"))
    with pytest.raises(ValueError, match=r"sb3_poplin >= 0\.2\.0 \(mpc\.pth\).*sb3_poplin 0\.1\.0.*Save the agent again"):
        POPLIN.load(tmp_path / "stripped.zip")


def test_zips_record_the_release_that_saved_them(tmp_path: Path) -> None:
    model = tiny()
    assert model.sb3_poplin_version is None  # made here, not loaded
    model.save(tmp_path / "agent.zip")
    assert saved_data(tmp_path / "agent.zip")["sb3_poplin_version"] == sb3_poplin.__version__
    assert POPLIN.load(tmp_path / "agent").sb3_poplin_version == sb3_poplin.__version__
    # a recorded release is taken as it is, also one that differs from the running one
    rewrite_data(tmp_path / "agent.zip", tmp_path / "future.zip", lambda data: data.update(sb3_poplin_version="9.9.9"))
    assert POPLIN.load(tmp_path / "future.zip").sb3_poplin_version == "9.9.9"


@pytest.mark.parametrize("env_id", ["sb3_poplin/PETSCheetah-v0", "HalfCheetah-v5", "Swimmer-v5", "Hopper-v5"])
def test_a_zip_records_its_hooks_and_loads_with_them_when_the_task_changes(
    env_id: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from dataclasses import replace

    import sb3_poplin.tasks as tasks

    agent = POPLIN("poplin-p", env_id, seed=0, **TINY)
    assert agent.model_hooks == (make_task(env_id).hooks if tasks.has_task(env_id) else ModelHooks())
    agent.save(tmp_path / "agent.zip")
    assert "ModelHooks" in saved_data(tmp_path / "agent.zip")["model_hooks"][":type:"]
    obs = np.stack([agent.observation_space.sample() * 0.1 for _ in range(3)]).astype(np.float32)
    actions = np.zeros((3, agent.action_space.shape[0]), dtype=np.float32)
    before = predicted(agent, obs, actions)
    # the task's hooks change (here: none at all), as a later release may do by editing the task's spec alone
    monkeypatch.setitem(tasks._REGISTRY, env_id, replace(make_task(env_id), **ModelHooks().network_kwargs()))
    loaded = POPLIN.load(tmp_path / "agent.zip")
    assert loaded.model_hooks == agent.model_hooks
    np.testing.assert_array_equal(predicted(loaded, obs, actions), before)
    loaded.control = agent.control = "policy"
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], agent.predict(obs, deterministic=True)[0])


def test_custom_objects_and_model_hooks_replace_the_saved_hooks(tmp_path: Path) -> None:
    agent = POPLIN("pets", "HalfCheetah-v5", seed=0, **TINY)
    agent.save(tmp_path / "agent.zip")
    other = HOOK_CANDIDATES["HalfCheetah-v5"]["sincos+progress"].hooks(policy=True)  # same shapes, another target
    assert POPLIN.load(tmp_path / "agent.zip", custom_objects={"model_hooks": other}).model_hooks == other
    assert POPLIN.load(tmp_path / "agent.zip", model_hooks=other).policy.model_hooks["targ_proc"] == other.targ_proc
    # a zip of an earlier release takes them too (its saved hooks are then not read)
    loaded = POPLIN.load(DATA / "legacy-0.4.0-pets-half-cheetah.zip", model_hooks=other)
    assert loaded.model_hooks == other


def test_an_earlier_zip_whose_hooks_no_longer_unpickle_names_the_fix(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    module = tmp_path / "gone_hooks.py"
    module.write_text("def preproc(obs):\n    return obs[..., 1:]\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    import gone_hooks  # type: ignore[import-not-found]

    serialized = cloudpickle.dumps(dict(model_input_exclude=[], obs_preproc=gone_hooks.preproc))

    def with_gone_hooks(data: dict[str, Any]) -> None:
        import base64

        data["policy_kwargs"] = {":type:": "<class 'dict'>", ":serialized:": base64.b64encode(serialized).decode()}

    rewrite_data(DATA / "legacy-0.4.0-pets-half-cheetah.zip", tmp_path / "gone.zip", with_gone_hooks)
    del sys.modules["gone_hooks"]
    module.unlink()
    with pytest.raises(ValueError, match=r"gone\.zip: the model hooks .* cannot be read \(ModuleNotFoundError.*gone_hooks"):
        POPLIN.load(tmp_path / "gone.zip")
    # the fix the message names
    fixed = POPLIN.load(tmp_path / "gone.zip", model_hooks=ModelHooks(), custom_objects={"policy_kwargs": {}})
    assert fixed.model_hooks == ModelHooks() and fixed.policy.dynamics.in_dim == 18 + 6


def test_hooks_given_through_custom_objects_or_unreadable_saved_ones(tmp_path: Path) -> None:
    other = HOOK_CANDIDATES["HalfCheetah-v5"]["sincos+progress"].hooks(policy=True)
    old = DATA / "legacy-0.4.0-pets-half-cheetah.zip"
    # a zip without the record takes custom_objects' hooks too, and its own policy_kwargs stay the source otherwise
    assert POPLIN.load(old, custom_objects={"model_hooks": other}).model_hooks == other
    assert POPLIN.load(old, custom_objects={"policy_kwargs": {}}).model_hooks == POPLIN.load(old).model_hooks
    assert POPLIN.load(old, model_hooks=None).model_hooks == POPLIN.load(old).model_hooks  # None: the saved ones
    # a zip of this release whose hooks no longer unpickle names the fix instead of failing later
    agent = POPLIN("pets", "HalfCheetah-v5", seed=0, **TINY)
    agent.save(tmp_path / "agent.zip")

    def unreadable(data: dict[str, Any]) -> None:
        import base64

        data["model_hooks"][":serialized:"] = base64.b64encode(b"not a pickle").decode()

    rewrite_data(tmp_path / "agent.zip", tmp_path / "unreadable.zip", unreadable)
    with pytest.raises(ValueError, match=r"unreadable\.zip: its model hooks cannot be read .*model_hooks=ModelHooks"):
        POPLIN.load(tmp_path / "unreadable.zip")
    fixed = POPLIN.load(
        tmp_path / "unreadable.zip", model_hooks=agent.model_hooks, custom_objects={"model_hooks": None, "policy_kwargs": {}}
    )
    assert fixed.model_hooks == agent.model_hooks


def test_load_takes_settings_and_saved_attributes_and_rejects_misspelt_keywords(tmp_path: Path) -> None:
    """A setting given to ``load`` replaces the saved one in the planner it builds (the budget of a trained agent
    changed for an evaluation); a keyword that is neither a setting nor in the zip is a TypeError that names it and
    the close setting, where SB3 would set it on the agent and plan with the saved value."""
    tiny().save(tmp_path / "agent")
    loaded = POPLIN.load(tmp_path / "agent", population_size=12, num_elites=3, seed=5, verbose=0)
    assert (loaded.settings.population_size, loaded.settings.num_elites) == (12, 3)
    assert (loaded.mpc.planner.optimizer.population_size, loaded.mpc.planner.optimizer.num_elites) == (12, 3)
    assert POPLIN.load(tmp_path / "agent").mpc.planner.optimizer.population_size == TINY["population_size"]
    with pytest.raises(TypeError, match=r"'populaton_size' \(did you mean 'population_size'\?\).*never read"):
        POPLIN.load(tmp_path / "agent", populaton_size=12)
    with pytest.raises(TypeError, match=r"'no_such_thing' that are neither a setting"):
        POPLIN.load(tmp_path / "agent", horizon=3, no_such_thing=1)
    with pytest.raises(ValueError, match=r"num_elites must be between 1 and population_size \(20\), got 30"):
        POPLIN.load(tmp_path / "agent", num_elites=30)  # a setting's value is checked as the constructor does
    # a zip of a release before a setting existed takes it too (it is not in its data: iCEM came in 0.4.0)
    old = DATA / "legacy-0.1.0-pets.zip"
    assert "optimizer" not in saved_data(old)
    assert POPLIN.load(old, env=gym.make("Pendulum-v1"), optimizer="icem").settings.optimizer == "icem"
