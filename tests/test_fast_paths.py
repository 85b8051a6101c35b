"""The optimised planning paths give the same results as plain ones: chunking, batching, bf16."""

import numpy as np
import pytest
import torch as th
import torch.nn.functional as F

from sb3_poplin import POPLIN

SMALL = dict(horizon=6, population_size=24, num_elites=4, cem_iterations=2, ensemble_size=4, dynamics_net_arch=(32, 32))
CASES = [
    dict(policy="pets", propagation="expectation"),
    dict(policy="pets", propagation="tsinf", num_particles=8),
    dict(policy="pets", propagation="ts1", num_particles=8),
    dict(policy="pets", propagation="ds", num_particles=8),
    dict(policy="poplin-a", proposal="replan", propagation="ts1", num_particles=4),
    dict(policy="poplin-p", noise="sep", propagation="tsinf", num_particles=4),
]


def trained(case, env="InvertedPendulum-v5", **kwargs):
    model = POPLIN(env=env, seed=0, **case, **SMALL, **kwargs)
    model.learn(300)  # fitted model and (for POPLIN) distilled policy, so the numbers are not trivial
    return model


@pytest.mark.parametrize("case", CASES, ids=lambda c: "/".join(str(v) for v in c.values()))
def test_chunked_rollout_equals_unchunked(case):
    model = trained(case)
    planner = model.planner
    obs = th.tensor([[0.01, -0.05, 0.2, 0.3], [0.0, 0.1, -0.1, 0.0]])
    z = th.randn(2, 24, planner.search_space.dim, generator=th.Generator().manual_seed(0)) * 0.3
    context = planner.search_space.prepare(obs, planner)
    results = []
    for rows in (None, 7, 1):  # no bound, odd chunks, one candidate at a time
        planner.max_batch_rows = rows
        with th.inference_mode():
            results.append(planner.rollout(obs, z, context, th.Generator().manual_seed(1)))
    assert th.allclose(results[0], results[1], atol=1e-5) and th.allclose(results[0], results[2], atol=1e-5)
    assert results[0].std() > 0  # candidates really differ


def test_chunked_planning_gives_the_same_actions():
    model = trained(dict(policy="pets", propagation="tsinf", num_particles=8))
    obs = np.array([[0.01, -0.05, 0.2, 0.3], [0.0, 0.1, -0.1, 0.0]], dtype=np.float32)
    actions = []
    for rows in (None, 5):
        model.planner.max_batch_rows = rows
        model.set_random_seed(4)
        actions.append(model.predict(obs, episode_start=np.ones(2, dtype=bool))[0])
    np.testing.assert_allclose(actions[0], actions[1], atol=1e-5)


def reference_rollout(model, obs, z):
    """Plain PETS expectation rollout: a loop over candidates, steps and members, the maths written out."""
    dynamics, task = model.policy.dynamics, model.planner
    layers = [*dynamics.hidden, dynamics.output]
    returns = []
    for c in range(z.shape[0]):
        s, total = obs.clone(), 0.0
        for t in range(model.settings.horizon):
            a = z[c, t : t + 1].clamp(-1, 1)  # one action dim
            x = (th.cat([s, a]) - dynamics.input_mean) / dynamics.input_std
            means = []
            for e in range(dynamics.ensemble_size):
                h = x
                for i, layer in enumerate(layers):
                    h = h @ layer.weight[e] + layer.bias[e, 0]
                    if i < len(layers) - 1:
                        h = F.silu(h)
                means.append(h[: dynamics.out_dim])
            delta = th.stack(means).mean(0) * dynamics.target_std + dynamics.target_mean
            nxt = s + delta
            total += task.reward_fn(s[None], task.to_env_units(a)[None], nxt[None]).item() if task.reward_fn else 0.0
            s = nxt
        returns.append(total)
    return th.tensor(returns)


def test_batched_rollout_equals_a_plain_loop():
    model = trained(dict(policy="pets", propagation="expectation"), env="Pendulum-v1")
    obs = th.tensor([0.3, 0.95, -0.5])
    z = th.randn(1, 10, model.planner.search_space.dim, generator=th.Generator().manual_seed(2))
    with th.inference_mode():
        batched = model.planner.rollout(obs[None], z, None)[0]
        plain = reference_rollout(model, obs, z[0])
    assert th.allclose(batched, plain, atol=1e-4, rtol=1e-5)


def test_bfloat16_planning_stays_close_to_float32():
    model = trained(dict(policy="pets", propagation="expectation"), env="Pendulum-v1")
    planner = model.planner
    obs = th.tensor([[0.3, 0.95, -0.5]])
    z = th.rand(1, 200, planner.search_space.dim, generator=th.Generator().manual_seed(3)) * 2 - 1
    with th.inference_mode():
        fp32 = planner.rollout(obs, z, None)
        planner.dtype = th.bfloat16
        bf16 = planner.rollout(obs, z, None)
    assert bf16.dtype == th.float32
    spread = fp32.max() - fp32.min()
    assert (bf16 - fp32).abs().max() < 0.05 * spread  # small next to the differences CEM ranks by
    top_fp32 = set(fp32[0].topk(20).indices.tolist())
    top_bf16 = set(bf16[0].topk(20).indices.tolist())
    assert len(top_fp32 & top_bf16) >= 15  # the elite sets mostly agree


def test_bad_speed_settings():
    with pytest.raises(ValueError, match=r"Unknown planning_dtype 'float16'; accepted values: \['float32', 'bfloat16'\]"):
        POPLIN("pets", "Pendulum-v1", planning_dtype="float16")
    with pytest.raises(ValueError, match="max_batch_rows must be an integer >= 1"):
        POPLIN("pets", "Pendulum-v1", max_batch_rows=0)
