"""A small MLP over many rows on the CPU, differentiable (C++ kernel, csrc/small_mlp.cpp).

Splatting models run small networks (widths of tens, a few layers) once per Gaussian: tens of
thousands of rows. torch evaluates such a network op by op, and writes and reads every
(rows x width) intermediate of every op, forward and backward; the kernel takes the rows in
blocks of 64 and carries each block through all layers (bias and activation fused) while it
sits in the first-level caches, and its backward skips the rows whose output gradient is zero
(Gaussians that drew nothing).

Any stack of ``torch.nn.Linear`` layers, each followed by one of ReLU, Sigmoid, Tanh or nothing:
:func:`layers_of` reads them from an ``nn.Sequential`` (None when it holds anything else), and
:func:`mlp` evaluates them; :func:`mlp_torch` is the reference (plain torch.nn.functional) that
the tests compare against, in values and in gradients (inputs, weights and biases).
:func:`mlp_kernel_applies` says whether the kernel takes a call (float32 CPU tensors, kernels
built); callers keep the module itself for everything else.

An :class:`InputEncoding` has the kernel build the network's input itself, block by block in the
caches: the sin/cos positional encoding of the first columns (a NeRF-style gamma(x)) and the other
columns passed through, and the real SH basis of a view direction in the last three columns
(sh.sh_basis), so a caller hands it the raw rows instead of a (rows x encoded width) tensor built
and differentiated op by op in torch. :func:`encode_inputs` is its reference.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import nn

from .build import kernels_take, load_kernels
from .sh import sh_basis

# Activation codes of csrc/small_mlp.h (enum Activation).
ACTIVATIONS = {"identity": 0, "relu": 1, "sigmoid": 2, "tanh": 3}
_MODULE_ACTIVATIONS = {nn.ReLU: "relu", nn.Sigmoid: "sigmoid", nn.Tanh: "tanh", nn.Identity: "identity"}


@dataclass
class Layer:
    """``y = activation(x @ weight.T + bias)``: weight (out, in) as nn.Linear stores it."""

    weight: torch.Tensor
    bias: torch.Tensor | None
    activation: str = "identity"


@dataclass(frozen=True)
class InputEncoding:
    """The first ``columns`` input columns x_i enter the network as
    ``[x_i, sin(2^k pi x_i), cos(2^k pi x_i)]_{k<freqs}``, ordered
    ``[x_0..x_{c-1}, sines, cosines, other columns]`` with sine and cosine (i, k) at ``i * freqs + k``
    (``columns = freqs = 0``: none).

    ``view_degree`` (None: no view direction): the last three raw columns are a unit direction d,
    and the encoded row ends with its SH basis ``sh_basis(view_degree, d)`` in place of d, the bands
    above ``view_active`` (default: all) fed as zeros (bands a training schedule has not switched on
    yet): ``[x_0..x_{c-1}, sines, cosines, other columns, SH(d)]``."""

    columns: int
    freqs: int
    view_degree: int | None = None
    view_active: int | None = None

    def __post_init__(self):
        if self.columns < 0 or self.freqs < 0 or (self.columns == 0) != (self.freqs == 0):
            raise ValueError(f"an input encoding needs columns and freqs both >= 1 (or both 0), got {self}")
        if self.view_degree is None:
            if self.columns == 0 or self.view_active is not None:
                raise ValueError(f"an input encoding needs encoded columns or a view direction, got {self}")
            return
        if not 0 <= self.view_degree <= 3:
            raise ValueError(f"view_degree must be 0..3, got {self.view_degree}")
        if self.view_active is None:
            object.__setattr__(self, "view_active", self.view_degree)
        if not 0 <= self.view_active <= self.view_degree:
            raise ValueError(
                f"view_active must be 0..view_degree ({self.view_degree}), got {self.view_active}"
            )

    @property
    def view_columns(self) -> int:
        """Columns of the view direction's SH basis in the encoded row (0: none)."""
        return 0 if self.view_degree is None else (self.view_degree + 1) ** 2

    def raw_columns(self) -> int:
        """The fewest raw columns the encoding reads: the encoded ones and the direction."""
        return self.columns + (0 if self.view_degree is None else 3)

    def width(self, raw_width: int) -> int:
        """The encoded width of ``raw_width`` raw columns."""
        view = 0 if self.view_degree is None else self.view_columns - 3
        return raw_width + 2 * self.columns * self.freqs + view

    def kernel_args(self) -> tuple[int, int, int, int]:
        """(enc_cols, enc_freqs, view_degree, view_active) as csrc/small_mlp.h takes them (-1: no view)."""
        if self.view_degree is None:
            return (self.columns, self.freqs, -1, -1)
        return (self.columns, self.freqs, self.view_degree, self.view_active)


def encode_inputs(x: torch.Tensor, encoding: InputEncoding | None) -> torch.Tensor:
    """The reference of the kernel's input encoding (plain torch ops, any dtype, differentiable)."""
    if encoding is None:
        return x
    if encoding.raw_columns() > x.shape[-1]:
        raise ValueError(
            f"an encoding of {encoding.raw_columns()} raw columns needs as many, got {x.shape[-1]}"
        )
    head = x[..., : encoding.columns]
    parts = [head]
    if encoding.freqs > 0:
        scales = (2.0 ** torch.arange(encoding.freqs, dtype=x.dtype, device=x.device)) * math.pi
        angles = (head[..., None] * scales).flatten(-2)
        parts += [torch.sin(angles), torch.cos(angles)]
    if encoding.view_degree is None:
        return torch.cat([*parts, x[..., encoding.columns :]], dim=-1)
    basis = sh_basis(encoding.view_degree, x[..., -3:])
    keep = (encoding.view_active + 1) ** 2
    if keep < basis.shape[-1]:
        basis = torch.cat(
            [basis[..., :keep], basis.new_zeros(*basis.shape[:-1], basis.shape[-1] - keep)], dim=-1
        )
    return torch.cat([*parts, x[..., encoding.columns : -3], basis], dim=-1)


def layers_of(net: nn.Module, output_activation: str = "identity") -> list[Layer] | None:
    """The layers of an ``nn.Sequential`` of Linear modules, each optionally followed by one
    activation module; ``output_activation`` is applied after the last (e.g. a sigmoid the caller
    applies outside the Sequential). None when the module holds anything else."""
    if output_activation not in ACTIVATIONS:
        raise ValueError(f"output_activation must be one of {sorted(ACTIVATIONS)}, got {output_activation!r}")
    if not isinstance(net, nn.Sequential):
        return None
    layers: list[Layer] = []
    for module in net:
        if isinstance(module, nn.Linear):
            layers.append(Layer(module.weight, module.bias))
            continue
        name = _MODULE_ACTIVATIONS.get(type(module))
        if name is None or not layers or layers[-1].activation != "identity":
            return None
        layers[-1].activation = name
    if not layers:
        return None
    if output_activation != "identity":
        if layers[-1].activation != "identity":
            return None
        layers[-1].activation = output_activation
    return layers


def fold_constant_inputs(layers: list[Layer], columns: slice, values: torch.Tensor) -> list[Layer]:
    """``layers`` for inputs without ``columns``, whose value is the same ``values`` in every row:
    their product with the first weight is added to its bias once, instead of once per row (a pose
    code or a time code fed to a per-Gaussian network). Differentiable in the weights and values."""
    first = layers[0]
    weight = first.weight
    start, stop, step = columns.indices(weight.shape[1])
    if step != 1 or stop - start != values.numel():
        raise ValueError(
            f"columns {columns} of a {weight.shape[1]}-wide input do not match {values.numel()} values"
        )
    shift = weight[:, start:stop] @ values.reshape(-1).to(weight.dtype)
    bias = shift if first.bias is None else first.bias + shift
    kept = torch.cat([weight[:, :start], weight[:, stop:]], dim=1)
    return [Layer(kept, bias, first.activation), *layers[1:]]


def _groups(x: torch.Tensor | Sequence[torch.Tensor]) -> list[torch.Tensor]:
    return [x] if isinstance(x, torch.Tensor) else list(x)


def mlp_torch(
    x: torch.Tensor | Sequence[torch.Tensor],
    layers: list[Layer],
    encoding: InputEncoding | None = None,
    rows: torch.Tensor | None = None,
) -> torch.Tensor:
    """The reference: the same inputs, encoding and layers with torch (any device and dtype)."""
    groups = _groups(x)
    x = groups[0] if len(groups) == 1 else torch.cat(groups, dim=-1)
    if rows is not None:
        x = x.index_select(0, rows)
    x = encode_inputs(x, encoding)
    functions = {"identity": lambda t: t, "relu": torch.relu, "sigmoid": torch.sigmoid, "tanh": torch.tanh}
    for layer in layers:
        x = functions[layer.activation](nn.functional.linear(x, layer.weight, layer.bias))
    return x


def mlp_kernel_applies(x: torch.Tensor | Sequence[torch.Tensor], layers: list[Layer]) -> bool:
    """Whether :func:`mlp` can take this call: float32 CPU tensors and the kernels build here."""
    return kernels_take(*_groups(x), *(t for layer in layers for t in (layer.weight, layer.bias)))


def _f32(t: torch.Tensor) -> torch.Tensor:
    return t.detach().to(torch.float32).contiguous()


_NO_ROWS = torch.empty(0, dtype=torch.long)


class _Mlp(torch.autograd.Function):
    """Inputs: rows (or None), the activations, the encoding's kernel arguments, whether a graph is
    kept, the number of column groups, then the groups, the weights and the biases."""

    @staticmethod
    def forward(ctx, rows, acts, enc, grad, count_x, *tensors):
        ops = load_kernels().ops
        count = len(acts)
        xs = [_f32(t) for t in tensors[:count_x]]
        params = tensors[count_x:]
        weights = [_f32(w) for w in params[:count]]
        biases = [torch.empty(0) if b is None else _f32(b) for b in params[count:]]
        select = rows is not None
        index = rows.contiguous() if select else _NO_ROWS
        threads = torch.get_num_threads()
        out, hidden = ops.mlp_fwd(xs, index, select, weights, biases, list(acts), *enc, grad, threads)
        if grad:
            ctx.save_for_backward(index, out, *xs, *weights, *biases, *hidden)
        ctx.args = (acts, enc, select, count_x, [b is not None for b in params[count:]])
        return out

    @staticmethod
    def backward(ctx, g_out):
        acts, enc, select, count_x, has_bias = ctx.args
        count = len(acts)
        saved = ctx.saved_tensors
        index, out = saved[0], saved[1]
        xs = list(saved[2 : 2 + count_x])
        weights = list(saved[2 + count_x : 2 + count_x + count])
        biases = list(saved[2 + count_x + count : 2 + count_x + 2 * count])
        hidden = list(saved[2 + count_x + 2 * count :])
        ops = load_kernels().ops
        first = 5  # the tensors' place among forward's inputs
        want_gx = [int(ctx.needs_input_grad[first + g]) for g in range(count_x)]
        g_x, g_w, g_b = ops.mlp_bwd(
            xs,
            index,
            select,
            weights,
            biases,
            list(acts),
            *enc,
            hidden,
            out,
            _f32(g_out),
            want_gx,
            torch.get_num_threads(),
        )
        grads_x = [g if want else None for g, want in zip(g_x, want_gx, strict=True)]
        p0 = first + count_x
        grads_w = [g if ctx.needs_input_grad[p0 + i] else None for i, g in enumerate(g_w)]
        grads_b = [
            g if has_bias[i] and ctx.needs_input_grad[p0 + count + i] else None for i, g in enumerate(g_b)
        ]
        return (None, None, None, None, None, *grads_x, *grads_w, *grads_b)


def mlp(
    x: torch.Tensor | Sequence[torch.Tensor],
    layers: list[Layer],
    encoding: InputEncoding | None = None,
    rows: torch.Tensor | None = None,
) -> torch.Tensor:
    """``layers`` applied to the rows of ``x (N, in)`` with the C++ kernel -> ``(N, out)``; with an
    ``encoding``, to the rows ``encode_inputs(x, encoding)``, built inside the kernel.

    ``x`` may be a sequence of column groups (each (N, in_g)), read as their concatenation without
    building it; ``rows`` (int64 (M,), distinct) evaluates those rows only -> ``(M, out)``, read where
    they lie (a per-step subset of a table: no gathered copy, and each group's gradient comes back
    at its table rows, zero elsewhere). :func:`mlp_torch` is the same with torch.cat and
    index_select.

    Differentiable with respect to ``x`` and every weight and bias. Float32 CPU tensors (see
    :func:`mlp_kernel_applies`); computed in float32 like torch's own CPU path.
    """
    groups = _groups(x)
    if not groups or any(t.dim() != 2 or t.shape[0] != groups[0].shape[0] for t in groups):
        shapes = [tuple(t.shape) for t in groups]
        raise ValueError(f"mlp takes (rows, features) column groups of the same rows, got shapes {shapes}")
    if rows is not None and (rows.dim() != 1 or rows.dtype != torch.long):
        raise ValueError(f"rows must be a 1-D int64 index, got {rows.dtype} of shape {tuple(rows.shape)}")
    width = sum(t.shape[1] for t in groups)
    enc = (0, 0, -1, -1)
    if encoding is not None:
        if encoding.raw_columns() > width:
            raise ValueError(f"an encoding of {encoding.raw_columns()} raw columns got {width}")
        enc = encoding.kernel_args()
        width = encoding.width(width)
    for i, layer in enumerate(layers):
        if layer.weight.dim() != 2 or layer.weight.shape[1] != width:
            raise ValueError(f"layer {i}: weight must be (out, {width}), got {tuple(layer.weight.shape)}")
        width = layer.weight.shape[0]
        if layer.bias is not None and layer.bias.shape != (width,):
            raise ValueError(f"layer {i}: bias must be ({width},), got {tuple(layer.bias.shape)}")
        if layer.activation not in ACTIVATIONS:
            raise ValueError(f"layer {i}: unknown activation {layer.activation!r}")
    acts = tuple(ACTIVATIONS[layer.activation] for layer in layers)
    params = [layer.weight for layer in layers] + [layer.bias for layer in layers]
    grad = torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in [*groups, *params])
    return _Mlp.apply(rows, acts, enc, grad, len(groups), *groups, *params)
