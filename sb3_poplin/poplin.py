"""
POPLIN as a Stable-Baselines3 algorithm: SB3 glue only.

:class:`POPLIN` subclasses ``OffPolicyAlgorithm``: SB3 runs the loop, the replay buffer, logging,
callbacks and save/load. This module resolves the settings, builds the networks
(:mod:`sb3_poplin.policies`), the planner (:mod:`sb3_poplin.planning`) and the task
(:mod:`sb3_poplin.tasks`), and overrides ``predict`` (MPC control), ``train`` (fit the model after
each episode) and the save hooks.

Loop (Wang & Ba 2019, after PETS): uniform random actions until the model has been fitted once
(one episode by default), then after every ``train_freq`` period (one episode) fit the model on
all data and collect the next period with MPC.
"""

from __future__ import annotations

import io
import json
import math
import pathlib
import warnings
import zipfile
from collections.abc import Iterable, Sequence
from typing import Any, ClassVar, TypeVar

import os

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback
from stable_baselines3.common.vec_env import VecEnv

from sb3_poplin.distillation import (
    DISTILLATIONS,
    average_perturbation,
    behaviour_cloning,
    gan_distillation,
    saturated_fraction,
)
from sb3_poplin.dynamics import PROPAGATIONS
from sb3_poplin.planning import (
    CEM,
    PlanResult,
    NOISES,
    PROPOSALS,
    SAMPLINGS,
    ActionSequences,
    MPCPlanner,
    PolicyActionNoise,
    PolicyParameterNoise,
    RandomShooting,
    SearchSpace,
)
from sb3_poplin.policies import POPLINPolicy
from sb3_poplin.tasks import RewardFn, TerminationFn, check_observation_space, has_task, make_task

SelfPOPLIN = TypeVar("SelfPOPLIN", bound="POPLIN")

CONTROLS = ("mpc", "policy")
PLANNING_DTYPES = {"float32": th.float32, "bfloat16": th.bfloat16}
# variant -> initial CEM variance of its search space (the paper's demo settings)
DEFAULT_INIT_VAR = {"pets": 0.25, "rs": 0.25, "poplin-a": 0.25, "poplin-p": 0.1}
# variant -> default hidden widths of the policy network (None: the variant has none)
DEFAULT_POLICY_NET_ARCH: dict[str, list[int] | None] = {"pets": None, "rs": None, "poplin-a": [64, 64], "poplin-p": [32]}
# variant -> distill the final elites too ("imagined" data: BC-AI for POPLIN-A, as in the paper's demos)
DEFAULT_DISTILL_IMAGINED = {"pets": False, "rs": False, "poplin-a": True, "poplin-p": False}
GAN_DISCRIMINATOR_NET_ARCH = [64, 64]


def _env_id(env: GymEnv | str | None) -> str | None:
    """The gymnasium id behind an env id, Env or VecEnv (None when it cannot be told)."""
    if env is None or isinstance(env, str):
        return env
    try:
        spec = env.get_attr("spec", [0])[0] if isinstance(env, VecEnv) else env.unwrapped.spec
    except (AttributeError, IndexError):
        return None
    return None if spec is None else spec.id


def _max_episode_steps(env: GymEnv | None) -> int | None:
    if env is None:
        return None
    try:
        spec = env.get_attr("spec", [0])[0] if isinstance(env, VecEnv) else env.spec
    except (AttributeError, IndexError):
        return None
    return None if spec is None else spec.max_episode_steps


def _check_spaces(env: GymEnv | None) -> None:
    """Reject what the planner cannot handle, with the reason and the fix."""
    if env is None:
        return
    action_space, observation_space = env.action_space, env.observation_space
    if not isinstance(action_space, spaces.Box):
        raise ValueError(
            f"POPLIN plans continuous actions and needs a Box action space, got {action_space}. "
            "Use a continuous-action environment (e.g. Pendulum-v1), or a model-free SB3 algorithm "
            "such as DQN or PPO for discrete actions."
        )
    if not (np.all(np.isfinite(action_space.low)) and np.all(np.isfinite(action_space.high))):
        raise ValueError(
            f"POPLIN needs finite action bounds, got low={action_space.low}, high={action_space.high}. "
            "Wrap the env with gymnasium.wrappers.ClipAction or RescaleAction to bound it."
        )
    check_observation_space(observation_space, _env_id(env))


def _check_saved_agent(path: str | pathlib.Path | io.BufferedIOBase) -> None:
    """Reject, with the reason and the fix, anything that is not a complete POPLIN zip."""
    where = str(path) if isinstance(path, (str, pathlib.Path)) else "the given file object"
    if isinstance(path, (str, pathlib.Path)) and not os.path.exists(path):
        if os.path.exists(f"{path}.zip"):
            path = f"{path}.zip"
        else:
            raise FileNotFoundError(f"No saved agent at {where} (nor {where}.zip): check the path given to POPLIN.load.")
    start = path.tell() if isinstance(path, io.BufferedIOBase) else None
    try:
        with zipfile.ZipFile(path) as archive:  # type: ignore[arg-type]
            names = set(archive.namelist())
            corrupted = archive.testzip()
            data = json.loads(archive.read("data")) if "data" in names else None
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError) as error:
        raise ValueError(
            f"{where} is not a readable POPLIN zip (truncated or corrupted? {error}). "
            "Load a file written by POPLIN.save / model.save."
        ) from None
    finally:
        if start is not None:
            path.seek(start)  # type: ignore[union-attr]
    if corrupted is not None:
        raise ValueError(f"{where} is corrupted: its member {corrupted!r} fails the CRC check. Save the agent again.")
    if not isinstance(data, dict) or "variant" not in data:
        saved_by = data.get("policy_class", {}).get("__module__", "unknown") if isinstance(data, dict) else "unknown"
        raise ValueError(
            f"{where} was not saved by POPLIN (its policy comes from {saved_by!r}): "
            "load it with the algorithm that saved it, e.g. stable_baselines3.SAC.load."
        )
    missing = {"policy.pth", "policy.dynamics_optimizer.pth"} - names
    if missing:
        raise ValueError(f"{where} is an incomplete POPLIN zip (missing {sorted(missing)}). Save the agent again.")


class POPLIN(OffPolicyAlgorithm):
    """
    Model-based planning with a learned probabilistic ensemble: POPLIN-A, POPLIN-P, and the PETS
    and random-shooting baselines. Paper: https://arxiv.org/abs/1906.08649 (Wang & Ba, 2019);
    PETS: https://arxiv.org/abs/1805.12114 (Chua et al., 2018).

    :param policy: the variant: ``"pets"`` (CEM over action sequences), ``"rs"`` (random shooting),
        ``"poplin-a"`` (CEM over action noise around a policy network's proposals) or ``"poplin-p"``
        (CEM over noise on the policy network's parameters)
    :param env: env id or (Vec)Env with a Box action space and a flat Box observation space
    :param horizon: planning horizon H
    :param population_size: candidates per CEM iteration (random shooting: the number of samples)
    :param num_elites: elites per CEM iteration
    :param cem_iterations: CEM iterations per env step
    :param cem_alpha: CEM momentum: ``new = alpha * old + (1 - alpha) * elite``, in [0, 1)
    :param init_var: initial CEM variance of the search space; ``None`` for the variant default
        (PETS and POPLIN-A 0.25, in scaled action units; POPLIN-P 0.1, in parameter units)
    :param cem_sampling: ``"truncated"`` (normal truncated at 2 sigma) or ``"clipped"``
    :param proposal: POPLIN-A only: ``"init"`` (policy rolled open-loop through the model once per plan)
        or ``"replan"`` (policy re-queried on every imagined state)
    :param noise: POPLIN-P only: ``"sep"`` (one parameter-noise block per planning step) or ``"uni"``
        (one block shared by all steps)
    :param distillation: how the policy network learns from the planner after each episode:
        POPLIN-A ``"bc"``; POPLIN-P ``"avg"`` (default), ``"bc"`` or ``"gan"``; ``None`` for the default
    :param distill_imagined: also distill the final CEM elites' first steps ("imagined" data);
        ``None``: POPLIN-A yes (BC-AI), POPLIN-P no
    :param distill_window: BC and GAN train on the most recent ``distill_window`` planned real steps (the
        actions the planner executed, which stay valid targets as the policy changes); ``None``: only the steps
        since the last distillation, as in the original code. Avg always uses the steps since the last update.
    :param avg_step_size: POPLIN-P Avg only: ``theta <- theta + avg_step_size * mean(omega)``, in (0, 1]. 1 is the
        paper's equation, which drives the clipped policy output into saturation within a few episodes (a
        policy stuck at full torque that the parameter noise cannot leave); 0.1 averages the planner's
        perturbations over about ten episodes (see the README)
    :param policy_net_arch: hidden widths of the policy network (tanh); ``None``: POPLIN-A [64, 64], POPLIN-P [32]
    :param policy_learning_rate: Adam learning rate of the policy network (and the GAN discriminator)
    :param policy_epochs: maximum BC epochs per distillation (early stopping on a 20 % holdout), or GAN epochs
        (``None``: BC 100, GAN 40)
    :param policy_batch_size: minibatch size of the distillation
    :param ensemble_size: members of the dynamics ensemble
    :param dynamics_net_arch: hidden widths of each member (swish)
    :param propagation: ``"expectation"`` (mean over members, no particles), ``"ts1"``, ``"tsinf"``
        or ``"ds"`` (PETS trajectory sampling / distribution sampling with ``num_particles``)
    :param num_particles: particles per candidate for the sampling propagations; a multiple of
        ``ensemble_size``
    :param planning_dtype: ``"float32"``, or ``"bfloat16"`` to run the planner's network matmuls in bf16 with
        fp32 accumulation (faster on CPUs with bf16 units and on GPUs; returns are summed in fp32)
    :param max_batch_rows: bound on the rows pushed through the ensemble at once while planning; larger
        populations are evaluated in chunks (identical results, flat memory). ``None``: no bound
    :param model_epochs: epochs over all data at every model fit
    :param model_batch_size: minibatch size of the model fit (per member)
    :param model_learning_rate: Adam learning rate of the model
    :param holdout_ratio: fraction of the data held out for early stopping of the model fit
    :param learned_reward: the ensemble also predicts the reward and the planner uses it;
        ``None``: only when no reward is known for the env
    :param reward_fn: ``(obs, action in env units, next_obs) -> [B]`` torch reward; overrides the task registry
    :param termination_fn: ``(obs, action, next_obs) -> bool [B]``; overrides the task registry
    :param learning_starts: random-action steps before planning; ``None``: until the model has been
        fitted once (one episode with the default ``train_freq``)
    :param train_freq: when the model is refit; ``None``: after every episode, or with several envs
        after every episode length's worth of steps
    :param buffer_size: replay buffer size
    :param control: what ``predict`` does: ``"mpc"`` plans every action with the model; ``"policy"`` runs the
        policy network alone (POPLIN-A/P only). Training always collects data with MPC.
    :param stats_window_size: window for rollout logging averages
    :param tensorboard_log: tensorboard log folder
    :param verbose: 0 none, 1 training info, 2 debug
    :param seed: random seed (also seeds the planner's generator)
    :param device: ``"auto"``, ``"cpu"`` or ``"cuda"``
    :param _init_setup_model: build the networks at construction (SB3 interface)
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "pets": POPLINPolicy,
        "rs": POPLINPolicy,
        "poplin-a": POPLINPolicy,
        "poplin-p": POPLINPolicy,
    }
    policy: POPLINPolicy

    def __init__(
        self,
        policy: str | type[POPLINPolicy] = "pets",
        env: GymEnv | str | None = None,
        horizon: int = 30,
        population_size: int = 500,
        num_elites: int = 50,
        cem_iterations: int = 5,
        cem_alpha: float = 0.1,
        init_var: float | None = None,
        cem_sampling: str = "truncated",
        proposal: str = "init",
        noise: str = "sep",
        distillation: str | None = None,
        distill_imagined: bool | None = None,
        distill_window: int | None = 10_000,
        avg_step_size: float = 0.1,
        policy_net_arch: Sequence[int] | None = None,
        policy_learning_rate: float = 3e-3,
        policy_epochs: int | None = None,
        policy_batch_size: int = 64,
        ensemble_size: int = 5,
        dynamics_net_arch: Sequence[int] = (200, 200, 200, 200),
        propagation: str = "expectation",
        num_particles: int = 20,
        planning_dtype: str = "float32",
        max_batch_rows: int | None = 65536,
        model_epochs: int = 5,
        model_batch_size: int = 32,
        model_learning_rate: float = 1e-3,
        holdout_ratio: float = 0.0,
        learned_reward: bool | None = None,
        reward_fn: RewardFn | None = None,
        termination_fn: TerminationFn | None = None,
        learning_starts: int | None = None,
        train_freq: int | tuple[int, str] | None = None,
        buffer_size: int = 1_000_000,
        control: str = "mpc",
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ) -> None:
        if isinstance(policy, str):
            if policy not in self.policy_aliases:
                raise ValueError(f"Unknown POPLIN variant {policy!r}; accepted values: {list(self.policy_aliases)}")
            self.variant = policy
        elif _init_setup_model:
            raise ValueError(f"policy must be a variant name, one of {list(self.policy_aliases)}; got {policy!r}")
        self.task_id = _env_id(env)
        if isinstance(env, str):
            env = gym.make(env, **(make_task(env).env_kwargs if has_task(env) else {}))
        _check_spaces(env)

        self.horizon = horizon
        self.population_size = population_size
        self.num_elites = num_elites
        self.cem_iterations = cem_iterations
        self.cem_alpha = cem_alpha
        self.init_var = init_var
        self.cem_sampling = cem_sampling
        self.proposal = proposal
        self.noise = noise
        self.distillation = distillation
        self.distill_imagined = distill_imagined
        self.distill_window = distill_window
        self.avg_step_size = avg_step_size
        self.policy_net_arch = None if policy_net_arch is None else list(policy_net_arch)
        self.policy_learning_rate = policy_learning_rate
        self.policy_epochs = policy_epochs
        self.policy_batch_size = policy_batch_size
        self.ensemble_size = ensemble_size
        self.dynamics_net_arch = list(dynamics_net_arch)
        self.propagation = propagation
        self.num_particles = num_particles
        self.planning_dtype = planning_dtype
        self.max_batch_rows = max_batch_rows
        self.model_epochs = model_epochs
        self.model_batch_size = model_batch_size
        self.model_learning_rate = model_learning_rate
        self.holdout_ratio = holdout_ratio
        self.learned_reward = learned_reward
        self.user_reward_fn = reward_fn
        self.user_termination_fn = termination_fn
        self._model_fitted = False
        if _init_setup_model:
            self._check_settings()
            self._resolve_variant_defaults()
        self._control = "mpc"

        default_train_freq = train_freq is None
        super().__init__(
            policy=policy,
            env=env,  # type: ignore[arg-type]
            learning_rate=model_learning_rate,
            buffer_size=buffer_size,
            learning_starts=0 if learning_starts is None else learning_starts,
            batch_size=model_batch_size,
            train_freq=(1, "episode") if default_train_freq else train_freq,  # type: ignore[arg-type]
            gradient_steps=1,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            device=device,
            support_multi_env=True,
            seed=seed,
            sde_support=False,
            supported_action_spaces=(spaces.Box,),
        )
        if _init_setup_model and default_train_freq and self.n_envs > 1:
            # SB3 counts episodes with one env only: refit every episode length's worth of steps
            self.train_freq = (_max_episode_steps(self.env) or 1000, "step")
        if _init_setup_model:
            self.control = control
            self._setup_model()

    # ------------------------------------------------------------------ settings
    def _check_positive_ints(self, *names: str, optional: bool = False) -> None:
        """Each named setting must be an integer >= 1 (or None when ``optional``)."""
        for name in names:
            value = getattr(self, name)
            if optional and value is None:
                continue
            if not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")

    def _check_settings(self) -> None:
        self._check_positive_ints(
            "horizon", "population_size", "cem_iterations", "ensemble_size", "model_epochs", "model_batch_size"
        )
        if self.variant != "rs" and not 1 <= self.num_elites <= self.population_size:
            raise ValueError(
                f"num_elites must be between 1 and population_size ({self.population_size}), got {self.num_elites}"
            )
        if not 0.0 <= self.cem_alpha < 1.0:
            raise ValueError(f"cem_alpha must be in [0, 1), got {self.cem_alpha}")
        if self.init_var is not None and not self.init_var > 0:
            raise ValueError(f"init_var must be > 0 (or None for the variant default), got {self.init_var}")
        if self.cem_sampling not in SAMPLINGS:
            raise ValueError(f"Unknown cem_sampling {self.cem_sampling!r}; accepted values: {list(SAMPLINGS)}")
        if self.propagation not in PROPAGATIONS:
            raise ValueError(f"Unknown propagation {self.propagation!r}; accepted values: {list(PROPAGATIONS)}")
        if self.propagation != "expectation" and (self.num_particles < 1 or self.num_particles % self.ensemble_size):
            raise ValueError(
                f"num_particles ({self.num_particles}) must be a positive multiple of ensemble_size "
                f"({self.ensemble_size}) so that each member gets the same number of particles"
            )
        if self.planning_dtype not in PLANNING_DTYPES:
            raise ValueError(f"Unknown planning_dtype {self.planning_dtype!r}; accepted values: {list(PLANNING_DTYPES)}")
        if self.max_batch_rows is not None and self.max_batch_rows < 1:
            raise ValueError(f"max_batch_rows must be >= 1 (or None for no bound), got {self.max_batch_rows}")
        if not 0.0 <= self.holdout_ratio < 1.0:
            raise ValueError(f"holdout_ratio must be in [0, 1), got {self.holdout_ratio}")
        self._check_policy_settings()

    def _check_policy_settings(self) -> None:
        if self.proposal not in PROPOSALS:
            raise ValueError(f"Unknown proposal {self.proposal!r} (POPLIN-A); accepted values: {list(PROPOSALS)}")
        if self.noise not in NOISES:
            raise ValueError(f"Unknown noise {self.noise!r} (POPLIN-P); accepted values: {list(NOISES)}")
        accepted = DISTILLATIONS.get(self.variant, ())
        if self.distillation is not None and self.distillation not in accepted:
            if not accepted:
                raise ValueError(
                    f"The {self.variant!r} variant has no policy network to distill into; got distillation="
                    f"{self.distillation!r}. Leave distillation=None, or use 'poplin-a' / 'poplin-p'."
                )
            raise ValueError(
                f"Unknown distillation {self.distillation!r} for {self.variant!r}; accepted values: {list(accepted)}"
            )
        self._check_positive_ints("policy_batch_size")
        self._check_positive_ints("policy_epochs", "distill_window", optional=True)
        if not 0.0 < self.avg_step_size <= 1.0:
            raise ValueError(f"avg_step_size must be in (0, 1] (1 = the paper's Avg), got {self.avg_step_size}")

    def _resolve_variant_defaults(self) -> None:
        """Resolve every ``None`` default that depends on the variant, in one place."""
        if self.distillation is None and self.variant in DISTILLATIONS:
            self.distillation = DISTILLATIONS[self.variant][0]
        if self.policy_net_arch is None:
            self.policy_net_arch = DEFAULT_POLICY_NET_ARCH[self.variant]
        elif self.variant in ("pets", "rs"):
            raise ValueError(f"The {self.variant!r} variant has no policy network: leave policy_net_arch=None.")
        if self.distill_imagined is None:
            self.distill_imagined = DEFAULT_DISTILL_IMAGINED[self.variant]
        if self.policy_epochs is None:
            self.policy_epochs = 40 if self.distillation == "gan" else 100
        if self.init_var is None:
            self.init_var = DEFAULT_INIT_VAR[self.variant]

    @property
    def control(self) -> str:
        """What ``predict`` does: ``"mpc"`` plans with the model, ``"policy"`` runs the policy network."""
        return self._control

    @control.setter
    def control(self, value: str) -> None:
        if value not in CONTROLS:
            raise ValueError(f"Unknown control {value!r}; accepted values: {list(CONTROLS)}")
        if value == "policy" and self.variant in ("pets", "rs"):
            raise ValueError(
                f"The {self.variant!r} variant has no policy network, so control='policy' is not available: "
                "use control='mpc', or a 'poplin-a' / 'poplin-p' agent."
            )
        self._control = value

    # ------------------------------------------------------------------ setup
    def _resolve_task(self) -> tuple[RewardFn | None, TerminationFn | None, tuple[int, ...]]:
        task = make_task(self.task_id) if self.task_id is not None and has_task(self.task_id) else None
        reward_fn = self.user_reward_fn or (task.reward_fn if task else None)
        termination_fn = self.user_termination_fn or (task.termination_fn if task else None)
        exclude = task.model_input_exclude if task else ()
        if self.learned_reward is None:
            self.learned_reward = reward_fn is None
        if self.learned_reward and termination_fn is None and task is None:
            warnings.warn(
                f"No reward or termination function is known for {self.task_id!r}: the model learns the reward and "
                "the planner assumes episodes never terminate. Pass termination_fn= (or register a TaskSpec with "
                "sb3_poplin.tasks.register_task) if this env can terminate.",
                stacklevel=3,
            )
        return (None if self.learned_reward else reward_fn), termination_fn, tuple(exclude)

    def _make_search_space(self) -> SearchSpace:
        assert self.init_var is not None
        action_dim = int(self.action_space.shape[0])  # type: ignore[index]
        if self.variant == "poplin-a":
            assert self.policy.actor is not None
            return PolicyActionNoise(self.horizon, action_dim, self.init_var, self.policy.actor, self.proposal)
        if self.variant == "poplin-p":
            assert self.policy.actor is not None
            return PolicyParameterNoise(self.horizon, action_dim, self.init_var, self.policy.actor, self.noise)
        return ActionSequences(self.horizon, action_dim, self.init_var)

    def _setup_model(self) -> None:
        reward_fn, termination_fn, exclude = self._resolve_task()
        self.policy_kwargs = dict(
            ensemble_size=self.ensemble_size,
            dynamics_net_arch=self.dynamics_net_arch,
            model_input_exclude=list(exclude),
            learned_reward=self.learned_reward,
            model_learning_rate=self.model_learning_rate,
            policy_net_arch=self.policy_net_arch,
            policy_learning_rate=self.policy_learning_rate,
            discriminator_net_arch=GAN_DISCRIMINATOR_NET_ARCH if self.distillation == "gan" else None,
        )
        self._generator = th.Generator(device=self.device)
        super()._setup_model()
        self.policy.set_training_mode(False)
        optimizer: CEM | RandomShooting
        if self.variant == "rs":
            optimizer = RandomShooting(self.population_size)
        else:
            optimizer = CEM(self.population_size, self.num_elites, self.cem_iterations, self.cem_alpha, self.cem_sampling)
        assert isinstance(self.action_space, spaces.Box)
        self.planner = MPCPlanner(
            model=self.policy.dynamics,
            search_space=self._make_search_space(),
            optimizer=optimizer,
            reward_fn=reward_fn,
            termination_fn=termination_fn,
            propagation=self.propagation,
            num_particles=self.num_particles,
            action_low=th.as_tensor(self.action_space.low, dtype=th.float32, device=self.device),
            action_high=th.as_tensor(self.action_space.high, dtype=th.float32, device=self.device),
            dtype=PLANNING_DTYPES[self.planning_dtype],
            max_batch_rows=self.max_batch_rows,
        )
        self._warm_start: th.Tensor | None = None
        self._plan_return_sum = th.zeros((), device=self.device)
        self._plan_count = 0
        self._fallbacks = 0  # plans with no finite candidate since the last log
        self._fallback_warned = False
        self._collecting = False  # True while SB3's rollout collection asks for an action
        # planned real steps since the last distillation (one dict of tensors per planned step)
        self._planned: list[dict[str, th.Tensor]] = []
        # the BC/GAN dataset: the most recent `distill_window` planned steps (states, actions, imagined actions)
        self._distill_data: dict[str, th.Tensor] = {}
        saved = self.__dict__.pop("_saved_planner_state", None)  # restored by load()
        if saved is not None:
            self._restore_planner_state(saved)

    def set_random_seed(self, seed: int | None = None) -> None:
        """Seed python, numpy, torch, the action space and the planner's generator."""
        super().set_random_seed(seed)
        generator = getattr(self, "_generator", None)
        if generator is not None:
            if seed is None:
                generator.seed()
            else:
                generator.manual_seed(seed)

    # ------------------------------------------------------------------ acting
    def predict(
        self,
        observation: np.ndarray | dict[str, np.ndarray],
        state: Any = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, Any]:
        """
        Plan actions for one observation or a VecEnv batch (all envs in one batched plan).

        The returned state is the planner's warm start (the shifted CEM mean, one row per env);
        pass it back with ``episode_start`` as ``evaluate_policy`` does. Without state and
        episode_start the agent keeps its own warm start between calls (as during training).
        Planning is stochastic either way; ``deterministic`` is accepted for SB3 compatibility and
        executes the final CEM mean, as in the paper.

        :param observation: observation(s) in env units
        :param state: warm start returned by the previous call, or None
        :param episode_start: per-env flags; True resets that env's warm start
        :param deterministic: SB3 interface (see above)
        :return: actions in env units and the new warm start
        """
        if self.control == "policy" and not self._collecting:
            return self.policy.predict(observation, state, episode_start, deterministic)
        obs_tensor, vectorized = self.policy.obs_to_tensor(observation)
        assert isinstance(obs_tensor, th.Tensor)
        obs = obs_tensor.float()
        n_envs = obs.shape[0]
        space = self.planner.search_space
        internal = state is None and episode_start is None
        if internal and self._warm_start is not None and self._warm_start.shape[0] == n_envs:
            mean = self._warm_start
        elif state is None:
            mean = space.initial_mean(n_envs, self.device)
        else:
            mean = th.as_tensor(state, dtype=th.float32, device=self.device)
            if mean.shape != (n_envs, space.dim):
                raise ValueError(
                    f"state has shape {tuple(mean.shape)} but the planner needs ({n_envs}, {space.dim}): pass back the "
                    "state returned by the previous predict() call for the same observations, or None"
                )
        if episode_start is not None:
            reset = th.as_tensor(np.asarray(episode_start, dtype=bool).reshape(-1), device=self.device)
            mean = th.where(reset.unsqueeze(1), space.initial_mean(n_envs, self.device), mean)
        result = self.planner.plan(obs, mean, self._generator)
        if internal:
            self._warm_start = result.next_mean
        self._plan_return_sum = self._plan_return_sum + result.elite_return.sum()
        self._plan_count += n_envs
        # one device-to-host transfer for the actions and the fallback flags
        host = th.cat([self.planner.to_env_units(result.action), result.fallback.unsqueeze(1).float()], dim=1).cpu().numpy()
        actions, fallback = host[:, :-1], host[:, -1] > 0
        if fallback.any():
            self._on_fallback(int(fallback.sum()))
        if self._collecting and self.policy.actor is not None:
            self._record_planned_step(obs, result, th.as_tensor(~fallback, device=self.device))
        if not vectorized:
            actions = actions.squeeze(0)
        return actions, result.next_mean

    @th.no_grad()
    def _record_planned_step(self, obs: th.Tensor, result: PlanResult, keep: th.Tensor) -> None:
        """
        Keep what distillation needs of a planned real step (a failed plan says nothing): the state and
        the executed action; for Avg the executed perturbation block; with ``distill_imagined`` the final
        elites' first actions (or blocks), computed now with the policy the planner used.
        """
        space = self.planner.search_space
        states = obs[keep]
        record = {"states": states, "actions": result.action[keep]}
        if self.distillation == "avg":
            record["blocks"] = space.first_block(result.solution)[keep]
        if self.distill_imagined:
            elite_blocks = space.first_block(result.elites)[keep]  # [b, K, block]
            if self.distillation == "avg":
                record["elite_blocks"] = elite_blocks
            else:
                b, k = elite_blocks.shape[:2]
                imagined = space.executed_action(elite_blocks.flatten(0, 1), states.repeat_interleave(k, dim=0), None)
                record["imagined"] = imagined.view(b, k, -1)  # [b, K, A]
        self._planned.append(record)

    def _on_fallback(self, count: int) -> None:
        self._fallbacks += count
        if not self._fallback_warned:
            self._fallback_warned = True
            fallback = "the policy network's action" if self.policy.actor is not None else "the action-space centre"
            warnings.warn(
                f"No planned candidate had a finite return (the model or the observation produced NaN/inf): "
                f"executing {fallback} instead. Counted in the logger as plan/fallbacks; warned once.",
                stacklevel=3,
            )

    def _sample_action(
        self, learning_starts: int, action_noise: ActionNoise | None = None, n_envs: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        # The original: uniform random actions until the model has been trained once.
        if not self._model_fitted:
            learning_starts = max(learning_starts, self.num_timesteps + 1)
        self._collecting = True  # training always plans (MPC), whatever `control` says
        try:
            return super()._sample_action(learning_starts, action_noise, n_envs)
        finally:
            self._collecting = False

    def _store_transition(
        self,
        replay_buffer: ReplayBuffer,
        buffer_action: np.ndarray,
        new_obs: np.ndarray | dict[str, np.ndarray],
        reward: np.ndarray,
        dones: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        super()._store_transition(replay_buffer, buffer_action, new_obs, reward, dones, infos)
        if np.any(dones):
            self._record_plan_stats()  # logged with the episode they describe (SB3 dumps right after)
        if self._warm_start is not None and np.any(dones):
            reset = th.as_tensor(np.asarray(dones, dtype=bool), device=self.device)
            fresh = self.planner.search_space.initial_mean(len(dones), self.device)
            self._warm_start = th.where(reset.unsqueeze(1), fresh, self._warm_start)

    def _record_plan_stats(self) -> None:
        """Log the planner's statistics since the last call: mean elite return and fallbacks."""
        if self._plan_count:
            self.logger.record("plan/elite_return", (self._plan_return_sum / self._plan_count).item())
            self.logger.record("plan/fallbacks", self._fallbacks)
        self._plan_return_sum = th.zeros((), device=self.device)
        self._plan_count = 0
        self._fallbacks = 0

    # ------------------------------------------------------------------ training
    def _transitions(self) -> tuple[th.Tensor, th.Tensor, th.Tensor, th.Tensor]:
        """All stored transitions as float32 tensors: obs, scaled actions, next obs, rewards."""
        buffer = self.replay_buffer
        assert buffer is not None
        upper = buffer.buffer_size if buffer.full else buffer.pos

        def flat(array: np.ndarray) -> th.Tensor:
            array = array[:upper]
            return th.as_tensor(array.reshape(upper * array.shape[1], -1), dtype=th.float32, device=self.device)

        return flat(buffer.observations), flat(buffer.actions), flat(buffer.next_observations), flat(buffer.rewards)[:, 0]

    def _distill(self) -> dict[str, float]:
        """Train the policy network from the planned steps (Avg: those since the last call; BC/GAN: the window)."""
        actor = self.policy.actor
        if actor is None or not self._planned:
            return {}
        new = {key: th.cat([record[key] for record in self._planned]) for key in self._planned[0]}
        self._planned = []
        if self.distillation == "avg":  # perturbations are relative to the theta they were planned with
            blocks = new["blocks"]
            if "elite_blocks" in new:
                blocks = th.cat([blocks, new["elite_blocks"].flatten(0, 1)])
            stats = average_perturbation(actor, blocks, self.avg_step_size)
            actor.update_whitening(new["states"])
            return {**stats, "policy_saturation": saturated_fraction(actor, new["states"])}
        for key, value in new.items():
            kept = th.cat([self._distill_data[key], value]) if key in self._distill_data else value
            self._distill_data[key] = kept if self.distill_window is None else kept[-self.distill_window :]
        data = new if self.distill_window is None else self._distill_data
        states, targets = data["states"], data["actions"]
        if "imagined" in data:
            k = data["imagined"].shape[1]
            states = th.cat([states, states.repeat_interleave(k, dim=0)])
            targets = th.cat([targets, data["imagined"].flatten(0, 1)])
        actor.update_whitening(new["states"])  # changes the parametrisation, not the function
        assert self.policy_epochs is not None
        with th.enable_grad():
            if self.distillation == "gan":
                assert self.policy.discriminator is not None and self.init_var is not None
                stats = gan_distillation(
                    actor,
                    self.policy.actor_optimizer,
                    self.policy.discriminator,
                    self.policy.discriminator_optimizer,
                    states,
                    targets,
                    noise_var=self.init_var,
                    epochs=self.policy_epochs,
                    batch_size=self.policy_batch_size,
                    generator=self._generator,
                )
            else:
                stats = behaviour_cloning(
                    actor,
                    self.policy.actor_optimizer,
                    states,
                    targets,
                    epochs=self.policy_epochs,
                    batch_size=self.policy_batch_size,
                    generator=self._generator,
                )
        saturation = saturated_fraction(actor, new["states"])
        return {**stats, "policy_samples": float(states.shape[0]), "policy_saturation": saturation}

    def train(self, gradient_steps: int, batch_size: int) -> None:
        """Refit the dynamics model on all data (``model_epochs`` epochs), then distill the policy."""
        self.policy.set_training_mode(True)
        obs, actions, next_obs, rewards = self._transitions()
        result = self.policy.dynamics.fit(
            obs,
            actions,
            next_obs,
            self.policy.dynamics_optimizer,
            rewards=rewards if self.learned_reward else None,
            epochs=self.model_epochs,
            batch_size=self.model_batch_size,
            holdout_ratio=self.holdout_ratio,
            generator=self._generator,
        )
        distill_stats = self._distill()
        self.policy.set_training_mode(False)
        self._model_fitted = True
        for key, value in distill_stats.items():
            self.logger.record(f"train/{key}", value)
        self._n_updates += 1
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/model_loss", result.loss)
        self.logger.record("train/model_mse", result.train_mse)
        if not math.isnan(result.holdout_mse):
            self.logger.record("train/model_holdout_mse", result.holdout_mse)
        self.logger.record("train/model_epochs", result.epochs)
        self.logger.record("train/n_transitions", int(obs.shape[0]))

    def learn(
        self: SelfPOPLIN,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 1,
        tb_log_name: str = "POPLIN",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfPOPLIN:
        return super().learn(
            total_timesteps=total_timesteps,
            callback=callback,
            log_interval=log_interval,
            tb_log_name=tb_log_name,
            reset_num_timesteps=reset_num_timesteps,
            progress_bar=progress_bar,
        )

    # ------------------------------------------------------------------ saving
    def _restore_planner_state(self, saved: dict[str, Any]) -> None:
        try:
            self._generator.set_state(saved["generator"])
        except (RuntimeError, TypeError):  # saved on another kind of device: keep the seeded generator
            warnings.warn("The planner's random state was saved on another device and is not restored.", stacklevel=2)
        warm = saved.get("warm_start")
        self._warm_start = None if warm is None else warm.to(self.device)
        self._distill_data = {key: value.to(self.device) for key, value in saved.get("distill_data", {}).items()}
        self._planned = [{key: value.to(self.device) for key, value in record.items()} for record in saved.get("planned", [])]

    def save(
        self,
        path: str | pathlib.Path | io.BufferedIOBase,
        exclude: Iterable[str] | None = None,
        include: Iterable[str] | None = None,
    ) -> None:
        """
        Save everything needed to plan and to keep training: settings, networks and normalisers,
        optimizers, the control mode, the planner's random state, its warm start and the planned steps
        not yet distilled (not the replay buffer: ``save_replay_buffer``).
        """
        warm = None if self._warm_start is None else self._warm_start.detach().cpu()
        self._saved_planner_state = {
            "generator": self._generator.get_state(),
            "warm_start": warm,
            "distill_data": {key: value.detach().cpu() for key, value in self._distill_data.items()},
            # planned steps since the last distillation: a save in mid-episode must not drop them
            "planned": [{key: value.detach().cpu() for key, value in record.items()} for record in self._planned],
        }
        try:
            super().save(path, exclude, include)
        finally:
            del self._saved_planner_state

    @classmethod
    def load(  # type: ignore[override]
        cls: type[SelfPOPLIN],
        path: str | pathlib.Path | io.BufferedIOBase,
        env: GymEnv | None = None,
        device: th.device | str = "auto",
        custom_objects: dict[str, Any] | None = None,
        print_system_info: bool = False,
        force_reset: bool = True,
        control: str | None = None,
        **kwargs: Any,
    ) -> SelfPOPLIN:
        """
        Load a saved agent (an env is optional: planning needs none). Same arguments as SB3's
        ``load``, plus:

        :param control: ``"mpc"`` or ``"policy"`` to override the saved control mode
        """
        _check_saved_agent(path)
        model = super().load(path, env, device, custom_objects, print_system_info, force_reset, **kwargs)
        if control is not None:
            model.control = control
        return model

    def _excluded_save_params(self) -> list[str]:
        return [
            *super()._excluded_save_params(),
            "planner",
            "_generator",
            "_warm_start",
            "_plan_return_sum",
            "_planned",
            "_distill_data",
        ]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        return ["policy", *self.policy.optimizer_names()], []
