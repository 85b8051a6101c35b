"""
The reward surface a planner searches (Wang & Ba 2019, section 5.3): at one real state, record every candidate of
every CEM iteration, fit a 2-D PCA on the method's own search vectors, and evaluate the model-predicted planning
return on a grid in PCA coordinates with the planner's own rollout. A surface with many local maxima and large jumps
between neighbouring cells is hard for CEM; the paper reports a rough action-space surface (PETS) and a smooth
parameter-space one (POPLIN-P).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch as th

from sb3_poplin.planning import MPCController


@dataclass
class SearchRecord:
    """What one plan searched: per CEM iteration its candidates ``[N, D]`` and their returns ``[N]`` (one env)."""

    candidates: list[th.Tensor]
    returns: list[th.Tensor]
    planned_return: float  # the final elites' mean return

    @property
    def all_candidates(self) -> th.Tensor:
        """``[iterations * N, D]``"""
        return th.cat(self.candidates)


def record_search(controller: MPCController, obs: th.Tensor) -> SearchRecord:
    """
    Plan once from a fresh start at one real state and keep every candidate of every iteration.

    :param controller: the controller to plan with (its generator is used)
    :param obs: the real observation ``[o]``
    """
    candidates: list[th.Tensor] = []
    returns: list[th.Tensor] = []

    def observe(z: th.Tensor, r: th.Tensor) -> None:
        candidates.append(z[0].clone())
        returns.append(r[0].clone())

    planner = controller.planner
    obs = obs.reshape(1, -1)
    plan = planner.plan(obs, planner.initial_state(1, obs.device), controller.generator, observer=observe)
    return SearchRecord(candidates, returns, float(plan.elite_return[0]))


@dataclass
class PCA2:
    """A 2-D principal component analysis: ``z = mean + coords @ components``."""

    mean: th.Tensor  # [D]
    components: th.Tensor  # [2, D], orthonormal rows
    explained_variance_ratio: tuple[float, float]

    @classmethod
    def fit(cls, vectors: th.Tensor) -> PCA2:
        """:param vectors: ``[M, D]`` search vectors (M >= 2)"""
        x = vectors.double()
        mean = x.mean(dim=0)
        _, s, vh = th.linalg.svd(x - mean, full_matrices=False)
        variance = s**2
        total = float(variance.sum()) or 1.0
        components = vh[:2]
        if components.shape[0] < 2:  # a one-dimensional search: pad with an orthogonal direction
            pad = th.zeros(1, x.shape[1], dtype=x.dtype)
            pad[0, int(components[0].abs().argmin())] = 1.0
            components = th.cat([components, pad])
        ratios = [float(v) / total for v in variance[:2]] + [0.0, 0.0]
        return cls(mean.float(), components.float(), (ratios[0], ratios[1]))

    def transform(self, vectors: th.Tensor) -> th.Tensor:
        """``[M, D]`` -> coordinates ``[M, 2]``"""
        return (vectors - self.mean) @ self.components.T

    def inverse_transform(self, coords: th.Tensor) -> th.Tensor:
        """``[M, 2]`` -> search vectors ``[M, D]`` in the plane of the two components"""
        return self.mean + coords @ self.components


def grid_returns(
    controller: MPCController, obs: th.Tensor, pca: PCA2, x: np.ndarray, y: np.ndarray, seed: int = 0
) -> np.ndarray:
    """
    The model-predicted planning return on a grid in PCA coordinates, with the planner's own rollout.

    :param controller: the controller whose planner scores the grid
    :param obs: the real observation ``[o]``
    :param pca: the search vectors' PCA
    :param x: first-component coordinates ``[Gx]``
    :param y: second-component coordinates ``[Gy]``
    :param seed: seed of the propagation noise (particle propagations); the same for every grid point
    :return: returns ``[Gy, Gx]``
    """
    planner = controller.planner
    gx, gy = np.meshgrid(x, y)
    coords = th.as_tensor(np.stack([gx.ravel(), gy.ravel()], axis=1), dtype=th.float32)
    z = pca.inverse_transform(coords).to(obs.device).unsqueeze(0)  # [1, G, D]
    obs = obs.reshape(1, -1)
    with th.inference_mode():
        context = planner.search_space.prepare(obs, planner)
        generator = th.Generator(device=obs.device).manual_seed(seed)
        returns = planner.rollout(obs, z, context, generator)[0]
    return returns.cpu().numpy().reshape(gy.shape)


def roughness(surface: np.ndarray) -> dict[str, float]:
    """
    Scale-free roughness of a surface on a grid.

    :param surface: values ``[Gy, Gx]`` (non-finite cells are ignored)
    :return: ``roughness``: the mean absolute second difference of neighbouring cells (along both axes) over the
        surface's range: 0 for a plane, small for a smooth bowl, growing with noise and ridges, whatever the return's
        scale; ``local_maxima``: interior cells strictly above their 8 neighbours
    """
    values = np.asarray(surface, dtype=np.float64)
    finite = values[np.isfinite(values)]
    span = float(finite.max() - finite.min()) if finite.size else 0.0
    second = np.concatenate([np.diff(values, n=2, axis=0).ravel(), np.diff(values, n=2, axis=1).ravel()])
    second = np.abs(second[np.isfinite(second)])
    rough = float(second.mean() / span) if span > 0 and second.size else 0.0
    centre = values[1:-1, 1:-1]
    is_max = np.isfinite(centre)
    rows, cols = values.shape
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy or dx:
                neighbour = values[1 + dy : rows - 1 + dy, 1 + dx : cols - 1 + dx]
                is_max &= centre > np.where(np.isfinite(neighbour), neighbour, -np.inf)
    return {"roughness": rough, "local_maxima": float(is_max.sum())}


@dataclass
class Surface:
    """One method's searched surface."""

    method: str
    record: SearchRecord
    pca: PCA2
    x: np.ndarray
    y: np.ndarray
    returns: np.ndarray  # [Gy, Gx]

    @property
    def stats(self) -> dict[str, float]:
        return {
            **roughness(self.returns),
            "explained_variance_1": self.pca.explained_variance_ratio[0],
            "explained_variance_2": self.pca.explained_variance_ratio[1],
            "planned_return": self.record.planned_return,
        }


def reward_surface(controller: MPCController, method: str, obs: th.Tensor, grid: int = 25, margin: float = 0.1) -> Surface:
    """
    Record one plan at ``obs``, fit the PCA of its candidates and evaluate the return on a ``grid x grid`` lattice
    covering them (plus ``margin`` of their range on every side).
    """
    record = record_search(controller, obs)
    vectors = record.all_candidates
    pca = PCA2.fit(vectors.cpu())
    coords = pca.transform(vectors.cpu().float()).numpy()
    axes = []
    for k in range(2):
        low, high = float(coords[:, k].min()), float(coords[:, k].max())
        pad = margin * max(high - low, 1e-6)
        axes.append(np.linspace(low - pad, high + pad, grid))
    returns = grid_returns(controller, obs, pca, axes[0], axes[1])
    return Surface(method, record, pca, axes[0], axes[1], returns)


def plot_surface(surface: Surface, path: str) -> None:
    """A contour of the surface with every iteration's candidates on it (colour: iteration)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 5))
    finite = np.where(np.isfinite(surface.returns), surface.returns, np.nan)
    contour = ax.contourf(surface.x, surface.y, finite, levels=30, cmap="viridis")
    fig.colorbar(contour, ax=ax, label="model-predicted return")
    iterations = len(surface.record.candidates)
    colours = plt.get_cmap("autumn")(np.linspace(0, 1, max(iterations, 2)))
    for i, z in enumerate(surface.record.candidates):
        c = surface.pca.transform(z.cpu().float()).numpy()
        ax.scatter(c[:, 0], c[:, 1], s=4, color=colours[i], label=f"iteration {i + 1}")
    stats = surface.stats
    ax.set_title(
        f"{surface.method}: roughness {stats['roughness']:.3f}, {int(stats['local_maxima'])} local maxima\n"
        f"PC1 {stats['explained_variance_1']:.0%}, PC2 {stats['explained_variance_2']:.0%} of the variance"
    )
    ax.set_xlabel("PC 1")
    ax.set_ylabel("PC 2")
    ax.legend(loc="upper right", fontsize=7, markerscale=3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
