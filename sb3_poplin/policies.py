"""
The SB3 policy object of POPLIN: the container of every trained network and its optimizer.

:class:`POPLINPolicy` holds the dynamics ensemble (``dynamics``, with its normalisers as buffers)
and its optimizer, so that SB3's save/load, ``get_parameters`` and device moves cover them. MPC
control lives in the algorithm (it needs the warm-start state and the task); the policy's own
``predict`` is policy control, which PETS and random shooting do not have.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule

from sb3_poplin.dynamics import ProbabilisticEnsemble


class POPLINPolicy(BasePolicy):
    """
    Networks of a model-based planning agent.

    :param observation_space: flat Box observation space
    :param action_space: Box action space
    :param lr_schedule: unused (SB3 interface); the model has its own learning rate
    :param ensemble_size: members of the dynamics ensemble
    :param dynamics_net_arch: hidden layer widths of each member
    :param model_input_exclude: observation indices the model does not see as inputs
    :param learned_reward: the ensemble also predicts the reward
    :param model_learning_rate: Adam learning rate of the dynamics model
    :param model_weight_decays: L2 coefficient per layer, ``None`` for the paper's
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
    ) -> None:
        super().__init__(observation_space, action_space, squash_output=True)
        assert isinstance(observation_space, spaces.Box) and isinstance(action_space, spaces.Box)
        self.ensemble_size = ensemble_size
        self.dynamics_net_arch = list(dynamics_net_arch)
        self.model_input_exclude = list(model_input_exclude)
        self.learned_reward = learned_reward
        self.model_learning_rate = model_learning_rate
        self.model_weight_decays = None if model_weight_decays is None else list(model_weight_decays)
        self.dynamics = ProbabilisticEnsemble(
            obs_dim=int(observation_space.shape[0]),
            action_dim=int(action_space.shape[0]),
            ensemble_size=ensemble_size,
            hidden_sizes=self.dynamics_net_arch,
            input_exclude=self.model_input_exclude,
            learned_reward=learned_reward,
            weight_decays=self.model_weight_decays,
        )
        self.dynamics_optimizer = th.optim.Adam(self.dynamics.parameters(), lr=model_learning_rate)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            ensemble_size=self.ensemble_size,
            dynamics_net_arch=self.dynamics_net_arch,
            model_input_exclude=self.model_input_exclude,
            learned_reward=self.learned_reward,
            model_learning_rate=self.model_learning_rate,
            model_weight_decays=self.model_weight_decays,
        )
        return data

    def forward(self, obs: PyTorchObs, deterministic: bool = True) -> th.Tensor:
        return self._predict(obs, deterministic)

    def _predict(self, observation: PyTorchObs, deterministic: bool = True) -> th.Tensor:
        raise ValueError(
            "This agent has no policy network (PETS and random shooting plan every action): "
            "use control='mpc', or a 'poplin-a' / 'poplin-p' agent for policy control."
        )
