"""
The GPU path: ``pytest -m cuda`` (every test here is skipped on a machine without CUDA; ``benchmarks/device_check.sh``
runs them on a machine with one).

Tolerance of the CPU / CUDA comparisons: both devices plan in fp32 (TF32 is switched off here, as it is by default in
torch: with TF32 the matmuls keep 10 mantissa bits and the two devices would differ by ~1e-3 relative). The CPU runs
the ensemble through oneDNN's fused linear, CUDA through cuBLAS batched matmuls; their summation orders differ by a
few ulps per layer (~1e-6 relative), which a 10-step rollout through a 2-layer model grows to ~1e-5 relative. So
returns are compared with rtol 1e-4, atol 1e-3 (returns here are -10 to -100), and plans drawn from the same
candidates must pick the same elites (neighbouring candidates' returns differ by far more than 1e-4) and execute
actions equal to 1e-4 (actions in [-1, 1]). The devices draw their candidates from different random streams by
design (SFC64 chunks on the CPU, the CUDA generator on the GPU), so those tests feed both the same candidates.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env

from sb3_poplin import POPLIN, kernels, sampling
from sb3_poplin.sampling import CandidateSampler

pytestmark = [
    pytest.mark.cuda,
    pytest.mark.skipif(not th.cuda.is_available(), reason="needs a CUDA GPU (run on a GPU machine: pytest -m cuda)"),
    # a zip saved on one kind of device carries a generator state the other kind cannot take (POPLIN warns)
    pytest.mark.filterwarnings("ignore:The planner's random state"),
]

SMALL = dict(horizon=10, population_size=64, num_elites=8, cem_iterations=3, ensemble_size=3, dynamics_net_arch=(32, 32))
VARIANTS = [
    ("pets", {}),
    ("rs", {}),
    ("poplin-a", {"proposal": "init"}),
    ("poplin-a", {"proposal": "replan"}),
    ("poplin-p", {"noise": "sep"}),
    ("poplin-p", {"noise": "uni"}),
    # iCEM: colored noise (a matmul over the horizon), kept, carried and mean candidates, decayed populations
    ("pets", {"optimizer": "icem"}),
    ("poplin-p", {"noise": "sep", "optimizer": "icem", "optimizer_kwargs": {"noise_beta": 0.25}}),
]
CEM_VARIANTS = [v for v in VARIANTS if v[0] != "rs"]


@pytest.fixture(autouse=True)
def no_tf32() -> Iterator[None]:
    """fp32 matmuls in fp32 (torch's default), whatever the process set before."""
    previous = th.backends.cuda.matmul.allow_tf32
    th.backends.cuda.matmul.allow_tf32 = False
    yield
    th.backends.cuda.matmul.allow_tf32 = previous


def cpu_agent(variant: str, options: dict, tmp_path: Path, **kwargs) -> tuple[POPLIN, Path]:
    """A CPU agent whose model has been fitted once (one random episode), and its zip."""
    model = POPLIN(variant, "Pendulum-v1", seed=0, device="cpu", **SMALL, **options, **kwargs)  # type: ignore[arg-type]
    model.learn(200)
    path = tmp_path / f"{variant}_cpu.zip"
    model.save(path)
    return model, path


def observations(n_envs: int = 2) -> th.Tensor:
    """Pendulum observations ``[n_envs, 3]``: cos, sin, angular velocity."""
    theta = th.linspace(-3.0, 3.0, n_envs)
    return th.stack([theta.cos(), theta.sin(), th.linspace(-1.0, 1.0, n_envs)], dim=1)


class SameCandidates:
    """Replaces CEM's sampler with one that gives both devices the same candidates (drawn on the CPU, then moved)."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.generator = th.Generator()
        source = self

        def sample(
            sampler: CandidateSampler,
            mean: th.Tensor,
            std: th.Tensor,
            generator: th.Generator | None,
            count: int | None = None,
        ) -> th.Tensor:
            n_envs, dim = mean.shape
            rows = sampler.population_size if count is None else count
            noise = th.randn((n_envs, rows, dim), generator=source.generator).clamp(-2.0, 2.0)
            return mean.unsqueeze(1) + std.unsqueeze(1) * noise.to(mean.device)

        monkeypatch.setattr(CandidateSampler, "sample", sample)  # CEM draws its candidates through it

    def reset(self) -> None:
        self.generator.manual_seed(0)


@pytest.mark.parametrize("variant, options", VARIANTS)
def test_rollout_returns_match_the_cpu_on_the_same_candidates(variant: str, options: dict, tmp_path: Path) -> None:
    cpu, path = cpu_agent(variant, options, tmp_path)
    gpu = POPLIN.load(path, device="cuda")
    obs = observations()
    z = th.randn(2, SMALL["population_size"], cpu.planner.search_space.dim, generator=th.Generator().manual_seed(1))
    with th.inference_mode():
        returns = {}
        for model, device in ((cpu, "cpu"), (gpu, "cuda")):
            planner = model.planner
            context = planner.search_space.prepare(obs.to(device), planner)
            returns[device] = planner.rollout(obs.to(device), (0.3 * z).to(device), context).cpu()
    assert returns["cuda"].shape == (2, SMALL["population_size"])
    th.testing.assert_close(returns["cuda"], returns["cpu"], rtol=1e-4, atol=1e-3)


@pytest.mark.parametrize("variant, options", CEM_VARIANTS)
def test_plan_matches_the_cpu_when_both_draw_the_same_candidates(
    variant: str, options: dict, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    cpu, path = cpu_agent(variant, options, tmp_path)
    gpu = POPLIN.load(path, device="cuda")
    candidates = SameCandidates(monkeypatch)
    obs = observations()
    plans = {}
    for model, device in ((cpu, "cpu"), (gpu, "cuda")):
        candidates.reset()
        mean = model.planner.initial_state(2, th.device(device))
        plans[device] = model.planner.plan(obs.to(device), mean, model.mpc.generator)
    on_cpu, on_gpu = plans["cpu"], plans["cuda"]
    th.testing.assert_close(on_gpu.elites.cpu(), on_cpu.elites, rtol=0.0, atol=1e-6)  # the same elites, same order
    th.testing.assert_close(on_gpu.elite_return.cpu(), on_cpu.elite_return, rtol=1e-4, atol=1e-3)
    th.testing.assert_close(on_gpu.action.cpu(), on_cpu.action, rtol=0.0, atol=1e-4)
    th.testing.assert_close(on_gpu.next_state.cpu(), on_cpu.next_state, rtol=0.0, atol=1e-4)


@pytest.mark.parametrize("dtype", ["float32", "bfloat16"])
@pytest.mark.parametrize("propagation", ["expectation", "tsinf"])
@pytest.mark.parametrize("variant, options", VARIANTS)
def test_planning_makes_no_host_round_trip(
    variant: str, options: dict, propagation: str, dtype: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A plan queues its kernels without waiting on the GPU (no .item(), no boolean masks, no copies to the host),
    and the CPU-only fast paths (SFC64 sampling shared among threads, oneDNN's fused linear) stay out of it."""
    model = POPLIN(
        variant, "Pendulum-v1", seed=0, device="cuda", propagation=propagation, num_particles=6, planning_dtype=dtype,
        **SMALL, **options,  # type: ignore[arg-type]
    )  # fmt: skip
    obs = observations().cuda()
    mean = model.planner.initial_state(2, obs.device)
    model.planner.plan(obs, mean, model.mpc.generator)  # warm-up: cuBLAS handles, cached parameter copies

    def cpu_only(*args: object, **kwargs: object) -> None:
        raise AssertionError("a CPU-only fast path ran while planning on CUDA")

    monkeypatch.setattr(np.random, "SFC64", cpu_only)
    monkeypatch.setattr(sampling, "run_shares", cpu_only)
    monkeypatch.setattr(kernels, "onednn_fused_linear", cpu_only)
    th.cuda.synchronize()
    th.cuda.set_sync_debug_mode("error")
    try:
        result = model.planner.plan(obs, mean, model.mpc.generator)
    finally:
        th.cuda.set_sync_debug_mode("default")
    action = result.action.cpu()
    assert action.shape == (2, 1) and bool(th.isfinite(action).all()) and float(action.abs().max()) <= 1.0


def test_short_learning_run_on_cuda() -> None:
    model = POPLIN("poplin-p", "Pendulum-v1", seed=0, device="cuda", **SMALL)  # type: ignore[arg-type]
    assert model.mpc.generator.device.type == "cuda"
    assert model.policy.actor is not None
    theta = model.policy.actor.flat_parameters().detach().clone()
    model.learn(600)  # a random episode, then two planned episodes, each followed by a fit and a distillation
    assert all(p.device.type == "cuda" for p in model.policy.parameters())
    assert model.replay_buffer is not None and model.replay_buffer.size() == 600
    assert not th.equal(model.policy.actor.flat_parameters().detach(), theta)  # Avg moved the policy
    action, state = model.predict(np.array([1.0, 0.0, 0.0], dtype=np.float32))
    assert action.shape == (1,) and np.isfinite(action).all() and abs(float(action[0])) <= 2.0
    assert isinstance(state, np.ndarray) and state.shape == (1, model.planner.search_space.dim)  # SB3's type


def test_save_on_cuda_load_on_cpu_and_back(tmp_path: Path) -> None:
    gpu = POPLIN("poplin-p", "Pendulum-v1", seed=0, device="cuda", **SMALL).learn(400)  # type: ignore[arg-type]
    gpu.save(tmp_path / "gpu.zip")
    cpu = POPLIN.load(tmp_path / "gpu.zip", device="cpu")
    assert cpu.device.type == "cpu" and cpu.mpc.generator.device.type == "cpu"
    saved = gpu.policy.state_dict()
    for name, tensor in cpu.policy.state_dict().items():
        assert tensor.device.type == "cpu", name
        assert th.equal(tensor, saved[name].cpu()), name
    obs = np.stack([np.array([math.cos(a), math.sin(a), 0.5], dtype=np.float32) for a in np.linspace(-3, 3, 8)])
    gpu.control = cpu.control = "policy"
    np.testing.assert_allclose(cpu.predict(obs)[0], gpu.predict(obs)[0], rtol=0, atol=1e-5)
    cpu.control = "mpc"
    actions, _ = cpu.predict(obs)
    assert actions.shape == (8, 1) and np.isfinite(actions).all() and np.abs(actions).max() <= 2.0

    cpu.save(tmp_path / "cpu.zip")
    back = POPLIN.load(tmp_path / "cpu.zip", device="cuda", env=make_vec_env("Pendulum-v1", seed=1))
    for name, tensor in back.policy.state_dict().items():
        assert tensor.device.type == "cuda", name
        assert th.equal(tensor.cpu(), saved[name].cpu()), name
    for state in back.policy.dynamics_optimizer.state.values():  # Adam's moments follow the parameters
        assert all(v.device.type == "cuda" for v in state.values() if isinstance(v, th.Tensor) and v.dim() > 0)
    back.learn(200, reset_num_timesteps=False)  # keeps training on the GPU
    assert back.num_timesteps == 600


def test_bf16_planning_on_cuda_ranks_candidates_like_fp32(tmp_path: Path) -> None:
    _, path = cpu_agent("pets", {}, tmp_path)
    gpu = POPLIN.load(path, device="cuda")
    planner = gpu.planner
    obs = observations().cuda()
    z = 0.5 * th.randn(2, SMALL["population_size"], planner.search_space.dim, generator=th.Generator().manual_seed(2))
    with th.inference_mode():
        planner.dtype = th.float32
        fp32 = planner.rollout(obs, z.cuda(), None).cpu()
        planner.dtype = th.bfloat16
        bf16 = planner.rollout(obs, z.cuda(), None).cpu()
    assert bf16.dtype == th.float32 and bool(th.isfinite(bf16).all())  # returns are summed in fp32
    spread = (fp32.max(dim=1).values - fp32.min(dim=1).values).unsqueeze(1)
    assert bool(((bf16 - fp32).abs() <= 0.05 * spread).all())
    k = SMALL["num_elites"]
    for env in range(2):
        overlap = set(fp32[env].topk(k).indices.tolist()) & set(bf16[env].topk(k).indices.tolist())
        assert len(overlap) >= k - 2, (env, len(overlap))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model = POPLIN("poplin-p", "Pendulum-v1", seed=0, device="cuda", planning_dtype="bfloat16", **SMALL)  # type: ignore[arg-type]
        model.learn(400)
    assert not [w for w in caught if "No planned candidate" in str(w.message)]  # every bf16 plan had finite candidates
    action, _ = model.predict(np.array([1.0, 0.0, 0.0], dtype=np.float32))
    assert np.isfinite(action).all() and abs(float(action[0])) <= 2.0
