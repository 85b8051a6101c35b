"""
The speed layer of the ensemble's no-gradient forwards (planning and evaluation): the same numbers as
:meth:`sb3_poplin.dynamics.ProbabilisticEnsemble.forward`, computed faster.

- On a CPU with oneDNN, each member's layers run as oneDNN linear primitives with the bias and SiLU fused into the
  matmul (:func:`onednn_fused_linear`, probed once per process and dtype against the plain computation), from
  :data:`FUSED_MIN_ROWS` rows per member on: each such call has a fixed cost of tens of microseconds, which the
  fusion repays on the paper's 500-row planner but not on the CPU budget's 200 rows.
- Elsewhere (and below that size) the shared-input forward of expectation propagation is one broadcast matmul for
  the first layer (no copy of the input per member) and plain batched matmuls after it, with the bias added and SiLU
  applied in place.
- Under a bf16 autocast the whole forward runs in bf16 on bf16 copies of the parameters, made once per parameter
  update (:class:`ParameterCache`; autocast would cast every weight at every call and mix dtypes in the element-wise
  ops).

Measurements behind these choices are in ``benchmarks/RESULTS.md`` (``benchmarks/speed/planner_parts.py``,
``benchmarks/speed/planning_speed.py``).
"""

from __future__ import annotations

import functools
import weakref
from collections.abc import Callable
from typing import TYPE_CHECKING, ClassVar

import torch as th
import torch.nn.functional as F

if TYPE_CHECKING:
    from sb3_poplin.dynamics import ProbabilisticEnsemble

Layers = list[tuple[th.Tensor, th.Tensor]]

# Rows per member from which the fused per-member oneDNN forward runs; fewer go through the batched matmuls. Measured on an
# Intel Xeon without AMX (1 thread, ``benchmarks/speed/planner_parts.py --parts 5``): with 100-300 rows the batched matmuls
# took 0.24-0.86x the fused forward's time for members of 3 x 64, 3 x 128 and 4 x 200 (the CPU budget plans 200 rows); from 400
# rows on the wider members were as fast or faster fused (4 x 200: 1.11x at 600 rows, 1.62x at 1000). A whole CPU-budget plan
# became 1.6-2.5x faster (``speed/plan_time_variants.py --setting cpu|cheetah-cpu``). The two paths agree to float32 rounding,
# not bit for bit: 0 replays runs made before the threshold existed (on the same host; ``benchmarks/probes/fidelity_ab.py``
# does).
FUSED_MIN_ROWS = 320


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


def compute_dtype(x: th.Tensor) -> th.dtype:
    """The dtype a no-gradient forward of ``x`` runs in: the autocast dtype where autocast is on, else ``x``'s."""
    device = x.device.type
    return th.get_autocast_dtype(device) if th.is_autocast_enabled(device) else x.dtype


def fused_dtype(x: th.Tensor) -> th.dtype | None:
    """
    The dtype the fused oneDNN forward runs ``x`` (``[B, in]`` or ``[E, B, in]``) in, else ``None``: where gradients
    are on, off a CPU, without oneDNN, or for fewer than :data:`FUSED_MIN_ROWS` rows ``B``.
    """
    if th.is_grad_enabled() or x.device.type != "cpu" or x.shape[-2] < FUSED_MIN_ROWS:
        return None
    dtype = compute_dtype(x)
    if dtype not in (th.float32, th.bfloat16):
        return None
    return dtype if onednn_fused_linear(dtype) is not None else None


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
        :param layout: ``"batched"``: weight ``[E, in, out]``, bias ``[E, 1, out]``, only the mean half of the output
            layer (the parameters themselves where nothing changes); ``"members"``: weight ``[E, out, in]`` and bias
            ``[E, out]``, contiguous per member, as oneDNN's linear takes them
        """
        layers = [*model.hidden, model.output]
        last = len(layers) - 1

        def mean_half(i: int, t: th.Tensor) -> th.Tensor:
            return t[..., : model.out_dim] if i == last else t

        if layout == "batched" and dtype == model.output.weight.dtype:
            return [(mean_half(i, layer.weight), mean_half(i, layer.bias)) for i, layer in enumerate(layers)]
        key = tuple((p._version, p.data_ptr()) for layer in layers for p in (layer.weight, layer.bias))
        caches = cls._caches.setdefault(model, {})
        cached = caches.get((dtype, layout))
        if cached is None or cached[0] != key:
            copies = []
            for i, layer in enumerate(layers):
                weight, bias = layer.weight.detach(), layer.bias.detach()
                if layout == "members":
                    weight, bias = weight.transpose(1, 2), bias.squeeze(1)
                else:
                    weight, bias = mean_half(i, weight), mean_half(i, bias)
                copies.append((weight.to(dtype).contiguous(), bias.to(dtype).contiguous()))
            cached = (key, copies)
            caches[(dtype, layout)] = cached
        return cached[1]


def member_layers(model: ProbabilisticEnsemble, x: th.Tensor, mean_only: bool) -> th.Tensor:
    """
    The network member by member with oneDNN's fused linear + bias + SiLU (no gradients, CPU).

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


def fused_output(model: ProbabilisticEnsemble, x: th.Tensor) -> th.Tensor | None:
    """
    The raw output layer ``[E, B, 2 out]`` of a per-member input ``[E, B, in]`` through the fused oneDNN forward, or
    ``None`` where it does not apply (gradients on, not a CPU, no oneDNN): then the caller computes the plain forward.
    Float32 output under a bf16 autocast.
    """
    dtype = fused_dtype(x)
    if dtype is None:
        return None
    with th.autocast(x.device.type, enabled=False):
        return member_layers(model, x.to(dtype), mean_only=False).to(th.float32 if dtype == th.bfloat16 else x.dtype)


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
        if fused_dtype(x) is not None:
            return member_layers(model, x.to(dtype), mean_only=True).to(x.dtype)
        layers = ParameterCache.layers(model, dtype, "batched")
        weight, bias = layers[0]
        h = th.matmul(x.to(dtype), weight)  # [B, in] @ [E, in, H] -> [E, B, H]
        if len(layers) == 1:  # no hidden layer: that product is the output layer's
            return h.add_(bias).to(x.dtype)
        for i, (weight, bias) in enumerate(layers[:-1]):
            if i > 0:
                h = th.bmm(h, weight)
            F.silu(h.add_(bias), inplace=True)
        weight, bias = layers[-1]
        return th.baddbmm(bias, h, weight).to(x.dtype)
