"""
Distillation: after each episode, train the policy network from what the planner did
(Wang & Ba 2019, section 4.3).

:class:`Distiller` records, for every *planned* real step (random warm-up steps are never recorded),
the real state, the executed action and the first block of the planner's solution (POPLIN-A: the
action noise ``mu_0``; POPLIN-P: the parameter perturbation ``mu_0``), and optionally the final
elites' first blocks ("imagined" data), turned into actions by the search space with the policy as
it was while planning. After each model fit it runs one of the schemes below on what it recorded:

- :func:`behaviour_cloning` (POPLIN-A and POPLIN-P "BC"): regress ``pi_theta(s)`` onto the planned
  actions, with a random 80/20 split for early stopping (the original trained on the first 80 % in
  time order and tested on an overlapping subset: bug Q2, not copied).
- :func:`gan_distillation` (POPLIN-P "GAN"): the generator ``pi_{theta + z}(s)``, ``z ~ N(0, init_var)``
  truncated at 2 sigma, against a discriminator on ``[action, whitened state]`` with an entropy
  bonus ``lambda = 1e-3``.
- :func:`average_perturbation` (POPLIN-P "Avg"): ``theta <- theta + step * mean(omega)`` over the recorded
  perturbations (``step = 1``: the paper's equation), or ``theta <- mean(omega)`` (``"overwrite"``: what the
  original code did, quirk Q4).

The target actions are either the *executed* ones (clipped to [-1, 1]) or the *planned* ones, before the clip
(POPLIN-P: the network as it was while planning, with the executed perturbation: the original's BC-PR target). GAN's
fake samples go through the same clip as the real ones, or neither.

:func:`sb3_poplin.variants.original_code_settings` gives the settings that reproduce the original code's choices.
"""

from __future__ import annotations

import math
from typing import Any

import torch as th
import torch.nn.functional as F

from sb3_poplin.common import check_state_keys
from sb3_poplin.planning import PlanResult, PolicySearchSpace
from sb3_poplin.policies import Discriminator, POPLINPolicy, PolicyNetwork
from sb3_poplin.sampling import truncated_normal

AVG_UPDATES = ("add", "overwrite")
DISTILL_TARGETS = ("executed", "planned")


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


def clip_straight_through(actions: th.Tensor) -> th.Tensor:
    """
    Clip to [-1, 1] in the forward pass, identity in the backward pass: the discriminator sees actions in the bounds
    while a saturated policy output still gets the gradient that pulls it back (a plain clip passes none).

    :param actions: raw policy outputs
    :return: the clipped values, differentiable as ``actions``
    """
    return actions + (actions.clamp(-1.0, 1.0) - actions).detach()


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
    clip: bool = False,
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
    :param clip: clip real and fake actions to [-1, 1] (executed-action targets; the fake ones with
        :func:`clip_straight_through`); ``False``: neither (planned targets), so that the discriminator cannot tell
        them apart by ``|a| > 1`` alone
    :param generator: random generator
    :return: logged statistics
    """
    n, w = states.shape[0], policy.num_params
    if clip:
        targets = targets.clamp(-1.0, 1.0)
    d_losses, g_losses = [], []
    for _ in range(epochs):
        z = truncated_normal((n, w), states.device, generator) * math.sqrt(noise_var)
        for rows in _minibatches(n, batch_size, states.device, generator):
            whitened = policy.whiten(states[rows]).detach()
            fake = policy.forward_perturbed(states[rows].unsqueeze(1), z[rows])[:, 0]
            if clip:
                fake = clip_straight_through(fake)
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
def average_perturbation(
    policy: PolicyNetwork, perturbations: th.Tensor, step_size: float = 1.0, update: str = "add"
) -> dict[str, float]:
    """
    POPLIN-P Avg: ``theta <- theta + step_size * mean(omega)`` (the paper's equation with ``step_size = 1``), or with
    ``update="overwrite"`` ``theta <- mean(omega)`` (the original code; ``step_size`` unused).

    :param policy: the policy network
    :param perturbations: planned parameter perturbations ``[B, W]``
    :param step_size: fraction of the mean perturbation to apply
    :param update: ``"add"`` or ``"overwrite"``
    :return: logged statistics
    """
    mean = perturbations.mean(dim=0)
    before = policy.flat_parameters()
    if update == "overwrite":
        policy.set_parameters(mean)
    else:
        policy.add_to_parameters(mean.mul_(step_size))
    return {"avg_step_norm": (policy.flat_parameters() - before).norm().item()}


@th.no_grad()
def saturated_fraction(policy: PolicyNetwork, states: th.Tensor) -> float:
    """
    :param policy: the policy network
    :param states: raw observations ``[B, o]``
    :return: the fraction of action components the network puts beyond [-1, 1], where the clip makes it
        insensitive to its parameters (logged as ``train/policy_saturation``)
    """
    return float((policy(states).abs() > 1.0).float().mean())


class Distiller:
    """
    What POPLIN distills from, and the distillation step: while acting, :meth:`record` keeps what each planned real
    step says about the planner (the state, the executed action; for Avg the executed perturbation block; with
    ``imagined`` the final elites' first actions or blocks, computed with the policy the planner used); after each
    model fit, :meth:`distill` trains the policy network from it. Its :meth:`state_dict` is saved with the agent.

    :param method: ``"avg"``, ``"bc"`` or ``"gan"``
    :param search_space: the planner's search space (a policy search space)
    :param networks: the agent's networks (``actor``, ``actor_optimizer``, and for GAN ``discriminator`` and
        ``discriminator_optimizer``)
    :param imagined: also distill the final elites' first steps
    :param window: BC and GAN train on the most recent ``window`` planned steps; ``None``: on the steps since the
        last distillation only. Avg always uses the steps since the last update.
    :param avg_step_size: Avg's ``theta <- theta + avg_step_size * mean(omega)``
    :param avg_update: ``"overwrite"`` (``theta <- mean(omega)``, the original code) or ``"add"`` (the line above)
    :param target: BC's and GAN's target actions: ``"executed"`` (clipped) or ``"planned"`` (before the clip)
    :param whitening: what a whitening update does to the first layer (:data:`sb3_poplin.policies.WHITENING_MODES`)
    :param epochs: BC's maximum epochs, or GAN's epochs
    :param batch_size: minibatch size of BC and GAN
    :param noise_var: variance of GAN's generator noise (the planner's ``init_var``)
    """

    def __init__(
        self,
        method: str,
        search_space: PolicySearchSpace,
        networks: POPLINPolicy,
        imagined: bool,
        window: int | None,
        avg_step_size: float,
        epochs: int,
        batch_size: int,
        noise_var: float,
        avg_update: str = "overwrite",
        target: str = "executed",
        whitening: str = "function",
    ) -> None:
        assert networks.actor is not None, "distillation needs a policy network"
        self.method = method
        self.search_space = search_space
        self.networks = networks
        self.imagined = imagined
        self.window = window
        self.avg_step_size = avg_step_size
        self.epochs = epochs
        self.batch_size = batch_size
        self.noise_var = noise_var
        self.avg_update = avg_update
        self.target = target
        self.whitening = whitening
        self.planned: list[dict[str, th.Tensor]] = []  # one record per planned step since the last distillation
        self.data: dict[str, th.Tensor] = {}  # BC/GAN with a window: its most recent planned steps

    @th.no_grad()
    def record(self, obs: th.Tensor, plan: PlanResult) -> None:
        """
        Keep what distillation needs of a planned real step; a failed plan (``plan.fallback``) says nothing and is
        dropped at :meth:`distill` (the mask stays on the device until then).

        :param obs: the real observations ``[n_envs, o]``
        :param plan: the plan that chose the executed actions
        """
        space = self.search_space
        action = plan.action if self.target == "executed" else space.planned_action(plan.solution, obs, None)
        record = {"states": obs.clone(), "actions": action, "keep": ~plan.fallback}
        # the blocks are copied out of the search vectors: a view would keep (and a save would write) the whole vector
        if self.method == "avg":  # the final mean, as the original Avg (also when the best candidate is executed)
            record["blocks"] = space.first_block(plan.mean).clone()
        if self.imagined:
            elite_blocks = space.first_block(plan.elites)  # [n_envs, K, block]
            if self.method == "avg":
                record["elite_blocks"] = elite_blocks.clone()
            else:
                b, k = elite_blocks.shape[:2]
                to_action = space.executed_action if self.target == "executed" else space.planned_action
                imagined = to_action(elite_blocks.flatten(0, 1), obs.repeat_interleave(k, dim=0), None)
                record["imagined"] = imagined.view(b, k, -1)  # [n_envs, K, A]
        self.planned.append(record)

    def _take_planned(self) -> dict[str, th.Tensor]:
        """The recorded steps since the last call, failed plans dropped."""
        new = {key: th.cat([record[key] for record in self.planned]) for key in self.planned[0]}
        self.planned = []
        keep = new.pop("keep")
        return {key: value[keep] for key, value in new.items()}

    def distill(self, generator: th.Generator | None) -> dict[str, float]:
        """
        Train the policy network from the planned steps (Avg: those since the last call; BC/GAN: the window).

        :param generator: random generator for the splits, minibatches and GAN noise
        :return: statistics to log (empty when nothing was planned since the last call)
        """
        if not self.planned:
            return {}
        actor = self.networks.actor
        assert actor is not None
        new = self._take_planned()
        if self.method == "avg":  # perturbations are relative to the theta they were planned with
            blocks = new["blocks"]
            if "elite_blocks" in new:
                blocks = th.cat([blocks, new["elite_blocks"].flatten(0, 1)])
            stats = average_perturbation(actor, blocks, self.avg_step_size, self.avg_update)
            actor.update_whitening(new["states"], self.whitening)
            return {**stats, "policy_saturation": saturated_fraction(actor, new["states"])}
        data = new
        if self.window is not None:
            for key, value in new.items():
                self.data[key] = (th.cat([self.data[key], value]) if key in self.data else value)[-self.window :]
            data = self.data
        states, targets = data["states"], data["actions"]
        if "imagined" in data:
            k = data["imagined"].shape[1]
            states = th.cat([states, states.repeat_interleave(k, dim=0)])
            targets = th.cat([targets, data["imagined"].flatten(0, 1)])
        actor.update_whitening(new["states"], self.whitening)
        with th.enable_grad():
            if self.method == "gan":
                assert self.networks.discriminator is not None
                stats = gan_distillation(
                    actor,
                    self.networks.actor_optimizer,
                    self.networks.discriminator,
                    self.networks.discriminator_optimizer,
                    states,
                    targets,
                    noise_var=self.noise_var,
                    epochs=self.epochs,
                    batch_size=self.batch_size,
                    clip=self.target == "executed",
                    generator=generator,
                )
            else:
                stats = behaviour_cloning(
                    actor,
                    self.networks.actor_optimizer,
                    states,
                    targets,
                    epochs=self.epochs,
                    batch_size=self.batch_size,
                    generator=generator,
                )
        saturation = saturated_fraction(actor, new["states"])
        return {**stats, "policy_samples": float(states.shape[0]), "policy_saturation": saturation}

    def state_dict(self) -> dict[str, Any]:
        """The planned steps not yet distilled and the window's data (CPU tensors): a save in mid-episode keeps them."""
        return {
            "planned": [{key: value.detach().cpu() for key, value in record.items()} for record in self.planned],
            "data": {key: value.detach().cpu() for key, value in self.data.items()},
        }

    def load_state_dict(self, state: dict[str, Any], strict: bool = True) -> None:
        """
        :param state: what :meth:`state_dict` returned
        :param strict: every key must be there
        """
        check_state_keys("Distiller", state, ("planned", "data"), strict)
        device = self.networks.device
        self.planned = [{key: value.to(device) for key, value in record.items()} for record in state.get("planned", [])]
        self.data = {key: value.to(device) for key, value in state.get("data", {}).items()}
