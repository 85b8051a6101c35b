"""
Distillation: after each episode, train the policy network from what the planner did
(Wang & Ba 2019, section 4.3).

The algorithm records, for every *planned* real step (random warm-up steps are never recorded),
the real state and the first block of the planner's solution (POPLIN-A: the action noise
``mu_0``; POPLIN-P: the parameter perturbation ``mu_0``), and optionally the final elites' first
blocks ("imagined" data). The search space turns a (state, block) pair into the action the planner
meant, with the policy as it was while planning; the schemes below distill from those:

- :func:`behaviour_cloning` (POPLIN-A and POPLIN-P "BC"): regress ``pi_theta(s)`` onto the planned
  actions, with a random 80/20 split for early stopping (the original trained on the first 80 % in
  time order and tested on an overlapping subset: bug Q2, not copied).
- :func:`gan_distillation` (POPLIN-P "GAN"): the generator ``pi_{theta + z}(s)``, ``z ~ N(0, init_var)``
  truncated at 2 sigma, against a discriminator on ``[action, whitened state]`` with an entropy
  bonus ``lambda = 1e-3``.
- :func:`average_perturbation` (POPLIN-P "Avg"): ``theta <- theta + mean(omega)`` over the recorded
  perturbations, the paper's equation (the original code overwrote theta with the mean: bug Q4).
"""

from __future__ import annotations

import math

import torch as th
import torch.nn.functional as F

from sb3_poplin.planning import truncated_normal
from sb3_poplin.policies import Discriminator, PolicyNetwork

# variant -> accepted distillations, the first being the default
DISTILLATIONS: dict[str, tuple[str, ...]] = {"poplin-a": ("bc",), "poplin-p": ("avg", "bc", "gan")}


def _minibatches(n: int, batch_size: int, device: th.device, generator: th.Generator | None) -> list[th.Tensor]:
    """Shuffled index batches; a last partial batch is kept when it is the only one."""
    order = th.randperm(n, device=device, generator=generator)
    size = min(batch_size, n)
    return [order[i : i + size] for i in range(0, n - size + 1, size)] or [order]


def behaviour_cloning(
    policy: PolicyNetwork,
    optimizer: th.optim.Optimizer,
    states: th.Tensor,
    targets: th.Tensor,
    epochs: int = 100,
    batch_size: int = 64,
    holdout_ratio: float = 0.2,
    check_every: int = 5,
    generator: th.Generator | None = None,
) -> dict[str, float]:
    """
    Mean-squared-error regression of the (unclipped) policy output onto target actions. Every
    ``check_every`` epochs the holdout loss is measured; training stops when it went up, and the
    best parameters seen at a check are kept.

    :param policy: the policy network to train
    :param optimizer: its optimizer
    :param states: real (or imagined) states ``[B, o]``
    :param targets: scaled target actions ``[B, A]``
    :param epochs: maximum epochs
    :param batch_size: minibatch size
    :param holdout_ratio: random fraction held out for early stopping
    :param check_every: epochs between holdout checks
    :param generator: random generator for the split and the shuffling
    :return: logged statistics
    """
    n = states.shape[0]
    perm = th.randperm(n, device=states.device, generator=generator)
    n_hold = int(n * holdout_ratio) if n >= 10 else 0
    hold, train = perm[:n_hold], perm[n_hold:]

    def holdout_loss() -> float:
        with th.no_grad():
            return F.mse_loss(policy(states[hold]), targets[hold]).item() if n_hold else math.nan

    def snapshot() -> dict[str, th.Tensor]:
        return {k: v.clone() for k, v in policy.state_dict().items()}

    best_loss, best_state, epochs_run, train_loss = holdout_loss(), snapshot(), 0, math.nan
    for epoch in range(1, epochs + 1):
        epochs_run = epoch
        losses = []
        for idx in _minibatches(train.numel(), batch_size, states.device, generator):
            rows = train[idx]
            loss = F.mse_loss(policy(states[rows]), targets[rows])
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            losses.append(loss.detach())
        train_loss = th.stack(losses).mean().item()
        if n_hold and epoch % check_every == 0:
            check = holdout_loss()
            if check > best_loss:
                break
            best_loss, best_state = check, snapshot()
    if n_hold and holdout_loss() > best_loss:
        policy.load_state_dict(best_state)
    return {"policy_loss": train_loss, "policy_holdout_loss": holdout_loss(), "policy_epochs": float(epochs_run)}


def _bernoulli_entropy(logits: th.Tensor) -> th.Tensor:
    """Entropy of Bernoulli(sigmoid(logits)), computed stably."""
    return F.softplus(logits) - logits * th.sigmoid(logits)


def gan_distillation(
    policy: PolicyNetwork,
    policy_optimizer: th.optim.Optimizer,
    discriminator: Discriminator,
    discriminator_optimizer: th.optim.Optimizer,
    states: th.Tensor,
    targets: th.Tensor,
    noise_var: float,
    epochs: int = 40,
    batch_size: int = 64,
    entropy_coef: float = 1e-3,
    generator: th.Generator | None = None,
) -> dict[str, float]:
    """
    Adversarial distillation of POPLIN-P: real samples are the planned actions, fake samples the
    perturbed policy ``pi_{theta + z}(s)`` with fresh noise ``z`` every epoch. Per minibatch, one
    discriminator step then one generator (policy) step.

    :param policy: the policy network (the generator's base parameters theta)
    :param policy_optimizer: its optimizer
    :param discriminator: the discriminator
    :param discriminator_optimizer: its optimizer
    :param states: real states ``[B, o]``
    :param targets: planned actions ``[B, A]``
    :param noise_var: variance of the generator's parameter noise (the planner's ``init_var``)
    :param epochs: passes over the data
    :param batch_size: minibatch size
    :param entropy_coef: weight lambda of the discriminator's entropy bonus
    :param generator: random generator
    :return: logged statistics
    """
    n, w = states.shape[0], policy.num_params
    d_losses, g_losses = [], []
    for _ in range(epochs):
        z = truncated_normal((n, w), states.device, generator) * math.sqrt(noise_var)
        for rows in _minibatches(n, batch_size, states.device, generator):
            whitened = policy.whiten(states[rows]).detach()
            fake = policy.forward_perturbed(states[rows].unsqueeze(1), z[rows])[:, 0]
            real_logits = discriminator(th.cat([targets[rows], whitened], dim=-1))
            fake_logits = discriminator(th.cat([fake.detach(), whitened], dim=-1))
            entropy = _bernoulli_entropy(th.cat([real_logits, fake_logits])).mean()
            d_loss = (
                F.binary_cross_entropy_with_logits(real_logits, th.ones_like(real_logits))
                + F.binary_cross_entropy_with_logits(fake_logits, th.zeros_like(fake_logits))
                - entropy_coef * entropy
            )
            discriminator_optimizer.zero_grad(set_to_none=True)
            d_loss.backward()
            discriminator_optimizer.step()

            fake_logits = discriminator(th.cat([fake, whitened], dim=-1))
            g_loss = F.binary_cross_entropy_with_logits(fake_logits, th.ones_like(fake_logits))
            policy_optimizer.zero_grad(set_to_none=True)
            g_loss.backward()
            policy_optimizer.step()
            d_losses.append(d_loss.detach())
            g_losses.append(g_loss.detach())
    with th.no_grad():
        mse = F.mse_loss(policy(states), targets).item()
    return {
        "discriminator_loss": th.stack(d_losses).mean().item(),
        "generator_loss": th.stack(g_losses).mean().item(),
        "policy_loss": mse,
    }


@th.no_grad()
def average_perturbation(policy: PolicyNetwork, perturbations: th.Tensor, step_size: float = 1.0) -> dict[str, float]:
    """
    POPLIN-P Avg: ``theta <- theta + step_size * mean(omega)`` (the paper's equation with ``step_size = 1``).

    :param policy: the policy network
    :param perturbations: planned parameter perturbations ``[B, W]``
    :param step_size: fraction of the mean perturbation to apply
    :return: logged statistics
    """
    step = perturbations.mean(dim=0).mul_(step_size)
    policy.add_to_parameters(step)
    return {"avg_step_norm": step.norm().item()}


@th.no_grad()
def saturated_fraction(policy: PolicyNetwork, states: th.Tensor) -> float:
    """
    :param policy: the policy network
    :param states: raw observations ``[B, o]``
    :return: the fraction of action components the network puts beyond [-1, 1], where the clip makes it
        insensitive to its parameters (logged as ``train/policy_saturation``)
    """
    return float((policy(states).abs() > 1.0).float().mean())
