"""
rl-zoo3 front end: train, play, record and plot POPLIN (and the model-free baselines) with rl-zoo3.

rl-zoo3 has no plugin mechanism: its ``--algo`` choices come from the ``rl_zoo3.ALGOS`` table when its
argument parser is built. This module adds ``poplin`` to that table (and an optuna sampler for
``-optimize``), then hands the command line to rl-zoo3's own ``train`` / ``enjoy`` / ``record_video``
/ plot scripts::

    python -m sb3_poplin.zoo train --algo poplin --env Pendulum-v1 --num-threads 1
    python -m sb3_poplin.zoo enjoy --algo poplin --env Pendulum-v1 -f logs --no-render
    python -m sb3_poplin.zoo plots all_plots -a poplin sac -e Pendulum-v1 -f logs --output-dir plots

(``sb3-poplin-zoo`` is the same as ``python -m sb3_poplin.zoo``.) What it adds to rl-zoo3:

* ``--conf-file`` defaults to the packaged ``sb3_poplin/hyperparams/<algo>.yml`` for ``poplin``, ``sac``,
  ``td3``, ``ppo``, ``crossq`` and ``tqc`` when it has an entry for the env (these files have the
  MuJoCo ``-v5`` keys that rl-zoo3 lacks); otherwise rl-zoo3's own file is used. Every spelling of rl-zoo3's option
  is honoured (``-conf``, ``--conf-file``, ``-c``, ...), and a packaged file can be named from any folder by its name
  (``--conf-file poplin_cpu.yml``, or ``hyperparams/poplin_cpu.yml``; a local file of that name wins).
* ``-params`` takes the values of POPLIN's string settings bare (``policy:poplin-a``) and refuses a value that is not
  Python with the fix. With several envs (``n_envs``), the packaged files' episodic ``train_freq`` becomes the steps of
  one episode of each env, as POPLIN's own default.
* POPLIN envs get the env kwargs their task's reward needs (``sb3_poplin.tasks``) when the config
  does not set them; the evaluation env gets the config's env kwargs too (rl-zoo3 2.9 gives them only
  with ``--env-kwargs``), and they are recorded in ``args.yml`` so ``enjoy`` and ``record_video``
  rebuild the same env.
* POPLIN-A/P runs also evaluate policy control (the distilled network alone) at the same steps as the
  zoo's MPC evaluation and write ``evaluations_policy.npz`` next to ``evaluations.npz``
  (``--no-policy-eval`` turns it off; ``--policy-eval-freq N`` evaluates it every ``N`` steps instead: policy control
  plans nothing, so it can be evaluated far more often than MPC).
* ``train --checkpoints`` saves a checkpoint after every episode (:mod:`.checkpoints`) and ``train --resume RUN_DIR``
  continues a killed run in its folder from its last checkpoint, with nothing recorded twice or lost.
* ``compare`` runs the head-to-head of algorithms x tasks x seeds and writes its report (``sb3_poplin.experiments.compare``).
* ``enjoy`` and ``record_video`` load POPLIN with a one-transition replay buffer.
* ``plots`` saves every figure of the zoo's plot scripts as a PNG (``--output-dir``, default ``.``);
  ``--show`` also displays them.
"""

from __future__ import annotations

import argparse
import functools
import inspect
import io
import os
import pathlib
import re
import runpy
import shutil
import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any, ClassVar, TypeVar

import gymnasium as gym
import optuna
import rl_zoo3.train
from rl_zoo3 import ALGOS
from rl_zoo3.exp_manager import ExperimentManager
from rl_zoo3.hyperparams_opt import HYPERPARAMS_CONVERTER, HYPERPARAMS_SAMPLER
from rl_zoo3.utils import StoreDict
from stable_baselines3.common.type_aliases import GymEnv

from sb3_poplin.experiments import checkpoints as resume
from sb3_poplin.callbacks import ControlModesEvalCallback
from sb3_poplin.poplin import POPLIN
from sb3_poplin.experiments.presets import HYPERPARAMS_DIR, PACKAGED_ALGOS, config_path, load_config
from sb3_poplin.tasks import task_env_kwargs
from sb3_poplin import variants
from sb3_poplin.variants import POLICY_VARIANTS

ALGO = "poplin"
PLOT_COMMANDS = ("all_plots", "plot_train", "plot_from_file")
COMMANDS = ("train", "compare", "enjoy", "record_video", "plots", *PLOT_COMMANDS)

SelfPlayedPOPLIN = TypeVar("SelfPlayedPOPLIN", bound="PlayedPOPLIN")


# ---------------------------------------------------------------------------------------- hyperparameter files
def default_config(algo: str, env_id: str, budget: str = "paper") -> str | None:
    """
    The ``--conf-file`` used when none is given: the packaged file when it has an entry for the env.

    :param algo: rl-zoo3 algorithm name
    :param env_id: gymnasium id
    :param budget: ``"paper"`` or ``"cpu"`` (see :func:`config_path`)
    :return: the file to pass, or ``None`` to let rl-zoo3 use its own file. POPLIN always gets the
        packaged file, since rl-zoo3 has none for it.
    """
    path = config_path(algo, budget)
    if path is None:
        return None
    if algo == ALGO or env_id in load_config(path):
        return str(path)
    return None


def resolve_conf_file(conf_file: str) -> str:
    """
    The hyperparameter file a ``--conf-file`` names. An existing file (relative to the working directory) is used as it
    is; otherwise a packaged file's name, bare or as ``hyperparams/NAME`` (``poplin_cpu.yml``,
    ``hyperparams/sac.yml``), is that packaged file, so the commands of the documentation work outside the repository.

    :param conf_file: the ``--conf-file`` value: a ``.yml`` / ``.yaml`` / ``.py`` file or a Python package name
    :return: the path to give rl-zoo3 (a package name unchanged: rl-zoo3 imports it)
    :raises FileNotFoundError: a file that neither exists nor is a packaged file, with the packaged files' names
    """
    if not conf_file.endswith((".yml", ".yaml", ".py")) or os.path.exists(conf_file):
        return conf_file
    parts = pathlib.PurePath(conf_file).parts
    if len(parts) == 1 or (len(parts) == 2 and parts[0] == "hyperparams"):
        packaged = HYPERPARAMS_DIR / parts[-1]
        if packaged.is_file():
            return str(packaged)
    names = sorted(path.name for path in HYPERPARAMS_DIR.glob("*.yml"))
    raise FileNotFoundError(
        f"--conf-file {conf_file}: no such file in {os.getcwd()}, and no packaged file of that name. Give the path of "
        f"an rl-zoo3 hyperparameter file, or one of the packaged files by name (also as hyperparams/NAME): "
        f"{', '.join(names)} (in {HYPERPARAMS_DIR})."
    )


def _episode_length(env_id: str, env_kwargs: dict[str, Any] | None) -> int:
    """
    :param env_id: gymnasium id
    :param env_kwargs: the kwargs the env will be made with (``max_episode_steps`` overrides the registered length)
    :return: the env's episode length, 1000 when it has no time limit (as :class:`POPLIN` counts it with several envs)
    """
    length = (env_kwargs or {}).get("max_episode_steps") or gym.spec(env_id).max_episode_steps
    return int(length) if length else 1000


# ---------------------------------------------------------------------------------------- optuna sampler
ELITE_FRACTIONS = (0.05, 0.1, 0.2)


def convert_poplin_params(sampled_params: dict[str, Any]) -> dict[str, Any]:
    """
    Turn sampled optuna parameters into POPLIN keyword arguments (``HYPERPARAMS_CONVERTER["poplin"]``,
    used by rl-zoo3 to load a trial from a study).

    :param sampled_params: trial parameters; ``elite_fraction`` becomes ``num_elites``
    :return: POPLIN keyword arguments
    """
    params = dict(sampled_params)
    fraction = params.pop("elite_fraction", None)
    if fraction is not None:
        params["num_elites"] = max(1, round(int(params["population_size"]) * float(fraction)))
    return params


def sample_poplin_params(
    trial: optuna.Trial,
    n_actions: int,
    n_envs: int,
    additional_args: dict[str, Any],
    variant: str | None = None,
) -> dict[str, Any]:
    """
    Sample POPLIN planner settings for rl-zoo3's ``-optimize`` (``HYPERPARAMS_SAMPLER["poplin"]``).

    Every variant: horizon, population size and model epochs. CEM variants: elite fraction, CEM
    iterations, momentum and initial variance (POPLIN-P in parameter units, 0.01-0.3; the others in
    scaled action units, 0.05-1). POPLIN-A: the proposal; POPLIN-P: the noise and the distillation.

    :param trial: the optuna trial
    :param n_actions: action dimension (rl-zoo3 interface; unused)
    :param n_envs: number of envs (rl-zoo3 interface; unused)
    :param additional_args: rl-zoo3 interface (unused)
    :param variant: the variant being tuned (the config's ``policy``); ``None`` samples it too
    :return: POPLIN keyword arguments, merged by rl-zoo3 over the config's
    """
    del n_actions, n_envs, additional_args
    sampled: dict[str, Any] = {}
    if variant is None:
        variant = str(trial.suggest_categorical("policy", list(POPLIN.policy_aliases)))
        sampled["policy"] = variant
    sampled["horizon"] = trial.suggest_categorical("horizon", [10, 15, 20, 25, 30])
    sampled["population_size"] = trial.suggest_categorical("population_size", [100, 200, 300, 500])
    sampled["model_epochs"] = trial.suggest_categorical("model_epochs", [3, 5, 10])
    if variant != "rs":
        sampled["elite_fraction"] = trial.suggest_categorical("elite_fraction", list(ELITE_FRACTIONS))
        sampled["cem_iterations"] = trial.suggest_int("cem_iterations", 1, 5)
        sampled["cem_alpha"] = trial.suggest_categorical("cem_alpha", [0.0, 0.1, 0.25])
        low, high = (0.01, 0.3) if variant == "poplin-p" else (0.05, 1.0)
        sampled["init_var"] = trial.suggest_float("init_var", low, high, log=True)
    if variant == "poplin-a":
        sampled["proposal"] = trial.suggest_categorical("proposal", ["init", "replan"])
    if variant == "poplin-p":
        sampled["noise"] = trial.suggest_categorical("noise", ["sep", "uni"])
        sampled["distillation"] = trial.suggest_categorical("distillation", ["avg", "bc", "gan"])
    return convert_poplin_params(sampled)


# ---------------------------------------------------------------------------------------- zoo integration
class PlayedPOPLIN(POPLIN):
    """
    POPLIN as loaded by ``enjoy`` and ``record_video``: with a one-transition replay buffer, since the
    agent only acts (rl-zoo3 does this for a fixed list of its own off-policy algorithms only).
    """

    @classmethod
    def load(  # type: ignore[override]
        cls: type[SelfPlayedPOPLIN],
        path: str | pathlib.Path | io.BufferedIOBase,
        env: GymEnv | None = None,
        device: Any = "auto",
        custom_objects: dict[str, Any] | None = None,
        print_system_info: bool = False,
        force_reset: bool = True,
        control: str | None = None,
        **kwargs: Any,
    ) -> SelfPlayedPOPLIN:
        """
        Load a saved POPLIN agent for playing, as :meth:`POPLIN.load` with ``buffer_size`` 1 by default.

        :param path: the saved zip
        :param env: optional env (planning needs none)
        :param device: torch device
        :param custom_objects: saved attributes to replace (rl-zoo3 passes learning-rate placeholders)
        :param print_system_info: print the saving and loading systems' info
        :param force_reset: reset the env before the next ``learn``
        :param control: ``"mpc"`` or ``"policy"`` to override the saved control mode
        :param kwargs: attributes to set on the loaded agent (e.g. ``buffer_size``, ``seed``)
        :return: the agent
        """
        kwargs.setdefault("buffer_size", 1)
        return super().load(path, env, device, custom_objects, print_system_info, force_reset, control, **kwargs)


class PoplinExperimentManager(ExperimentManager):
    """
    rl-zoo3's ``ExperimentManager`` with what POPLIN runs need: the task's env kwargs, the config's
    env kwargs for the evaluation env and in ``args.yml``, the variant given to the ``-optimize``
    sampler, and policy-control evaluations for POPLIN-A/P (``evaluations_policy.npz``).
    """

    #: add a policy-control evaluation next to the zoo's MPC evaluation (POPLIN-A/P runs)
    policy_eval: ClassVar[bool] = True
    #: its period in env steps (``None``: the MPC evaluation's, ``--eval-freq``)
    policy_eval_freq: ClassVar[int | None] = None
    #: save a checkpoint after every episode (``sb3_poplin.experiments.checkpoints``)
    checkpoints: ClassVar[bool] = False
    #: continue the run in this folder from its last checkpoint (implies ``checkpoints``)
    resume_dir: ClassVar[str | None] = None
    poplin_variant: str | None = None

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        """
        rl-zoo3's ``ExperimentManager`` (same arguments), with the hyperparameter file chosen as ``train`` documents it:
        ``config`` ``None`` is the packaged file when it has the env (:func:`default_config`; else rl-zoo3's own), and a
        packaged file may be named without its folder (:func:`resolve_conf_file`). The file used is recorded as
        ``conf_file`` in ``args.yml``.
        """
        bound = inspect.signature(ExperimentManager.__init__).bind(self, *args, **kwargs)
        given = bound.arguments.get("config")
        config = default_config(bound.arguments["algo"], bound.arguments["env_id"]) if given is None else given
        bound.arguments["config"] = None if config is None else resolve_conf_file(config)
        super().__init__(*bound.args[1:], **bound.kwargs)
        if bound.arguments["config"] is not None:
            self.args.conf_file = bound.arguments["config"]
        if self.policy_eval_freq is not None:
            self.args.policy_eval_freq = self.policy_eval_freq  # in args.yml: the run's settings identify it
        self.checkpoints_asked = self.checkpoints or self.resume_dir is not None
        self.checkpointing = self.checkpoints_asked
        self.restored = False
        self.training_finished = False
        self.lock: resume.RunLock | None = None
        if self.resume_dir is not None:
            self.save_path = os.path.abspath(self.resume_dir)
            self.params_path = f"{self.save_path}/{self.env_name}"

    def read_hyperparameters(self) -> tuple[dict[str, Any], dict[str, Any]]:
        """
        rl-zoo3's look-up, then: POPLIN's task env kwargs and its variant for the sampler; the env kwargs
        for the evaluation env and ``args.yml``.

        :return: the hyperparameters and the ones saved in ``config.yml``
        """
        hyperparams, saved_hyperparams = super().read_hyperparameters()
        if self.algo == ALGO:
            variant = hyperparams.get("policy")
            self.poplin_variant = variant if isinstance(variant, str) else None
            HYPERPARAMS_SAMPLER[ALGO] = functools.partial(sample_poplin_params, variant=self.poplin_variant)
            env_kwargs = task_env_kwargs(self.env_name.gym_id, hyperparams.get("env_kwargs", self.env_kwargs))
            if env_kwargs:
                hyperparams["env_kwargs"] = env_kwargs
                saved_hyperparams["env_kwargs"] = env_kwargs
            self._train_freq_for_several_envs(hyperparams, saved_hyperparams)
        if hyperparams.get("env_kwargs"):
            # rl-zoo3 2.9 gives the config's env kwargs to the evaluation env only with --env-kwargs,
            # and enjoy / record_video read them from args.yml
            if self._eval_env_kwargs_args is None:
                self.eval_env_kwargs = hyperparams["env_kwargs"]
            if getattr(self.args, "env_kwargs", None) is None:
                self.args.env_kwargs = dict(hyperparams["env_kwargs"])
        return hyperparams, saved_hyperparams

    def _train_freq_for_several_envs(self, hyperparams: dict[str, Any], saved_hyperparams: dict[str, Any]) -> None:
        """
        With several envs (``n_envs``), an episodic ``train_freq`` from the file (the packaged files' ``[1, episode]``)
        becomes the steps of as many episodes of each env, as POPLIN's own default does (SB3 counts episodes with one
        env only); the change is printed.

        :param hyperparams: the hyperparameters, changed in place
        :param saved_hyperparams: the ones saved in ``config.yml``, changed in place
        :raises ValueError: an episodic ``train_freq`` given with ``-params``, with the steps to give instead
        """
        n_envs = int(hyperparams.get("n_envs", 1))
        train_freq = hyperparams.get("train_freq")
        episodic = isinstance(train_freq, (list, tuple)) and len(train_freq) == 2 and str(train_freq[1]) == "episode"
        if n_envs <= 1 or not episodic:
            return
        assert isinstance(train_freq, (list, tuple))
        episodes = int(train_freq[0])
        steps = [episodes * _episode_length(self.env_name.gym_id, hyperparams.get("env_kwargs")), "step"]
        what = "one episode" if episodes == 1 else f"{episodes} episodes"
        if "train_freq" in (self.custom_hyperparams or {}):
            raise ValueError(
                f"train_freq {list(train_freq)} with n_envs {n_envs}: SB3 counts episodes with one env only. Give the "
                f"steps of {what} of each env instead, -params train_freq:\"({steps[0]}, 'step')\", or train with one env."
            )
        print(
            f"train_freq {list(train_freq)} with n_envs {n_envs}: SB3 counts episodes with one env only, so the model is "
            f"refit after the steps of {what} of each env instead: train_freq {steps} (as POPLIN's default does)"
        )
        hyperparams["train_freq"] = steps
        saved_hyperparams["train_freq"] = steps

    def create_callbacks(self) -> None:
        """rl-zoo3's callbacks, plus a policy-control evaluation for POPLIN-A/P (not during ``-optimize``)."""
        super().create_callbacks()
        if self.algo != ALGO or self.optimize_hyperparameters:
            return
        existing = [callback for callback in self.callbacks if isinstance(callback, ControlModesEvalCallback)]
        for callback in existing:
            if callback.log_path is None:
                callback.log_path = self.save_path
        if existing or not self.policy_eval or self.poplin_variant not in POLICY_VARIANTS:
            return
        # by default the zoo's EvalCallback's frequency (already per env) and episodes: matched steps
        eval_freq = self.eval_freq if self.policy_eval_freq is None else max(self.policy_eval_freq // self.n_envs, 1)
        if eval_freq <= 0:
            return
        self.callbacks.append(
            ControlModesEvalCallback(
                eval_env=self.create_envs(self.n_eval_envs, eval_env=True),
                eval_freq=eval_freq,
                n_eval_episodes=self.n_eval_episodes,
                log_path=self.save_path,
                modes=("policy",),
                deterministic=self.deterministic_eval,
            )
        )

    def _save_config(self, saved_hyperparams: dict[str, Any]) -> None:
        """rl-zoo3's ``config.yml`` and ``args.yml``; a resumed run keeps the files it has (they identify it)."""
        if self.resume_dir is not None and os.path.isfile(os.path.join(self.params_path, "args.yml")):
            print(f"Continuing with the settings of {self.params_path}")
            return
        super()._save_config(saved_hyperparams)

    def create_envs(self, n_envs: int, eval_env: bool = False, no_log: bool = False) -> Any:
        """rl-zoo3's envs; with checkpoints, the training env's resets are recorded (to replay them on resume)."""
        env = super().create_envs(n_envs, eval_env, no_log)
        if self.checkpointing and not eval_env and resume.dummy_vec_env(env) is not None:
            resume.record_resets(env)
        return env

    def setup_experiment(self) -> Any:
        """
        rl-zoo3's set-up; with checkpoints, the run's folder is locked, a checkpoint callback added and, with
        ``--resume``, the run continued from its last checkpoint (or started again in its folder when it has none).
        """
        if not self.checkpointing or self.optimize_hyperparameters:
            return super().setup_experiment()
        self.lock = resume.RunLock(self.save_path)
        self.lock.acquire()  # before the Monitor's CSV is opened for writing
        result = super().setup_experiment()
        if result is None:
            return result
        model, saved_hyperparams = result
        # there from the start until training finishes, also for a run without checkpoints: a run stopped early (Ctrl-C
        # saves its model) is not complete
        os.makedirs(os.path.join(self.save_path, resume.CHECKPOINT_FOLDER), exist_ok=True)
        env = model.get_env()
        assert env is not None
        reason = resume.unsupported_reason(model, env)
        if reason is not None:
            print(f"warning: no checkpoints for this run ({reason}); an interrupted run starts again from zero")
            self.checkpointing = False
        checkpoint = resume.latest_checkpoint(self.save_path) if self.resume_dir is not None and reason is None else None
        if checkpoint is not None:
            model = resume.restore_checkpoint(checkpoint, type(model), env, self.callbacks, device=model.device)
            self.restored = True
            print(f"Resumed {self.save_path} from {checkpoint.name} ({model.num_timesteps} of {self.n_timesteps} steps)")
        elif self.resume_dir is not None:
            # no checkpoint to continue from: start again in the same folder, without what the killed run wrote
            for path in pathlib.Path(self.save_path).iterdir():
                if path.is_file() and (path.name == "best_model.zip" or resume.RESULT_FILE_PATTERN.match(path.name)):
                    if not path.name.endswith(".monitor.csv"):  # the new Monitor has just started it again
                        path.unlink()
            for stale in resume.checkpoint_folders(self.save_path):
                shutil.rmtree(stale, ignore_errors=True)
            print(f"Starting {self.save_path} again: it has no checkpoint")
        if self.checkpointing:
            self.callbacks.append(resume.EpisodeCheckpointCallback(self.save_path, list(self.callbacks)))
        return model, saved_hyperparams

    def learn(self, model: Any) -> None:
        """rl-zoo3's ``learn``; a run continued from a checkpoint trains the steps it has left."""
        if not self.restored:
            super().learn(model)  # Ctrl-C: rl-zoo3 saves the model; the checkpoints stay, so the run can be resumed
        else:
            kwargs: dict[str, Any] = {"callback": self.callbacks}
            if self.log_interval != -1:  # rl-zoo3's convention: -1 the default, below it no logging
                kwargs["log_interval"] = self.log_interval if self.log_interval > -1 else None
            try:
                model.learn(max(self.n_timesteps - model.num_timesteps, 0), reset_num_timesteps=False, **kwargs)
            except KeyboardInterrupt:
                pass
            finally:
                self.callbacks[0].on_training_end()
                if model.env is not None:
                    model.env.close()
        self.training_finished = model.num_timesteps >= self.n_timesteps

    def save_trained_model(self, model: Any) -> None:
        """rl-zoo3's save; a run that finished training then drops its checkpoints."""
        super().save_trained_model(model)
        if self.checkpoints_asked and self.training_finished:
            resume.drop_checkpoints(self.save_path)
        if self.lock is not None:
            self.lock.release()


def register() -> None:
    """Add ``poplin`` to rl-zoo3's algorithm table and its ``-optimize`` sampler and converter tables."""
    ALGOS[ALGO] = POPLIN
    HYPERPARAMS_SAMPLER.setdefault(ALGO, sample_poplin_params)
    HYPERPARAMS_CONVERTER[ALGO] = convert_poplin_params


def read_hyperparameters(
    algo: str,
    env_id: str,
    conf_file: str | None = None,
    hyperparams: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """
    The hyperparameters ``train`` would use (rl-zoo3's own look-up, plus this module's env kwargs),
    without creating anything.

    :param algo: rl-zoo3 algorithm name
    :param env_id: gymnasium id
    :param conf_file: hyperparameter file, or a packaged file's name (:func:`resolve_conf_file`); ``None``: as
        ``train`` picks it (:func:`default_config`)
    :param hyperparams: ``-params`` overrides
    :return: the hyperparameters, as saved in the run's ``config.yml``
    """
    register()
    manager = PoplinExperimentManager(
        argparse.Namespace(env_kwargs=None),
        algo,
        env_id,
        log_folder=os.devnull,
        hyperparams=hyperparams,
        config=conf_file,
    )
    _, saved = manager.read_hyperparameters()
    return dict(saved)


# ---------------------------------------------------------------------------------------- command line
#: POPLIN settings whose values are strings: ``-params`` also takes them bare (``policy:poplin-a``)
STRING_SETTINGS = ("policy", *variants.STRING_SETTINGS, "control", "device")
_BARE_WORD = re.compile(r"[A-Za-z_][\w.:/+-]*")


class ZooStoreDict(StoreDict):
    """
    rl-zoo3's ``KEY:VALUE ...`` action (``-params``, ``--env-kwargs``, ``--eval-env-kwargs``), which evaluates every
    value as Python, with two changes: with ``-params`` the values of POPLIN's string settings (:data:`STRING_SETTINGS`)
    may be given bare (``policy:poplin-a`` for ``policy:"'poplin-a'"``; ``None``, ``True`` and ``False`` stay Python),
    and a value that is not Python is refused with the setting and the fix instead of ``eval``'s ``NameError``.
    """

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: str | Sequence[Any] | None,
        option_string: str | None = None,
    ) -> None:
        """
        :param parser: the parser
        :param namespace: where the ``{key: value}`` dict is stored
        :param values: the ``KEY:VALUE`` strings
        :param option_string: the option as given
        :raises argparse.ArgumentError: an item without ``:`` or a value that is not Python (the parser exits with it)
        """
        settings: dict[str, Any] = {}
        for item in [values] if isinstance(values, str) else list(values or []):
            key, colon, value = str(item).partition(":")
            if not colon:
                raise argparse.ArgumentError(self, f"{item!r}: expected KEY:VALUE, e.g. horizon:30")
            bare = _BARE_WORD.fullmatch(value) is not None and value not in ("None", "True", "False")
            if self.dest == "hyperparams" and key in STRING_SETTINGS and bare:
                settings[key] = value
                continue
            parsed = argparse.Namespace()
            try:
                super().__call__(parser, parsed, [item], option_string)
            except Exception as error:
                raise argparse.ArgumentError(
                    self,
                    f"{item}: {value!r} is not a Python value ({type(error).__name__}: {error}). rl-zoo3 evaluates "
                    f"every value as Python: quote a string, e.g. {key}:\"'{value}'\"",
                ) from error
            settings.update(getattr(parsed, self.dest))
        setattr(namespace, self.dest, settings)


@contextmanager
def _argv(prog: str, args: Sequence[str]) -> Iterator[None]:
    """
    Set ``sys.argv`` for an rl-zoo3 script, restored afterwards.

    :param prog: the program name shown in the script's messages
    :param args: its arguments
    """
    saved = sys.argv
    sys.argv = [prog, *args]
    try:
        yield
    finally:
        sys.argv = saved


def _train(args: Sequence[str]) -> None:
    """
    rl-zoo3 ``train`` with :class:`PoplinExperimentManager` (the default ``--conf-file``) and :class:`ZooStoreDict`.

    :param args: the ``train`` command line (plus ``--no-policy-eval``, ``--policy-eval-freq``, ``--checkpoints`` and
        ``--resume``, spelled in full: an abbreviation such as ``--c`` is rl-zoo3's, here ``--conf-file``)
    """
    parser = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    parser.add_argument("--no-policy-eval", action="store_true")
    parser.add_argument("--policy-eval-freq", type=int)
    parser.add_argument("--checkpoints", action="store_true")
    parser.add_argument("--resume")
    own, rest = parser.parse_known_args(list(args))
    if own.resume is not None and not os.path.isdir(own.resume):
        raise SystemExit(f"--resume {own.resume}: no such run folder. Give the folder of the run to continue.")
    if own.policy_eval_freq is not None and own.policy_eval_freq < 1:
        raise SystemExit(f"--policy-eval-freq must be >= 1 (env steps), got {own.policy_eval_freq}.")
    PoplinExperimentManager.policy_eval = not own.no_policy_eval
    PoplinExperimentManager.policy_eval_freq = own.policy_eval_freq
    PoplinExperimentManager.checkpoints = own.checkpoints
    PoplinExperimentManager.resume_dir = own.resume
    # rl_zoo3.train() builds its ExperimentManager and its KEY:VALUE options' action from these module attributes
    setattr(rl_zoo3.train, "ExperimentManager", PoplinExperimentManager)  # noqa: B010
    setattr(rl_zoo3.train, "StoreDict", ZooStoreDict)  # noqa: B010
    with _argv("sb3-poplin-zoo train", rest):
        rl_zoo3.train.train()


def _play(command: str, args: Sequence[str]) -> None:
    """
    rl-zoo3 ``enjoy`` or ``record_video``, with POPLIN loaded as :class:`PlayedPOPLIN`.

    :param command: ``"enjoy"`` or ``"record_video"``
    :param args: its command line
    """
    ALGOS[ALGO] = PlayedPOPLIN
    with _argv(f"sb3-poplin-zoo {command}", args):
        if command == "enjoy":
            from rl_zoo3.enjoy import enjoy

            enjoy()
        else:  # record_video is a script with no entry function
            runpy.run_module("rl_zoo3.record_video", run_name="__main__", alter_sys=False)


def _figure_file(command: str, label: str, number: int) -> str:
    """
    :param command: the plot script
    :param label: the figure's label
    :param number: the figure's number (used when the label is empty)
    :return: the PNG file name
    """
    slug = re.sub(r"[^0-9A-Za-z.-]+", "_", label).strip("_") or f"figure_{number}"
    return f"{command}_{slug}.png"


def _plots(command: str, args: Sequence[str]) -> list[str]:
    """
    Run an rl-zoo3 plot script and save its figures as PNGs.

    :param command: ``"all_plots"``, ``"plot_train"`` or ``"plot_from_file"``
    :param args: its command line, plus ``--output-dir DIR`` and ``--show``
    :return: the PNG files written
    """
    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument("--output-dir", default=".")
    parser.add_argument("--show", action="store_true")
    own, rest = parser.parse_known_args(list(args))
    import matplotlib

    if not own.show:
        matplotlib.use("Agg")
    from matplotlib import pyplot as plt
    from rl_zoo3 import plots

    os.makedirs(own.output_dir, exist_ok=True)
    written: list[str] = []

    def save_open_figures() -> None:
        for number in plt.get_fignums():
            figure = plt.figure(number)
            path = os.path.join(own.output_dir, _figure_file(command, str(figure.get_label()), number))
            figure.savefig(path, dpi=120, bbox_inches="tight")
            if path not in written:
                written.append(path)
                print(f"Saved {path}")

    original_show = plt.show

    def show(*show_args: Any, **show_kwargs: Any) -> None:
        save_open_figures()
        if own.show:
            original_show(*show_args, **show_kwargs)

    script: Callable[[], None] = getattr(plots, command)
    setattr(plt, "show", show)  # noqa: B010
    try:
        with _argv(f"sb3-poplin-zoo {command}", rest):
            script()
        save_open_figures()
    finally:
        setattr(plt, "show", original_show)  # noqa: B010
        plt.close("all")
    return written


USAGE = f"""usage: sb3-poplin-zoo COMMAND [ARGS...]   (or: python -m sb3_poplin.zoo COMMAND [ARGS...])

rl-zoo3 with POPLIN registered as --algo {ALGO}. Commands:
  train         rl-zoo3 train; --conf-file defaults to sb3_poplin/hyperparams/<algo>.yml for
                {", ".join(PACKAGED_ALGOS)} when it has the env (a packaged file can be named
                by its name alone, e.g. --conf-file poplin_cpu.yml); --no-policy-eval skips the
                policy-control evaluation (evaluations_policy.npz) of POPLIN-A/P runs,
                --policy-eval-freq N makes it every N steps (default: --eval-freq);
                --checkpoints saves a checkpoint after every episode, --resume RUN_DIR continues
                a killed run from its last one
  compare       the head-to-head: algorithms x tasks x seeds, run (resumable) and reported
  enjoy         rl-zoo3 enjoy (POPLIN is loaded with a one-transition replay buffer)
  record_video  rl-zoo3 record_video
  plots NAME    one of {", ".join(PLOT_COMMANDS)} (also accepted as commands); every figure is saved
                as a PNG in --output-dir (default .); --show also displays them

Packaged hyperparameter files: {HYPERPARAMS_DIR}
Run "sb3-poplin-zoo COMMAND -h" for the options of a command.
"""


def main(argv: Sequence[str] | None = None) -> None:
    """
    Entry point of ``python -m sb3_poplin.zoo`` and the ``sb3-poplin-zoo`` console script.

    :param argv: the command and its arguments; ``None``: ``sys.argv[1:]``
    """
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help"):
        print(USAGE)
        return
    command, rest = args[0], args[1:]
    if command not in COMMANDS:
        raise SystemExit(f"Unknown command {command!r}; accepted values: {list(COMMANDS)}\n\n{USAGE}")
    if command == "compare":
        from sb3_poplin.experiments import compare

        raise SystemExit(compare.main(rest))
    register()
    if command == "train":
        _train(rest)
    elif command in ("enjoy", "record_video"):
        _play(command, rest)
    else:
        if command == "plots":
            if not rest or rest[0] not in PLOT_COMMANDS:
                raise SystemExit(f"plots needs one of {list(PLOT_COMMANDS)}, e.g. 'plots all_plots -a poplin -e ...'")
            command, rest = rest[0], rest[1:]
        _plots(command, rest)


if __name__ == "__main__":
    main()
