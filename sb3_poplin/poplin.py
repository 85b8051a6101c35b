"""
POPLIN as a Stable-Baselines3 algorithm: SB3 glue only.

:class:`POPLIN` subclasses ``OffPolicyAlgorithm``: SB3 runs the loop, the replay buffer, logging, callbacks and
save/load. The parts live elsewhere: the variants, their defaults and the settings' validation in
:mod:`sb3_poplin.variants`; the networks in :mod:`sb3_poplin.policies`; MPC (planner, warm starts, plan statistics)
in :class:`sb3_poplin.planning.MPCController`; what is distilled and how in
:class:`sb3_poplin.distillation.Distiller`; the env's task in :mod:`sb3_poplin.tasks`; zip checks in
:mod:`sb3_poplin.saving`. This module wires them into SB3: ``predict`` (MPC or policy control), ``train`` (fit the
model after each episode, then distill) and the save hooks.

Loop (Wang & Ba 2019, after PETS): uniform random actions until the model has been fitted once (one episode by
default), then after every ``train_freq`` period (one episode) fit the model on all data and collect the next
period with MPC.
"""

from __future__ import annotations

import hashlib
import io
import math
import pathlib
from dataclasses import replace
from collections.abc import Iterable, Sequence
from typing import Any, ClassVar, TypeVar

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.save_util import load_from_zip_file, recursive_getattr, save_to_zip_file
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, TensorDict

from sb3_poplin import compat, saving, variants
from sb3_poplin.distillation import Distiller
from sb3_poplin.dynamics import FitResult
from sb3_poplin.planning import MPCController, MPCPlanner, PolicySearchSpace
from sb3_poplin.policies import POPLINPolicy
from sb3_poplin.tasks import (
    ModelHooks,
    RewardFn,
    TerminationFn,
    check_spaces,
    env_id,
    max_episode_steps,
    resolve_task,
    task_env_kwargs,
    task_hooks,
)

SelfPOPLIN = TypeVar("SelfPOPLIN", bound="POPLIN")


def replay_transitions(buffer: ReplayBuffer, device: th.device) -> tuple[th.Tensor, th.Tensor, th.Tensor, th.Tensor]:
    """All stored transitions of a replay buffer as float32 tensors: obs, scaled actions, next obs, rewards."""
    upper = buffer.buffer_size if buffer.full else buffer.pos

    def flat(array: np.ndarray) -> th.Tensor:
        array = array[:upper]
        return th.as_tensor(array.reshape(upper * array.shape[1], -1), dtype=th.float32, device=device)

    return flat(buffer.observations), flat(buffer.actions), flat(buffer.next_observations), flat(buffer.rewards)[:, 0]


class POPLIN(OffPolicyAlgorithm):
    """
    Model-based planning with a learned probabilistic ensemble: POPLIN-A, POPLIN-P, and the PETS
    and random-shooting baselines. Paper: https://arxiv.org/abs/1906.08649 (Wang & Ba, 2019);
    PETS: https://arxiv.org/abs/1805.12114 (Chua et al., 2018).

    :param policy: the variant: ``"pets"`` (CEM over action sequences), ``"rs"`` (random shooting),
        ``"poplin-a"`` (CEM over action noise around a policy network's proposals) or ``"poplin-p"``
        (CEM over noise on the policy network's parameters); or one of the paper's named configurations
        (``"poplin-a/replan"``, ``"poplin-p/sep/bc"``, ...: :data:`sb3_poplin.variants.NAMED_CONFIGURATIONS`), which
        sets the variant and its options (``proposal``, ``noise``, ``distillation``)
    :param env: env id or (Vec)Env with a Box action space (any shape: the planner works on the flattened actions, a
        ``reward_fn`` gets them flat) and a flat Box observation space
    :param horizon: planning horizon H
    :param population_size: candidates per CEM iteration (random shooting: the number of samples)
    :param num_elites: elites per CEM iteration
    :param cem_iterations: CEM iterations per env step
    :param cem_alpha: CEM momentum: ``new = alpha * old + (1 - alpha) * elite``, in [0, 1)
    :param init_var: initial CEM variance of the search space; ``None`` for the variant default
        (PETS and POPLIN-A 0.25, in scaled action units; POPLIN-P 0.1, in parameter units)
    :param cem_sampling: ``"truncated"`` (normal truncated at 2 sigma) or ``"clipped"``
    :param optimizer: what searches: ``"cem"`` (PETS/POPLIN's CEM) or ``"icem"`` (iCEM's defaults: colored noise,
        kept and shifted elites, population decay, the mean as a candidate, the best candidate executed); ``None``:
        the variant's own (random shooting for ``"rs"``, else ``"cem"``)
    :param optimizer_kwargs: iCEM's options, each on its own, over the optimizer's defaults
        (:class:`sb3_poplin.planning.CEMOptions`: ``noise_beta``, ``keep_elites``, ``shift_elites``,
        ``population_decay``, ``add_mean``, ``execute``), e.g. ``dict(noise_beta=0.25)``
    :param proposal: POPLIN-A only: ``"init"`` (policy rolled open-loop through the model once per plan)
        or ``"replan"`` (policy re-queried on every imagined state)
    :param noise: POPLIN-P only: ``"sep"`` (one parameter-noise block per planning step) or ``"uni"``
        (one block shared by all steps)
    :param distillation: how the policy network learns from the planner after each episode:
        POPLIN-A ``"bc"``; POPLIN-P ``"avg"`` (default), ``"bc"`` or ``"gan"``; ``None`` for the default
    :param distill_imagined: also distill the final CEM elites' first steps ("imagined" data);
        ``None``: POPLIN-A yes (BC-AI), POPLIN-P no
    :param distill_window: BC and GAN train on the most recent ``distill_window`` planned real steps (recorded
        when acting, so they stay valid targets as the policy changes); ``None``: only the steps since the last
        distillation, as in the original code; ``"auto"``: the variant's default (POPLIN-A 10 000, POPLIN-P
        ``None``; why: docs/results.md). Avg always uses the steps since the last update.
    :param avg_update: POPLIN-P Avg only: ``"overwrite"`` (``theta <- mean(omega)``, what the original code does:
        from the second update on the search runs around near-zero weights) or ``"add"`` (``theta <- theta +
        avg_step_size * mean(omega)``); why overwrite is the default: docs/results.md
    :param avg_step_size: ``avg_update="add"`` only: the step, in (0, 1]. 1 is the paper's equation, which drives the
        clipped policy output into saturation within a few episodes (a policy stuck at full torque that the
        parameter noise cannot leave); 0.1 averages the planner's perturbations over about ten episodes
    :param distill_target: BC's and GAN's target actions: ``"executed"`` (the executed actions, clipped to the
        bounds) or ``"planned"`` (the planner's first action before the clip; POPLIN-P: the network it planned
        with, perturbed by the executed perturbation: the original's BC-PR target). GAN's fake samples are clipped
        like the targets. ``None``: the variant's default, as the original code: POPLIN-A ``"executed"`` (BC-AI),
        POPLIN-P ``"planned"`` (BC-PR; why: docs/results.md)
    :param whitening: what updating the policy's input whitening does to its first layer: ``"function"``
        (the first update only sets the statistics, so the normc network starts on whitened inputs; later updates
        re-express the layer so that the network's function is unchanged), ``"function_from_raw"`` (the first
        update re-expresses too, keeping the initial network's function of raw observations: sb3_poplin 0.2.0)
        or ``"plain"`` (never re-express: the original code)
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
    :param standardise_targets: the dynamics model standardises its training targets per dimension (statistics
        refit before every fit, the learned log-variance bounds then act in standardised units); ``False`` (the
        default; why: docs/results.md): it predicts them in env units, as PETS's code did
    :param learned_reward: the ensemble also predicts the reward and the planner uses it;
        ``None``: only when no reward is known for the env
    :param reward_fn: ``(obs, action in env units, next_obs) -> [B]`` torch reward; overrides the task registry
    :param termination_fn: ``(obs, action, next_obs) -> bool [B]``; overrides the task registry
    :param model_hooks: how the networks see observations (:class:`sb3_poplin.tasks.ModelHooks`: the model's input
        features and targets, the policy's inputs), e.g. ``LocomotionHooks(...).hooks(policy=True)``; ``None``: the
        task's (:attr:`TaskSpec.hooks <sb3_poplin.tasks.TaskSpec.hooks>`). Saved with the agent: a loaded agent's
        networks are built from the hooks it was trained with
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
    :param policy_kwargs: not taken: POPLIN's networks are set by its own keyword arguments (``policy_net_arch``,
        ``dynamics_net_arch``, ``ensemble_size``, ...); giving it raises a ``TypeError`` that names them
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        name: POPLINPolicy for name in (*variants.VARIANTS, *variants.NAMED_CONFIGURATIONS)
    }
    policy: POPLINPolicy
    mpc: MPCController
    distiller: Distiller | None
    # every setting, resolved (variants.resolve_settings): what the planner, the networks, the fit and the distillation
    # are built from. A zip holds each under its own name in its data, as every release saved them
    settings: variants.Settings
    # the networks' observation handling, saved with the agent (a loaded agent keeps the hooks it was trained with)
    model_hooks: ModelHooks
    # not a keyword argument: the release that saved the zip this agent was loaded from (None for an agent made here;
    # ``save`` records the running release, not this one)
    sb3_poplin_version: str | None

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
        optimizer: str | None = None,
        optimizer_kwargs: dict[str, Any] | None = None,
        proposal: str = "init",
        noise: str = "sep",
        distillation: str | None = None,
        distill_imagined: bool | None = None,
        distill_window: int | str | None = "auto",
        avg_update: str = "overwrite",
        avg_step_size: float = 0.1,
        distill_target: str | None = None,
        whitening: str = "function",
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
        standardise_targets: bool = False,
        learned_reward: bool | None = None,
        reward_fn: RewardFn | None = None,
        termination_fn: TerminationFn | None = None,
        model_hooks: ModelHooks | None = None,
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
        policy_kwargs: dict[str, Any] | None = None,
    ) -> None:
        if policy_kwargs is not None:
            raise TypeError(
                f"POPLIN takes no policy_kwargs (got {policy_kwargs!r}): its networks are set by its own keyword "
                "arguments: policy_net_arch (the policy network's hidden widths), dynamics_net_arch and ensemble_size "
                "(the model), policy_learning_rate, model_learning_rate. E.g. POPLIN('poplin-p', env, "
                "policy_net_arch=[64, 64], dynamics_net_arch=[200, 200, 200])."
            )
        given = {name: value for name, value in locals().items() if name in variants.SETTINGS}
        if isinstance(policy, str):
            policy, given = variants.apply_configuration(policy, given, DEFAULT_SETTINGS)
            self.variant = variants.variant(policy).name
        elif _init_setup_model:
            raise ValueError(f"policy must be a variant name, one of {list(self.policy_aliases)}; got {policy!r}")
        self.task_id = env_id(env)
        if isinstance(env, str):
            env = gym.make(env, **task_env_kwargs(env))
        check_spaces(env)
        if _init_setup_model:  # else (load) the zip's data brings the settings
            self.settings = variants.resolve_settings(self.variant, given)
            variants.check_control(self.variant, control)
        self._control = control
        self.user_reward_fn = reward_fn
        self.user_termination_fn = termination_fn
        self._model_fitted = False
        if model_hooks is not None and not isinstance(model_hooks, ModelHooks):
            raise TypeError(
                f"model_hooks must be a sb3_poplin.tasks.ModelHooks, got {type(model_hooks).__name__}: e.g. "
                "ModelHooks(model_input_exclude=(0,)), or LocomotionHooks(...).hooks(policy=True)."
            )
        if model_hooks is not None or _init_setup_model:  # else (load) the zip's, or for an earlier release's compat's
            self.model_hooks = model_hooks if model_hooks is not None else task_hooks(self.task_id)
        self.sb3_poplin_version = None

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
            self.train_freq = (max_episode_steps(self.env) or 1000, "step")
        if _init_setup_model:
            self._setup_model()

    @property
    def control(self) -> str:
        """What ``predict`` does: ``"mpc"`` plans with the model, ``"policy"`` runs the policy network."""
        return self._control

    @control.setter
    def control(self, value: str) -> None:
        variants.check_control(self.variant, value)
        self._control = value

    def _collect_settings(self) -> None:
        """
        Settings found as attributes (a zip's data, or settings given to ``load``) become :attr:`settings`, over the
        agent's own or, for an agent being loaded, the constructor's defaults; resolved and validated again.
        """
        found = {key: self.__dict__.pop(key) for key in variants.SETTINGS if key in self.__dict__}
        if not found and "settings" in self.__dict__:
            return
        start = self.settings.as_dict() if "settings" in self.__dict__ else DEFAULT_SETTINGS
        self.settings = variants.resolve_settings(self.variant, {**start, **found})

    def _setup_model(self) -> None:
        self._collect_settings()
        for key in compat.DROPPED_DATA_KEYS:  # zips of earlier releases
            self.__dict__.pop(key, None)
        if getattr(self, "model_hooks", None) is None:
            raise ValueError("This agent has no model hooks: load it with POPLIN.load, or pass model_hooks=.")
        reward_fn, termination_fn, learned_reward = resolve_task(
            self.task_id, self.user_reward_fn, self.user_termination_fn, self.settings.learned_reward
        )
        self.settings = replace(self.settings, learned_reward=learned_reward)
        settings = self.settings
        self.policy_kwargs = dict(
            ensemble_size=settings.ensemble_size,
            dynamics_net_arch=settings.dynamics_net_arch,
            **self.model_hooks.network_kwargs(),
            standardise_targets=settings.standardise_targets,
            learned_reward=settings.learned_reward,
            model_learning_rate=settings.model_learning_rate,
            policy_net_arch=settings.policy_net_arch,
            policy_learning_rate=settings.policy_learning_rate,
            discriminator_net_arch=list(variants.GAN_DISCRIMINATOR_NET_ARCH) if settings.distillation == "gan" else None,
        )
        super()._setup_model()
        self.policy.set_training_mode(False)
        assert isinstance(self.action_space, spaces.Box)
        planner = variants.build_planner(
            self.variant,
            settings,
            self.policy.dynamics,
            self.policy.actor,
            reward_fn,
            termination_fn,
            self.action_space,
            self.device,
        )
        self.mpc = MPCController(planner, self.device)
        self.mpc.seed(self.seed)  # SB3 seeded everything else at the start of _setup_model
        self.distiller = None
        if self.policy.actor is not None:
            assert isinstance(planner.search_space, PolicySearchSpace) and settings.distillation is not None
            self.distiller = Distiller(
                settings.distillation,
                planner.search_space,
                self.policy,
                imagined=settings.distill_imagined,
                window=settings.distill_window,
                avg_step_size=settings.avg_step_size,
                epochs=settings.policy_epochs,
                batch_size=settings.policy_batch_size,
                noise_var=settings.init_var,
                avg_update=settings.avg_update,
                target=settings.distill_target,
                whitening=settings.whitening,
            )

    @property
    def planner(self) -> MPCPlanner:
        """The MPC planner: the search space, the optimizer and the rollout through the model."""
        return self.mpc.planner

    def set_random_seed(self, seed: int | None = None) -> None:
        """Seed python, numpy, torch, the action space and the planner's generator."""
        super().set_random_seed(seed)
        if hasattr(self, "mpc"):
            self.mpc.seed(seed)

    # ------------------------------------------------------------------ acting
    def predict(
        self,
        observation: np.ndarray | dict[str, np.ndarray],
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        """
        The action for one observation or a VecEnv batch: planned with the model (``control="mpc"``, all envs in
        one batched plan) or the policy network's (``control="policy"``).

        Under MPC the returned state is the planner's warm start (the shifted CEM solution, one row per env, as a
        numpy array): pass it back with ``episode_start``, as ``evaluate_policy`` does, so that each plan starts from
        the previous step's; ``state=None`` plans from a fresh start. The action is a function of the arguments:
        with ``deterministic=True`` the planner's random numbers are a fixed function of the agent's seed and the
        inputs (the same call gives the same action, also after save/load); with ``deterministic=False`` they are
        fresh draws from the planner's generator. Either way the executed action is the planner's (PETS/CEM: the
        final mean's first action, as in the paper). The training rollout plans with its own warm start instead
        (:meth:`_sample_action`).

        :param observation: observation(s) in env units
        :param state: warm start returned by the previous call, or None
        :param episode_start: per-env flags; True resets that env's warm start
        :param deterministic: plan with random numbers fixed by the seed and the inputs (see above)
        :return: actions in env units (the action space's shape and dtype) and the new warm start
        """
        if isinstance(observation, tuple) and len(observation) == 2 and isinstance(observation[1], dict):
            raise ValueError(
                "predict() got a tuple (observation, info): the return value of a gymnasium env's reset(). Pass the "
                "observation alone: obs, info = env.reset(); model.predict(obs). (A VecEnv's reset() returns the "
                "observations only.)"
            )
        if self.control == "policy":
            return self.policy.predict(observation, state, episode_start, deterministic)
        obs, vectorized = self._obs_tensor(observation)
        generator = self._deterministic_generator(observation, state) if deterministic else None
        step = self.mpc.step(obs, state, episode_start, generator)  # type: ignore[arg-type]
        actions = self._env_actions(step.actions)
        return (actions if vectorized else actions[0]), step.state  # type: ignore[return-value]

    def _obs_tensor(self, observation: np.ndarray | dict[str, np.ndarray]) -> tuple[th.Tensor, bool]:
        """:return: the observation(s) as a float32 ``[n_envs, o]`` tensor on the device, and whether a batch was given"""
        obs_tensor, vectorized = self.policy.obs_to_tensor(observation)
        assert isinstance(obs_tensor, th.Tensor)
        return obs_tensor.float(), vectorized

    def _env_actions(self, actions: np.ndarray) -> np.ndarray:
        """Planned actions ``[n_envs, A]`` in the action space's shape and dtype."""
        assert isinstance(self.action_space, spaces.Box)
        return actions.reshape((-1, *self.action_space.shape)).astype(self.action_space.dtype, copy=False)

    def _deterministic_generator(self, observation: Any, state: Any) -> th.Generator:
        """A generator seeded by the agent's seed, the observations and the warm start: ``deterministic=True``."""
        digest = hashlib.blake2b(np.int64(self.seed or 0).tobytes(), digest_size=8)
        digest.update(np.ascontiguousarray(observation, dtype=np.float32).tobytes())  # host data: no device round trip
        if state is not None:
            digest.update(np.ascontiguousarray(state, dtype=np.float32).tobytes())
        generator = th.Generator(device=self.device)
        generator.manual_seed(int.from_bytes(digest.digest(), "little") & (2**63 - 1))
        return generator

    def _sample_action(
        self, learning_starts: int, action_noise: ActionNoise | None = None, n_envs: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        """
        The training rollout's actions, whatever ``control`` says: uniform random actions until the model has been
        fitted once (the original's start), then MPC from the agent's own warm start (reset per env at episode ends)
        with the planner's generator; the plans are recorded for distillation.

        :return: the actions in env units and as the replay buffer stores them (scaled to [-1, 1])
        """
        if not self._model_fitted:
            learning_starts = max(learning_starts, self.num_timesteps + 1)
        assert isinstance(self.action_space, spaces.Box)
        if self.num_timesteps < learning_starts:
            unscaled = np.array([self.action_space.sample() for _ in range(n_envs)])
        else:
            assert isinstance(self._last_obs, np.ndarray)
            obs, _ = self._obs_tensor(self._last_obs)
            step = self.mpc.collect(obs)
            if self.distiller is not None:
                self.distiller.record(obs, step.plan)
            unscaled = self._env_actions(step.actions)
        scaled = self.policy.scale_action(unscaled)
        if action_noise is not None:
            scaled = np.clip(scaled + action_noise(), -1, 1)
        return self.policy.unscale_action(scaled), scaled

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
            # logged with the episode they describe (SB3 dumps right after)
            for key, value in self.mpc.pop_statistics().items():
                self.logger.record(key, value)
            self.mpc.episodes_ended(dones)

    # ------------------------------------------------------------------ training
    def train(self, gradient_steps: int, batch_size: int) -> None:
        """Refit the dynamics model on all data (``model_epochs`` epochs), then distill the policy."""
        self.policy.set_training_mode(True)
        assert self.replay_buffer is not None
        obs, actions, next_obs, rewards = replay_transitions(self.replay_buffer, self.device)
        result = self.fit_dynamics(obs, actions, next_obs, rewards)
        distill_stats = {} if self.distiller is None else self.distiller.distill(self.mpc.generator)
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

    def fit_dynamics(self, obs: th.Tensor, actions: th.Tensor, next_obs: th.Tensor, rewards: th.Tensor) -> FitResult:
        """
        One refit of the dynamics ensemble on the given transitions, as :meth:`train` does after every episode:
        ``model_epochs`` epochs (early stopping with ``holdout_ratio``), the agent's persistent model optimizer and
        its planner's random generator. ``python -m sb3_poplin.analysis model-quality`` replays a recorded dataset
        through this method.

        :param obs: ``[B, o]`` observations
        :param actions: ``[B, a]`` actions scaled to [-1, 1] (as the replay buffer stores them)
        :param next_obs: ``[B, o]`` next observations
        :param rewards: ``[B]`` rewards (a target only with ``learned_reward``)
        :return: the fit's :class:`~sb3_poplin.dynamics.FitResult`
        """
        return self.policy.dynamics.fit(
            obs,
            actions,
            next_obs,
            self.policy.dynamics_optimizer,
            rewards=rewards if self.settings.learned_reward else None,
            epochs=self.settings.model_epochs,
            batch_size=self.settings.model_batch_size,
            holdout_ratio=self.settings.holdout_ratio,
            generator=self.mpc.generator,
        )

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
    @classmethod
    def load(  # type: ignore[override]
        cls: type[SelfPOPLIN],
        path: str | pathlib.Path | io.BufferedIOBase,
        env: GymEnv | str | None = None,
        device: th.device | str = "auto",
        custom_objects: dict[str, Any] | None = None,
        print_system_info: bool = False,
        force_reset: bool = True,
        control: str | None = None,
        **kwargs: Any,
    ) -> SelfPOPLIN:
        """
        Load a saved agent (an env is optional: planning needs none). Its networks are built with the model hooks it
        saved, whatever the task's are now; a zip of an earlier release continues as it was trained (see
        :mod:`sb3_poplin.compat` for which). ``sb3_poplin_version`` names the release that saved the zip. Same
        arguments as SB3's ``load`` (``env`` may also be an env id, made with the task's env kwargs as the constructor
        does; a setting given as a keyword, ``model_hooks=`` too, replaces the saved one), plus:

        :param control: ``"mpc"`` or ``"policy"`` to override the saved control mode
        :raises TypeError: a keyword that is neither a setting nor an attribute the zip holds (SB3 would set a
            misspelt ``populaton_size=`` on the agent, where nothing reads it)
        """
        if kwargs.get("model_hooks") is None:  # model_hooks=None: the saved ones
            kwargs.pop("model_hooks", None)
            if (custom_objects or {}).get("model_hooks") is not None:  # also for a zip without the record
                kwargs["model_hooks"] = custom_objects["model_hooks"]  # type: ignore[index]
        # a zip of an earlier release continues as it was trained (sb3_poplin.compat)
        restored = saving.check_saved_agent(
            path, custom_objects, hooks_given="model_hooks" in kwargs, given=kwargs, settings=variants.SETTINGS
        )
        kwargs = {**restored, **kwargs}
        if isinstance(env, str):  # an env id, as the constructor takes
            env = gym.make(env, **task_env_kwargs(env))
        model = super().load(path, env, device, custom_objects, print_system_info, force_reset, **kwargs)
        if control is not None:
            model.control = control
        return model

    def save(
        self,
        path: str | pathlib.Path | io.BufferedIOBase,
        exclude: Iterable[str] | None = None,
        include: Iterable[str] | None = None,
    ) -> None:
        """
        SB3's ``save``: the zip's ``data`` (every setting under its own name, and ``sb3_poplin_version``: the running
        release, also when this agent was loaded from a zip of another release), the networks' and optimizers'
        ``.pth`` files (:meth:`get_parameters`), and beside them the planner's state (``mpc.pth``: random generator
        and warm start) and, for POPLIN-A/P, the distiller's (``distiller.pth``), so that a loaded agent continues
        training exactly where this one is.

        :param path: path to the file where the agent should be saved
        :param exclude: names of attributes to exclude in addition to the default ones
        :param include: names of attributes that might be excluded but should be included anyway
        """
        dropped = set(exclude or ()) | set(self._excluded_save_params())
        dropped -= set(include or ())
        state_dicts, torch_variables = self._get_torch_save_params()
        dropped |= {name.split(".")[0] for name in (*state_dicts, *torch_variables)}
        data = {key: value for key, value in self.__dict__.items() if key not in dropped}
        data.update(self.settings.as_dict(), sb3_poplin_version=saving.current_release())
        params = {**self.get_parameters(), **self.planner_state_dict()}
        variables = {name: recursive_getattr(self, name) for name in torch_variables}
        save_to_zip_file(path, data=data, params=params, pytorch_variables=variables)

    def planner_state_dict(self) -> dict[str, dict[str, Any]]:
        """
        What the agent carries beside its parameters, saved with it: the MPC controller's state (the planner's random
        generator, the training rollout's warm start) and the distiller's (the planned steps not yet distilled).

        :return: attribute name -> state dict
        """
        state = {"mpc": self.mpc.state_dict()}
        if self.distiller is not None:
            state["distiller"] = self.distiller.state_dict()
        return state

    def _excluded_save_params(self) -> list[str]:
        # settings: saved by name (see save); mpc, distiller: their state is saved beside the parameters
        return [*super()._excluded_save_params(), "settings", *PLANNER_STATE]

    def set_parameters(
        self, load_path_or_dict: str | TensorDict, exact_match: bool = True, device: th.device | str = "auto"
    ) -> None:
        """
        SB3's ``set_parameters`` (what :meth:`get_parameters` returns: the networks and optimizers). A zip, or a dict
        read from one, also holds the planner's and distiller's state (:meth:`planner_state_dict`): restored too (a
        0.1.0 zip's planner state, restored into ``data`` by ``load``, is upgraded).
        """
        params: dict[str, Any]
        if isinstance(load_path_or_dict, dict):
            params = dict(load_path_or_dict)
        else:
            _, loaded, _ = load_from_zip_file(load_path_or_dict, device=device, load_data=False)
            params = dict(loaded or {})
        state: dict[str, Any] = {name: params.pop(name) for name in PLANNER_STATE if name in params}
        legacy = self.__dict__.pop("_saved_planner_state", None)
        if legacy is not None:
            state = {**compat.upgrade_legacy_state(legacy, with_distiller=self.distiller is not None), **state}
        super().set_parameters(params, exact_match, device)  # type: ignore[arg-type]
        if "distiller" in state and self.distiller is None:
            raise ValueError(
                "The given state has a distiller's state but this agent has no policy network to distill into: it "
                f"comes from a POPLIN-A/P agent, this one is {self.variant!r}. Load it into an agent of its variant."
            )
        for name, value in state.items():
            getattr(self, name).load_state_dict(value)

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        # the parameters: the networks and their optimizers (the planner's state is saved beside them, see save)
        return ["policy", *self.policy.optimizer_names()], []


# attributes whose state a zip holds beside the parameters (POPLIN.planner_state_dict)
PLANNER_STATE = ("mpc", "distiller")
# the constructor's defaults of the settings: what a setting missing from a loaded zip starts from
DEFAULT_SETTINGS = variants.DEFAULT_SETTINGS
