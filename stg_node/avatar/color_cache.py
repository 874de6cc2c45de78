"""Per-Gaussian colours carried from frame to frame of a live stream, recomputed in turns.

The colour MLP's output moves slowly with the pose and the view: between two frames of a 30 fps
stream a Gaussian's colour changes by a fraction of a grey level, yet evaluating the network for
every Gaussian costs about as much as the rest of the pose. A :class:`ColorCache` (one per stream:
one camera following one body) recomputes the colour of every ``refresh_every``-th Gaussian per
frame, in turn (row r when ``r % refresh_every`` equals the frame's turn), and keeps the others'
colours from their last evaluation, so no colour is more than ``refresh_every - 1`` frames old.
Rows never evaluated yet (a new snapshot, rows that were culled until now) are always
evaluated. ``refresh_every=1`` evaluates every row every frame (the exact render).

The renderer keeps one cache per stream (AvatarRenderer.render(..., stream=...)); a one-shot
render has none and is always exact. The cache belongs to one model: a different model, a
different table size or SH degree starts it afresh.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch


class ColorCache:
    def __init__(self, refresh_every: int = 2):
        if int(refresh_every) < 1:
            raise ValueError(f"refresh_every must be >= 1, got {refresh_every}")
        self.refresh_every = int(refresh_every)
        self.frame = 0
        self._key: tuple | None = None
        self._colors: torch.Tensor | None = None  # (table rows, C)
        self._known: torch.Tensor | None = None  # (table rows,) bool: evaluated at least once
        self.evaluated = 0  # rows evaluated in the last call (for tests and benchmarks)

    def reset(self) -> None:
        self._key = self._colors = self._known = None

    def colors(
        self,
        evaluate: Callable[[torch.Tensor | None], torch.Tensor],
        rows: torch.Tensor | None,
        num_rows: int,
        key: tuple,
    ) -> torch.Tensor:
        """Colours of the rendered rows: ``rows`` (M,) are their table rows (None: every row, in
        order); ``evaluate(sel)`` returns the colours of the rendered rows at positions ``sel``
        (None: all of them). ``key`` names what the colours belong to (the model, the SH degree):
        a new key starts afresh."""
        key = (*key, int(num_rows))
        if key != self._key or self._colors is None:
            self.reset()
            self._key = key
        turn = self.frame % self.refresh_every
        self.frame += 1
        if self.refresh_every == 1 or self._colors is None:
            fresh = evaluate(None)
            self.evaluated = fresh.shape[0]
            if self.refresh_every > 1:
                self._colors = fresh.new_zeros((num_rows, fresh.shape[1]))
                self._known = torch.zeros(num_rows, dtype=torch.bool, device=fresh.device)
                ids = torch.arange(num_rows, device=fresh.device) if rows is None else rows
                self._colors[ids] = fresh
                self._known[ids] = True
            return fresh
        if rows is None and bool(self._known.all()):  # every row, all seen: this turn's slice
            sel = torch.arange(turn, num_rows, self.refresh_every, device=self._colors.device)
            self.evaluated = int(sel.numel())
            if self.evaluated:
                self._colors[turn :: self.refresh_every] = evaluate(sel).to(self._colors.dtype)
            return self._colors
        ids = torch.arange(num_rows, device=self._colors.device) if rows is None else rows
        due = (ids % self.refresh_every == turn) | ~self._known[ids]
        sel = due.nonzero().squeeze(1)
        self.evaluated = int(sel.numel())
        if self.evaluated:
            fresh = evaluate(sel)
            target = ids[sel]
            self._colors[target] = fresh.to(self._colors.dtype)
            self._known[target] = True
        return self._colors[ids]


class _Refreshed(torch.autograd.Function):
    """``carried`` (no graph) with its rows ``sel`` replaced by ``fresh``, whose gradient is ``scale``
    times theirs: one node where an out-of-place ``index_put`` of ``fresh`` behind a gradient-scaling
    node made two (and ``index_put``'s backward built a masked copy of the whole gradient for the
    carried rows, which take none). The same values and gradient to the bit."""

    @staticmethod
    def forward(ctx, carried, sel, fresh, scale):
        ctx.save_for_backward(sel)
        ctx.scale = scale
        return carried.index_copy(0, sel, fresh)

    @staticmethod
    def backward(ctx, grad):
        (sel,) = ctx.saved_tensors
        return None, None, grad.index_select(0, sel) * ctx.scale, None


class TrainingColorTurns:
    """The colour MLP in turns during training (issue 24; ``TrainConfig.color_every``).

    A step evaluates the network, with its gradient, for the rows whose turn it is (table row r on
    step ``it`` when ``r % every == it % every``) and for rows never evaluated; every other row
    keeps its colour from its last evaluation, as a constant. The fresh rows' gradient is taken
    ``every`` times (the value is unchanged), so each network weight and each row's feature get in
    expectation the gradient they would get from the full evaluation. Colours are carried only
    while the rows are the same rows: a change of the table (densification, a restore), of the
    SH degree, or :meth:`reset` starts a full evaluation. The carried colours are checkpointed
    (:meth:`state_arrays`), so a resumed run makes the same steps as one that never stopped.
    ``every=1`` is the exact step (every row every step)."""

    def __init__(self, every: int):
        if int(every) < 1:
            raise ValueError(f"color_every must be >= 1, got {every}")
        self.every = int(every)
        self._key: tuple | None = None
        self._colors: torch.Tensor | None = None  # (table rows, 3), no graph
        self._known: torch.Tensor | None = None  # (table rows,) bool
        self._restored: tuple[int, int] | None = None
        self.evaluated = 0  # rows evaluated by the last call (tests, benchmarks)

    def reset(self) -> None:
        self._key = self._colors = self._known = None
        self._restored: tuple[int, int] | None = None  # (SH degree, rows) of restored colours

    def state_arrays(self) -> dict[str, np.ndarray]:
        """The carried colours for a checkpoint (float32 as they are: exact), or {} with none."""
        if self._colors is None:
            return {}
        return {
            "colors": self._colors.cpu().numpy(),
            "known": self._known.cpu().numpy().astype(np.float32),
            "degree": np.asarray([self._key[1]], np.float32),
        }

    def load_state_arrays(self, arrays: dict[str, np.ndarray], device) -> None:
        """From :meth:`state_arrays`: carried again from the first step on the same rows and SH
        degree (a checkpoint written without them starts with a full evaluation)."""
        self.reset()
        if "colors" not in arrays:
            return
        colors = np.array(arrays["colors"], np.float32)  # a copy: the checkpoint's arrays are read-only
        self._colors = torch.from_numpy(colors.reshape(colors.shape[0], -1)).to(device)
        self._known = torch.as_tensor(np.asarray(arrays["known"]) > 0.5, device=device)
        self._restored = (int(np.asarray(arrays["degree"]).reshape(-1)[0]), colors.shape[0])

    def colors(
        self,
        evaluate: Callable[[torch.Tensor | None], torch.Tensor],
        rows: torch.Tensor | None,
        num_rows: int,
        iteration: int,
        key: tuple,
    ) -> torch.Tensor:
        """Colours of the rendered rows (``rows`` (M,): their table rows, None: every row in order)
        at step ``iteration``; ``evaluate(sel)`` is the network on the rendered rows at positions
        ``sel`` (None: all), with its graph. ``key`` (model, SH degree, table version) names the
        rows and what the colours are of."""
        key = (*key, int(num_rows))
        if self._restored is not None:  # the model and table are new objects: the same rows?
            if self._restored == (key[1], key[-1]):
                self._key = key
            self._restored = None
        if self.every == 1 or key != self._key or self._colors is None:
            fresh = evaluate(None)
            self.evaluated = fresh.shape[0]
            if self.every > 1:
                self._key = key
                self._colors = fresh.new_zeros((num_rows, fresh.shape[1]))
                self._known = torch.zeros(num_rows, dtype=torch.bool, device=fresh.device)
                ids = slice(None) if rows is None else rows
                self._colors[ids] = fresh.detach()
                self._known[ids] = True
            return fresh
        ids = torch.arange(num_rows, device=self._colors.device) if rows is None else rows
        due = (ids % self.every == iteration % self.every) | ~self._known[ids]
        sel = due.nonzero().squeeze(1)
        self.evaluated = int(sel.numel())
        carried = self._colors.index_select(0, ids)  # a gather: its own tensor, no graph
        if self.evaluated == 0:
            return carried
        fresh = evaluate(sel)
        target = ids[sel]
        # index_copy_ / index_fill_: the same writes as an advanced-index assignment (distinct rows),
        # without index_put's general indexing machinery
        self._colors.index_copy_(0, target, fresh.detach().to(self._colors.dtype))
        self._known.index_fill_(0, target, True)
        return _Refreshed.apply(carried, sel, fresh, float(self.every))
