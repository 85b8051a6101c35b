"""
mbrl-lib's PETS model on a recorded dataset, measured by the same code as ours
(``python -m sb3_poplin.analysis model-quality``): the reference side of the model table.

mbrl-lib 0.2.0 pins an old gymnasium and hydra, so it runs in a virtualenv of its own; nothing in the package or its
tests imports this script. Set-up (Python 3.11, from the repository root)::

    python3.11 -m venv /tmp/mbrl-venv
    /tmp/mbrl-venv/bin/pip install torch==2.13.0
    /tmp/mbrl-venv/bin/pip install --no-deps mbrl==0.2.0
    /tmp/mbrl-venv/bin/pip install "gymnasium>=1" hydra-core omegaconf numpy termcolor tqdm
    /tmp/mbrl-venv/bin/pip install -e .    # sb3_poplin: the dataset and the measurement
    /tmp/mbrl-venv/bin/python benchmarks/diagnosis/mbrl_model_quality.py --data D.npz --train-episodes 8 --output out/

The model is mbrl-lib's PETS half-cheetah configuration (``pets_halfcheetah.yaml`` with ``gaussian_mlp_ensemble``):
7 members of 4 x 200 SiLU layers, 5 elites, fixed log-variance bounds, Adam with learning rate 2.8e-4 and weight decay
1e-4, batch 32, 12 epochs with patience 12 and no validation split (the best weights by training score kept, the elites
chosen by it), inputs normalised in double precision, refit after every episode with a persistent trainer, as its
PETS example does. Per task the input hook and the targets are what mbrl-lib gives a user of the task:
``sb3_poplin/PETSCheetah-v0``: its own half-cheetah ``preprocess_fn`` and the velocity predicted absolutely
(``no_delta_list [0]``; the same as our task's hooks); ``HalfCheetah-v5`` (x kept), for which it has no hooks: the x
position dropped from the input, every entry predicted as a delta (our "raw" candidate, the task's hooks before
0.4.0). The measured prediction is the elites' mean (our planner's expectation propagation averages all members).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from typing import Any

import numpy as np
import omegaconf
import torch as th

import mbrl.models
import mbrl.util.common
import mbrl.util.replay_buffer
from mbrl.env.pets_halfcheetah import HalfCheetahEnv

from sb3_poplin.experiments.analysis import markdown_table
from sb3_poplin.analysis.model_quality import TransitionDataset, evaluate, fit_after_every_episode
from sb3_poplin.tasks import make_task

TRAINING = omegaconf.OmegaConf.create(
    dict(model_batch_size=32, validation_ratio=0.0, num_epochs_train_model=12, patience=12, bootstrap_permutes=False)
)


def drop_x(obs: Any) -> Any:
    """HalfCheetah-v5 with x kept: the model input without the x position."""
    return obs[..., 1:]


# per task: the input hook and the entries predicted absolutely (not as deltas)
TASKS = {
    "sb3_poplin/PETSCheetah-v0": (HalfCheetahEnv.preprocess_fn, [0]),
    "HalfCheetah-v5": (drop_x, []),
}


class MbrlModel:
    """mbrl-lib's ensemble as a ``ModelUnderTest``, refit with its trainer."""

    def __init__(self, data: TransitionDataset, seed: int) -> None:
        if data.env_id not in TASKS:
            raise SystemExit(f"{data.env_id}: this script knows the tasks {sorted(TASKS)}.")
        th.manual_seed(seed)
        self.process, self.no_delta = TASKS[data.env_id]
        obs_dim, action_dim = data.obs.shape[1], data.actions.shape[1]
        in_size = int(self.process(np.zeros((1, obs_dim))).shape[-1]) + action_dim
        network = mbrl.models.GaussianMLP(
            in_size,
            obs_dim,
            "cpu",
            num_layers=4,
            ensemble_size=7,
            hid_size=200,
            propagation_method="random_model",
            learn_logvar_bounds=False,
            activation_fn_cfg={"_target_": "torch.nn.SiLU"},
        )
        self.model = mbrl.models.OneDTransitionRewardModel(
            network,
            target_is_delta=True,
            normalize=True,
            normalize_double_precision=True,
            learned_rewards=False,
            obs_process_fn=self.process,
            no_delta_list=self.no_delta,
            num_elites=5,
        )
        self.trainer = mbrl.models.ModelTrainer(self.model, optim_lr=2.8e-4, weight_decay=1e-4)
        self.rng = np.random.default_rng(seed)

    def fit(self, data: TransitionDataset) -> None:
        buffer = mbrl.util.replay_buffer.ReplayBuffer(len(data.obs), data.obs.shape[1:], data.actions.shape[1:], rng=self.rng)
        for row in range(len(data.obs)):
            buffer.add(
                data.obs[row],
                data.actions[row],
                data.next_obs[row],
                float(data.rewards[row]),
                bool(data.terminated[row]),
                False,
            )
        mbrl.util.common.train_model_and_save_model_and_data(self.model, self.trainer, TRAINING, buffer)

    def _elite_means(self, obs: th.Tensor, actions: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        x = self.model._get_model_input(obs.numpy(), actions.numpy())
        mean, logvar = self.model.model.forward(x, use_propagation=False)
        elites = list(self.model.model.elite_models or range(len(self.model.model)))
        return mean[elites], logvar[elites]

    @th.no_grad()
    def one_step(self, obs: th.Tensor, actions: th.Tensor, next_obs: th.Tensor, rewards: th.Tensor) -> tuple[float, float]:
        target = next_obs - obs
        target[:, self.no_delta] = next_obs[:, self.no_delta]
        mean, logvar = self._elite_means(obs, actions)
        nll = 0.5 * ((target - mean) ** 2 * th.exp(-logvar) + logvar + np.log(2.0 * np.pi))
        return float(nll.mean()), float(((target - mean) ** 2).mean())

    @th.no_grad()
    def step(self, states: th.Tensor, actions: th.Tensor) -> th.Tensor:
        mean, _ = self._elite_means(states, actions)
        prediction = mean.mean(dim=0)
        next_states = states + prediction
        next_states[:, self.no_delta] = prediction[:, self.no_delta]
        return next_states


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", required=True)
    parser.add_argument("--steps", type=int, default=None, help="the dataset's first steps (whole episodes)")
    parser.add_argument("--train-episodes", type=int, required=True)
    parser.add_argument("--heldout-episodes", type=int, default=None)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--stride", type=int, default=5)
    parser.add_argument("--output", default=".")
    args = parser.parse_args()
    th.set_num_threads(1)
    data = TransitionDataset.load(args.data)
    if args.steps is not None:
        data = data.first_steps(args.steps)
    stop = data.num_episodes if args.heldout_episodes is None else args.train_episodes + args.heldout_episodes
    train, heldout = data.episodes(0, args.train_episodes), data.episodes(args.train_episodes, stop)
    task = make_task(data.env_id)
    state_dims = [i for i in range(data.obs.shape[1]) if i not in task.model_input_exclude]
    rows, results = [], []
    for seed in args.seeds:
        model = MbrlModel(data, seed)
        start = time.perf_counter()
        fit_after_every_episode(model.fit, train)
        seconds = time.perf_counter() - start
        report = evaluate(model, heldout, task.reward_fn, task.termination_fn, state_dims=state_dims, stride=args.stride)
        report["fit_seconds"] = seconds
        results.append(dict(model="mbrl-lib 0.2.0", seed=seed, **report))
        rows.append(
            ["mbrl-lib", seed, *(report["state_error"][k] for k in (1, 5, 15, 30))]
            + [v for h in (15, 30) for v in (report["return_error"][h], report["return_correlation"][h])]
            + [report["nll"], report["mse"], seconds]
        )
    header = ["model", "seed", "k=1", "k=5", "k=15", "k=30", "ret15 err", "ret15 corr", "ret30 err", "ret30 corr"]
    table = markdown_table([*header, "NLL", "MSE", "fit s"], rows)
    print(table)
    os.makedirs(args.output, exist_ok=True)
    stem = os.path.splitext(os.path.basename(args.data))[0] + (f"-first{args.steps}" if args.steps else "")
    with open(os.path.join(args.output, f"mbrl_model_quality_{stem}.json"), "w") as file:
        json.dump(results, file, indent=2)


if __name__ == "__main__":
    main()
