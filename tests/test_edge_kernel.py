"""The C++ edge-length kernel (stg_node.splat.edge_ops) against independent truth: closed-form
cases and autograd through the torch implementation in float64, values and gradients."""

from __future__ import annotations

import pytest
import torch

from stg_node.avatar.isometry import approximate_knn
from stg_node.splat import edge_ops

pytestmark = pytest.mark.usefixtures("cpu_kernels")  # skips where the kernels cannot build


def graph_case(n=600, seed=0):
    """Canonical points on a noisy sphere, posed by a random rotation, a bend and noise, with a
    k-NN graph of the canonical points (edges both ways and repeated, as an index would give)."""
    gen = torch.Generator().manual_seed(seed)
    c = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    c = c / c.norm(dim=1, keepdim=True) * (1 + 0.05 * torch.rand(n, 1, generator=gen, dtype=torch.float64))
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=torch.float64))
    x = c @ q.T + 0.3 * c[:, :1] ** 2 + 0.01 * torch.randn(n, 3, generator=gen, dtype=torch.float64)
    nbrs = approximate_knn(c.float(), 6)
    a = torch.arange(n)[:, None].expand_as(nbrs).reshape(-1)
    return x, c, a, nbrs.reshape(-1)


def kernel_value_and_grads(x, c, a, b):
    xl = x.detach().float().requires_grad_(True)
    cl = c.detach().float().requires_grad_(True)
    value = edge_ops.edge_length_loss(xl, cl, a, b)
    (3.0 * value).backward()
    return value.detach().double(), xl.grad.double(), cl.grad.double()


def oracle_value_and_grads(x, c, a, b):
    xl = x.detach().double().requires_grad_(True)
    cl = c.detach().double().requires_grad_(True)
    value = edge_ops.edge_length_loss_torch(xl, cl, a, b)
    (3.0 * value).backward()
    return value.detach(), xl.grad, cl.grad


def test_the_kernel_takes_float32_cpu_points_only():
    x, c, _, _ = graph_case(20)
    assert edge_ops.edge_kernel_applies(x.float(), c.float())
    assert not edge_ops.edge_kernel_applies(x, c)  # float64: the torch reference


@pytest.mark.parametrize("seed", [0, 1])
def test_values_and_gradients_match_float64_autograd(seed):
    x, c, a, b = graph_case(seed=seed)
    value, gx, gc = kernel_value_and_grads(x, c, a, b)
    ref_value, ref_gx, ref_gc = oracle_value_and_grads(x, c, a, b)
    assert value.item() == pytest.approx(ref_value.item(), rel=1e-5)
    scale = ref_gx.abs().max()
    torch.testing.assert_close(gx, ref_gx, atol=1e-5 * scale, rtol=1e-4)
    torch.testing.assert_close(gc, ref_gc, atol=1e-5 * scale, rtol=1e-4)
    assert gc.abs().sum() > 0 and gx.abs().sum() > 0


def test_a_rigid_motion_costs_nothing_and_a_stretch_costs_its_length():
    """Closed form: a rotated and translated copy keeps every length (loss 0); scaled by s, each
    edge contributes (s - 1) |c_a - c_b|, and the gradient of x_a is along the edge."""
    x, c, a, b = graph_case(200)
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64))
    moved = c @ q.T + torch.tensor([0.5, -1.0, 2.0], dtype=torch.float64)
    assert edge_ops.edge_length_loss(moved.float(), c.float(), a, b).item() == pytest.approx(0.0, abs=1e-6)
    s = 1.5
    expected = ((s - 1.0) * (c[a] - c[b]).norm(dim=1)).mean().item()
    assert edge_ops.edge_length_loss((s * c).float(), c.float(), a, b).item() == pytest.approx(
        expected, rel=1e-5
    )
    # one edge: d/dx_a = (x_a - x_b) / |x_a - x_b| when stretched, the opposite for x_b
    two = torch.tensor([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]], requires_grad=True)
    canon = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    edge_ops.edge_length_loss(two, canon, torch.tensor([0]), torch.tensor([1])).backward()
    torch.testing.assert_close(two.grad, torch.tensor([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]))


def test_zero_lengths_and_ties_have_torchs_zero_gradient():
    """Coincident points (a zero length) and edges whose lengths agree exactly: gradient 0 there,
    as autograd through norm and abs gives."""
    x = torch.tensor(
        [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 3.0, 0.0]], dtype=torch.float64
    )
    c = torch.tensor(
        [[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 3.0, 0.0]], dtype=torch.float64
    )
    a, b = torch.tensor([0, 0, 2, 3]), torch.tensor([1, 2, 0, 3])
    value, gx, gc = kernel_value_and_grads(x, c, a, b)
    ref_value, ref_gx, ref_gc = oracle_value_and_grads(x, c, a, b)
    assert value.item() == pytest.approx(ref_value.item())
    torch.testing.assert_close(gx, ref_gx)
    torch.testing.assert_close(gc, ref_gc)


def test_only_the_wanted_gradient_is_made():
    x, c, a, b = graph_case(100)
    xl = x.float().requires_grad_(True)
    edge_ops.edge_length_loss(xl, c.float(), a, b).backward()
    _, ref_gx, _ = oracle_value_and_grads(x, c, a, b)
    torch.testing.assert_close(3.0 * xl.grad.double(), ref_gx, atol=1e-6, rtol=1e-4)


def test_no_edges_is_zero_and_bad_input_is_refused():
    x, c, a, b = graph_case(50)
    empty = torch.zeros(0, dtype=torch.int64)
    assert edge_ops.edge_length_loss(x.float(), c.float(), empty, empty).item() == 0.0
    with pytest.raises(ValueError, match=r"\(M, 3\)"):
        edge_ops.edge_length_loss(x.float()[:, :2], c.float()[:, :2], a, b)
    with pytest.raises(ValueError, match="edge ends"):
        edge_ops.edge_length_loss(x.float(), c.float(), a, b[:-1])
    with pytest.raises(RuntimeError, match="must index the 50 points"):
        edge_ops.edge_length_loss(x.float(), c.float(), a, b + 50)


def test_the_isometry_term_takes_the_kernel_and_matches_its_torch_path():
    """IsometryGraph.loss on a table: the kernel (auto) and the reference (kernels.reference())
    give the same value and gradients, posed rows a subset of the table (an index) included."""
    from stg_node.avatar import kernels
    from stg_node.avatar.isometry import IsometryGraph

    x, c, _, _ = graph_case(300)

    class Table:  # what IsometryGraph reads of a GaussianTable
        num, version = 300, 0

        def __getitem__(self, name):
            return c.float()

    table, graph = Table(), IsometryGraph()
    index = torch.arange(0, 300, 2)
    results = []
    for reference in (False, True):
        xl = x[index].float().requires_grad_(True)
        cl = c[index].float().requires_grad_(True)
        with kernels.reference() if reference else torch.enable_grad():
            loss = graph.loss(table, xl, cl, index)
        loss.backward()
        assert ("EdgeLength" in type(loss.grad_fn.next_functions[0][0]).__name__) != reference
        results.append((loss.detach(), xl.grad, cl.grad))
    (v1, gx1, gc1), (v2, gx2, gc2) = results
    assert v1.item() == pytest.approx(v2.item(), rel=1e-5) and v1.item() > 0
    torch.testing.assert_close(gx1, gx2, rtol=1e-4, atol=1e-6 * gx2.abs().max().item())
    torch.testing.assert_close(gc1, gc2, rtol=1e-4, atol=1e-6 * gc2.abs().max().item())


def test_the_isometry_term_keeps_exactly_the_edges_between_posed_rows():
    """The table-row edges mapped to posed rows (an unordered, partial index): the same loss as
    the edges picked one by one in Python, both ends posed, in the graph's order."""
    from stg_node.avatar.isometry import IsometryGraph

    x, c, _, _ = graph_case(300)

    class Table:
        num, version = 300, 0

        def __getitem__(self, name):
            return c.float()

    graph = IsometryGraph()
    index = torch.randperm(300, generator=torch.Generator().manual_seed(2))[:170]
    graph.loss(Table(), x[index].float(), c[index].float(), index)  # builds the graph
    a, b = graph.edges()
    where = {int(row): i for i, row in enumerate(index)}
    kept = [
        (where[int(i)], where[int(j)])
        for i, j in zip(a, b, strict=True)
        if int(i) in where and int(j) in where
    ]
    assert 0 < len(kept) < a.numel()
    ea, eb = (torch.tensor(col) for col in zip(*kept, strict=True))
    xl, cl = x[index].float(), c[index].float()
    want = 100.0 * edge_ops.edge_length_loss_torch(xl, cl, ea, eb)
    torch.testing.assert_close(graph.loss(Table(), xl, cl, index), want, rtol=1e-5, atol=0)
