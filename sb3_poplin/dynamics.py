"""
The learned dynamics: a probabilistic ensemble (PE) of Gaussian MLPs, after PETS (Chua et al. 2018).

This module owns the ensemble's parameters, its input/target normalisation, fitting on a batch of
transitions, and propagation of imagined states during planning. All members live in one module
with weights ``[E, in, out]``: a forward pass is one batched matmul per layer, whatever E is.

The observation goes through three hooks, PETS's names (a task may define them, see
:class:`sb3_poplin.tasks.TaskSpec`):

- ``obs_preproc(obs) -> features``: the model input, concatenated with the action scaled to [-1, 1] and
  standardised with statistics refit on all data before each fit. Default: the observation without the
  ``input_exclude`` indices (e.g. the x position).
- ``targ_proc(obs, next_obs) -> target``: what the network learns to predict. Default: the delta ``next_obs - obs``
  (all indices, excluded ones included); with ``learned_reward`` the reward is appended.
- ``obs_postproc(obs, prediction) -> next_obs``: the next observation from a predicted target. Default: ``obs +
  prediction``.

With ``standardise_targets`` the targets are standardised per dimension too (the learned log-variance bounds then
act in standardised units); without, the network predicts them in env units, as PETS's code did.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Sequence
from itertools import pairwise
from typing import NamedTuple

import torch as th
import torch.nn.functional as F
from torch import nn

from sb3_poplin import kernels

PROPAGATIONS = ("expectation", "ts1", "tsinf", "ds")

ObsPreproc = Callable[[th.Tensor], th.Tensor]
TargProc = Callable[[th.Tensor, th.Tensor], th.Tensor]
ObsPostproc = Callable[[th.Tensor, th.Tensor], th.Tensor]


def check_model_hooks(
    input_exclude: Sequence[int],
    obs_preproc: ObsPreproc | None,
    targ_proc: TargProc | None,
    obs_postproc: ObsPostproc | None,
    owner: str = "",
) -> None:
    """
    The model hooks must be consistent: ``targ_proc`` and ``obs_postproc`` together (each the other's inverse), and
    ``obs_preproc`` not with ``input_exclude``.

    :param owner: named at the start of the message (e.g. ``"TaskSpec 'X-v0': "``)
    :raises ValueError: naming the problem and the fix
    """
    if (targ_proc is None) != (obs_postproc is None):
        raise ValueError(
            f"{owner}targ_proc and obs_postproc come together (obs_postproc(obs, targ_proc(obs, next_obs)) must give "
            "next_obs back): pass both, or neither for the default delta target."
        )
    if obs_preproc is not None and len(input_exclude):
        raise ValueError(
            f"{owner}Pass either input_exclude or obs_preproc (a TaskSpec's model_input_exclude or obs_preproc), not "
            "both: drop the excluded indices inside obs_preproc."
        )


def delta_target(obs: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    """The default ``targ_proc``: ``next_obs - obs``."""
    return next_obs - obs


def add_delta(obs: th.Tensor, prediction: th.Tensor) -> th.Tensor:
    """The default ``obs_postproc``: ``obs + prediction``."""
    return obs + prediction


def default_weight_decays(num_hidden: int) -> list[float]:
    """
    Per-layer L2 coefficients of the PETS/POPLIN code for ``num_hidden`` hidden layers plus the
    output layer: 2.5e-5, 5e-5, then 7.5e-5 for the remaining hidden layers, and 1e-4 on the output.
    """
    hidden = [2.5e-5, 5e-5] + [7.5e-5] * max(num_hidden - 2, 0)
    return [*hidden[:num_hidden], 1e-4]


class EnsembleLinear(nn.Module):
    """
    ``E`` independent linear layers applied as one batched matmul.

    :param ensemble_size: number of members E
    :param in_features: input width
    :param out_features: output width
    """

    def __init__(self, ensemble_size: int, in_features: int, out_features: int) -> None:
        super().__init__()
        self.weight = nn.Parameter(th.empty(ensemble_size, in_features, out_features))
        self.bias = nn.Parameter(th.zeros(ensemble_size, 1, out_features))
        # truncated normal, std 1 / (2 sqrt(fan_in)), as in the PETS code
        std = 1.0 / (2.0 * math.sqrt(in_features))
        nn.init.trunc_normal_(self.weight, std=std, a=-2 * std, b=2 * std)

    def forward(self, x: th.Tensor) -> th.Tensor:
        """:param x: ``[E, B, in]`` -> ``[E, B, out]``"""
        return th.baddbmm(self.bias, x, self.weight)


class StepNoise(NamedTuple):
    """
    The randomness of one propagation step for ``[N, P]`` particles, drawn up front so that
    evaluating the candidates in chunks gives exactly the same result as all at once.
    """

    order: th.Tensor | None  # [N, P] particle order (ts1 / ds): the first P/E particles go to member 0, ...
    eps: th.Tensor | None  # [N, P, out] standard normal for sampling the Gaussian heads
    resample: th.Tensor | None  # [N, P, out] standard normal for ds's moment-matched resampling

    def rows(self, index: slice) -> StepNoise:
        """The noise of a slice of candidates (dim 1 of ``[n_envs, N, P, ...]`` tensors)."""
        return StepNoise(*(None if t is None else t[:, index] for t in self))

    def flatten(self) -> StepNoise:
        """``[n_envs, N, P, ...]`` -> ``[n_envs * N, P, ...]``."""
        return StepNoise(*(None if t is None else t.flatten(0, 1) for t in self))


class FitResult(NamedTuple):
    """Summary of one call to :meth:`ProbabilisticEnsemble.fit`."""

    loss: float  # mean training loss of the last epoch (NLL + penalties)
    train_mse: float  # mean squared error of the member means on the training data, env units
    holdout_mse: float  # same on the holdout split (nan without holdout)
    epochs: int  # epochs actually run (fewer with early stopping)


class ProbabilisticEnsemble(nn.Module):
    """
    Ensemble of Gaussian MLPs predicting ``targ_proc(obs, next_obs)`` (by default the next-observation delta) and
    optionally the reward.

    :param obs_dim: observation size
    :param action_dim: action size
    :param ensemble_size: number of members E
    :param hidden_sizes: hidden layer widths (swish activations)
    :param input_exclude: observation indices not fed to the network (their delta is still predicted); only
        without ``obs_preproc``
    :param learned_reward: also predict the reward (one extra output)
    :param weight_decays: L2 coefficient per layer (hidden layers then output); ``None`` gives
        :func:`default_weight_decays`
    :param obs_preproc: ``obs [..., o] -> model input features [..., f]``; ``None``: drop ``input_exclude``
    :param targ_proc: ``(obs, next_obs) -> training target [..., t]``; ``None``: :func:`delta_target`
    :param obs_postproc: ``(obs, prediction [..., t]) -> next_obs``; ``None``: :func:`add_delta`. Given with
        ``targ_proc`` (each is the other's inverse)
    :param standardise_targets: standardise the training targets per dimension (statistics refit before every
        fit); ``False`` (the default, as ``POPLIN``'s): the network predicts them in env units (PETS)
    """

    obs_index: th.Tensor
    input_mean: th.Tensor
    input_std: th.Tensor
    target_mean: th.Tensor
    target_std: th.Tensor

    def __init__(
        self,
        obs_dim: int,
        action_dim: int,
        ensemble_size: int = 5,
        hidden_sizes: Sequence[int] = (200, 200, 200, 200),
        input_exclude: Sequence[int] = (),
        learned_reward: bool = False,
        weight_decays: Sequence[float] | None = None,
        obs_preproc: ObsPreproc | None = None,
        targ_proc: TargProc | None = None,
        obs_postproc: ObsPostproc | None = None,
        standardise_targets: bool = False,
    ) -> None:
        super().__init__()
        if ensemble_size < 1:
            raise ValueError(f"ensemble_size must be >= 1, got {ensemble_size}")
        check_model_hooks(input_exclude, obs_preproc, targ_proc, obs_postproc)
        self.obs_dim = obs_dim
        self.action_dim = action_dim
        self.ensemble_size = ensemble_size
        self.learned_reward = learned_reward
        self.standardise_targets = standardise_targets
        self.hidden_sizes = list(hidden_sizes)
        kept = [i for i in range(obs_dim) if i not in set(input_exclude)]
        self.register_buffer("obs_index", th.tensor(kept, dtype=th.long), persistent=False)
        self.hooks = (obs_preproc, targ_proc or delta_target, obs_postproc or add_delta)
        probe = th.zeros(1, obs_dim)
        self.feature_dim = int(self.obs_preproc(probe).shape[-1])
        self.target_dim = int(self.targ_proc(probe, probe).shape[-1])
        self.in_dim = self.feature_dim + action_dim
        self.out_dim = self.target_dim + int(learned_reward)

        sizes = [self.in_dim, *hidden_sizes]
        self.hidden = nn.ModuleList(EnsembleLinear(ensemble_size, a, b) for a, b in pairwise(sizes))
        self.output = EnsembleLinear(ensemble_size, sizes[-1], 2 * self.out_dim)
        decays = default_weight_decays(len(hidden_sizes)) if weight_decays is None else list(weight_decays)
        if len(decays) != len(hidden_sizes) + 1:
            raise ValueError(
                f"weight_decays needs one value per layer ({len(hidden_sizes) + 1}: hidden layers then output), "
                f"got {len(decays)}"
            )
        self.weight_decays = decays
        # learned soft bounds on the log-variance (PETS), penalised by 0.01 * (sum max - sum min)
        self.max_logvar = nn.Parameter(th.full((1, 1, self.out_dim), 0.5))
        self.min_logvar = nn.Parameter(th.full((1, 1, self.out_dim), -10.0))
        # normalisers (saved with the model)
        self.register_buffer("input_mean", th.zeros(self.in_dim))
        self.register_buffer("input_std", th.ones(self.in_dim))
        self.register_buffer("target_mean", th.zeros(self.out_dim))
        self.register_buffer("target_std", th.ones(self.out_dim))

    # ------------------------------------------------------------------ forward
    def obs_preproc(self, obs: th.Tensor) -> th.Tensor:
        """Model input features of raw observations ``[..., o]`` (by default: without the ``input_exclude`` indices)."""
        preproc = self.hooks[0]
        return obs.index_select(-1, self.obs_index) if preproc is None else preproc(obs)

    def targ_proc(self, obs: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
        """The training target of a transition, in env units (by default the delta)."""
        return self.hooks[1](obs, next_obs)

    def obs_postproc(self, obs: th.Tensor, prediction: th.Tensor) -> th.Tensor:
        """The next observation from a predicted target (by default ``obs + prediction``)."""
        return self.hooks[2](obs, prediction)

    def raw_input(self, obs: th.Tensor, action: th.Tensor) -> th.Tensor:
        """Network input before standardisation: ``[obs_preproc(obs), action]`` from raw observations ``[..., o]``."""
        return th.cat([self.obs_preproc(obs), action], dim=-1)

    def model_input(self, obs: th.Tensor, action: th.Tensor) -> th.Tensor:
        """Standardised network input from raw observations ``[..., o]`` and scaled actions ``[..., a]``."""
        return (self.raw_input(obs, action) - self.input_mean) / self.input_std

    def training_target(self, obs: th.Tensor, next_obs: th.Tensor, rewards: th.Tensor | None = None) -> th.Tensor:
        """Target in env units: ``targ_proc(obs, next_obs)``, with the reward appended under ``learned_reward``."""
        target = self.targ_proc(obs, next_obs)
        if self.learned_reward:
            assert rewards is not None
            target = th.cat([target, rewards.reshape(-1, 1)], dim=-1)
        return target

    def next_observation(self, obs: th.Tensor, prediction: th.Tensor) -> tuple[th.Tensor, th.Tensor | None]:
        """
        :param obs: the current observations ``[..., o]``
        :param prediction: predicted targets in env units ``[..., out]``
        :return: the next observations (``obs_postproc``) and, under ``learned_reward``, the rewards ``[...]``
        """
        next_obs = self.obs_postproc(obs, prediction[..., : self.target_dim])
        return next_obs, (prediction[..., self.target_dim] if self.learned_reward else None)

    def forward(self, x: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """
        :param x: standardised input ``[E, B, in]``
        :return: mean and bounded log-variance of the standardised target, each ``[E, B, out]``
        """
        for layer in self.hidden:
            x = F.silu(layer(x))
        return self._gaussian_head(self.output(x))

    def _gaussian_head(self, out: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """Mean and log-variance from the output layer, the log-variance softly bounded (PETS)."""
        mean, logvar = out.chunk(2, dim=-1)
        logvar = self.max_logvar - F.softplus(self.max_logvar - logvar)
        logvar = self.min_logvar + F.softplus(logvar - self.min_logvar)
        return mean, logvar

    def predict(self, x: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """
        :meth:`forward` for evaluation and planning: the same numbers, through the speed layer
        (:mod:`sb3_poplin.kernels`) where it applies (no gradients, on a CPU). Float32 outputs under a bf16
        autocast.

        :param x: standardised input ``[E, B, in]``
        """
        out = kernels.no_grad_output(self, x)
        return self(x) if out is None else self._gaussian_head(out)

    def shared_input_mean(self, x: th.Tensor) -> th.Tensor:
        """
        The members' means for one input batch shared by all members (expectation propagation): the same numbers as
        ``self(x.expand(E, -1, -1))[0]``, without gradients through the speed layer
        (:func:`sb3_poplin.kernels.shared_input_mean`: no log-variance, no copy of the input per member).

        :param x: standardised input ``[B, in]``
        :return: mean of the standardised target ``[E, B, out]`` (float32 for a float32 ``x``)
        """
        if th.is_grad_enabled():
            return self(x.expand(self.ensemble_size, -1, -1))[0]
        return kernels.shared_input_mean(self, x)

    def _to_delta(self, normalised: th.Tensor) -> th.Tensor:
        return normalised * self.target_std + self.target_mean

    # ------------------------------------------------------------------ propagation
    def draw_noise(
        self, shape: tuple[int, ...], propagation: str, device: th.device, generator: th.Generator | None = None
    ) -> StepNoise:
        """
        The randomness :meth:`propagate` needs for particles of the given leading shape (e.g. ``[N, P]``).

        :param shape: leading shape of the particles, ending with the particle dimension P
        :param propagation: one of :data:`PROPAGATIONS`
        :param device: where to draw
        :param generator: random generator
        """
        if propagation == "expectation":
            return StepNoise(None, None, None)
        out = (*shape, self.out_dim)
        order = th.rand(shape, device=device, generator=generator).argsort(dim=-1) if propagation in ("ts1", "ds") else None
        eps = th.randn(out, device=device, generator=generator)
        resample = th.randn(out, device=device, generator=generator) if propagation == "ds" else None
        return StepNoise(order, eps, resample)

    def propagate(
        self,
        states: th.Tensor,
        actions: th.Tensor,
        propagation: str,
        generator: th.Generator | None = None,
        noise: StepNoise | None = None,
    ) -> tuple[th.Tensor, th.Tensor | None]:
        """
        One imagined step for a batch of candidates, each with ``P`` particles.

        - ``expectation``: P must be 1; every candidate goes through all E members and the next
          state is the mean of the members' means (no sampling): ``[N, E]`` rows, not ``[N, P, E]``.
        - ``tsinf``: particle p of every candidate always uses member ``p // (P / E)``, so the
          particles of a candidate are spread evenly over the members; next states are sampled.
        - ``ts1``: like ``tsinf`` but the particle-to-member assignment is redrawn at every step
          (a random permutation per candidate, still P / E particles per member).
        - ``ds``: ``ts1``, then the candidate's particles are replaced by samples from a Gaussian
          fitted to them (moment matching).

        :param states: ``[N, P, o]`` raw observations
        :param actions: ``[N, P, a]`` scaled actions
        :param propagation: one of :data:`PROPAGATIONS`
        :param generator: random generator for sampling (when ``noise`` is not given)
        :param noise: this step's randomness from :meth:`draw_noise` (``[N, P]`` particles), drawn here if None
        :return: next states ``[N, P, o]`` and, with ``learned_reward``, predicted rewards ``[N, P]``
        """
        n, p, _ = states.shape
        e = self.ensemble_size
        x = self.model_input(states, actions)  # [N, P, in]
        if propagation == "expectation":
            mean = self.shared_input_mean(x.reshape(n * p, self.in_dim))  # [E, N*P, out]
            out = self._to_delta(mean.mean(dim=0)).view(n, p, self.out_dim)
        else:
            if noise is None:
                noise = self.draw_noise((n, p), propagation, x.device, generator)
            assert noise.eps is not None
            # the rows of member m: particles order[c, m k : (m + 1) k] of every candidate c (k = P / E; particle p
            # in place of order[c, p] without an order), gathered member-major from the flat particles [N P, d]: one
            # copy in and one out, no argsort to undo the shuffle
            per_member = p // e
            slots = th.arange(p, device=x.device) if noise.order is None else noise.order  # [P] or [N, P]
            flat = (th.arange(n, device=x.device) * p).unsqueeze(1) + slots  # [N, P] row of each slot's particle
            rows = flat.view(n, e, per_member).transpose(0, 1).reshape(-1)  # [E * N * k]
            mean, logvar = self.predict(x.reshape(n * p, -1).index_select(0, rows).view(e, n * per_member, -1))
            eps = noise.eps.reshape(n * p, -1).index_select(0, rows).view(e, n * per_member, -1)
            sample = mean + (0.5 * logvar).exp() * eps  # [E, N * k, out]
            out = th.empty(n * p, self.out_dim, dtype=sample.dtype, device=sample.device)
            out = self._to_delta(out.index_copy_(0, rows, sample.reshape(-1, self.out_dim)).view(n, p, self.out_dim))
            if noise.resample is not None:  # ds: resample from the particles' moments
                mu = out.mean(dim=1, keepdim=True)
                std = out.std(dim=1, keepdim=True, unbiased=False)
                out = mu + std * noise.resample
        return self.next_observation(states, out)

    # ------------------------------------------------------------------ fitting
    def _loss(self, x: th.Tensor, y: th.Tensor) -> th.Tensor:
        """Gaussian NLL summed over members (mean over batch and dims), plus weight decay and bound penalty."""
        mean, logvar = self(x)
        nll = ((mean - y) ** 2 * th.exp(-logvar) + logvar).mean(dim=(1, 2)).sum()
        layers = [*self.hidden, self.output]
        decay = sum(c * 0.5 * (layer.weight**2).sum() for c, layer in zip(self.weight_decays, layers, strict=True))
        bounds = 0.01 * (self.max_logvar.sum() - self.min_logvar.sum())
        return nll + decay + bounds

    @th.no_grad()
    def prediction_mse(self, inputs: th.Tensor, targets: th.Tensor, batch: int = 4096) -> float:
        """
        Mean squared error of each member's mean prediction, in target units (delta, reward).

        :param inputs: standardised inputs ``[B, in]``
        :param targets: raw targets ``[B, out]``
        """
        total, count = 0.0, 0
        for start in range(0, inputs.shape[0], batch):
            x = inputs[start : start + batch]
            mean, _ = self.predict(x.unsqueeze(0).expand(self.ensemble_size, -1, -1))
            err = (self._to_delta(mean) - targets[start : start + batch]) ** 2
            total += err.sum().item()
            count += err.numel()
        return total / max(count, 1)

    def _epoch(
        self, inputs: th.Tensor, targets: th.Tensor, order: th.Tensor, batch_size: int, optimizer: th.optim.Optimizer
    ) -> float:
        """One pass over the members' sample orders ``order [E, n]``: :return: the mean minibatch loss"""
        losses = []
        for start in range(0, order.shape[1], batch_size):
            idx = order[:, start : start + batch_size]  # [E, b]
            loss = self._loss(inputs[idx], targets[idx])
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            losses.append(loss.detach())
        return th.stack(losses).mean().item()

    @th.no_grad()
    def _refit_normalisers(self, raw_in: th.Tensor, targets: th.Tensor) -> None:
        """Input (and with ``standardise_targets`` target) statistics refit on all data (a std below 1e-12 counts as 1)."""
        pairs = [(raw_in, self.input_mean, self.input_std)]
        if self.standardise_targets:
            pairs.append((targets, self.target_mean, self.target_std))
        for data, mean, std in pairs:
            spread = data.std(dim=0, unbiased=False)
            mean.copy_(data.mean(dim=0))
            std.copy_(th.where(spread < 1e-12, th.ones_like(spread), spread))

    def fit(
        self,
        obs: th.Tensor,
        actions: th.Tensor,
        next_obs: th.Tensor,
        optimizer: th.optim.Optimizer,
        rewards: th.Tensor | None = None,
        epochs: int = 5,
        batch_size: int = 32,
        holdout_ratio: float = 0.0,
        patience: int = 5,
        generator: th.Generator | None = None,
    ) -> FitResult:
        """
        Fit the ensemble on all given transitions (PETS: bootstrap resample per member, the
        normalisers refit on all data first). With ``holdout_ratio > 0`` a random split is held
        out and training stops early once its error has not improved for ``patience`` epochs,
        restoring the best parameters.

        :param obs: ``[B, o]`` observations
        :param actions: ``[B, a]`` actions scaled to [-1, 1]
        :param next_obs: ``[B, o]`` next observations
        :param optimizer: optimizer over this module's parameters
        :param rewards: ``[B]`` rewards, required with ``learned_reward``
        :param epochs: passes over the (bootstrapped) training data
        :param batch_size: minibatch size per member
        :param holdout_ratio: fraction held out for validation / early stopping
        :param patience: epochs without holdout improvement before stopping
        :param generator: random generator for the split, resampling and shuffling
        :return: a :class:`FitResult`
        """
        if self.learned_reward and rewards is None:
            raise ValueError("This ensemble predicts rewards (learned_reward=True): pass rewards= to fit().")
        device = self.input_mean.device
        raw_in = self.raw_input(obs, actions)
        targets = self.training_target(obs, next_obs, rewards)
        n = raw_in.shape[0]
        self._refit_normalisers(raw_in, targets)
        inputs = (raw_in - self.input_mean) / self.input_std
        norm_targets = (targets - self.target_mean) / self.target_std

        perm = th.randperm(n, device=device, generator=generator)
        n_hold = int(n * holdout_ratio) if n > 1 else 0
        hold_idx, train_idx = perm[:n_hold], perm[n_hold:]
        n_train = train_idx.numel()
        batch_size = max(1, min(batch_size, n_train))
        e = self.ensemble_size
        # bootstrap: each member trains on its own with-replacement resample of the training split
        boot = train_idx[th.randint(n_train, (e, n_train), device=device, generator=generator)]

        best_mse, best_state, stale, epoch_loss = math.inf, None, 0, math.nan
        epochs_run = 0
        for _ in range(epochs):
            epochs_run += 1
            shuffle = th.rand(e, n_train, device=device, generator=generator).argsort(dim=1)
            epoch_loss = self._epoch(inputs, norm_targets, th.take_along_dim(boot, shuffle, dim=1), batch_size, optimizer)
            if n_hold > 0:
                mse = self.prediction_mse(inputs[hold_idx], targets[hold_idx])
                if mse < best_mse - 1e-12:
                    best_mse, best_state, stale = mse, copy.deepcopy(self.state_dict()), 0
                else:
                    stale += 1
                    if stale >= patience:
                        break
        if best_state is not None:
            self.load_state_dict(best_state)
        train_mse = self.prediction_mse(inputs[train_idx], targets[train_idx])
        holdout_mse = self.prediction_mse(inputs[hold_idx], targets[hold_idx]) if n_hold > 0 else math.nan
        return FitResult(loss=epoch_loss, train_mse=train_mse, holdout_mse=holdout_mse, epochs=epochs_run)
