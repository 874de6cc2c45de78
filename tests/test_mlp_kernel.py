"""The small-MLP C++ kernel (stg_node.splat.mlp_ops) against torch.nn in float64: values and the
gradients of inputs, weights and biases, for every activation, odd widths, skipped rows."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from stg_node.splat import mlp_ops

pytestmark = pytest.mark.usefixtures("cpu_kernels")  # skips where the kernels cannot build


def network(widths, activations, bias=True, seed=0):
    torch.manual_seed(seed)
    modules = {"relu": nn.ReLU, "sigmoid": nn.Sigmoid, "tanh": nn.Tanh}
    layers: list[nn.Module] = []
    for (a, b), act in zip(zip(widths[:-1], widths[1:], strict=False), activations, strict=False):
        layers.append(nn.Linear(a, b, bias=bias))
        if act != "identity":
            layers.append(modules[act]())
    return nn.Sequential(*layers).double()


def compare(net, rows=517, output_activation="identity", zero_rows=False, seed=1, encoding=None):
    """Kernel (float32) against torch.nn (float64): outputs and every gradient. With an
    ``encoding``, the raw rows (in [-1, 1], as a positional encoding expects them) go to both."""
    gen = torch.Generator().manual_seed(seed)
    width = net[0].in_features
    if encoding is None:
        x = torch.randn(rows, width, generator=gen, dtype=torch.float64)
    else:
        width -= encoding.width(0)
        x = torch.rand(rows, width, generator=gen, dtype=torch.float64) * 2.0 - 1.0
        if encoding.view_degree is not None:  # the view direction: unit vectors
            x[:, -3:] = torch.nn.functional.normalize(
                torch.randn(rows, 3, generator=gen, dtype=torch.float64), dim=1
            )
    layers64 = mlp_ops.layers_of(net, output_activation)
    out_dim = layers64[-1].weight.shape[0]
    g = torch.randn(rows, out_dim, generator=gen, dtype=torch.float64)
    if zero_rows:
        g[::3] = 0.0  # rows that drew nothing: skipped by the backward pass
    x64 = x.clone().requires_grad_(True)
    ref = mlp_ops.mlp_torch(x64, layers64, encoding)
    params64 = [x64] + list(net.parameters())
    ref_grads = torch.autograd.grad((ref * g).sum(), params64)

    net32 = [p.detach().float().requires_grad_(True) for p in net.parameters()]
    layers32, i = [], 0
    for layer in layers64:
        w = net32[i]
        b = net32[i + 1] if layer.bias is not None else None
        i += 2 if layer.bias is not None else 1
        layers32.append(mlp_ops.Layer(w, b, layer.activation))
    x32 = x.float().requires_grad_(True)
    out = mlp_ops.mlp(x32, layers32, encoding)
    grads = torch.autograd.grad((out * g.float()).sum(), [x32] + net32)
    torch.testing.assert_close(out.double(), ref, atol=2e-5, rtol=1e-4)
    for got, want in zip(grads, ref_grads, strict=False):
        scale = max(float(want.abs().max()), 1.0)
        torch.testing.assert_close(got.double(), want, atol=3e-5 * scale, rtol=1e-4)
    return x32, grads


@pytest.mark.parametrize(
    "widths, activations, output",
    [
        ((55, 64, 64, 3), ("relu", "relu", "identity"), "sigmoid"),  # the avatar's colour MLP
        ((47, 96, 96, 3), ("relu", "relu", "identity"), "sigmoid"),
        ((5, 13, 7), ("tanh", "identity"), "identity"),  # widths that are no multiple of 8
        ((9, 17), ("identity",), "relu"),  # one layer
        ((3, 40, 40, 40, 2), ("sigmoid", "relu", "tanh", "identity"), "tanh"),
    ],
)
def test_values_and_gradients_match_torch_in_float64(widths, activations, output):
    compare(network(widths, activations), output_activation=output)


def test_layers_without_bias():
    compare(network((20, 24, 3), ("relu", "identity"), bias=False), output_activation="sigmoid")


def test_rows_without_an_output_gradient_are_skipped_exactly():
    x, grads = compare(
        network((30, 32, 3), ("relu", "identity")), zero_rows=True, output_activation="sigmoid"
    )
    assert torch.equal(grads[0][::3], torch.zeros_like(grads[0][::3]))


def test_a_block_remainder_and_a_single_row():
    net = network((12, 16, 4), ("relu", "identity"))
    for rows in (1, 63, 64, 65, 130):
        compare(net, rows=rows, seed=rows)


@pytest.mark.parametrize(
    "columns, freqs, rest",
    [
        (3, 4, 32),  # the avatar's colour MLP: gamma(canonical centre), feature, SH basis
        (3, 1, 0),  # nothing but the encoded columns
        (2, 6, 5),  # widths that are no multiple of 8
        (7, 3, 1),
    ],
)
def test_the_kernels_input_encoding_matches_torch_in_float64(columns, freqs, rest):
    """The sin/cos encoding built inside the kernel: the values and the gradients of the raw
    inputs (the encoded and the passed-through columns), weights and biases, against float64
    autograd through encode_inputs + torch.nn."""
    encoding = mlp_ops.InputEncoding(columns, freqs)
    net = network((encoding.width(columns + rest), 64, 64, 3), ("relu", "relu", "identity"), seed=columns)
    compare(net, output_activation="sigmoid", encoding=encoding, zero_rows=True)
    for rows in (1, 65):
        compare(net, rows=rows, encoding=encoding, seed=rows)


@pytest.mark.parametrize(
    "columns, freqs, rest, degree, active",
    [
        (3, 4, 16, 1, 1),  # the balanced colour MLP: gamma(centre), feature, SH(d) of degree 1
        (3, 4, 24, 2, 1),  # the quality preset while its second band is still switched off
        (3, 2, 5, 3, 3),  # every band of degree 3
        (3, 2, 5, 3, 0),
        (0, 0, 7, 2, 2),  # a view direction without a positional encoding
        (0, 0, 0, 0, 0),  # nothing but the constant band
    ],
)
def test_the_kernels_view_encoding_matches_torch_in_float64(columns, freqs, rest, degree, active):
    """The SH basis of the view direction built inside the kernel: the values and the gradients of
    the raw inputs (the direction's three columns through the basis's derivative, the others as
    before), weights and biases, against float64 autograd through encode_inputs (sh.sh_basis) +
    torch.nn; bands not switched on take no gradient."""
    encoding = mlp_ops.InputEncoding(columns, freqs, view_degree=degree, view_active=active)
    raw = columns + rest + 3
    net = network((encoding.width(raw), 48, 3), ("relu", "identity"), seed=raw + degree)
    x, grads = compare(net, output_activation="sigmoid", encoding=encoding, zero_rows=True)
    if active == 0:  # the constant band alone: the direction takes no gradient
        assert torch.equal(grads[0][:, -3:], torch.zeros_like(grads[0][:, -3:]))
    for rows in (1, 65):
        compare(net, rows=rows, encoding=encoding, seed=rows)


@pytest.mark.parametrize("select", [False, True])
def test_column_groups_and_selected_rows_match_torch_in_float64(select):
    """The raw rows read from column groups where they lie, at selected table rows: the values and
    each group's gradient (zero at the rows not evaluated, and for a group without a gradient none)
    against float64 autograd through torch.cat + index_select + encode_inputs + torch.nn."""
    encoding = mlp_ops.InputEncoding(3, 4, view_degree=1)
    net = network((encoding.width(3 + 5 + 3), 32, 3), ("relu", "identity"), seed=5)
    gen = torch.Generator().manual_seed(6)
    table = 300
    groups64 = [
        torch.rand(table, 3, generator=gen, dtype=torch.float64) * 2 - 1,
        torch.randn(table, 5, generator=gen, dtype=torch.float64),
        torch.nn.functional.normalize(torch.randn(table, 3, generator=gen, dtype=torch.float64), dim=1),
    ]
    rows = torch.randperm(table, generator=gen)[:131] if select else None  # distinct, in no order
    count = table if rows is None else rows.numel()
    g = torch.randn(count, 3, generator=gen, dtype=torch.float64)
    g[::4] = 0.0  # rows that drew nothing
    layers64 = mlp_ops.layers_of(net, "sigmoid")
    leaves64 = [t.clone().requires_grad_(i < 2) for i, t in enumerate(groups64)]  # no grad: directions
    ref = mlp_ops.mlp_torch(leaves64, layers64, encoding, rows)
    ref_grads = torch.autograd.grad((ref * g).sum(), [*leaves64[:2], *net.parameters()])
    params32 = [p.detach().float().requires_grad_(True) for p in net.parameters()]
    layers32 = [
        mlp_ops.Layer(params32[2 * i], params32[2 * i + 1], layer.activation)
        for i, layer in enumerate(layers64)
    ]
    leaves32 = [t.float().requires_grad_(i < 2) for i, t in enumerate(groups64)]
    out = mlp_ops.mlp(leaves32, layers32, encoding, rows)
    grads = torch.autograd.grad((out * g.float()).sum(), [*leaves32[:2], *params32])
    torch.testing.assert_close(out.double(), ref, atol=2e-5, rtol=1e-4)
    for got, want in zip(grads, ref_grads, strict=True):
        torch.testing.assert_close(
            got.double(), want, atol=3e-5 * max(float(want.abs().max()), 1.0), rtol=1e-4
        )
    if rows is not None:  # the rows not evaluated take no gradient
        others = torch.ones(table, dtype=torch.bool)
        others[rows] = False
        assert torch.equal(grads[1][others], torch.zeros_like(grads[1][others]))


def test_selected_rows_must_be_distinct_rows_of_the_table():
    layer = mlp_ops.Layer(torch.randn(4, 3), torch.randn(4), "relu")
    x = torch.randn(10, 3)
    with pytest.raises(RuntimeError, match="twice"):
        mlp_ops.mlp(x, [layer], rows=torch.tensor([1, 4, 1]))
    with pytest.raises(RuntimeError, match="not a row"):
        mlp_ops.mlp(x, [layer], rows=torch.tensor([1, 10]))
    with pytest.raises(ValueError, match="int64"):
        mlp_ops.mlp(x, [layer], rows=torch.tensor([1.0]))
    with pytest.raises(ValueError, match="same rows"):
        mlp_ops.mlp([x, torch.randn(9, 2)], [mlp_ops.Layer(torch.randn(4, 5), None)])


def test_the_view_encoding_is_the_colour_mlps():
    """The view columns as the colour MLP's torch path feeds them: SH(d) with the bands not yet on
    set to zero."""
    from stg_node.avatar.color import sh_basis

    dirs = torch.nn.functional.normalize(torch.randn(9, 3), dim=1)
    rest = torch.randn(9, 5)
    got = mlp_ops.encode_inputs(
        torch.cat([rest, dirs], 1), mlp_ops.InputEncoding(0, 0, view_degree=2, view_active=1)
    )
    want = torch.cat([rest, sh_basis(1, dirs), torch.zeros(9, 5)], 1)
    assert torch.equal(got, want)


def test_the_input_encoding_is_the_colour_mlps():
    """encode_inputs lays the columns out as the avatar's encoded_inputs does (one layout for the
    kernel and the torch path, so a trained network reads the same inputs on either)."""
    from stg_node.avatar.color import encoded_inputs

    x, rest = torch.rand(9, 3) * 2 - 1, torch.randn(9, 5)
    got = mlp_ops.encode_inputs(torch.cat([x, rest], 1), mlp_ops.InputEncoding(3, 4))
    assert torch.equal(got, encoded_inputs(x, 4, rest))


def test_an_input_encoding_that_does_not_fit_is_refused():
    layer = mlp_ops.Layer(torch.randn(4, 11), torch.randn(4))
    with pytest.raises(ValueError, match="columns"):
        mlp_ops.mlp(torch.randn(5, 2), [layer], mlp_ops.InputEncoding(3, 1))
    with pytest.raises(ValueError, match="weight"):
        mlp_ops.mlp(torch.randn(5, 3), [layer], mlp_ops.InputEncoding(3, 2))  # 15 wide, not 11
    with pytest.raises(ValueError, match="freqs"):
        mlp_ops.InputEncoding(3, 0)
    with pytest.raises(ValueError, match="view direction"):
        mlp_ops.InputEncoding(0, 0)
    with pytest.raises(ValueError, match="view_active"):
        mlp_ops.InputEncoding(3, 1, view_degree=1, view_active=2)
    with pytest.raises(ValueError, match="view_degree"):
        mlp_ops.InputEncoding(3, 1, view_degree=4)
    with_view = mlp_ops.InputEncoding(3, 1, view_degree=0)
    with pytest.raises(ValueError, match="raw columns"):  # the direction's three columns are missing
        mlp_ops.mlp(torch.randn(5, 4), [mlp_ops.Layer(torch.randn(4, 12), None)], with_view)


def test_two_threads_give_the_one_thread_result():
    net = network((47, 64, 64, 3), ("relu", "relu", "identity")).float()
    layers = mlp_ops.layers_of(net, "sigmoid")
    x = torch.randn(3000, 47, requires_grad=True)
    results = []
    for threads in (1, 2):
        previous = torch.get_num_threads()
        torch.set_num_threads(threads)
        try:
            out = mlp_ops.mlp(x, layers)
            grads = torch.autograd.grad(out.square().sum(), [x, *net.parameters()])
            results.append([out.detach(), *grads])
        finally:
            torch.set_num_threads(previous)
    for a, b in zip(*results, strict=False):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)


def _has_avx512() -> bool:
    try:
        with open("/proc/cpuinfo") as f:
            return any(line.startswith("flags") and " avx512f" in line for line in f)
    except OSError:
        return False


@pytest.mark.skipif(not _has_avx512(), reason="the 16-lane path runs on AVX-512 CPUs only")
@pytest.mark.parametrize("widths", [(47, 64, 64, 3), (33, 48, 16, 5), (31, 80, 24, 3)])
def test_the_16_lane_products_equal_the_8_lane_ones_bit_for_bit(widths, monkeypatch):
    """Each output column sums its products in the same order on either vector width (small_mlp.cpp,
    gemm16): the AVX-512 path must reproduce the 8-lane path exactly, forward and backward, with an
    input encoding and selected rows (the colour MLP's call)."""
    net = network(widths, ("relu", "relu", "identity")).float()
    layers = mlp_ops.layers_of(net, "sigmoid")
    encoding = mlp_ops.InputEncoding(3, 4, view_degree=1)
    raw = widths[0] - encoding.width(0)
    gen = torch.Generator().manual_seed(3)
    x = (torch.rand(700, raw, generator=gen) * 2 - 1).requires_grad_(True)
    rows = torch.randperm(700, generator=gen)[:517].sort().values
    results = []
    for off in ("1", "0"):
        monkeypatch.setenv("STG_SPLAT_NO_AVX512", off)
        out = mlp_ops.mlp(x, layers, encoding, rows=rows)
        g = torch.randn(out.shape, generator=torch.Generator().manual_seed(4))
        grads = torch.autograd.grad((out * g).sum(), [x, *net.parameters()])
        results.append([out.detach(), *grads])
    for a, b in zip(*results, strict=True):
        assert torch.equal(a, b)


def test_folding_row_constant_inputs_into_the_bias_changes_nothing():
    """A pose code repeated in every row: folded into the first layer's bias, same outputs and
    the same gradients for the weights and the code."""
    net = network((10, 16, 3), ("relu", "identity"))
    gen = torch.Generator().manual_seed(2)
    rows = torch.randn(40, 7, generator=gen, dtype=torch.float64)
    code = torch.randn(3, generator=gen, dtype=torch.float64, requires_grad=True)
    layers = mlp_ops.layers_of(net, "sigmoid")
    full = mlp_ops.mlp_torch(torch.cat([rows[:, :4], code.expand(40, 3), rows[:, 4:]], 1), layers)
    g_full = torch.autograd.grad(full.sum(), [code, *net.parameters()])
    folded = mlp_ops.mlp_torch(rows, mlp_ops.fold_constant_inputs(layers, slice(4, 7), code))
    g_folded = torch.autograd.grad(folded.sum(), [code, *net.parameters()])
    torch.testing.assert_close(folded, full)
    for a, b in zip(g_folded, g_full, strict=False):
        torch.testing.assert_close(a, b)
    with pytest.raises(ValueError, match="columns"):
        mlp_ops.fold_constant_inputs(layers, slice(4, 6), code)


def test_layers_of_reads_linear_stacks_only():
    assert mlp_ops.layers_of(nn.Sequential(nn.Linear(3, 4), nn.ReLU(), nn.Linear(4, 1))) is not None
    assert mlp_ops.layers_of(nn.Sequential(nn.Linear(3, 4), nn.GELU())) is None  # no kernel for it
    assert mlp_ops.layers_of(nn.Sequential(nn.ReLU(), nn.Linear(3, 4))) is None  # activation first
    assert mlp_ops.layers_of(nn.Sequential(nn.Linear(3, 4), nn.ReLU(), nn.ReLU())) is None
    assert mlp_ops.layers_of(nn.Sequential(nn.Linear(3, 4), nn.Tanh()), "sigmoid") is None
    assert mlp_ops.layers_of(nn.Linear(3, 4)) is None
    with pytest.raises(ValueError, match="output_activation"):
        mlp_ops.layers_of(nn.Sequential(nn.Linear(3, 4)), "gelu")


def test_bad_shapes_are_refused():
    layer = mlp_ops.Layer(torch.randn(4, 3), torch.randn(4), "relu")
    with pytest.raises(ValueError, match="weight"):
        mlp_ops.mlp(torch.randn(5, 2), [layer])
    with pytest.raises(ValueError, match="bias"):
        mlp_ops.mlp(torch.randn(5, 3), [mlp_ops.Layer(torch.randn(4, 3), torch.randn(3), "relu")])
    with pytest.raises(ValueError, match="rows, features"):
        mlp_ops.mlp(torch.randn(5), [layer])
    assert not mlp_ops.mlp_kernel_applies(torch.randn(5, 3, dtype=torch.float64), [layer])
