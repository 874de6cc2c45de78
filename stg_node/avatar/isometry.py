"""As-isometric-as-possible: Gaussians that are neighbours in canonical space keep their distances
when posed.

Skinning moves a Gaussian with the blend of its bones. Neighbours with the same blend move as one
rigid piece; neighbours whose learned weights differ (or whose non-rigid offsets do) drift apart
or through each other under poses the training clip never showed: gaps, and splats dragged
across the body. This term (3DGS-Avatar's as-isometric-as-possible regulariser on the centres)
asks every Gaussian's posed distance to its ``k`` canonical neighbours to stay its canonical
distance, in the training poses it sees:

    L_iso = mean_ij | |x_i(pose) - x_j(pose)| - |c_i - c_j| |        (cm)

over the graph's undirected edges (a pair that are each other's neighbours counts once), with
``c`` the canonical centres including the spacetime offsets (what is skinned), so the term
constrains the skinning, not the non-rigid motion (rigidity.py does that).

Neighbours: an approximate k-nearest-neighbour graph of the canonical centres, rebuilt when the
table's rows change (densification) and saved in checkpoints (a run resumed between two
rebuilds must keep the graph it had, or it would not continue exactly). Exact k-NN over 30k
points costs seconds per rebuild on a CPU (a dense distance matrix); here the points are sorted
along a Morton (z-order) curve, twice, the second time on a grid shifted by half a cell so the
curve's seams fall elsewhere, and each point's ``k`` nearest are chosen among its ``WINDOW``
predecessors and successors in either order: for points on a surface, about three quarters are
the true nearest and the rest nearly as near (tested), at a fraction of the cost.
"""

from __future__ import annotations

import weakref

import torch

from stg_node.avatar import kernels
from stg_node.splat.edge_ops import edge_length_loss, edge_length_loss_torch

K_NEIGHBOURS = 8
WINDOW = 16  # candidates on each side along each curve
GRID_BITS = 10  # Morton grid of 2^10 cells per axis over the points' box


def _spread_bits(v: torch.Tensor) -> torch.Tensor:
    """Insert two zero bits between each of the low 10 bits of ``v`` (int64): Morton interleaving."""
    v = v & 0x3FF
    v = (v | (v << 16)) & 0x030000FF
    v = (v | (v << 8)) & 0x0300F00F
    v = (v | (v << 4)) & 0x030C30C3
    v = (v | (v << 2)) & 0x09249249
    return v


def morton_order(points: torch.Tensor, shift: float = 0.0) -> torch.Tensor:
    """Indices sorting ``points`` (N, 3) along a Morton curve on a 2^10 grid over their box,
    shifted by ``shift`` cells."""
    lo = points.min(dim=0).values
    span = (points.max(dim=0).values - lo).max().clamp_min(1e-9)
    cells = (1 << GRID_BITS) - 1
    q = ((points - lo) / span * (cells - 1) + shift).floor().clamp(0, cells).to(torch.int64)
    code = _spread_bits(q[:, 0]) | (_spread_bits(q[:, 1]) << 1) | (_spread_bits(q[:, 2]) << 2)
    return torch.argsort(code)


@torch.no_grad()
def approximate_knn(points: torch.Tensor, k: int = K_NEIGHBOURS, window: int = WINDOW) -> torch.Tensor:
    """(N, k) indices of (approximately) the ``k`` nearest other points of each of ``points`` (N, 3)."""
    n = points.shape[0]
    k = min(k, n - 1)
    if k < 1:
        return torch.zeros(n, 0, dtype=torch.int64, device=points.device)
    offsets = torch.cat([torch.arange(-window, 0), torch.arange(1, window + 1)]).to(points.device)
    candidates = []
    for shift in (0.0, 0.5):
        order = morton_order(points, shift)
        rank = torch.empty_like(order)
        rank[order] = torch.arange(n, device=points.device)
        pos = (rank[:, None] + offsets[None, :]).clamp(0, n - 1)  # (N, 2w) positions along the curve
        candidates.append(order[pos])
    cand = torch.cat(candidates, dim=1)  # (N, 4w); may repeat a point or hold the point itself
    dist = (points[cand] - points[:, None]).norm(dim=-1)
    dist = torch.where(cand == torch.arange(n, device=points.device)[:, None], float("inf"), dist)
    # Duplicates: keep the first of equal candidates (sort by index, mask repeats).
    cand_sorted, perm = cand.sort(dim=1)
    dist_sorted = dist.gather(1, perm)
    repeat = torch.zeros_like(cand_sorted, dtype=torch.bool)
    repeat[:, 1:] = cand_sorted[:, 1:] == cand_sorted[:, :-1]
    dist_sorted = torch.where(repeat, float("inf"), dist_sorted)
    best = dist_sorted.topk(k, dim=1, largest=False).indices
    return cand_sorted.gather(1, best)


class IsometryGraph:
    """The canonical neighbour graph and the isometry loss over it (see module docstring)."""

    def __init__(self, k: int = K_NEIGHBOURS):
        self.k = k
        self.neighbours: torch.Tensor | None = None  # (N, k) rows of the table
        self._table = None  # weak reference to the table the graph was built for
        self._version = -1  # ... and its version (bumped by every row edit) then
        self._edges: tuple | None = None  # (neighbours, (E,) rows a, (E,) rows b): see edges()

    def _built_for(self, table) -> None:
        self._table, self._version = weakref.ref(table), table.version

    def _stale(self, table) -> bool:
        # The table by identity (a weak reference: never an id() that a new object may reuse, as
        # the means column replaced by a prune and an append of as many rows may), its rows by version.
        built_for = self._table() if self._table is not None else None
        if built_for is table and table.version == self._version:
            return False
        self._built_for(table)
        return True

    def state_arrays(self, table=None) -> dict[str, torch.Tensor]:
        """What a checkpoint keeps: the graph (as float32, exact for row indices below 2^24); none
        when ``table``'s rows changed since it was built (densification between two steps that
        evaluate the term, ``loss.isometry_every``): the resumed run rebuilds it where this one will."""
        built_for = self._table() if self._table is not None else None
        if self.neighbours is None or (
            table is not None and (built_for is not table or table.version != self._version)
        ):
            return {}
        return {"neighbours": self.neighbours.float()}

    def load_state_arrays(self, arrays: dict[str, torch.Tensor], table) -> None:
        """Take the graph of a checkpoint as the one of ``table`` (rows unchanged since it was saved)."""
        if "neighbours" in arrays and arrays["neighbours"].shape[0] == table.num:
            self.neighbours = arrays["neighbours"].round().long().to(table["means"].device)
            self._built_for(table)

    def loss(self, table, means: torch.Tensor, canonical: torch.Tensor, index: torch.Tensor | None):
        """L_iso over the posed ``means`` (M, 3) of the table rows ``index`` (None: all rows), whose
        canonical centres (offsets included) are ``canonical`` (M, 3); edges to rows not posed are
        left out."""
        if self._stale(table):
            self.neighbours = approximate_knn(table["means"].detach(), self.k)
        a, b = self.edges()
        if a.numel() == 0:
            return means.new_zeros(())
        if index is not None:
            # index_copy / index_select / nonzero: the same edges in the same order as advanced and
            # boolean indexing, at under half their cost on a CPU (~1.4 -> ~0.6 ms a step, 96k edges)
            pos = torch.full((table.num,), -1, dtype=torch.int64, device=means.device)
            pos.index_copy_(0, index.long(), torch.arange(index.shape[0], device=means.device))
            a, b = pos.index_select(0, a), pos.index_select(0, b)
            valid = torch.minimum(a, b) >= 0
            if not bool(valid.all()):
                keep = valid.nonzero().squeeze(1)
                if keep.numel() == 0:
                    return means.new_zeros(())
                a, b = a.index_select(0, keep), b.index_select(0, keep)
        canonical = canonical.to(means.dtype)
        if not kernels.use_kernels(means, canonical):  # other devices, float64, or switched off
            return 100.0 * edge_length_loss_torch(means, canonical, a, b)
        return 100.0 * edge_length_loss(means, canonical, a, b)  # one pass over the edges each way

    def edges(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The graph's undirected edges as table rows (a, b), a < b, each pair once (two points that
        are each other's neighbours count once), computed once per graph."""
        nbrs = self.neighbours
        if self._edges is not None and self._edges[0] is nbrs:
            return self._edges[1], self._edges[2]
        if nbrs is None or nbrs.shape[1] == 0:
            empty = torch.zeros(0, dtype=torch.int64)
            a = b = empty if nbrs is None else empty.to(nbrs.device)
        else:
            n = nbrs.shape[0]
            rows = torch.arange(n, device=nbrs.device)[:, None].expand_as(nbrs)
            lo, hi = torch.minimum(rows, nbrs).reshape(-1), torch.maximum(rows, nbrs).reshape(-1)
            keys = torch.unique(lo[lo != hi] * n + hi[lo != hi])
            a, b = keys // n, keys % n
        self._edges = (nbrs, a, b)
        return a, b
