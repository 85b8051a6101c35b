"""
Model-predictive planning: one CEM core, random shooting, search spaces, and one rollout loop.

- An *optimizer* (:class:`CEM`, :class:`RandomShooting`) searches vectors ``z [n_envs, N, D]``
  given ``evaluate(z) -> returns [n_envs, N]``; it knows nothing about models or variants.
- A *search space* says what ``z`` means: its size D, its initial mean and variance, how the mean
  is warm-started between env steps (``shift``), and how ``z`` plus imagined states become
  actions (``actions``) and which action is executed (``executed_action``). PETS searches action
  sequences (:class:`ActionSequences`); POPLIN-A searches action noise around a policy network's
  proposals (:class:`PolicyActionNoise`), POPLIN-P noise on its parameters (:class:`PolicyParameterNoise`).
- :class:`MPCPlanner` owns the rollout loop through the learned model. It never names a variant.

All actions inside the planner are in the scaled space [-1, 1] the replay buffer uses; the task's
reward function receives them in env units.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol

import warnings

import numpy as np
import torch as th

from sb3_poplin.common import check_choice, check_positive_int, check_state_keys
from sb3_poplin.dynamics import ProbabilisticEnsemble, StepNoise
from sb3_poplin.policies import PolicyNetwork
from sb3_poplin.sampling import SAMPLINGS, CandidateSampler, Workspace
from sb3_poplin.tasks import RewardFn, TerminationFn

Evaluate = Callable[[th.Tensor], th.Tensor]
PROPOSALS = ("init", "replan")
NOISES = ("sep", "uni")
PLANNING_DTYPES = {"float32": th.float32, "bfloat16": th.bfloat16}


class OptimizerResult(NamedTuple):
    """What an optimizer found for each env."""

    solution: th.Tensor  # [n_envs, D]: what is executed: CEM's final mean or best candidate, random shooting's best
    elite_return: th.Tensor  # [n_envs]: mean return of the final elites (or the best sample)
    elites: th.Tensor  # [n_envs, K, D]: the final elites, best first (random shooting: the best sample, K = 1)
    found: th.Tensor  # [n_envs] bool: some candidate had a finite return (else the solution is the incoming mean)
    mean: th.Tensor  # [n_envs, D]: the final mean (random shooting: the solution); the next step's warm start


EXECUTES = ("mean", "best")


@dataclass(frozen=True)
class CEMOptions:
    """
    The modifications of iCEM (Pinneri et al. 2020, "Sample-efficient Cross-Entropy Method for Real-time Planning")
    as options of :class:`CEM`, each on its own; the defaults are the plain CEM of PETS/POPLIN.

    :param noise_beta: exponent of the power-law spectrum of the sampling noise along the horizon: each candidate's
        noise, per search dimension of a step block, has power ``~ 1 / f^beta`` over the H steps (0: white noise, as
        CEM; larger: smoother, more correlated steps). Needs a search space with a horizon axis
    :param keep_elites: fraction of the elites kept into the next iteration (rounded up to whole candidates) and
        ranked again with the new samples; they are re-evaluated, except under the ``"expectation"`` propagation where
        their return is known exactly
    :param shift_elites: carry the kept fraction of the final elites, shifted one step like the mean, into the next
        env step's first iteration (part of the warm start). Needs ``keep_elites > 0``
    :param population_decay: iteration ``i`` samples ``min(N, max(2 K, floor(N / decay^i)))`` new candidates
        (1: ``N`` every iteration)
    :param add_mean: the final mean is one more candidate of the last iteration
    :param execute: ``"mean"``: the final mean's first step is executed (CEM); ``"best"``: the best candidate's of
        the last iteration
    :param variance_cap: sample with the search space's bound-aware variance cap (PETS's action sequences: 2 sigma
        inside the bounds; the other spaces have none); ``False``: the distribution's own variance, samples clipped to
        the bounds (iCEM: with the cap, iCEM's candidates lose their extremes; docs/variants.md, "iCEM")
    """

    noise_beta: float = 0.0
    keep_elites: float = 0.0
    shift_elites: bool = False
    population_decay: float = 1.0
    add_mean: bool = False
    execute: str = "mean"
    variance_cap: bool = True

    def __post_init__(self) -> None:
        for name in ("shift_elites", "add_mean", "variance_cap"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"optimizer_kwargs[{name!r}] must be True or False, got {getattr(self, name)!r}")
        if not (isinstance(self.noise_beta, (int, float)) and 0.0 <= self.noise_beta <= 8.0):
            raise ValueError(
                f"optimizer_kwargs['noise_beta'] must be a number in [0, 8] (0: white noise, 2: iCEM's default), "
                f"got {self.noise_beta!r}"
            )
        if not (isinstance(self.keep_elites, (int, float)) and 0.0 <= self.keep_elites <= 1.0):
            raise ValueError(f"optimizer_kwargs['keep_elites'] must be a fraction in [0, 1], got {self.keep_elites!r}")
        if not (isinstance(self.population_decay, (int, float)) and self.population_decay >= 1.0):
            raise ValueError(
                f"optimizer_kwargs['population_decay'] must be >= 1 (1: no decay, iCEM: 1.25), got {self.population_decay!r}"
            )
        check_choice("optimizer_kwargs['execute']", self.execute, EXECUTES)
        if self.shift_elites and self.keep_elites == 0:
            raise ValueError(
                "optimizer_kwargs: shift_elites=True carries the kept fraction of the elites to the next env step, but "
                "keep_elites is 0: set keep_elites > 0 (iCEM: 0.3) or shift_elites=False"
            )


# iCEM's defaults (Pinneri et al. 2020): what optimizer="icem" selects before the user's optimizer_kwargs
ICEM_OPTIONS = CEMOptions(
    noise_beta=2.0,
    keep_elites=0.3,
    shift_elites=True,
    population_decay=1.25,
    add_mean=True,
    execute="best",
    variance_cap=False,
)
OPTIMIZERS = {"cem": CEMOptions(), "icem": ICEM_OPTIONS}


def colored_noise_filter(steps: int, beta: float) -> th.Tensor:
    """
    The linear map ``[steps, steps]`` that turns white noise along a horizon of ``steps`` into noise with a power-law
    spectrum: each frequency ``f = k / steps`` (k = 1 .. steps // 2) of the white input is scaled by ``f^(-beta / 2)``
    (the zero frequency like the lowest non-zero one), and the result is scaled to unit variance per step. Applied to
    independent standard normal steps it gives a stationary Gaussian sequence whose expected periodogram is
    proportional to ``f^-beta`` (circular along the horizon). ``beta = 0`` gives the identity.

    :param steps: the horizon length (number of step blocks)
    :param beta: the spectrum's exponent, >= 0
    """
    if steps == 1 or beta == 0:
        return th.eye(steps, dtype=th.float64)
    freqs = th.fft.rfftfreq(steps, dtype=th.float64)
    freqs[0] = freqs[1]
    scale = freqs ** (-beta / 2.0)
    # column j: the map applied to the unit impulse at step j
    filtered = th.fft.irfft(th.fft.rfft(th.eye(steps, dtype=th.float64), dim=0) * scale.unsqueeze(1), n=steps, dim=0)
    return filtered / filtered.square().sum(dim=1, keepdim=True).sqrt()


class CEM:
    """
    Cross-entropy method with momentum (PETS/POPLIN): sample ``population_size`` candidates from
    N(mean, var), keep the ``num_elites`` best, and move mean and variance towards the elites'
    statistics: ``new = alpha * old + (1 - alpha) * elite``. A candidate whose return is NaN or
    +-inf is never an elite; if an env has no finite candidate, its distribution is left unchanged.
    With :class:`CEMOptions` it becomes iCEM, or any part of it.

    :param population_size: candidates per iteration and env
    :param num_elites: elites per iteration
    :param iterations: CEM iterations per plan
    :param alpha: momentum of the old statistics, in [0, 1)
    :param sampling: ``"truncated"`` (normal truncated at 2 sigma, redrawn beyond) or ``"clipped"``
        (plain normal; the search space clips to its bounds). With colored noise the white draws are
        truncated or not, then colored
    :param options: the iCEM options (default: none)
    """

    def __init__(
        self,
        population_size: int,
        num_elites: int,
        iterations: int,
        alpha: float = 0.1,
        sampling: str = "truncated",
        options: CEMOptions | None = None,
    ) -> None:
        check_choice("cem_sampling", sampling, SAMPLINGS)
        self.population_size = population_size
        self.num_elites = num_elites
        self.iterations = iterations
        self.alpha = alpha
        self.sampling = sampling
        self.options = CEMOptions() if options is None else options
        self.sampler = CandidateSampler(population_size, sampling)
        self._workspace = Workspace()
        self._filters: dict[tuple[int, str], th.Tensor] = {}

    @property
    def kept(self) -> int:
        """Elites kept into the next iteration (and carried to the next env step with ``shift_elites``)."""
        return min(self.num_elites, math.ceil(self.options.keep_elites * self.num_elites))

    @property
    def carried(self) -> int:
        """Shifted elites carried to the next env step's first iteration."""
        return self.kept if self.options.shift_elites else 0

    def samples(self, iteration: int) -> int:
        """New candidates sampled at an iteration (decayed with ``population_decay``)."""
        decay = self.options.population_decay
        if decay == 1.0:
            return self.population_size
        return min(self.population_size, max(2 * self.num_elites, int(self.population_size / decay**iteration)))

    def evaluations(self, reuse: bool) -> int:
        """
        Candidates evaluated per plan and env: the samples of every iteration, the carried elites at the first, the
        kept elites at the others (unless ``reuse``: their returns are known), the mean at the last.

        :param reuse: the kept elites' returns are reused (exact under the ``"expectation"`` propagation)
        """
        total = sum(self.samples(i) for i in range(self.iterations)) + self.carried
        if not reuse:
            total += self.kept * (self.iterations - 1)
        return total + (1 if self.options.add_mean else 0)

    def _colored(self, eps: th.Tensor, steps: int) -> th.Tensor:
        """White noise ``[n_envs, n, D]`` (D = steps x block) colored along the steps, in a new tensor."""
        key = (steps, str(eps.device))
        if key not in self._filters:
            self._filters[key] = colored_noise_filter(steps, self.options.noise_beta).to(eps.device, th.float32)
        n_envs, n, dim = eps.shape
        return th.matmul(self._filters[key], eps.view(n_envs, n, steps, dim // steps)).view(n_envs, n, dim)

    def _sample(self, mean: th.Tensor, std: th.Tensor, count: int, steps: int, generator: th.Generator | None) -> th.Tensor:
        """``count`` candidates per env; white noise in the sampler's reused buffer, colored noise in a new tensor."""
        if self.options.noise_beta == 0:
            return self.sampler.sample(mean, std, generator, count)
        if mean.shape[1] % steps:
            raise ValueError(f"colored noise: the search vector's size {mean.shape[1]} is not a multiple of {steps} steps")
        eps = self.sampler.sample(th.zeros_like(mean), th.ones_like(std), generator, count)
        return th.addcmul(mean.unsqueeze(1), self._colored(eps, steps), std.unsqueeze(1))

    def optimize(
        self,
        evaluate: Evaluate,
        mean: th.Tensor,
        var: th.Tensor,
        constrain_var: Callable[[th.Tensor, th.Tensor], th.Tensor],
        generator: th.Generator | None = None,
        steps: int = 1,
        carried: th.Tensor | None = None,
        reuse: bool = False,
    ) -> OptimizerResult:
        """
        :param evaluate: ``z [n_envs, N, D] -> returns [n_envs, N]``
        :param mean: initial mean ``[n_envs, D]``
        :param var: initial variance ``[n_envs, D]``
        :param constrain_var: the search space's variance constraint ``(mean, var) -> var``
        :param generator: random generator for the samples
        :param steps: step blocks along the search vector (its horizon axis; 1: none), for colored noise
        :param carried: with ``shift_elites``, the previous step's shifted elites ``[n_envs, carried, D]``; a NaN row
            (no previous plan) is replaced by one more sample
        :param reuse: the returns of kept elites are known exactly (deterministic evaluation): not re-evaluated
        """
        n_envs, dim = mean.shape
        if self.options.noise_beta > 0 and steps == 1:
            raise ValueError("noise_beta > 0 needs a search space with a horizon axis (one block per planning step)")
        elite_return = th.zeros(n_envs, device=mean.device)
        elites = mean.unsqueeze(1).expand(n_envs, self.num_elites, dim)
        found = th.zeros(n_envs, dtype=th.bool, device=mean.device)
        kept: tuple[th.Tensor, th.Tensor] | None = None  # the previous iteration's best elites and their returns
        for i in range(self.iterations):
            std = (constrain_var(mean, var) if self.options.variance_cap else var).sqrt()
            n = self.samples(i)
            first_carries = i == 0 and self.carried > 0
            z = self._sample(mean, std, n + (self.carried if first_carries else 0), steps, generator)  # [n_envs, n, D]
            extra = []
            if first_carries:  # the carried elites replace the last samples, except where there are none (NaN)
                assert carried is not None and carried.shape == (n_envs, self.carried, dim), "carried elites missing"
                z[:, n:] = th.where(carried.isnan().any(dim=2, keepdim=True), z[:, n:], carried)
            elif i > 0 and kept is not None and not reuse:
                extra.append(kept[0])
            if i == self.iterations - 1 and self.options.add_mean:
                extra.append(mean.unsqueeze(1))
            if extra:
                z = th.cat([z, *extra], dim=1)
            returns = evaluate(z)  # [n_envs, N]
            if i > 0 and kept is not None and reuse:
                z, returns = th.cat([z, kept[0]], dim=1), th.cat([returns, kept[1]], dim=1)
            returns = th.where(th.isfinite(returns), returns, th.full_like(returns, -math.inf))
            top, idx = returns.topk(self.num_elites, dim=1)  # [n_envs, K], best first
            # [n_envs, K, D]: one row gather (take_along_dim would expand the index to K x D and wrap it)
            rows = (idx + th.arange(n_envs, device=idx.device).unsqueeze(1) * z.shape[1]).view(-1)
            elites = z.reshape(n_envs * z.shape[1], dim).index_select(0, rows).view(n_envs, -1, dim)
            if self.kept:
                kept = (elites[:, : self.kept], top[:, : self.kept])
            valid = th.isfinite(top)  # [n_envs, K]: -inf rows are not elites
            count = valid.sum(dim=1, keepdim=True).clamp(min=1).to(z.dtype)  # [n_envs, 1]
            # weighted means as [1, K] x [K, D] products: one pass over the elites each (element-wise weighting and a
            # reduction over K take five)
            weight = (valid / count).to(z.dtype).unsqueeze(1)  # [n_envs, 1, K]
            elite_mean = th.bmm(weight, elites)  # [n_envs, 1, D]
            deviation = self._workspace.get("deviation", elites.numel(), z.dtype, z.device).view(elites.shape)
            th.sub(elites, elite_mean, out=deviation).square_()
            elite_var = th.bmm(weight, deviation).squeeze(1)
            elite_mean = elite_mean.squeeze(1)
            has_elites = valid.any(dim=1, keepdim=True)  # [n_envs, 1]
            found = found | has_elites.squeeze(1)
            mean = th.where(has_elites, self.alpha * mean + (1 - self.alpha) * elite_mean, mean)
            var = th.where(has_elites, self.alpha * var + (1 - self.alpha) * elite_var, var)
            elite_return = th.where(valid, top, th.zeros_like(top)).sum(dim=1) / count.squeeze(1)
        solution = mean if self.options.execute == "mean" else th.where(found.unsqueeze(1), elites[:, 0], mean)
        return OptimizerResult(solution, elite_return, elites, found, mean)


class Optimizer(Protocol):
    """
    What searches a space for the planner (:class:`CEM`, :class:`RandomShooting`): anything with these can plan.

    ``population_size`` and ``iterations``: its budget.
    """

    population_size: int
    iterations: int

    @property
    def carried(self) -> int:
        """The elites carried to the next env step (0: none)."""
        ...

    def optimize(
        self,
        evaluate: Evaluate,
        mean: th.Tensor,
        var: th.Tensor,
        constrain_var: Callable[[th.Tensor, th.Tensor], th.Tensor],
        generator: th.Generator | None = None,
        steps: int = 1,
        carried: th.Tensor | None = None,
        reuse: bool = False,
    ) -> OptimizerResult:
        """
        Search from ``mean`` / ``var`` ``[n_envs, D]``, scoring candidates ``[n_envs, N, D]`` with ``evaluate``.

        :return: the solution, its return, the final elites, whether a finite candidate was found, the mean
        """
        ...


class RandomShooting:
    """
    Random shooting: one round of ``population_size`` uniform samples over [-1, 1]^D per env;
    the best candidate is the solution. Non-finite returns rank last.

    :param population_size: candidates per env
    """

    carried = 0  # nothing is carried to the next env step

    def __init__(self, population_size: int) -> None:
        self.population_size = population_size
        self.iterations = 1

    def evaluations(self, reuse: bool) -> int:
        """Candidates evaluated per plan and env."""
        return self.population_size

    def optimize(
        self,
        evaluate: Evaluate,
        mean: th.Tensor,
        var: th.Tensor,
        constrain_var: Callable[[th.Tensor, th.Tensor], th.Tensor],
        generator: th.Generator | None = None,
        steps: int = 1,
        carried: th.Tensor | None = None,
        reuse: bool = False,
    ) -> OptimizerResult:
        n_envs, dim = mean.shape
        z = th.rand((n_envs, self.population_size, dim), device=mean.device, generator=generator) * 2.0 - 1.0
        returns = evaluate(z)
        returns = th.where(th.isfinite(returns), returns, th.full_like(returns, -math.inf))
        best_return, best = returns.max(dim=1)
        solution = th.take_along_dim(z, best.view(n_envs, 1, 1), dim=1).squeeze(1)
        # with no finite candidate at all, fall back to the incoming mean
        finite = th.isfinite(best_return).unsqueeze(1)
        solution = th.where(finite, solution, mean)
        found = finite.squeeze(1)
        return OptimizerResult(solution, th.where(found, best_return, 0.0), solution.unsqueeze(1), found, solution)


class SearchSpace(ABC):
    """
    What the planner searches over. Subclasses define the search vector's size and meaning.

    The search vector is a sequence of per-step blocks of size :attr:`block` (one block per
    planning step, or a single block shared by all steps). By default the warm start drops the
    executed step's block and appends a zero block.

    :param horizon: planning horizon H
    :param action_dim: action size A
    :param init_var: initial CEM variance of every search dimension
    """

    def __init__(self, horizon: int, action_dim: int, init_var: float) -> None:
        self.horizon = horizon
        self.action_dim = action_dim
        self.init_var = init_var

    @property
    @abstractmethod
    def block(self) -> int:
        """Size of the block that drives one planning step."""

    @property
    def dim(self) -> int:
        """Size D of the search vector (one block per planning step by default)."""
        return self.horizon * self.block

    @property
    def steps(self) -> int:
        """Blocks along the search vector: its horizon axis (1 when one block drives every step)."""
        return self.dim // self.block

    def first_block(self, solution: th.Tensor) -> th.Tensor:
        """The block of ``solution [..., D]`` that drives the executed step, ``[..., block]``."""
        return solution[..., : self.block]

    def initial_mean(self, n_envs: int, device: th.device) -> th.Tensor:
        """Mean at an episode start, ``[n_envs, D]`` (zero noise / centred actions)."""
        return th.zeros(n_envs, self.dim, device=device)

    def initial_var(self, mean: th.Tensor) -> th.Tensor:
        """Variance at the start of every plan (the variance is never carried over)."""
        return th.full_like(mean, self.init_var)

    def constrain_var(self, mean: th.Tensor, var: th.Tensor) -> th.Tensor:
        """Variance actually sampled with; the identity unless the space has hard bounds."""
        return var

    def shift(self, mean: th.Tensor) -> th.Tensor:
        """Warm start for the next env step from the final mean ``[n_envs, D]``: drop the first block, append zeros."""
        return th.cat([mean[:, self.block :], th.zeros_like(mean[:, : self.block])], dim=1)

    def prepare(self, obs: th.Tensor, planner: MPCPlanner) -> Any:
        """Per-plan context computed once from the real observations ``[n_envs, o]`` (default: none)."""
        return None

    @abstractmethod
    def actions(self, z: th.Tensor, t: int, states: th.Tensor, context: Any) -> th.Tensor:
        """
        :param z: search vectors ``[n_envs, N, D]``
        :param t: planning step
        :param states: imagined states ``[n_envs, N, P, o]``
        :param context: what :meth:`prepare` returned
        :return: scaled actions ``[n_envs, N, P, A]`` in [-1, 1]
        """

    @abstractmethod
    def planned_action(self, solution: th.Tensor, obs: th.Tensor, context: Any) -> th.Tensor:
        """
        The first action of a solution before the clip to the action bounds: ``[n_envs, A]`` scaled, from the
        optimizer's solution ``[n_envs, D]`` (POPLIN-P: the perturbed network's linear output; POPLIN-A: the
        clipped proposal plus the noise). Distillation's ``"planned"`` target.
        """

    def executed_action(self, solution: th.Tensor, obs: th.Tensor, context: Any) -> th.Tensor:
        """Scaled action ``[n_envs, A]`` to execute from the optimizer's solution ``[n_envs, D]``: the planned one, clipped."""
        return self.planned_action(solution, obs, context).clamp(-1.0, 1.0)

    fallback_description = "the action-space centre"

    def fallback_action(self, obs: th.Tensor) -> th.Tensor:
        """Scaled action ``[n_envs, A]`` when no candidate had a finite return: the action-space centre."""
        return th.zeros(obs.shape[0], self.action_dim, device=obs.device)


class ActionSequences(SearchSpace):
    """
    PETS: the search vector is the action sequence ``a_0 .. a_{H-1}`` (scaled), ``D = H * A``.
    The sampled variance is capped so that 2 sigma stays inside the bounds:
    ``var <= min(((mean + 1) / 2)^2, ((1 - mean) / 2)^2)``. The warm start drops the executed
    first action and appends zeros (the action-space centre).
    """

    @property
    def block(self) -> int:
        return self.action_dim

    def constrain_var(self, mean: th.Tensor, var: th.Tensor) -> th.Tensor:
        room = th.minimum(mean + 1.0, 1.0 - mean).clamp(min=0.0) / 2.0
        return th.minimum(var, room**2)

    def actions(self, z: th.Tensor, t: int, states: th.Tensor, context: Any) -> th.Tensor:
        a = z[:, :, t * self.action_dim : (t + 1) * self.action_dim].clamp(-1.0, 1.0)  # [n_envs, N, A]
        return a.unsqueeze(2).expand(-1, -1, states.shape[2], -1)

    def planned_action(self, solution: th.Tensor, obs: th.Tensor, context: Any) -> th.Tensor:
        return solution[:, : self.action_dim]


class PolicySearchSpace(SearchSpace):
    """
    A search space around a policy network (POPLIN): when no candidate had a finite return, the policy's own action
    is executed.

    :param policy: the policy network
    """

    fallback_description = "the policy network's action"

    def __init__(self, horizon: int, action_dim: int, init_var: float, policy: PolicyNetwork) -> None:
        super().__init__(horizon, action_dim, init_var)
        self.policy = policy

    def fallback_action(self, obs: th.Tensor) -> th.Tensor:
        return self.policy.act(obs)


class PolicyActionNoise(PolicySearchSpace):
    """
    POPLIN-A (Wang & Ba 2019, section 4.1): the search vector is additive action noise
    ``delta_0 .. delta_{H-1}`` around the policy network's proposals, ``D = H * A``.

    - ``proposal="init"``: the policy is rolled open-loop through the model once per plan (mean
      model, from the real observation); candidate step t plays ``clip(a_ref_t + delta_t)``.
    - ``proposal="replan"``: the policy is re-queried on every imagined state; step t plays
      ``clip(pi(s_t) + delta_t)``.

    The executed action is ``clip(pi(s) + mu_0)``. No bound-aware variance cap (as in the paper;
    actions are clipped instead).

    :param policy: the policy network
    :param proposal: ``"init"`` or ``"replan"``
    """

    def __init__(self, horizon: int, action_dim: int, init_var: float, policy: PolicyNetwork, proposal: str) -> None:
        check_choice("proposal", proposal, PROPOSALS)
        super().__init__(horizon, action_dim, init_var, policy)
        self.proposal = proposal

    @property
    def block(self) -> int:
        return self.action_dim

    def prepare(self, obs: th.Tensor, planner: MPCPlanner) -> th.Tensor | None:
        if self.proposal != "init":
            return None
        states, proposals = obs.unsqueeze(1), []  # [n_envs, 1, o]
        for _ in range(self.horizon):
            action = self.policy.act(states)  # [n_envs, 1, A]
            proposals.append(action[:, 0])
            states, _ = planner.model.propagate(states, action, "expectation")
        return th.stack(proposals, dim=1)  # [n_envs, H, A]

    def actions(self, z: th.Tensor, t: int, states: th.Tensor, context: th.Tensor | None) -> th.Tensor:
        delta = z[:, :, t * self.action_dim : (t + 1) * self.action_dim]  # [n_envs, N, A]
        if context is not None:  # open-loop reference actions
            a = (context[:, t].unsqueeze(1) + delta).clamp(-1.0, 1.0)
            return a.unsqueeze(2).expand(-1, -1, states.shape[2], -1)
        return (self.policy.act(states) + delta.unsqueeze(2)).clamp(-1.0, 1.0)  # [n_envs, N, P, A]

    def planned_action(self, solution: th.Tensor, obs: th.Tensor, context: Any) -> th.Tensor:
        return self.policy.act(obs) + solution[:, : self.action_dim]


class PolicyParameterNoise(PolicySearchSpace):
    """
    POPLIN-P (Wang & Ba 2019, section 4.2): the search vector perturbs the policy network's
    parameters, ``omega`` in the flat layout of :class:`PolicyNetwork` (size W). Every candidate
    runs its own network ``pi_{theta + omega}`` on its imagined states.

    - ``noise="sep"``: one block per planning step, ``D = H * W``; the warm start shifts by a block.
    - ``noise="uni"``: one block shared by all steps, ``D = W``; the warm start keeps the mean unchanged.

    The executed action is ``clip(pi_{theta + mu_0}(s))``.

    :param policy: the policy network
    :param noise: ``"sep"`` or ``"uni"``
    """

    def __init__(self, horizon: int, action_dim: int, init_var: float, policy: PolicyNetwork, noise: str) -> None:
        check_choice("noise", noise, NOISES)
        super().__init__(horizon, action_dim, init_var, policy)
        self.noise = noise

    @property
    def block(self) -> int:
        return self.policy.num_params

    @property
    def dim(self) -> int:
        return self.horizon * self.block if self.noise == "sep" else self.block

    def shift(self, mean: th.Tensor) -> th.Tensor:
        return super().shift(mean) if self.noise == "sep" else mean

    def actions(self, z: th.Tensor, t: int, states: th.Tensor, context: Any) -> th.Tensor:
        n_envs, pop, p, o = states.shape
        w = self.block
        omega = z[:, :, t * w : (t + 1) * w] if self.noise == "sep" else z  # [n_envs, N, W]
        a = self.policy.forward_perturbed(states.reshape(n_envs * pop, p, o), omega.reshape(n_envs * pop, w))
        return a.clamp(-1.0, 1.0).view(n_envs, pop, p, -1)

    def planned_action(self, solution: th.Tensor, obs: th.Tensor, context: Any) -> th.Tensor:
        return self.policy.forward_perturbed(obs.unsqueeze(1), self.first_block(solution))[:, 0]


class PlanResult(NamedTuple):
    """One plan for a batch of envs."""

    action: th.Tensor  # [n_envs, A] scaled action to execute
    next_state: th.Tensor  # [n_envs, S] warm start for the next env step (MPCPlanner.state_dim)
    elite_return: th.Tensor  # [n_envs] planned return of the final elites
    solution: th.Tensor  # [n_envs, D] the executed solution (CEM: the final mean, or the best candidate)
    elites: th.Tensor  # [n_envs, K, D] the final elites, best first
    fallback: th.Tensor  # [n_envs] bool: no candidate was finite, the fallback action was used
    mean: th.Tensor  # [n_envs, D] the final mean (random shooting: the solution)


class MPCPlanner:
    """
    Plans with a learned model: the one rollout loop shared by every variant.

    :param model: the dynamics ensemble
    :param search_space: what is searched
    :param optimizer: an :class:`Optimizer` (:class:`CEM` or :class:`RandomShooting`)
    :param reward_fn: task reward ``(obs, action in env units, next_obs) -> [B]``; ``None`` when
        the model predicts the reward
    :param termination_fn: task termination, or ``None`` (never terminates); rewards after a
        predicted termination are masked
    :param propagation: one of :data:`sb3_poplin.dynamics.PROPAGATIONS`
    :param num_particles: particles per candidate (1 with ``"expectation"``)
    :param action_low: env lower bounds ``[A]``
    :param action_high: env upper bounds ``[A]``
    :param dtype: ``"float32"``, or ``"bfloat16"`` to run the networks' matmuls in bf16 (fp32 accumulation)
    :param max_batch_rows: upper bound on the rows pushed through the ensemble at once (per candidate:
        its particles, or the E members with ``"expectation"``); larger populations are evaluated in chunks
        of candidates, with identical results. ``None``: no bound.
    """

    def __init__(
        self,
        model: ProbabilisticEnsemble,
        search_space: SearchSpace,
        optimizer: Optimizer,
        reward_fn: RewardFn | None,
        termination_fn: TerminationFn | None,
        propagation: str,
        num_particles: int,
        action_low: th.Tensor,
        action_high: th.Tensor,
        dtype: str = "float32",
        max_batch_rows: int | None = None,
    ) -> None:
        if reward_fn is None and not model.learned_reward:
            raise ValueError("The planner needs a reward: pass reward_fn or use a model with learned_reward=True.")
        check_choice("planning_dtype", dtype, list(PLANNING_DTYPES))
        check_positive_int("max_batch_rows", max_batch_rows, optional=True)
        self.model = model
        self.search_space = search_space
        self.optimizer = optimizer
        self.reward_fn = reward_fn
        self.termination_fn = termination_fn
        self.propagation = propagation
        self.num_particles = 1 if propagation == "expectation" else num_particles
        self.action_low = action_low
        self.action_scale = (action_high - action_low) / 2.0
        self.dtype = PLANNING_DTYPES[dtype]
        self.max_batch_rows = max_batch_rows

    @property
    def state_dim(self) -> int:
        """
        Width S of the warm start carried between env steps: the shifted mean ``[D]``, then, when the optimizer
        carries shifted elites (iCEM), those ``[carried x D]`` (NaN rows: none yet).
        """
        return self.search_space.dim * (1 + self.optimizer.carried)

    def initial_state(self, n_envs: int, device: th.device) -> th.Tensor:
        """The warm start at an episode start ``[n_envs, S]``: the search space's initial mean, no carried elites."""
        mean = self.search_space.initial_mean(n_envs, device)
        if not self.optimizer.carried:
            return mean
        return th.cat([mean, th.full((n_envs, self.state_dim - mean.shape[1]), math.nan, device=device)], dim=1)

    def to_env_units(self, scaled: th.Tensor) -> th.Tensor:
        """Map scaled actions in [-1, 1] to env units."""
        return self.action_low + (scaled + 1.0) * self.action_scale

    def _step(
        self, z: th.Tensor, t: int, states: th.Tensor, context: Any, noise: StepNoise
    ) -> tuple[th.Tensor, th.Tensor, th.Tensor | None]:
        """
        One imagined step for a chunk of candidates.

        :param z: search vectors ``[n_envs, n, D]``
        :param states: imagined states ``[n_envs, n, P, o]``
        :return: next states ``[n_envs, n, P, o]``, rewards ``[n_envs, n, P]`` and terminations (or None)
        """
        n_envs, pop, p, o = states.shape
        actions = self.search_space.actions(z, t, states, context)  # [n_envs, n, P, A]
        flat_states, flat_actions = states.reshape(n_envs * pop, p, o), actions.reshape(n_envs * pop, p, -1)
        with th.autocast(states.device.type, dtype=th.bfloat16, enabled=self.dtype == th.bfloat16):
            next_flat, model_reward = self.model.propagate(flat_states, flat_actions, self.propagation, noise=noise.flatten())
        next_flat = next_flat.float()
        transition = (
            flat_states.reshape(-1, o),
            self.to_env_units(flat_actions.reshape(-1, actions.shape[-1])),
            next_flat.reshape(-1, o),
        )
        if self.reward_fn is None:
            assert model_reward is not None
            reward = model_reward.float()
        else:
            reward = self.reward_fn(*transition)
        done = None if self.termination_fn is None else self.termination_fn(*transition).view(n_envs, pop, p)
        return next_flat.view(n_envs, pop, p, o), reward.reshape(n_envs, pop, p), done

    def rollout(self, obs: th.Tensor, z: th.Tensor, context: Any, generator: th.Generator | None = None) -> th.Tensor:
        """
        Mean return over particles of each candidate, through the learned model.

        The horizon loop is outside, the candidate chunks inside: each step's randomness is drawn
        for all candidates at once, so the chunk size never changes the result.

        :param obs: real observations ``[n_envs, o]``
        :param z: search vectors ``[n_envs, N, D]``
        :param context: what the search space's ``prepare`` returned
        :param generator: random generator for propagation
        :return: returns ``[n_envs, N]`` (NaN/inf where the model diverged)
        """
        n_envs, pop, _ = z.shape
        p, o = self.num_particles, obs.shape[-1]
        rows_per_candidate = n_envs * (self.model.ensemble_size if self.propagation == "expectation" else p)
        chunk = pop if self.max_batch_rows is None else max(1, min(pop, self.max_batch_rows // rows_per_candidate))
        states = obs.view(n_envs, 1, 1, o).expand(n_envs, pop, p, o)  # [n_envs, N, P, o]
        total = th.zeros(n_envs, pop, p, device=obs.device)
        alive = th.ones(n_envs, pop, p, dtype=th.bool, device=obs.device)
        for t in range(self.search_space.horizon):
            noise = self.model.draw_noise((n_envs, pop, p), self.propagation, obs.device, generator)
            parts = [
                self._step(
                    z[:, start : start + chunk],
                    t,
                    states[:, start : start + chunk],
                    context,
                    noise.rows(slice(start, start + chunk)),
                )
                for start in range(0, pop, chunk)
            ]
            states = th.cat([part[0] for part in parts], dim=1) if len(parts) > 1 else parts[0][0]
            reward = th.cat([part[1] for part in parts], dim=1) if len(parts) > 1 else parts[0][1]
            total += th.where(alive, reward, th.zeros_like(reward))
            if self.termination_fn is not None:
                done = th.cat([part[2] for part in parts], dim=1)  # type: ignore[misc]
                alive &= ~done
        return total.mean(dim=2)

    @th.inference_mode()
    def plan(
        self,
        obs: th.Tensor,
        state: th.Tensor,
        generator: th.Generator | None = None,
        observer: Callable[[th.Tensor, th.Tensor], None] | None = None,
    ) -> PlanResult:
        """
        :param obs: real observations ``[n_envs, o]``
        :param state: warm start ``[n_envs, S]`` (:attr:`state_dim`; the mean ``[n_envs, D]`` unless elites are carried)
        :param generator: random generator for sampling and propagation
        :param observer: called with every iteration's candidates ``[n_envs, N, D]`` and their returns
            ``[n_envs, N]`` (the candidates' buffer is reused: copy what you keep); for analyses
        """
        context = self.search_space.prepare(obs, self)

        def evaluate(z: th.Tensor) -> th.Tensor:
            returns = self.rollout(obs, z, context, generator)
            if observer is not None:
                observer(z, returns)
            return returns

        space = self.search_space
        n_envs, dim, carried = obs.shape[0], space.dim, self.optimizer.carried
        mean = state[:, :dim]
        result = self.optimizer.optimize(
            evaluate,
            mean,
            space.initial_var(mean),
            space.constrain_var,
            generator,
            steps=space.steps,
            carried=state[:, dim:].view(n_envs, carried, dim) if carried else None,
            reuse=self.propagation == "expectation",  # a deterministic rollout: a kept elite's return is known
        )
        found = result.found.unsqueeze(1)
        action = th.where(found, space.executed_action(result.solution, obs, context), space.fallback_action(obs))
        # never a non-finite action (e.g. a NaN observation): the action-space centre instead
        action = th.nan_to_num(action, nan=0.0, posinf=1.0, neginf=-1.0).clamp(-1.0, 1.0)
        next_state = space.shift(result.mean)
        if carried:  # the best elites, shifted like the mean
            shifted = space.shift(result.elites[:, :carried].reshape(n_envs * carried, dim)).view(n_envs, carried * dim)
            next_state = th.cat([next_state, shifted], dim=1)
        # an env whose plan failed starts afresh at the next step
        next_state = th.where(found, next_state, self.initial_state(n_envs, obs.device))
        return PlanResult(action, next_state, result.elite_return, result.solution, result.elites, ~result.found, result.mean)


class MPCStep(NamedTuple):
    """One MPC step for a batch of envs, on the host where SB3 wants it and on the device for distillation."""

    actions: np.ndarray  # [n_envs, A] in env units
    state: np.ndarray  # [n_envs, S] warm start for the next step (MPCPlanner.state_dim: the shifted mean, carried elites)
    plan: PlanResult  # the plan, on the device
    fallbacks: int = 0  # envs whose plan found no finite candidate (the fallback action was executed)


class MPCController:
    """
    Model-predictive control with a :class:`MPCPlanner`: one plan per env step, warm-started with the previous
    step's shifted solution (per env, reset at episode starts), with the planner's random generator and the plan
    statistics that are logged. Its :meth:`state_dict` is saved with the agent.

    :param planner: the planner
    :param device: where the planner runs
    """

    def __init__(self, planner: MPCPlanner, device: th.device | str) -> None:
        self.planner = planner
        self.device = th.device(device)
        self.generator = th.Generator(device=self.device)
        self.warm_start: th.Tensor | None = None  # the training rollout's own warm start (collect)
        self._return_sum = th.zeros((), device=self.device)
        self._plans = 0
        self._fallbacks = 0
        self._fallback_warned = False

    def seed(self, seed: int | None) -> None:
        """Seed the planner's generator (``None``: from a non-deterministic source)."""
        if seed is None:
            self.generator.seed()
        else:
            self.generator.manual_seed(seed)

    def _start_state(self, n_envs: int, state: np.ndarray | None, episode_start: np.ndarray | None) -> th.Tensor:
        planner = self.planner
        if state is None:
            start = planner.initial_state(n_envs, self.device)
        else:
            start = th.as_tensor(state, dtype=th.float32, device=self.device)
            if start.shape != (n_envs, planner.state_dim):
                raise ValueError(
                    f"state has shape {tuple(start.shape)} but the planner needs ({n_envs}, {planner.state_dim}): pass "
                    "back the state returned by the previous predict() call for the same observations, or None"
                )
        starts = None if episode_start is None else np.asarray(episode_start, dtype=bool).reshape(-1)
        if starts is not None and starts.any():  # nothing to send to the device on most steps
            reset = th.as_tensor(starts, device=self.device)
            start = th.where(reset.unsqueeze(1), planner.initial_state(n_envs, self.device), start)
        return start

    def step(
        self,
        obs: th.Tensor,
        state: np.ndarray | None = None,
        episode_start: np.ndarray | None = None,
        generator: th.Generator | None = None,
    ) -> MPCStep:
        """
        Plan the actions of a batch of envs from the given warm start: a function of its arguments and the
        generator's draws, which leaves the controller's own warm start and statistics alone (``predict``).

        :param obs: observations ``[n_envs, o]`` on the device
        :param state: the state returned by the previous step for these envs, or None (fresh plans)
        :param episode_start: per-env flags; True starts that env's plan afresh
        :param generator: the random generator to plan with; ``None``: the controller's own
        """
        start = self._start_state(obs.shape[0], state, episode_start)
        return self._step(obs, start, self.generator if generator is None else generator)

    def collect(self, obs: th.Tensor) -> MPCStep:
        """
        Plan the actions of the training rollout: from the controller's own warm start (reset per env by
        :meth:`episodes_ended`) with its own generator; keeps the new warm start and counts the plan statistics.

        :param obs: observations ``[n_envs, o]`` on the device
        """
        own = self.warm_start
        if own is not None and own.shape == (obs.shape[0], self.planner.state_dim):
            start = own
        else:
            start = self.planner.initial_state(obs.shape[0], self.device)
        step = self._step(obs, start, self.generator)
        self.warm_start = step.plan.next_state
        self._return_sum = self._return_sum + step.plan.elite_return.sum()
        self._plans += obs.shape[0]
        self._fallbacks += step.fallbacks
        return step

    def _step(self, obs: th.Tensor, start: th.Tensor, generator: th.Generator) -> MPCStep:
        plan = self.planner.plan(obs, start, generator)
        # one device-to-host transfer for the actions, the fallback flags and the warm starts
        actions = self.planner.to_env_units(plan.action)
        host = th.cat([actions, plan.fallback.unsqueeze(1).float(), plan.next_state], dim=1).cpu().numpy()
        n_actions = actions.shape[1]
        fallbacks = int((host[:, n_actions] > 0).sum())
        if fallbacks:
            self._warn_fallback()
        return MPCStep(host[:, :n_actions], host[:, n_actions + 1 :], plan, fallbacks)

    def _warn_fallback(self) -> None:
        if not self._fallback_warned:
            self._fallback_warned = True
            warnings.warn(
                "No planned candidate had a finite return (the model or the observation produced NaN/inf): executing "
                f"{self.planner.search_space.fallback_description} instead. Counted in the logger as plan/fallbacks; "
                "warned once.",
                stacklevel=4,
            )

    def episodes_ended(self, dones: np.ndarray) -> None:
        """Start the own warm start afresh for the envs whose episode ended."""
        if self.warm_start is not None and np.any(dones):
            reset = th.as_tensor(np.asarray(dones, dtype=bool), device=self.device)
            fresh = self.planner.initial_state(len(dones), self.device)
            self.warm_start = th.where(reset.unsqueeze(1), fresh, self.warm_start)

    def pop_statistics(self) -> dict[str, float | int]:
        """
        The training rollout's plan statistics since the last call (empty without plans): mean elite return and
        fallbacks (``predict``'s plans are not counted; a fallback there is warned about all the same).
        """
        stats: dict[str, float | int] = {}
        if self._plans:
            stats = {"plan/elite_return": (self._return_sum / self._plans).item(), "plan/fallbacks": self._fallbacks}
        self._return_sum = th.zeros((), device=self.device)
        self._plans = 0
        self._fallbacks = 0
        return stats

    def state_dict(self) -> dict[str, Any]:
        """The random generator's state and the own warm start (CPU tensors)."""
        warm = None if self.warm_start is None else self.warm_start.detach().cpu()
        return {"generator": self.generator.get_state(), "warm_start": warm}

    def load_state_dict(self, state: dict[str, Any], strict: bool = True) -> None:
        """
        :param state: what :meth:`state_dict` returned
        :param strict: every key must be there
        """
        check_state_keys("MPC controller", state, ("generator", "warm_start"), strict)
        if "generator" in state:
            saved = state["generator"]
            if not isinstance(saved, th.Tensor) or saved.dtype != th.uint8:
                raise ValueError(
                    "The MPC controller's 'generator' state must be the uint8 tensor of torch.Generator.get_state(), got "
                    f"{type(saved).__name__} {getattr(saved, 'dtype', '')}: pass back what state_dict() returned."
                )
            try:
                self.generator.set_state(saved.cpu())
            except (RuntimeError, TypeError):  # a state of another kind of device (sizes differ): keep the seeded one
                warnings.warn(
                    f"The planner's random state ({saved.numel()} bytes) does not fit this device's generator "
                    f"({self.device.type}): saved on another kind of device? It is not restored; the generator keeps "
                    "its seed.",
                    stacklevel=2,
                )
        warm = state.get("warm_start")
        # a warm start of another width (a zip loaded with another optimizer, e.g. optimizer="icem"): plan afresh
        if warm is not None and warm.shape[-1] != self.planner.state_dim:
            warm = None
        self.warm_start = None if warm is None else warm.to(self.device)


def _fused_linear_flops(x_shape: th.Size, w_shape: th.Size, *args: Any, **kwargs: Any) -> int:
    """FLOPs of oneDNN's fused linear (``x [..., in]``, ``w [out, in]``): 2 per multiply-add, as torch counts ``addmm``."""
    return 2 * math.prod(x_shape[:-1]) * w_shape[-1] * w_shape[0]


def plan_flops(
    planner: MPCPlanner, obs: th.Tensor | np.ndarray, state: th.Tensor | None = None, generator: th.Generator | None = None
) -> int:
    """
    FLOPs of one plan, counted while it runs: its matrix products (the networks' layers, CEM's refit to the elites and
    colored noise; 2 per multiply-add, element-wise work neglected) under :class:`torch.utils.flop_counter.FlopCounterMode`.
    It counts what the planner really does (iCEM's decayed populations and extra candidates, POPLIN-A Init's open-loop
    proposals, the executed and fallback actions; POPLIN-P's perturbed layers of one particle are two products,
    ``x theta + x omega``), so a speed benchmark's fraction of peak is that of the plan it timed.

    :param planner: the planner
    :param obs: real observations ``[n_envs, o]`` (on the planner's device)
    :param state: warm start ``[n_envs, S]`` (default: the episode start's, :meth:`MPCPlanner.initial_state`)
    :param generator: random generator of the plan (default: a fresh one seeded 0, so that no state is consumed)
    :return: the FLOPs of the plan for all ``n_envs`` envs
    """
    from torch.utils.flop_counter import FlopCounterMode

    obs = th.as_tensor(obs, dtype=th.float32, device=planner.action_low.device)
    if obs.dim() != 2:
        raise ValueError(f"plan_flops takes observations [n_envs, obs_dim], got shape {tuple(obs.shape)}: add a batch axis.")
    if state is None:
        state = planner.initial_state(obs.shape[0], obs.device)
    if generator is None:
        generator = th.Generator(device=obs.device).manual_seed(0)
    custom = {}
    if th.backends.mkldnn.is_available() and hasattr(th.ops.mkldnn, "_linear_pointwise"):
        custom[th.ops.mkldnn._linear_pointwise] = _fused_linear_flops
    # an uncounted plan first: it makes the host's first choice of forward paths, whose timing probe is not the plan's
    planner.plan(obs, state, th.Generator(device=obs.device).manual_seed(0))
    counter = FlopCounterMode(display=False, custom_mapping=custom)
    with counter:
        planner.plan(obs, state, generator)
    return int(counter.get_total_flops())
