"""
The speed layer of the ensemble's no-gradient forwards (planning and evaluation): the same numbers as
:meth:`sb3_poplin.dynamics.ProbabilisticEnsemble.forward`, computed faster.

Three ways to run the members' layers (:data:`PATHS`), which agree to float32 rounding:

- ``"batched"``: all members at once, a broadcast matmul for an input shared by all members (expectation
  propagation: no copy of the input per member) and batched matmuls after it, the bias added and SiLU applied in
  place;
- ``"members"``: member by member with the activations transposed (``[width, rows]``), each layer one
  ``addmm`` of the member's ``[out, in]`` weight: every product and its SiLU stay in the core's cache;
- ``"fused"``: member by member as oneDNN linear primitives with the bias and SiLU fused into the matmul
  (:func:`onednn_fused_linear`, probed once per process and dtype against the plain computation).

Which is fastest depends on the CPU (the oneDNN fusion repaid its fixed cost from about 400 rows on an Intel Xeon
without AMX, and lost at every size on one with AMX) and on the sizes, so from :data:`PROBE_MIN_ROWS` rows per
member on the path is chosen on each host by timing the candidates on the first input of a size class
(:func:`forward_path`) and remembered in a small cache file, so that a host always takes the same path (and rounds
the same way) once it has chosen; below that size, and off a CPU, the batched path runs. The environment variable
``SB3_POPLIN_FORWARD_PATH`` forces one path.

Under a bf16 autocast the whole forward runs in bf16 on bf16 copies of the parameters, made once per parameter
update (:class:`ParameterCache`; autocast would cast every weight at every call and mix dtypes in the element-wise
ops).

Why these choices: docs/results.md, "Planner speed".
"""

from __future__ import annotations

import functools
import json
import os
import platform
import statistics
import tempfile
import time
import weakref
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar

import torch as th
import torch.nn.functional as F

if TYPE_CHECKING:
    from sb3_poplin.dynamics import ProbabilisticEnsemble

Layers = list[tuple[th.Tensor, th.Tensor]]

PATHS = ("batched", "members", "fused")
PATH_ENV = "SB3_POPLIN_FORWARD_PATH"  # forces one of PATHS
CACHE_ENV = "SB3_POPLIN_CACHE_DIR"  # where the chosen paths are kept (default: $XDG_CACHE_HOME/sb3_poplin)

# Rows per member from which the path is chosen by timing; below it the batched matmuls run (a probe there would cost
# more than it saves, and the tests' tiny models keep one path on every host): docs/results.md, "Planner speed".
PROBE_MIN_ROWS = 320
PROBE_ROUNDS = 5


@functools.cache
def onednn_fused_linear(dtype: th.dtype) -> Callable[..., th.Tensor] | None:
    """
    oneDNN's CPU linear with a fused post-op (``torch.ops.mkldnn._linear_pointwise``, the op torch's own compiler
    emits for linear + activation), or ``None`` where this torch build lacks it or it does not compute
    ``silu(x @ w.T + b)`` and ``x @ w.T + b`` in ``dtype`` on a probe (checked once per process and dtype).

    :param dtype: float32 or bfloat16
    """
    if not th.backends.mkldnn.is_available():
        return None
    tol = 1e-5 if dtype == th.float32 else 5e-2
    generator = th.Generator().manual_seed(0)
    x, w, b = (th.randn(shape, generator=generator) for shape in ((7, 5), (3, 5), (3,)))
    try:
        linear = th.ops.mkldnn._linear_pointwise
        fused = linear(x.to(dtype), w.to(dtype), b.to(dtype), "swish", [], "").float()
        plain = linear(x.to(dtype), w.to(dtype), b.to(dtype), "none", [], "").float()
    except (AttributeError, RuntimeError, NotImplementedError):
        return None
    expected = x @ w.T + b
    ok = th.allclose(fused, F.silu(expected), atol=tol, rtol=tol) and th.allclose(plain, expected, atol=tol, rtol=tol)
    return linear if ok else None


def fused_available(dtype: th.dtype) -> bool:
    """Whether the fused oneDNN forward can run in ``dtype`` here."""
    return dtype in (th.float32, th.bfloat16) and onednn_fused_linear(dtype) is not None


class ParameterCache:
    """
    The ensemble's (weight, bias) per layer in a given dtype and layout, copied once per parameter update: an
    optimizer step or a load bumps a parameter's version, a replaced tensor changes its pointer. One cache per model
    (held weakly: it goes with the model).
    """

    _caches: ClassVar[weakref.WeakKeyDictionary[ProbabilisticEnsemble, dict[tuple[th.dtype, str], tuple[tuple, Layers]]]] = (
        weakref.WeakKeyDictionary()
    )

    @classmethod
    def layers(cls, model: ProbabilisticEnsemble, dtype: th.dtype, layout: str) -> Layers:
        """
        :param model: the ensemble
        :param dtype: float32 or bfloat16
        :param layout: ``"batched"``: weight ``[E, in, out]``, bias ``[E, 1, out]`` (the parameters themselves in
            their own dtype); ``"members"``: weight ``[E, out, in]`` and bias ``[E, out]``, contiguous per member, as
            oneDNN's linear and the transposed products take them. The output layer whole (mean and log-variance
            halves): the mean half is its first ``out`` columns (``"batched"``) or rows (``"members"``).
        """
        layers = [*model.hidden, model.output]
        if layout == "batched" and dtype == model.output.weight.dtype:
            return [(layer.weight, layer.bias) for layer in layers]
        key = tuple((p._version, p.data_ptr()) for layer in layers for p in (layer.weight, layer.bias))
        caches = cls._caches.setdefault(model, {})
        cached = caches.get((dtype, layout))
        if cached is None or cached[0] != key:
            copies = []
            for layer in layers:
                weight, bias = layer.weight.detach(), layer.bias.detach()
                if layout == "members":
                    weight, bias = weight.transpose(1, 2), bias.squeeze(1)
                copies.append((weight.to(dtype).contiguous(), bias.to(dtype).contiguous()))
            cached = (key, copies)
            caches[(dtype, layout)] = cached
        return cached[1]


def fused_layers(model: ProbabilisticEnsemble, x: th.Tensor, mean_only: bool) -> th.Tensor:
    """
    The ``"fused"`` path: member by member with oneDNN's fused linear + bias + SiLU (no gradients, CPU).

    :param model: the ensemble
    :param x: standardised input ``[B, in]`` shared by all members, or ``[E, B, in]``, in the compute dtype
    :param mean_only: compute only the mean half of the output layer
    :return: the output layer ``[E, B, out]`` (mean only) or ``[E, B, 2 out]``, in ``x``'s dtype
    """
    linear = onednn_fused_linear(x.dtype)
    assert linear is not None
    layers = ParameterCache.layers(model, x.dtype, "members")
    cols = model.out_dim if mean_only else 2 * model.out_dim
    outputs = []
    for member in range(model.ensemble_size):
        h = x if x.dim() == 2 else x[member]
        for weight, bias in layers[:-1]:
            h = linear(h, weight[member], bias[member], "swish", [], "")  # [B, d_in] -> [B, d_out]
        weight, bias = layers[-1]  # [E, 2 out, H]: the mean half is the first rows, contiguous
        outputs.append(linear(h, weight[member, :cols], bias[member, :cols], "none", [], ""))
    return th.stack(outputs)


def member_layers(model: ProbabilisticEnsemble, x: th.Tensor, mean_only: bool) -> th.Tensor:
    """
    The ``"members"`` path: member by member, the activations transposed (``[d, B]``), each layer one ``addmm`` with
    the member's ``[d_out, d_in]`` weight and SiLU in place. Arguments and result as :func:`fused_layers` (the result
    a transposed view).
    """
    layers = ParameterCache.layers(model, x.dtype, "members")
    cols = model.out_dim if mean_only else 2 * model.out_dim
    out = th.empty(model.ensemble_size, cols, x.shape[-2], dtype=x.dtype, device=x.device)
    for member in range(model.ensemble_size):
        h = (x if x.dim() == 2 else x[member]).t()  # [in, B]
        for weight, bias in layers[:-1]:
            h = F.silu(th.addmm(bias[member].unsqueeze(1), weight[member], h), inplace=True)  # [d_out, B]
        weight, bias = layers[-1]
        th.addmm(bias[member, :cols].unsqueeze(1), weight[member, :cols], h, out=out[member])
    return out.transpose(1, 2)


def batched_layers(model: ProbabilisticEnsemble, x: th.Tensor, mean_only: bool) -> th.Tensor:
    """
    The ``"batched"`` path: all members at once, the bias added and SiLU applied in place; an input shared by all
    members goes through the first layer as one broadcast matmul (no copy per member). Arguments and result as
    :func:`fused_layers`.
    """
    layers = ParameterCache.layers(model, x.dtype, "batched")
    cols = model.out_dim if mean_only else 2 * model.out_dim
    last = len(layers) - 1
    h = x
    for i, (weight, bias) in enumerate(layers):
        if i == last:
            weight, bias = weight[..., :cols], bias[..., :cols]
        if i == 0 and x.dim() == 2:  # [B, in] @ [E, in, d] -> [E, B, d]
            h = th.matmul(h, weight).add_(bias)
        elif i == last or x.dim() == 3:  # per-member inputs: the training forward's products
            h = th.baddbmm(bias, h, weight)
        else:
            h = th.bmm(h, weight).add_(bias)
        if i < last:
            F.silu(h, inplace=True)
    return h


LAYERS = {"batched": batched_layers, "members": member_layers, "fused": fused_layers}


@functools.cache
def cpu_name() -> str:
    """The CPU's model name (``/proc/cpuinfo`` where there is one), for the keys of the path cache."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def cache_file() -> Path:
    """The file where this host's chosen paths are kept: ``$SB3_POPLIN_CACHE_DIR/forward_paths.json``."""
    root = os.environ.get(CACHE_ENV) or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "sb3_poplin"
    )
    return Path(root) / "forward_paths.json"


class PathChoice:
    """The paths chosen in this process, by size class, and their cache file (read once, written on each choice)."""

    chosen: ClassVar[dict[str, str]] = {}
    loaded: ClassVar[bool] = False
    timer: ClassVar[Callable[[], float]] = time.perf_counter

    @staticmethod
    def size_class(model: ProbabilisticEnsemble, x: th.Tensor, mean_only: bool) -> tuple:
        """Threads, dtype, input kind, members, layer widths and rows (to the next power of 2) of a forward."""
        widths = (model.in_dim, *model.hidden_sizes, model.out_dim * (1 if mean_only else 2))
        kind = "shared" if x.dim() == 2 else "per-member"
        return (th.get_num_threads(), x.dtype, kind, model.ensemble_size, widths, 1 << (x.shape[-2] - 1).bit_length())

    @staticmethod
    @functools.cache
    def key(size_class: tuple) -> str:
        """The cache file's key of a size class: the host and torch, then the size class."""
        threads, dtype, kind, members, widths, rows = size_class
        return (
            f"{platform.machine()} {cpu_name()} | torch {th.__version__} | {threads} threads | "
            f"{str(dtype).removeprefix('torch.')} | {kind} x{members} {'-'.join(map(str, widths))} | {rows} rows"
        )

    @classmethod
    def load(cls) -> None:
        """Read this host's earlier choices from the cache file (once per process; a missing or bad file: none)."""
        cls.loaded = True
        try:
            stored = json.loads(cache_file().read_text())
        except (OSError, ValueError):
            return
        if isinstance(stored, dict):
            cls.chosen.update({k: v for k, v in stored.items() if v in PATHS and k not in cls.chosen})

    @classmethod
    def store(cls, key: str, path: str) -> None:
        """Add one choice to the cache file (rewritten whole, atomically; a read-only home keeps it in memory only)."""
        cls.chosen[key] = path
        file = cache_file()
        try:
            file.parent.mkdir(parents=True, exist_ok=True)
            try:
                stored = json.loads(file.read_text())
            except (OSError, ValueError):
                stored = {}
            stored = stored if isinstance(stored, dict) else {}
            stored[key] = path
            with tempfile.NamedTemporaryFile("w", dir=file.parent, delete=False, suffix=".tmp") as f:
                json.dump(stored, f, indent=1, sort_keys=True)
            os.replace(f.name, file)
        except OSError:
            pass

    @classmethod
    def probe(cls, model: ProbabilisticEnsemble, x: th.Tensor, mean_only: bool, candidates: list[str]) -> str:
        """The fastest candidate on ``x``: the median over :data:`PROBE_ROUNDS` interleaved rounds, after one warm-up each."""
        times: dict[str, list[float]] = {path: [] for path in candidates}
        for path in candidates:
            LAYERS[path](model, x, mean_only)
        for _ in range(PROBE_ROUNDS):
            for path in candidates:
                start = cls.timer()
                LAYERS[path](model, x, mean_only)
                times[path].append(cls.timer() - start)
        return min(candidates, key=lambda path: statistics.median(times[path]))


def forward_path(model: ProbabilisticEnsemble, x: th.Tensor, mean_only: bool) -> str:
    """
    Which of :data:`PATHS` runs the no-gradient forward of ``x`` (``[B, in]`` or ``[E, B, in]``, in the compute
    dtype): the one ``SB3_POPLIN_FORWARD_PATH`` names, else ``"batched"`` off a CPU or below :data:`PROBE_MIN_ROWS`
    rows, else the one this host chose for the size class (:class:`PathChoice`), timing the candidates on ``x`` the
    first time.
    """
    forced = os.environ.get(PATH_ENV)
    if forced:
        if forced not in PATHS:
            raise ValueError(f"{PATH_ENV}={forced!r} is not a forward path: use one of {', '.join(PATHS)}, or unset it.")
        if forced == "fused" and not (x.device.type == "cpu" and fused_available(x.dtype)):
            raise ValueError(
                f"{PATH_ENV}=fused, but this torch build has no oneDNN fused linear for {x.dtype} on {x.device.type}: "
                f"use {PATH_ENV}=batched or members, or unset it."
            )
        return forced
    if x.device.type != "cpu" or x.shape[-2] < PROBE_MIN_ROWS:
        return "batched"
    key = PathChoice.key(PathChoice.size_class(model, x, mean_only))
    if key not in PathChoice.chosen and not PathChoice.loaded:
        PathChoice.load()
    if key not in PathChoice.chosen:
        candidates = ["batched", "members"] + (["fused"] if fused_available(x.dtype) else [])
        PathChoice.store(key, PathChoice.probe(model, x, mean_only, candidates))
    return PathChoice.chosen[key]


def compute_dtype(x: th.Tensor) -> th.dtype:
    """The dtype a no-gradient forward of ``x`` runs in: the autocast dtype where autocast is on, else ``x``'s."""
    device = x.device.type
    return th.get_autocast_dtype(device) if th.is_autocast_enabled(device) else x.dtype


def no_grad_output(model: ProbabilisticEnsemble, x: th.Tensor) -> th.Tensor | None:
    """
    The raw output layer ``[E, B, 2 out]`` of a per-member input ``[E, B, in]`` through the speed layer, or ``None``
    with gradients on (then the caller computes the training forward). Float32 output under a bf16 autocast.
    """
    if th.is_grad_enabled():
        return None
    dtype = compute_dtype(x)
    with th.autocast(x.device.type, enabled=False):
        xd = x.to(dtype)
        out = LAYERS[forward_path(model, xd, False)](model, xd, False)
        return out.to(th.float32 if dtype == th.bfloat16 else x.dtype)


def shared_input_mean(model: ProbabilisticEnsemble, x: th.Tensor) -> th.Tensor:
    """
    The members' mean outputs for one input batch shared by all members, without gradients: the log-variance half of
    the output layer is skipped.

    :param model: the ensemble
    :param x: standardised input ``[B, in]``
    :return: the mean half of the output layer ``[E, B, out]`` (float32 for a float32 ``x``)
    """
    dtype = compute_dtype(x)
    with th.autocast(x.device.type, enabled=False):
        xd = x.to(dtype)
        return LAYERS[forward_path(model, xd, True)](model, xd, True).to(x.dtype)
