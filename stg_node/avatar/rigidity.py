"""Local rigidity of the non-rigid motion: neighbouring Gaussians move together.

From one camera, a Gaussian's spacetime offset is constrained only across the image plane, so
free per-Gaussian offsets can explain the training view with placements no other view agrees
with. Cloth moves as a sheet: this term asks every dynamic Gaussian's offset to match those of
its k nearest neighbours in space-time (static neighbours included, whose offset is zero, so
attachment seams hold), weighted by how present both are at this instant:

    L_rigid = sum_ij w_ij |offset_i(t) - offset_j(t)|_1 / sum_ij w_ij      (cm)

with ``w_ij = sigma_i(t) sigma_j(t)`` (temporal opacities, without gradient). Neighbours are found
in canonical space with the temporal centre as a fourth coordinate (``TIME_METRES`` metres per
time unit), so the copies of a Gaussian on other temporal windows do not count as its neighbours.
The graph is rebuilt whenever the table's rows (its ``version``, bumped by every append, prune
or column replacement) or the set of dynamic Gaussians (the gate, compared in full) change.
"""

from __future__ import annotations

import weakref

import torch

K_NEIGHBOURS = 8
TIME_METRES = 0.5
CHUNK = 2048


class NeighbourGraph:
    def __init__(self, k: int = K_NEIGHBOURS):
        self.k = k
        self.rows: torch.Tensor | None = None  # (D,) dynamic rows
        self.neighbours: torch.Tensor | None = None  # (D, k) rows of the whole table
        self.builds = 0  # how many times the graph was built (tests, profiling)
        self._table = None  # weak reference to the table the graph was built for
        self._version = -1  # ... and its version then
        self._gate: torch.Tensor | None = None  # ... and its gate then

    def _stale(self, table) -> bool:
        # The table is compared by identity (a weak reference: never an id() a new object may
        # reuse), its rows by version; the gate is edited in place (densification), so by value.
        gate = table.motion_gate()
        same_gate = (gate is None and self._gate is None) or (
            gate is not None and self._gate is not None and torch.equal(gate, self._gate)
        )
        built_for = self._table() if self._table is not None else None
        if built_for is table and table.version == self._version and same_gate:
            return False
        self._table, self._version = weakref.ref(table), table.version
        self._gate = None if gate is None else gate.clone()
        return True

    @torch.no_grad()
    def rebuild(self, table) -> None:
        self.builds += 1
        gate = table.motion_gate()
        if gate is None or not bool(gate.any()):
            self.rows = self.neighbours = None
            return
        points = table["means"].detach()
        if "t_center" in table:
            points = torch.cat([points, TIME_METRES * table["t_center"].detach()[:, None]], dim=1)
        rows = gate.nonzero().squeeze(1)
        k = min(self.k, table.num - 1)
        if k < 1:
            self.rows = self.neighbours = None
            return
        found = []
        for start in range(0, rows.numel(), CHUNK):
            q = rows[start : start + CHUNK]
            dist = torch.cdist(points[q], points)
            dist[torch.arange(q.numel()), q] = float("inf")  # not its own neighbour
            found.append(dist.topk(k, largest=False).indices)
        self.rows, self.neighbours = rows, torch.cat(found)

    def loss(self, table, offsets: torch.Tensor, temporal: torch.Tensor | None) -> torch.Tensor:
        if self._stale(table):
            self.rebuild(table)
        if self.rows is None:
            return offsets.new_zeros(())
        diff = 100.0 * (offsets[self.rows][:, None] - offsets[self.neighbours]).abs().sum(-1)  # (D, k) cm
        if temporal is None:
            return diff.mean()
        w = (temporal[self.rows][:, None] * temporal[self.neighbours]).detach()
        return (w * diff).sum() / w.sum().clamp_min(1e-6)
