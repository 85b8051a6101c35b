"""
The variants, in one table: what each searches, with which optimizer and defaults, what it distills; the one place
where settings are validated and every ``None`` default is resolved; the named configurations of the paper
(``"poplin-p/sep/avg"``, ...); and the planner built from a variant and its settings.

A variant is only a search space (:mod:`sb3_poplin.planning`) plus defaults: no other module branches on its name.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces

from sb3_poplin.common import check_choice, check_positive_int
from sb3_poplin.distillation import AVG_UPDATES, DISTILL_TARGETS
from sb3_poplin.dynamics import PROPAGATIONS, ProbabilisticEnsemble
from sb3_poplin.planning import (
    CEM,
    OPTIMIZERS,
    ActionSequences,
    CEMOptions,
    MPCController,
    MPCPlanner,
    PolicyActionNoise,
    PolicyParameterNoise,
    RandomShooting,
    SearchSpace,
)
from sb3_poplin.policies import WHITENING_MODES, PolicyNetwork
from sb3_poplin.tasks import RewardFn, TerminationFn

CONTROLS = ("mpc", "policy")
GAN_DISCRIMINATOR_NET_ARCH = (64, 64)
SearchSpaceFactory = Callable[["Settings", int, "PolicyNetwork | None"], SearchSpace]


def setting(group: str, default: Any) -> Any:
    """
    A field of :class:`Settings`: what :data:`SETTINGS`, :data:`PLANNER_SETTINGS` and :data:`DEFAULT_SETTINGS` are
    made from.

    :param group: ``"planner"``, ``"policy"`` (the policy network and its distillation) or ``"model"``
    :param default: ``POPLIN``'s default, as given (``None`` and ``"auto"`` resolve per variant)
    """
    return field(metadata={"group": group, "default": default})


@dataclass(frozen=True)
class Settings:
    """
    A POPLIN agent's settings, resolved (:func:`resolve_settings`: validated, every ``None`` default of the variant
    filled in): what the planner (:func:`build_planner`), the networks, the model fit and the distillation are built
    from. The one list of them: a new setting is a field here (with its group and ``POPLIN``'s default), a keyword of
    ``POPLIN`` (its docstring says what it means) and the code that reads it; a zip holds each under its own name.
    """

    horizon: int = setting("planner", 30)
    population_size: int = setting("planner", 500)
    num_elites: int = setting("planner", 50)
    cem_iterations: int = setting("planner", 5)
    cem_alpha: float = setting("planner", 0.1)
    init_var: float = setting("planner", None)
    cem_sampling: str = setting("planner", "truncated")
    optimizer: str = setting("planner", None)
    optimizer_kwargs: dict[str, Any] = setting("planner", None)
    proposal: str = setting("planner", "init")
    noise: str = setting("planner", "sep")
    propagation: str = setting("planner", "expectation")
    num_particles: int = setting("planner", 20)
    planning_dtype: str = setting("planner", "float32")
    max_batch_rows: int | None = setting("planner", 65536)
    distillation: str | None = setting("policy", None)
    distill_imagined: bool = setting("policy", None)
    distill_window: int | None = setting("policy", "auto")
    avg_update: str = setting("policy", "overwrite")
    avg_step_size: float = setting("policy", 0.1)
    distill_target: str = setting("policy", None)
    whitening: str = setting("policy", "function")
    policy_net_arch: list[int] | None = setting("policy", None)
    policy_learning_rate: float = setting("policy", 3e-3)
    policy_epochs: int = setting("policy", None)
    policy_batch_size: int = setting("policy", 64)
    ensemble_size: int = setting("model", 5)
    dynamics_net_arch: list[int] = setting("model", (200, 200, 200, 200))
    model_epochs: int = setting("model", 5)
    model_batch_size: int = setting("model", 32)
    model_learning_rate: float = setting("model", 1e-3)
    holdout_ratio: float = setting("model", 0.0)
    standardise_targets: bool = setting("model", False)
    learned_reward: bool | None = setting("model", None)  # None until the task is known (POPLIN resolves it)

    @property
    def cem_options(self) -> CEMOptions:
        """The CEM's options: the optimizer's defaults (``"cem"``: none, ``"icem"``: iCEM's), then ``optimizer_kwargs``."""
        return replace(OPTIMIZERS.get(self.optimizer, CEMOptions()), **self.optimizer_kwargs)

    def as_dict(self) -> dict[str, Any]:
        """The settings by name (as POPLIN keyword arguments, and as a zip's data holds them)."""
        return asdict(self)


@dataclass(frozen=True)
class Variant:
    """
    One planner variant.

    :param name: the ``policy`` name POPLIN takes
    :param search_space: ``(settings, action_dim, policy network or None) -> SearchSpace``
    :param optimizer: ``"cem"`` or ``"rs"`` (random shooting: one round of uniform samples)
    :param init_var: default initial CEM variance of the search space
    :param policy_net_arch: default hidden widths of the policy network; ``None``: the variant has none
    :param distillations: accepted distillations, the default first (none without a policy network)
    :param distill_imagined: default of ``distill_imagined`` (the final elites' first steps distilled too)
    :param distill_target: default of ``distill_target`` (BC's and GAN's target actions)
    :param distill_window: default of ``distill_window`` (``None``: the steps since the last distillation)
    """

    name: str
    search_space: SearchSpaceFactory
    optimizer: str
    init_var: float
    policy_net_arch: tuple[int, ...] | None
    distillations: tuple[str, ...] = ()
    distill_imagined: bool = False
    distill_target: str = "executed"
    distill_window: int | None = 10_000

    @property
    def has_policy(self) -> bool:
        """Whether the variant has a policy network (and so a policy-control mode and a distillation)."""
        return self.policy_net_arch is not None


def _actions(settings: Settings, action_dim: int, policy: PolicyNetwork | None) -> SearchSpace:
    return ActionSequences(settings.horizon, action_dim, settings.init_var)


def _action_noise(settings: Settings, action_dim: int, policy: PolicyNetwork | None) -> SearchSpace:
    assert policy is not None
    return PolicyActionNoise(settings.horizon, action_dim, settings.init_var, policy, settings.proposal)


def _parameter_noise(settings: Settings, action_dim: int, policy: PolicyNetwork | None) -> SearchSpace:
    assert policy is not None
    return PolicyParameterNoise(settings.horizon, action_dim, settings.init_var, policy, settings.noise)


# the paper's demo settings: initial variance in scaled action units (0.25) or parameter units (0.1)
VARIANTS: dict[str, Variant] = {
    variant.name: variant
    for variant in (
        Variant("pets", _actions, "cem", 0.25, None),
        Variant("rs", _actions, "rs", 0.25, None),
        Variant("poplin-a", _action_noise, "cem", 0.25, (64, 64), ("bc",), distill_imagined=True),  # BC-AI
        # BC-PR / GAN on the planned outputs of the steps since the last distillation, as the original
        Variant(
            "poplin-p",
            _parameter_noise,
            "cem",
            0.1,
            (32,),
            ("avg", "bc", "gan"),
            distill_target="planned",
            distill_window=None,
        ),
    )
}
POLICY_VARIANTS = tuple(name for name, variant in VARIANTS.items() if variant.has_policy)

# the settings in which the original code's POPLIN-P differs from our defaults (poplin_original.md, sections 3.2 and
# 6): plain whitening updates, Avg overwrites theta with the mean perturbation, BC/GAN targets are the unclipped
# planned actions of the latest iteration only, the dynamics model's targets are not standardised
ORIGINAL_CODE_SETTINGS: dict[str, Any] = dict(
    whitening="plain", avg_update="overwrite", distill_target="planned", distill_window=None, standardise_targets=False
)


def original_code_settings(policy: str) -> dict[str, Any]:
    """
    The settings that reproduce the original code's choices for one variant: :data:`ORIGINAL_CODE_SETTINGS`, except
    that the original's POPLIN-A cloned the *executed* actions (BC-AR: the real ``clip(pi(s) + delta)``; BC-AI adds
    the elites' clipped actions), not the planned ones (poplin_original.md, section 6.2).

    :param policy: the variant (``"poplin-a"``, ``"poplin-p"``, ``"pets"``, ``"rs"``)
    :return: POPLIN keyword arguments
    """
    check_choice("policy", policy, list(VARIANTS))
    settings = dict(ORIGINAL_CODE_SETTINGS)
    if policy == "poplin-a":
        settings["distill_target"] = "executed"
    return settings


# the paper's configurations by name: POPLIN keyword arguments
NAMED_CONFIGURATIONS: dict[str, dict[str, Any]] = {
    "pets": dict(policy="pets"),
    "rs": dict(policy="rs"),
    "poplin-a/init": dict(policy="poplin-a", proposal="init"),
    "poplin-a/replan": dict(policy="poplin-a", proposal="replan"),
    **{
        f"poplin-p/{noise}/{method}": dict(policy="poplin-p", noise=noise, distillation=method)
        for noise in ("sep", "uni")
        for method in VARIANTS["poplin-p"].distillations
    },
}


def configuration(name: str) -> dict[str, Any]:
    """
    :param name: a named configuration, e.g. ``"poplin-p/sep/avg"``
    :return: its POPLIN keyword arguments (a new dict)
    """
    check_choice("configuration", name, list(NAMED_CONFIGURATIONS))
    return dict(NAMED_CONFIGURATIONS[name])


def variant(name: str) -> Variant:
    """The :class:`Variant` of a ``policy`` name, or a clear error."""
    if name not in VARIANTS:
        raise ValueError(
            f"Unknown POPLIN variant {name!r}; accepted values: {list(VARIANTS)} or a named configuration "
            f"{[key for key in NAMED_CONFIGURATIONS if key not in VARIANTS]}"
        )
    return VARIANTS[name]


def apply_configuration(policy: str, given: Mapping[str, Any], defaults: Mapping[str, Any]) -> tuple[str, dict[str, Any]]:
    """
    A ``policy`` that names one of :data:`NAMED_CONFIGURATIONS` (``"poplin-p/sep/bc"``) becomes its variant, with the
    configuration's options over the settings left at their defaults.

    :param policy: a variant or a named configuration
    :param given: the settings as given to ``POPLIN`` (defaults included)
    :param defaults: the constructor's defaults of the settings
    :return: the variant and the settings
    :raises ValueError: a setting given explicitly contradicts the named configuration
    """
    if policy in VARIANTS or policy not in NAMED_CONFIGURATIONS:
        return policy, dict(given)
    config = configuration(policy)
    settings = dict(given)
    for key, value in config.items():
        if key == "policy":
            continue
        if settings.get(key) not in (value, defaults.get(key)):
            raise ValueError(
                f"policy={policy!r} sets {key}={value!r}, but {key}={settings[key]!r} was given: drop one of them "
                f"(e.g. policy={config['policy']!r} with {key}={settings[key]!r})."
            )
        settings[key] = value
    return str(config["policy"]), settings


def resolve_settings(name: str, settings: Mapping[str, Any]) -> Settings:
    """
    Validate POPLIN's settings for a variant and resolve every ``None`` default that depends on it. Choices that
    belong to one part (the CEM's sampling, the search spaces' ``proposal`` and ``noise``, the planner's dtype and
    batch bound) are checked by that part when the planner is built. Resolved settings resolve to themselves.

    :param name: the variant
    :param settings: POPLIN's keyword arguments of :data:`SETTINGS`, as given
    :return: the resolved settings
    :raises ValueError: naming the setting, the value and what is accepted
    """
    spec = variant(name)
    s = dict(settings)
    missing = set(SETTINGS) - set(s)
    if missing:
        raise ValueError(f"resolve_settings: settings {sorted(missing)} missing (pass every name of SETTINGS)")
    for key in ("policy_net_arch", "dynamics_net_arch"):
        s[key] = None if s[key] is None else list(s[key])
    if s["distill_target"] is None:
        s["distill_target"] = spec.distill_target
    if isinstance(s["distill_window"], str):
        if s["distill_window"] != "auto":
            raise ValueError(
                f"distill_window must be an integer >= 1, None (the steps since the last distillation) or 'auto' "
                f"(the variant's default), got {s['distill_window']!r}"
            )
        s["distill_window"] = spec.distill_window
    _check_ranges(s, spec)
    check_choice("propagation", s["propagation"], PROPAGATIONS)
    check_choice("whitening", s["whitening"], WHITENING_MODES)
    check_choice("avg_update", s["avg_update"], AVG_UPDATES)
    check_choice("distill_target", s["distill_target"], DISTILL_TARGETS)
    if s["propagation"] != "expectation" and (s["num_particles"] < 1 or s["num_particles"] % s["ensemble_size"]):
        raise ValueError(
            f"num_particles ({s['num_particles']}) must be a positive multiple of ensemble_size ({s['ensemble_size']}) "
            "so that each member gets the same number of particles"
        )
    _resolve_optimizer(name, spec, s)
    if not spec.has_policy:
        if s["distillation"] is not None:
            raise ValueError(
                f"The {name!r} variant has no policy network to distill into; got distillation={s['distillation']!r}. "
                "Leave distillation=None, or use 'poplin-a' / 'poplin-p'."
            )
        if s["policy_net_arch"] is not None:
            raise ValueError(f"The {name!r} variant has no policy network: leave policy_net_arch=None.")
    else:
        if s["distillation"] is None:
            s["distillation"] = spec.distillations[0]
        check_choice("distillation", s["distillation"], spec.distillations)
        if s["policy_net_arch"] is None:
            s["policy_net_arch"] = list(spec.policy_net_arch or ())
    if s["distill_imagined"] is None:
        s["distill_imagined"] = spec.distill_imagined
    if s["policy_epochs"] is None:
        s["policy_epochs"] = 40 if s["distillation"] == "gan" else 100
    if s["init_var"] is None:
        s["init_var"] = spec.init_var
    return Settings(**{key: s[key] for key in SETTINGS})


def _resolve_optimizer(name: str, spec: Variant, s: dict[str, Any]) -> None:
    """``optimizer`` and ``optimizer_kwargs``: the variant's optimizer by default, the options checked by name."""
    accepted = [spec.optimizer] if spec.optimizer == "rs" else list(OPTIMIZERS)
    if s["optimizer"] is None:
        s["optimizer"] = spec.optimizer
    if s["optimizer"] not in accepted:
        raise ValueError(
            f"optimizer={s['optimizer']!r} is not available for the {name!r} variant; accepted values: {accepted} "
            "(or None for the variant's own)"
        )
    kwargs = {} if s["optimizer_kwargs"] is None else s["optimizer_kwargs"]
    if not isinstance(kwargs, Mapping):
        raise ValueError(f"optimizer_kwargs must be a dict of CEM options (or None), got {kwargs!r}")
    if kwargs and spec.optimizer == "rs":
        raise ValueError(
            f"The 'rs' variant samples one round of uniform candidates and takes no optimizer_kwargs; got {dict(kwargs)}. "
            "Use 'pets' with optimizer='icem' for iCEM over action sequences."
        )
    names = [field.name for field in fields(CEMOptions)]
    unknown = sorted(set(kwargs) - set(names))
    if unknown:
        raise ValueError(f"Unknown optimizer_kwargs {unknown}; accepted: {names}")
    s["optimizer_kwargs"] = dict(kwargs)
    if spec.optimizer == "rs":
        return
    options = replace(OPTIMIZERS[s["optimizer"]], **kwargs)  # checks the values
    if options.noise_beta > 0 and spec.search_space is _parameter_noise and s["noise"] == "uni":
        raise ValueError(
            f"noise_beta={options.noise_beta} colors the sampling noise along the horizon, but POPLIN-P with "
            "noise='uni' has one parameter-noise block shared by all steps (no horizon axis): use noise='sep', or "
            "white noise with optimizer_kwargs={'noise_beta': 0}"
        )


def _check_ranges(s: dict[str, Any], spec: Variant) -> None:
    """The numeric settings' ranges."""
    for key in ("horizon", "population_size", "cem_iterations", "ensemble_size", "model_epochs", "model_batch_size"):
        check_positive_int(key, s[key])
    check_positive_int("policy_batch_size", s["policy_batch_size"])
    check_positive_int("policy_epochs", s["policy_epochs"], optional=True)
    check_positive_int("distill_window", s["distill_window"], optional=True)
    if spec.optimizer == "cem" and not 1 <= s["num_elites"] <= s["population_size"]:
        raise ValueError(f"num_elites must be between 1 and population_size ({s['population_size']}), got {s['num_elites']}")
    if not 0.0 <= s["cem_alpha"] < 1.0:
        raise ValueError(f"cem_alpha must be in [0, 1), got {s['cem_alpha']}")
    if s["init_var"] is not None and not s["init_var"] > 0:
        raise ValueError(f"init_var must be > 0 (or None for the variant default), got {s['init_var']}")
    if not 0.0 <= s["holdout_ratio"] < 1.0:
        raise ValueError(f"holdout_ratio must be in [0, 1), got {s['holdout_ratio']}")
    if not 0.0 < s["avg_step_size"] <= 1.0:
        raise ValueError(f"avg_step_size must be in (0, 1] (1 = the paper's Avg), got {s['avg_step_size']}")


def check_control(name: str, control: str) -> None:
    """``control`` must be a control mode the variant has."""
    check_choice("control", control, CONTROLS)
    if control == "policy" and not variant(name).has_policy:
        raise ValueError(
            f"The {name!r} variant has no policy network, so control='policy' is not available: "
            "use control='mpc', or a 'poplin-a' / 'poplin-p' agent."
        )


def build_planner(
    name: str,
    settings: Settings,
    dynamics: ProbabilisticEnsemble,
    policy: PolicyNetwork | None,
    reward_fn: RewardFn | None,
    termination_fn: TerminationFn | None,
    action_space: spaces.Box,
    device: th.device | str,
) -> MPCPlanner:
    """
    The planner of a variant: its search space, its optimizer, and the rollout through the model.

    :param name: the variant
    :param settings: resolved settings (:func:`resolve_settings`, an agent's ``settings``)
    :param dynamics: the learned ensemble
    :param policy: the policy network (variants with one)
    :param reward_fn: the task reward, ``None`` when the model predicts it
    :param termination_fn: the task termination, or ``None``
    :param action_space: the env's Box action space
    :param device: where to plan
    """
    spec = variant(name)
    optimizer: CEM | RandomShooting
    if spec.optimizer == "rs":
        optimizer = RandomShooting(settings.population_size)
    else:
        optimizer = CEM(
            settings.population_size,
            settings.num_elites,
            settings.cem_iterations,
            settings.cem_alpha,
            settings.cem_sampling,
            settings.cem_options,
        )
    return MPCPlanner(
        model=dynamics,
        search_space=spec.search_space(settings, int(np.prod(action_space.shape)), policy),
        optimizer=optimizer,
        reward_fn=reward_fn,
        termination_fn=termination_fn,
        propagation=settings.propagation,
        num_particles=settings.num_particles,
        action_low=th.as_tensor(action_space.low, dtype=th.float32, device=device).reshape(-1),
        action_high=th.as_tensor(action_space.high, dtype=th.float32, device=device).reshape(-1),
        dtype=settings.planning_dtype,
        max_batch_rows=settings.max_batch_rows,
    )


# POPLIN's settings that resolve_settings checks and resolves (its other arguments go to SB3 or the task), the ones a
# planner reads, their defaults as POPLIN takes them, and those whose values are strings (the zoo's -params takes them
# bare): all from Settings' fields
SETTINGS = tuple(f.name for f in fields(Settings))
PLANNER_SETTINGS = tuple(f.name for f in fields(Settings) if f.metadata["group"] == "planner")
DEFAULT_SETTINGS: dict[str, Any] = {f.name: f.metadata["default"] for f in fields(Settings)}
STRING_SETTINGS = tuple(
    f.name
    for f in fields(Settings)
    if "str" in (part.strip() for part in str(f.type).split("|")) or isinstance(DEFAULT_SETTINGS[f.name], str)
)


def replanner(agent: Any, name: str, seed: int | None = 0, **overrides: Any) -> MPCController:
    """
    An MPC controller that plans with a trained agent's model, task and policy network but searches as another
    variant (e.g. PETS's action search on a POPLIN-P agent's model): the planner settings are the agent's, except
    ``overrides``; ``init_var`` falls back to the other variant's default.

    :param agent: a POPLIN agent
    :param name: the variant to search as (``"poplin-a"``/``"poplin-p"`` need the agent's policy network)
    :param seed: seed of the controller's generator
    :param overrides: planner settings to change (see :data:`PLANNER_SETTINGS`)
    """
    unknown = set(overrides) - set(PLANNER_SETTINGS)
    if unknown:
        raise ValueError(f"replanner takes planner settings only, got {sorted(unknown)}; accepted: {list(PLANNER_SETTINGS)}")
    spec = variant(name)
    actor = agent.policy.actor
    if spec.has_policy and actor is None:
        raise ValueError(f"The agent has no policy network, so it cannot plan as {name!r}: use 'pets' or 'rs'.")
    changes: dict[str, Any] = {} if name == agent.variant else {"init_var": spec.init_var}
    if spec.optimizer == "rs":
        changes.update(optimizer="rs", optimizer_kwargs={})
    elif agent.settings.optimizer == "rs":
        changes["optimizer"] = "cem"  # a random-shooting agent searched as a CEM variant: plain CEM
    settings = replace(agent.settings, **{**changes, **overrides})
    planner = build_planner(
        name,
        settings,
        agent.policy.dynamics,
        actor,
        agent.planner.reward_fn,
        agent.planner.termination_fn,
        agent.action_space,
        agent.device,
    )
    controller = MPCController(planner, agent.device)
    controller.seed(seed)
    return controller
