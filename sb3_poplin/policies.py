"""
Networks of POPLIN and the SB3 policy object that holds them.

- :class:`PolicyNetwork`: the tanh MLP of POPLIN (Wang & Ba 2019, section 4), with input whitening
  from the real states seen so far and a linear output in the scaled action space (clipped to
  [-1, 1] when acting, then mapped to the env bounds). Its parameters have one flat layout
  (``W_0`` as ``[in, out]`` row-major, ``b_0``, ``W_1``, ``b_1``, ...), which is the space POPLIN-P
  perturbs; :meth:`PolicyNetwork.forward_perturbed` runs a batch in which every row carries its
  own perturbation, as one batched matmul per layer.
- :class:`POPLINPolicy`: the SB3 container of every trained network (dynamics ensemble, policy
  network, GAN discriminator) and their optimizers, so that SB3's save/load, ``get_parameters``
  and device moves cover them. MPC control lives in the algorithm (it needs the warm-start state
  and the task); the policy's own ``predict`` is policy control.
"""

from __future__ import annotations

from collections.abc import Sequence
from itertools import pairwise
from typing import Any

import numpy as np
import torch as th
import torch.nn.functional as F
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from torch import nn

from sb3_poplin.dynamics import ObsPostproc, ObsPreproc, ProbabilisticEnsemble, TargProc

# whitening: variance floored at 1e-2 (std >= 0.1), as in the original code
MIN_WHITENING_VAR = 1e-2
# what a whitening update does to the first layer (PolicyNetwork.update_whitening)
WHITENING_MODES = ("function", "function_from_raw", "plain")


def normc_(weight: th.Tensor, norm: float, dim: int) -> None:
    """
    "normc" initialisation in place: Gaussian, then every unit's incoming weight vector (the vectors along ``dim``)
    scaled to ``norm``.
    """
    with th.no_grad():
        weight.normal_()
        weight.mul_(norm / weight.norm(dim=dim, keepdim=True))


class PolicyNetwork(nn.Module):
    """
    POPLIN's policy MLP: whitened observation -> action in the scaled space (linear output).

    :param obs_dim: observation size
    :param action_dim: action size
    :param net_arch: hidden widths (tanh)
    :param input_exclude: observation indices the policy does not see (e.g. the x position)
    :param input_preproc: the policy's input features from raw observations ``[..., o] -> [..., f]`` (e.g. a task's
        ``obs_preproc``, shared with the model); ``None``: the observation without ``input_exclude``
    """

    obs_index: th.Tensor
    obs_mean: th.Tensor
    obs_var: th.Tensor
    obs_count: th.Tensor

    def __init__(
        self,
        obs_dim: int,
        action_dim: int,
        net_arch: Sequence[int],
        input_exclude: Sequence[int] = (),
        input_preproc: ObsPreproc | None = None,
    ) -> None:
        super().__init__()
        if input_preproc is not None and len(input_exclude):
            raise ValueError(
                "PolicyNetwork takes either input_exclude or input_preproc (a TaskSpec's policy_input_exclude or "
                "policy_obs_preproc), not both: drop the excluded indices inside the preproc."
            )
        kept = [i for i in range(obs_dim) if i not in set(input_exclude)]
        self.register_buffer("obs_index", th.tensor(kept, dtype=th.long), persistent=False)
        self.input_preproc = input_preproc
        in_dim = len(kept) if input_preproc is None else int(input_preproc(th.zeros(1, obs_dim)).shape[-1])
        self.in_dim, self.action_dim = in_dim, action_dim
        sizes = [self.in_dim, *net_arch, action_dim]
        self.shapes = list(pairwise(sizes))
        self.weights = nn.ParameterList(nn.Parameter(th.empty(a, b)) for a, b in self.shapes)
        self.biases = nn.ParameterList(nn.Parameter(th.zeros(b)) for _, b in self.shapes)
        # "normc" initialisation: each unit's incoming weight vector has norm 1 (0.01 on the output layer)
        for i, weight in enumerate(self.weights):
            normc_(weight, 0.01 if i == len(self.shapes) - 1 else 1.0, dim=0)  # [in, out]: a unit's weights are a column
        self.register_buffer("obs_mean", th.zeros(self.in_dim))
        self.register_buffer("obs_var", th.ones(self.in_dim))
        self.register_buffer("obs_count", th.zeros(()))

    @property
    def num_params(self) -> int:
        """Size W of the flat parameter vector (every layer's weights and biases)."""
        return sum(a * b + b for a, b in self.shapes)

    def flat_parameters(self) -> th.Tensor:
        """The parameters as one vector ``[W]`` in the flat layout."""
        return th.cat([t for w, b in zip(self.weights, self.biases, strict=True) for t in (w.reshape(-1), b)])

    @th.no_grad()
    def add_to_parameters(self, delta: th.Tensor) -> None:
        """``theta <- theta + delta`` for a flat ``delta [W]``."""
        offset = 0
        for weight, bias in zip(self.weights, self.biases, strict=True):
            weight.add_(delta[offset : offset + weight.numel()].view_as(weight))
            offset += weight.numel()
            bias.add_(delta[offset : offset + bias.numel()])
            offset += bias.numel()

    def features(self, obs: th.Tensor) -> th.Tensor:
        """The policy's input before whitening: ``input_preproc(obs)``, or the observation without ``input_exclude``."""
        return obs.index_select(-1, self.obs_index) if self.input_preproc is None else self.input_preproc(obs)

    def whiten(self, obs: th.Tensor) -> th.Tensor:
        """Whitened policy input from raw observations ``[..., o]``."""
        std = self.obs_var.clamp(min=MIN_WHITENING_VAR).sqrt()
        return (self.features(obs) - self.obs_mean) / std

    @th.no_grad()
    def set_parameters(self, flat: th.Tensor) -> None:
        """``theta <- flat`` for a flat vector ``[W]`` in the flat layout."""
        self.add_to_parameters(flat - self.flat_parameters())

    @th.no_grad()
    def update_whitening(self, obs: th.Tensor, mode: str = "function") -> None:
        """
        Add real states ``[B, o]`` to the running whitening statistics.

        :param obs: real observations ``[B, o]``
        :param mode: what happens to the first layer (see :data:`WHITENING_MODES`): ``"function"`` re-expresses it
            so that the network computes the same function as before, except at the first update, when the
            network has only ever seen unwhitened inputs and starts on whitened ones (its normc initialisation is
            then in the regime it was designed for: pre-activations of std about 1); ``"function_from_raw"``
            re-expresses at the first update too (sb3_poplin 0.2.0: the initial network's function of *raw*
            observations is kept, which saturates the tanh units on large-scale observations); ``"plain"``
            never re-expresses (the original code)
        """
        if obs.shape[0] == 0:
            return
        x = self.features(obs)
        reexpress = mode == "function_from_raw" or (mode == "function" and bool(self.obs_count > 0))
        old_std = self.obs_var.clamp(min=MIN_WHITENING_VAR).sqrt()
        old_mean = self.obs_mean.clone()
        n, m = self.obs_count, float(x.shape[0])
        batch_mean, batch_var = x.mean(dim=0), x.var(dim=0, unbiased=False)
        total = n + m
        delta = batch_mean - self.obs_mean
        self.obs_mean.add_(delta * m / total)
        self.obs_var.copy_((self.obs_var * n + batch_var * m + delta**2 * n * m / total) / total)
        self.obs_count.copy_(total)
        if reexpress:
            new_std = self.obs_var.clamp(min=MIN_WHITENING_VAR).sqrt()
            # (x - m_old) / s_old = (x_new * s_new + m_new - m_old) / s_old, x_new = (x - m_new) / s_new
            self.biases[0].add_(((self.obs_mean - old_mean) / old_std) @ self.weights[0])
            self.weights[0].mul_((new_std / old_std).unsqueeze(1))

    def forward(self, obs: th.Tensor) -> th.Tensor:
        """Unclipped scaled action ``[..., A]`` of raw observations ``[..., o]``."""
        x = self.whiten(obs)
        for i, (weight, bias) in enumerate(zip(self.weights, self.biases, strict=True)):
            x = th.addmm(bias, x.reshape(-1, x.shape[-1]), weight).view(*x.shape[:-1], -1)
            if i < len(self.shapes) - 1:
                x = th.tanh(x)
        return x

    def forward_perturbed(self, obs: th.Tensor, noise: th.Tensor) -> th.Tensor:
        """
        Every row with its own parameters ``theta + noise[r]``: one batched matmul per layer.

        :param obs: raw observations ``[R, P, o]`` (P particles share their row's parameters)
        :param noise: flat perturbations ``[R, W]``
        :return: unclipped scaled actions ``[R, P, A]``
        """
        x = self.whiten(obs)  # [R, P, in]
        rows, particles, offset = noise.shape[0], x.shape[1], 0
        for i, ((d_in, d_out), weight, bias) in enumerate(zip(self.shapes, self.weights, self.biases, strict=True)):
            d_weight = noise[:, offset : offset + d_in * d_out].view(rows, d_in, d_out)  # [R, in, out]
            offset += d_in * d_out
            d_bias = noise[:, offset : offset + d_out].view(rows, 1, d_out)  # [R, 1, out]
            offset += d_out
            if particles == 1:
                # x (theta + omega) = x theta + x omega: one shared matmul, the noise read in place (a strided view
                # of the search vector) instead of writing R perturbed weight matrices (POPLIN-P's expectation plans)
                shared = th.addmm(bias, x.reshape(rows, d_in), weight).view(rows, 1, d_out)
                x = th.baddbmm(shared.add_(d_bias), x, d_weight)  # [R, 1, out]
            else:
                # many particles per row: one perturbed matrix per row is cheaper than P extra shared products
                x = th.baddbmm(bias + d_bias, x, weight + d_weight)  # [R, P, out]
            if i < len(self.shapes) - 1:
                x = th.tanh(x)
        return x

    def act(self, obs: th.Tensor) -> th.Tensor:
        """Scaled action clipped to [-1, 1]."""
        return self.forward(obs).clamp(-1.0, 1.0)


class Discriminator(nn.Module):
    """
    GAN distillation's discriminator (POPLIN-P GAN): MLP on ``[action, whitened state]`` with
    leaky-ReLU hidden layers and one logit, initialised as the original code's (normc with norm 1 on every layer,
    the output layer included; biases 0).

    :param input_dim: action size + policy input size
    :param net_arch: hidden widths
    """

    def __init__(self, input_dim: int, net_arch: Sequence[int] = (64, 64)) -> None:
        super().__init__()
        sizes = [input_dim, *net_arch, 1]
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in pairwise(sizes))
        for layer in self.layers:
            assert isinstance(layer, nn.Linear)
            normc_(layer.weight, 1.0, dim=1)  # [out, in]: a unit's weights are a row
            nn.init.zeros_(layer.bias)

    def forward(self, x: th.Tensor) -> th.Tensor:
        """Logits ``[B]`` of ``[B, input_dim]`` inputs."""
        for layer in self.layers[:-1]:
            x = F.leaky_relu(layer(x))
        return self.layers[-1](x).squeeze(-1)


class POPLINPolicy(BasePolicy):
    """
    Networks of a model-based planning agent.

    :param observation_space: flat Box observation space
    :param action_space: Box action space
    :param lr_schedule: unused (SB3 interface); the networks have their own learning rates
    :param ensemble_size: members of the dynamics ensemble
    :param dynamics_net_arch: hidden layer widths of each member
    :param model_input_exclude: observation indices the model (and, by default, the policy) does not see as inputs
    :param learned_reward: the ensemble also predicts the reward
    :param model_learning_rate: Adam learning rate of the dynamics model
    :param model_weight_decays: L2 coefficient per layer, ``None`` for the paper's
    :param policy_net_arch: hidden widths of the policy network; ``None``: no policy network (PETS, RS)
    :param policy_learning_rate: Adam learning rate of the policy network (and the discriminator)
    :param discriminator_net_arch: hidden widths of the GAN discriminator; ``None``: no discriminator
    :param obs_preproc: the task's model-input hook (see :mod:`sb3_poplin.dynamics`); ``None``: the default
    :param targ_proc: the task's model-target hook; ``None``: the delta
    :param obs_postproc: the inverse of ``targ_proc``; ``None``: ``obs + prediction``
    :param standardise_targets: the dynamics model standardises its targets (default ``False``, as ``POPLIN``'s:
        raw targets, as PETS's code)
    :param policy_input_exclude: observation indices the policy network does not see; ``None``:
        ``model_input_exclude``
    :param policy_obs_preproc: the policy network's input features from raw observations (instead of
        ``policy_input_exclude``); ``None``: the observation without ``policy_input_exclude``
    :param normalize_images: SB3's base-policy option (saved by ``policy.save`` and given back by
        ``POPLINPolicy.load``); observations are flat vectors here, never images
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        lr_schedule: Schedule | None = None,
        ensemble_size: int = 5,
        dynamics_net_arch: Sequence[int] = (200, 200, 200, 200),
        model_input_exclude: Sequence[int] = (),
        learned_reward: bool = False,
        model_learning_rate: float = 1e-3,
        model_weight_decays: Sequence[float] | None = None,
        policy_net_arch: Sequence[int] | None = None,
        policy_learning_rate: float = 3e-3,
        discriminator_net_arch: Sequence[int] | None = None,
        obs_preproc: ObsPreproc | None = None,
        targ_proc: TargProc | None = None,
        obs_postproc: ObsPostproc | None = None,
        standardise_targets: bool = False,
        policy_input_exclude: Sequence[int] | None = None,
        policy_obs_preproc: ObsPreproc | None = None,
        normalize_images: bool = True,
    ) -> None:
        super().__init__(observation_space, action_space, squash_output=True, normalize_images=normalize_images)
        assert isinstance(observation_space, spaces.Box) and isinstance(action_space, spaces.Box)
        obs_dim, action_dim = int(observation_space.shape[0]), int(np.prod(action_space.shape))  # flat actions
        self.ensemble_size = ensemble_size
        self.dynamics_net_arch = list(dynamics_net_arch)
        self.model_input_exclude = list(model_input_exclude)
        self.policy_input_exclude = list(model_input_exclude if policy_input_exclude is None else policy_input_exclude)
        self.policy_obs_preproc = policy_obs_preproc
        self.learned_reward = learned_reward
        self.model_learning_rate = model_learning_rate
        self.model_weight_decays = None if model_weight_decays is None else list(model_weight_decays)
        self.policy_net_arch = None if policy_net_arch is None else list(policy_net_arch)
        self.policy_learning_rate = policy_learning_rate
        self.discriminator_net_arch = None if discriminator_net_arch is None else list(discriminator_net_arch)
        self.model_hooks: dict[str, Any] = dict(obs_preproc=obs_preproc, targ_proc=targ_proc, obs_postproc=obs_postproc)
        self.standardise_targets = standardise_targets
        self.dynamics = ProbabilisticEnsemble(
            obs_dim=obs_dim,
            action_dim=action_dim,
            ensemble_size=ensemble_size,
            hidden_sizes=self.dynamics_net_arch,
            input_exclude=self.model_input_exclude,
            learned_reward=learned_reward,
            weight_decays=self.model_weight_decays,
            standardise_targets=standardise_targets,
            **self.model_hooks,
        )
        self.dynamics_optimizer = th.optim.Adam(self.dynamics.parameters(), lr=model_learning_rate)
        self.actor: PolicyNetwork | None = None
        self.discriminator: Discriminator | None = None
        if self.policy_net_arch is not None:
            self.actor = PolicyNetwork(
                obs_dim, action_dim, self.policy_net_arch, self.policy_input_exclude, self.policy_obs_preproc
            )
            self.actor_optimizer = th.optim.Adam(self.actor.parameters(), lr=policy_learning_rate)
        if self.discriminator_net_arch is not None:
            assert self.actor is not None, "the GAN discriminator needs a policy network"
            self.discriminator = Discriminator(action_dim + self.actor.in_dim, self.discriminator_net_arch)
            self.discriminator_optimizer = th.optim.Adam(self.discriminator.parameters(), lr=policy_learning_rate)

    def optimizer_names(self) -> list[str]:
        """Attribute paths (from the algorithm) of every optimizer this policy holds, for SB3's save."""
        names = ["policy.dynamics_optimizer"]
        if self.actor is not None:
            names.append("policy.actor_optimizer")
        if self.discriminator is not None:
            names.append("policy.discriminator_optimizer")
        return names

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            ensemble_size=self.ensemble_size,
            dynamics_net_arch=self.dynamics_net_arch,
            model_input_exclude=self.model_input_exclude,
            policy_input_exclude=self.policy_input_exclude,
            policy_obs_preproc=self.policy_obs_preproc,
            learned_reward=self.learned_reward,
            model_learning_rate=self.model_learning_rate,
            model_weight_decays=self.model_weight_decays,
            policy_net_arch=self.policy_net_arch,
            policy_learning_rate=self.policy_learning_rate,
            discriminator_net_arch=self.discriminator_net_arch,
            standardise_targets=self.standardise_targets,
            **self.model_hooks,
        )
        return data

    def forward(self, obs: PyTorchObs, deterministic: bool = True) -> th.Tensor:
        return self._predict(obs, deterministic)

    def _predict(self, observation: PyTorchObs, deterministic: bool = True) -> th.Tensor:
        """Policy control: the policy network's action in [-1, 1] (SB3 maps it to the env bounds)."""
        if self.actor is None:
            raise ValueError(
                "This agent has no policy network (PETS and random shooting plan every action): "
                "use control='mpc', or a 'poplin-a' / 'poplin-p' agent for policy control."
            )
        assert isinstance(observation, th.Tensor)
        return self.actor.act(observation.float())
