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
from typing import Any, NamedTuple

import numpy as np
import torch as th

from sb3_poplin import parallel
from sb3_poplin.dynamics import ProbabilisticEnsemble, StepNoise
from sb3_poplin.policies import PolicyNetwork
from sb3_poplin.tasks import RewardFn, TerminationFn

Evaluate = Callable[[th.Tensor], th.Tensor]
SAMPLINGS = ("truncated", "clipped")
PROPOSALS = ("init", "replan")
NOISES = ("sep", "uni")

# the standard normal CDF at -2 and +2: bounds of the uniform draw for a normal truncated at 2 sigma
_PHI_MINUS_2 = 0.5 * (1.0 + math.erf(-2.0 / math.sqrt(2.0)))
_PHI_PLUS_2 = 0.5 * (1.0 + math.erf(2.0 / math.sqrt(2.0)))
# CPU sampling: a 16-bit uniform integer v picks the v-th of 65,536 equally likely bins of the truncated normal; the
# sample is the law's quantile at the bin's midpoint, Phi^-1(Phi(-2) + (Phi(2) - Phi(-2)) (v + 0.5) / 2^16), computed
# once in float64 (a table of 256 KiB per device and scale)
_LEVELS = 65536
_QUANTILE_TABLES: dict[tuple[str, bool], th.Tensor] = {}
_GATHER_CHUNK = 65536  # samples per table lookup: the int32 index chunk stays in cache
# CEM candidates on the CPU are drawn in chunks of rows of about this many samples (1 MiB of noise, which stays in
# cache until it is scaled into the candidates), chunk c from its own SFC64 stream seeded with base + c
_CHUNK_SAMPLES = 1 << 18


def _quantile_table(device: th.device, unit_variance: bool) -> th.Tensor:
    key = (str(device), unit_variance)
    if key not in _QUANTILE_TABLES:
        mid = (th.arange(_LEVELS, dtype=th.float64) + 0.5) / _LEVELS
        quantiles = th.special.ndtri(_PHI_MINUS_2 + (_PHI_PLUS_2 - _PHI_MINUS_2) * mid)
        if not unit_variance:
            quantiles = quantiles / math.sqrt(2.0)
        _QUANTILE_TABLES[key] = quantiles.to(device=device, dtype=th.float32)
    return _QUANTILE_TABLES[key]


def truncated_normal(
    shape: tuple[int, ...],
    device: th.device,
    generator: th.Generator | None = None,
    out: th.Tensor | None = None,
    scratch: th.Tensor | None = None,
    unit_variance: bool = True,
) -> th.Tensor:
    """
    Standard normal samples truncated to [-2, 2], by inverting the CDF.

    On the CPU, where the random number generator is what POPLIN-P's large searches wait for (tens of millions
    of samples per plan), each 64-bit draw gives four 16-bit uniforms, and each picks one of 65,536 equally
    likely bins: the sample is the truncated normal's quantile at the bin's midpoint, looked up in a table (a
    discretisation finer than 3e-4 in x everywhere, with the law's mean and variance), for less than half the
    cost of one 32-bit float uniform and an inverse CDF per sample. Elsewhere one float uniform per sample.

    :param shape: shape of the samples
    :param device: device of the samples
    :param generator: random generator
    :param out: float32 tensor of ``shape`` to fill (a reused buffer: fresh tens-of-megabyte tensors cost more
        in page faults than the sampling itself)
    :param scratch: contiguous int64 CPU buffer of at least ``ceil(numel / 4)`` elements for the raw bits
    :param unit_variance: False returns the samples divided by sqrt(2), which saves one pass when the caller
        scales them anyway
    :return: the samples (``out`` if given)
    """
    n = math.prod(shape)
    if out is None:
        out = th.empty(shape, device=device)
    elif tuple(out.shape) != tuple(shape) or not out.is_contiguous():
        raise ValueError(f"out must be a contiguous tensor of shape {tuple(shape)}, got {tuple(out.shape)}")
    flat = out.view(-1)
    if th.device(device).type == "cpu":
        n_words = (n + 3) // 4
        if scratch is None or scratch.numel() < n_words:
            scratch = th.empty(n_words, dtype=th.int64, device=device)
        bits = scratch[:n_words].random_(-(2**63), None, generator=generator)
        return _levels_to_samples(bits.view(th.uint16)[:n], out, unit_variance)
    flat.uniform_(2.0 * _PHI_MINUS_2 - 1.0, 2.0 * _PHI_PLUS_2 - 1.0, generator=generator)
    out.erfinv_().clamp_(-math.sqrt(2.0), math.sqrt(2.0))
    return out.mul_(math.sqrt(2.0)) if unit_variance else out


def _levels_to_samples(levels: th.Tensor, out: th.Tensor, unit_variance: bool, index: th.Tensor | None = None) -> th.Tensor:
    """
    Fill the contiguous CPU tensor ``out`` with the truncated-normal quantiles of the 16-bit ``levels``.

    :param index: int32 scratch of at least ``min(levels.numel(), _GATHER_CHUNK)`` elements (a reused buffer), or None
    """
    n, flat = levels.numel(), out.view(-1)
    table = _quantile_table(flat.device, unit_variance)
    if index is None or index.numel() < min(n, _GATHER_CHUNK):
        index = th.empty(min(n, _GATHER_CHUNK), dtype=th.int32)
    for start in range(0, n, _GATHER_CHUNK):
        stop = min(start + _GATHER_CHUNK, n)
        chunk = index[: stop - start]
        chunk.copy_(levels[start:stop])
        th.index_select(table, 0, chunk, out=flat[start:stop])
    return out


def _buffer(store: dict[str, th.Tensor], name: str, numel: int, dtype: th.dtype, device: th.device) -> th.Tensor:
    """A flat buffer of ``numel`` elements from ``store``, reused while large enough (grown otherwise)."""
    buffer = store.get(name)
    if buffer is None or buffer.numel() < numel or buffer.dtype != dtype or buffer.device != th.device(device):
        buffer = th.empty(numel, dtype=dtype, device=device)
        store[name] = buffer
    return buffer[:numel]


class OptimizerResult(NamedTuple):
    """What an optimizer found for each env."""

    solution: th.Tensor  # [n_envs, D]: CEM's final mean, or random shooting's best sample
    elite_return: th.Tensor  # [n_envs]: mean return of the final elites (or the best sample)
    elites: th.Tensor  # [n_envs, K, D]: the final elites (random shooting: the best sample, K = 1)
    found: th.Tensor  # [n_envs] bool: some candidate had a finite return (else the solution is the incoming mean)


class CEM:
    """
    Cross-entropy method with momentum (PETS/POPLIN): sample ``population_size`` candidates from
    N(mean, var), keep the ``num_elites`` best, and move mean and variance towards the elites'
    statistics: ``new = alpha * old + (1 - alpha) * elite``. A candidate whose return is NaN or
    +-inf is never an elite; if an env has no finite candidate, its distribution is left unchanged.

    :param population_size: candidates per iteration and env
    :param num_elites: elites per iteration
    :param iterations: CEM iterations per plan
    :param alpha: momentum of the old statistics, in [0, 1)
    :param sampling: ``"truncated"`` (normal truncated at 2 sigma, redrawn beyond) or ``"clipped"``
        (plain normal; the search space clips to its bounds)
    """

    def __init__(
        self,
        population_size: int,
        num_elites: int,
        iterations: int,
        alpha: float = 0.1,
        sampling: str = "truncated",
    ) -> None:
        if sampling not in SAMPLINGS:
            raise ValueError(f"Unknown CEM sampling {sampling!r}; accepted values: {list(SAMPLINGS)}")
        self.population_size = population_size
        self.num_elites = num_elites
        self.iterations = iterations
        self.alpha = alpha
        self.sampling = sampling
        self._buffers: dict[str, th.Tensor] = {}

    def _sample(self, mean: th.Tensor, std: th.Tensor, generator: th.Generator | None) -> th.Tensor:
        """
        Candidates ``z = mean + std * noise``, ``[n_envs, N, D]``, in a buffer reused across iterations and plans
        (at POPLIN-P's sizes a fresh tensor per iteration costs as much in page faults as drawing the samples; the
        candidates never leave :meth:`optimize`: elites are copies). For truncated sampling the noise is drawn divided
        by sqrt(2) (one pass fewer) and ``std`` comes scaled by sqrt(2) to match.

        On the CPU the rows are drawn in chunks of about :data:`_CHUNK_SAMPLES` samples, chunk ``c`` from a
        ``numpy.random.SFC64`` stream seeded with ``base + c`` (``base``: one draw from ``generator``): each chunk's
        noise is scaled into ``z`` while it is in cache, random bits come at twice the rate of torch's CPU
        generator, and the chunks are shared among the intra-op threads (:func:`sb3_poplin.parallel.run_shares`;
        torch's CPU generator is serial) with the same samples for any thread count.
        """
        n_envs, dim = mean.shape
        pop = self.population_size
        z = _buffer(self._buffers, "candidates", n_envs * pop * dim, th.float32, mean.device).view(n_envs, pop, dim)
        if mean.device.type != "cpu":
            if self.sampling == "truncated":
                truncated_normal(z.shape, z.device, generator, out=z, unit_variance=False)
            else:
                z.normal_(generator=generator)
            return th.addcmul(mean.unsqueeze(1), z, std.unsqueeze(1), out=z)
        rows = max(1, _CHUNK_SAMPLES // dim)
        chunks = [(env, start, min(start + rows, pop)) for env in range(n_envs) for start in range(0, pop, rows)]
        base = int(th.randint(0, 2**62, (1,), generator=generator).item())

        def share(index: int, first: int, last: int) -> Callable[[], None]:
            def run() -> None:
                noise = _buffer(self._buffers, f"noise{index}", rows * dim, th.float32, z.device)
                lookup = _buffer(self._buffers, f"index{index}", min(rows * dim, _GATHER_CHUNK), th.int32, z.device)
                chunk_generator = th.Generator() if self.sampling != "truncated" else None
                for c in range(first, last):
                    env, start, stop = chunks[c]
                    out = noise[: (stop - start) * dim].view(stop - start, dim)
                    if chunk_generator is None:
                        bits = th.from_numpy(np.random.SFC64(base + c).random_raw((out.numel() + 3) // 4))
                        _levels_to_samples(bits.view(th.uint16)[: out.numel()], out, False, lookup)
                    else:
                        out.normal_(generator=chunk_generator.manual_seed(base + c))
                    th.addcmul(mean[env], out, std[env], out=z[env, start:stop])

            return run

        ranges = parallel.split_range(len(chunks), th.get_num_threads())
        parallel.run_shares([share(i, first, last) for i, (first, last) in enumerate(ranges)])
        return z

    def optimize(
        self,
        evaluate: Evaluate,
        mean: th.Tensor,
        var: th.Tensor,
        constrain_var: Callable[[th.Tensor, th.Tensor], th.Tensor],
        generator: th.Generator | None = None,
    ) -> OptimizerResult:
        """
        :param evaluate: ``z [n_envs, N, D] -> returns [n_envs, N]``
        :param mean: initial mean ``[n_envs, D]``
        :param var: initial variance ``[n_envs, D]``
        :param constrain_var: the search space's variance constraint ``(mean, var) -> var``
        :param generator: random generator for the samples
        """
        n_envs, dim = mean.shape
        elite_return = th.zeros(n_envs, device=mean.device)
        elites = mean.unsqueeze(1).expand(n_envs, self.num_elites, dim)
        found = th.zeros(n_envs, dtype=th.bool, device=mean.device)
        for _ in range(self.iterations):
            std = constrain_var(mean, var).sqrt()
            if self.sampling == "truncated":  # _sample draws truncated-normal noise / sqrt(2)
                std = std * math.sqrt(2.0)
            z = self._sample(mean, std, generator)  # [n_envs, N, D]
            returns = evaluate(z)  # [n_envs, N]
            returns = th.where(th.isfinite(returns), returns, th.full_like(returns, -math.inf))
            top, idx = returns.topk(self.num_elites, dim=1)  # [n_envs, K]
            # [n_envs, K, D]: one row gather (take_along_dim would expand the index to K x D and wrap it)
            rows = (idx + th.arange(n_envs, device=idx.device).unsqueeze(1) * self.population_size).view(-1)
            elites = z.view(n_envs * self.population_size, dim).index_select(0, rows).view(n_envs, -1, dim)
            valid = th.isfinite(top)  # [n_envs, K]: -inf rows are not elites
            count = valid.sum(dim=1, keepdim=True).clamp(min=1).to(z.dtype)  # [n_envs, 1]
            # weighted means as [1, K] x [K, D] products: one pass over the elites each, where element-wise
            # weighting and a reduction over K took five (6 ms per POPLIN-P iteration on one core, 1 ms this way)
            weight = (valid / count).to(z.dtype).unsqueeze(1)  # [n_envs, 1, K]
            elite_mean = th.bmm(weight, elites)  # [n_envs, 1, D]
            deviation = _buffer(self._buffers, "deviation", elites.numel(), z.dtype, z.device).view(elites.shape)
            th.sub(elites, elite_mean, out=deviation).square_()
            elite_var = th.bmm(weight, deviation).squeeze(1)
            elite_mean = elite_mean.squeeze(1)
            has_elites = valid.any(dim=1, keepdim=True)  # [n_envs, 1]
            found = found | has_elites.squeeze(1)
            mean = th.where(has_elites, self.alpha * mean + (1 - self.alpha) * elite_mean, mean)
            var = th.where(has_elites, self.alpha * var + (1 - self.alpha) * elite_var, var)
            elite_return = th.where(valid, top, th.zeros_like(top)).sum(dim=1) / count.squeeze(1)
        return OptimizerResult(mean, elite_return, elites, found)


class RandomShooting:
    """
    Random shooting: one round of ``population_size`` uniform samples over [-1, 1]^D per env;
    the best candidate is the solution. Non-finite returns rank last.

    :param population_size: candidates per env
    """

    def __init__(self, population_size: int) -> None:
        self.population_size = population_size
        self.iterations = 1

    def optimize(
        self,
        evaluate: Evaluate,
        mean: th.Tensor,
        var: th.Tensor,
        constrain_var: Callable[[th.Tensor, th.Tensor], th.Tensor],
        generator: th.Generator | None = None,
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
        return OptimizerResult(solution, th.where(found, best_return, 0.0), solution.unsqueeze(1), found)


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
    def executed_action(self, solution: th.Tensor, obs: th.Tensor, context: Any) -> th.Tensor:
        """Scaled action ``[n_envs, A]`` to execute given the optimizer's solution ``[n_envs, D]``."""

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

    def executed_action(self, solution: th.Tensor, obs: th.Tensor, context: Any) -> th.Tensor:
        return solution[:, : self.action_dim].clamp(-1.0, 1.0)


class PolicyActionNoise(SearchSpace):
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
        super().__init__(horizon, action_dim, init_var)
        if proposal not in PROPOSALS:
            raise ValueError(f"Unknown POPLIN-A proposal {proposal!r}; accepted values: {list(PROPOSALS)}")
        self.policy = policy
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

    def executed_action(self, solution: th.Tensor, obs: th.Tensor, context: Any) -> th.Tensor:
        return (self.policy.act(obs) + solution[:, : self.action_dim]).clamp(-1.0, 1.0)

    def fallback_action(self, obs: th.Tensor) -> th.Tensor:
        return self.policy.act(obs)


class PolicyParameterNoise(SearchSpace):
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
        super().__init__(horizon, action_dim, init_var)
        if noise not in NOISES:
            raise ValueError(f"Unknown POPLIN-P noise {noise!r}; accepted values: {list(NOISES)}")
        self.policy = policy
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

    def executed_action(self, solution: th.Tensor, obs: th.Tensor, context: Any) -> th.Tensor:
        return self.policy.forward_perturbed(obs.unsqueeze(1), self.first_block(solution))[:, 0].clamp(-1.0, 1.0)

    def fallback_action(self, obs: th.Tensor) -> th.Tensor:
        return self.policy.act(obs)


class PlanResult(NamedTuple):
    """One plan for a batch of envs."""

    action: th.Tensor  # [n_envs, A] scaled action to execute
    next_mean: th.Tensor  # [n_envs, D] warm start for the next env step
    elite_return: th.Tensor  # [n_envs] planned return of the final elites
    solution: th.Tensor  # [n_envs, D] the optimizer's solution (CEM: final mean)
    elites: th.Tensor  # [n_envs, K, D] the final elites
    fallback: th.Tensor  # [n_envs] bool: no candidate was finite, the fallback action was used


class MPCPlanner:
    """
    Plans with a learned model: the one rollout loop shared by every variant.

    :param model: the dynamics ensemble
    :param search_space: what is searched
    :param optimizer: :class:`CEM` or :class:`RandomShooting`
    :param reward_fn: task reward ``(obs, action in env units, next_obs) -> [B]``; ``None`` when
        the model predicts the reward
    :param termination_fn: task termination, or ``None`` (never terminates); rewards after a
        predicted termination are masked
    :param propagation: one of :data:`sb3_poplin.dynamics.PROPAGATIONS`
    :param num_particles: particles per candidate (1 with ``"expectation"``)
    :param action_low: env lower bounds ``[A]``
    :param action_high: env upper bounds ``[A]``
    :param dtype: ``th.float32``, or ``th.bfloat16`` to run the networks' matmuls in bf16 (fp32 accumulation)
    :param max_batch_rows: upper bound on the rows pushed through the ensemble at once (per candidate:
        its particles, or the E members with ``"expectation"``); larger populations are evaluated in chunks
        of candidates, with identical results. ``None``: no bound.
    """

    def __init__(
        self,
        model: ProbabilisticEnsemble,
        search_space: SearchSpace,
        optimizer: CEM | RandomShooting,
        reward_fn: RewardFn | None,
        termination_fn: TerminationFn | None,
        propagation: str,
        num_particles: int,
        action_low: th.Tensor,
        action_high: th.Tensor,
        dtype: th.dtype = th.float32,
        max_batch_rows: int | None = None,
    ) -> None:
        if reward_fn is None and not model.learned_reward:
            raise ValueError("The planner needs a reward: pass reward_fn or use a model with learned_reward=True.")
        if dtype not in (th.float32, th.bfloat16):
            raise ValueError(f"Planning dtype must be float32 or bfloat16, got {dtype}")
        if max_batch_rows is not None and max_batch_rows < 1:
            raise ValueError(f"max_batch_rows must be >= 1 or None, got {max_batch_rows}")
        self.model = model
        self.search_space = search_space
        self.optimizer = optimizer
        self.reward_fn = reward_fn
        self.termination_fn = termination_fn
        self.propagation = propagation
        self.num_particles = 1 if propagation == "expectation" else num_particles
        self.action_low = action_low
        self.action_scale = (action_high - action_low) / 2.0
        self.dtype = dtype
        self.max_batch_rows = max_batch_rows

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
    def plan(self, obs: th.Tensor, mean: th.Tensor, generator: th.Generator | None = None) -> PlanResult:
        """
        :param obs: real observations ``[n_envs, o]``
        :param mean: warm-start mean ``[n_envs, D]``
        :param generator: random generator for sampling and propagation
        """
        context = self.search_space.prepare(obs, self)
        result = self.optimizer.optimize(
            lambda z: self.rollout(obs, z, context, generator),
            mean,
            self.search_space.initial_var(mean),
            self.search_space.constrain_var,
            generator,
        )
        space = self.search_space
        found = result.found.unsqueeze(1)
        action = th.where(found, space.executed_action(result.solution, obs, context), space.fallback_action(obs))
        # never a non-finite action (e.g. a NaN observation): the action-space centre instead
        action = th.nan_to_num(action, nan=0.0, posinf=1.0, neginf=-1.0).clamp(-1.0, 1.0)
        # an env whose plan failed starts afresh at the next step
        next_mean = th.where(found, space.shift(result.solution), space.initial_mean(obs.shape[0], obs.device))
        return PlanResult(action, next_mean, result.elite_return, result.solution, result.elites, ~result.found)
