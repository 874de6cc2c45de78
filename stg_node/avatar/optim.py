"""Adam over the Gaussian table's columns (one parameter group each) and the dense modules, with
row surgery: when densification appends or removes Gaussians, every column *and* its Adam
moments change together (new rows start with zero moments), as gsplat's strategies do.

Also owns the learning-rate schedule and the proximal L1 step that drives motion coefficients
to exactly zero.
"""

from __future__ import annotations

import logging
import math

import torch
from torch import nn

from stg_node.avatar.gaussians import GaussianTable
from stg_node.splat.build import kernels_take, load_kernels

log = logging.getLogger(__name__)


def _fusable(groups) -> bool | None:
    """torch's fused Adam (one kernel per parameter instead of a dozen ops: about 5x faster on a
    CPU table) where it runs: floating-point CPU or CUDA tensors; else None (torch's default)."""
    params = [p for g in groups for p in g["params"]]
    ok = params and all(p.is_floating_point() and p.device.type in ("cpu", "cuda") for p in params)
    return True if ok else None


# Set once the private op refuses its arguments (another torch): never tried again in this process.
_FUSED_CALL = {"broken": False}


def _fused_adam_step(adam: torch.optim.Adam) -> bool:
    """One step of a fused ``adam`` straight through ``torch._fused_adam_``, one call per group and
    one step-count increment for all of them; False (nothing done) where that is not exactly what
    ``adam.step()`` would do (a parameter without state yet, options the call does not take,
    mixed devices or dtypes, a torch without the op or whose op takes other arguments: the
    process then keeps to ``adam.step()``): the caller then runs ``adam.step()``.

    The same kernel on the same state as torch's fused path (bit-identical), without its per-group
    Python (state lookups, grouping by device and dtype, profiling and grad-mode wrappers): ~0.4 ms
    of a 20k-Gaussian training step on a CPU with its dozen parameter groups.
    """
    work = []
    for group in adam.param_groups:
        if not group.get("fused") or group["amsgrad"] or group["maximize"] or group["differentiable"]:
            return False
        if group.get("decoupled_weight_decay", False) or torch.is_tensor(group["lr"]):
            return False
        params = [p for p in group["params"] if p.grad is not None]
        if not params:
            continue
        states = [adam.state.get(p) for p in params]
        if not all(states):
            return False
        first = params[0]
        if any(p.device != first.device or p.dtype != first.dtype or p.grad.is_sparse for p in params):
            return False
        work.append((group, params, states))
    if not work:
        return True
    if _FUSED_CALL["broken"] or not hasattr(torch, "_fused_adam_"):
        return False
    steps = [s["step"] for _, _, states in work for s in states]
    torch._foreach_add_(steps, 1)
    for number, (group, params, states) in enumerate(work):
        beta1, beta2 = group["betas"]
        try:
            _call_fused_adam(group, params, states, beta1, beta2)
        except (TypeError, RuntimeError) as error:
            if number > 0:  # groups already stepped: nothing to hand back
                raise
            # A torch whose private op takes other arguments: undo the count, and leave this
            # and every later step to torch's public Adam.step (the same update, ~0.4 ms slower).
            torch._foreach_sub_(steps, 1)
            _FUSED_CALL["broken"] = True
            log.warning("torch._fused_adam_ refused the call (%s): using Adam.step", error)
            return False
    return True


def _call_fused_adam(group, params, states, beta1, beta2) -> None:
    torch._fused_adam_(
        params,
        [p.grad for p in params],
        [s["exp_avg"] for s in states],
        [s["exp_avg_sq"] for s in states],
        [],
        [s["step"] for s in states],
        amsgrad=False,
        lr=group["lr"],
        beta1=beta1,
        beta2=beta2,
        weight_decay=group["weight_decay"],
        eps=group["eps"],
        maximize=False,
        grad_scale=None,
        found_inf=None,
    )


def all_finite(tensors: list[torch.Tensor]) -> bool:
    """Whether every element of every tensor is finite: one read-only C++ pass over float32 CPU
    tensors (the exponent bits), else three batched torch ops over all of them (one test per
    tensor cost ~3 ms a step): ``g * 0`` is 0 where ``g`` is finite and NaN where it is not, and a
    sum of squares of zeros stays 0 exactly."""
    if not tensors:
        return True
    if all(t.is_contiguous() for t in tensors) and kernels_take(*tensors):
        return bool(load_kernels().ops.all_finite(tensors))
    zeros = torch._foreach_mul(tensors, 0.0)
    return bool(torch.stack(torch._foreach_norm(zeros)).sum() == 0)


class TableOptimizer:
    """One torch Adam for the table (a group per column) and one for dense modules (MLP, pose)."""

    def __init__(self, table: GaussianTable, lrs: dict[str, float], dense: dict[str, tuple[list, float]]):
        self.table = table
        self.base_lrs = dict(lrs)
        groups = []
        for name in table.trainable_names():
            lr = lrs.get(name, 0.0)
            groups.append({"params": [table[name]], "lr": lr, "name": name})
        self.adam = torch.optim.Adam(groups, lr=0.0, eps=1e-15, fused=_fusable(groups))
        dense_groups = []
        for name, (params, lr) in dense.items():
            params = [p for p in params if p.requires_grad]
            if params:
                dense_groups.append({"params": params, "lr": lr, "name": name})
                self.base_lrs[name] = lr
        self.dense = None
        if dense_groups:
            self.dense = torch.optim.Adam(dense_groups, lr=0.0, eps=1e-15, fused=_fusable(dense_groups))

    def groups(self):
        yield from self.adam.param_groups
        if self.dense is not None:
            yield from self.dense.param_groups

    def zero_grad(self) -> None:
        self.adam.zero_grad(set_to_none=True)
        if self.dense is not None:
            self.dense.zero_grad(set_to_none=True)

    def step(self) -> None:
        for adam in (self.adam, self.dense):
            if adam is not None and not _fused_adam_step(adam):
                adam.step()

    def set_schedule(
        self, progress: float, means_final: float, others_final: float, boost: dict[str, float] | None = None
    ) -> None:
        """Exponential decay of the means' rate to ``means_final`` x; cosine of the rest to
        ``others_final`` x; a group named in ``boost`` gets that factor on top."""
        p = min(max(progress, 0.0), 1.0)
        cosine = others_final + (1 - others_final) * 0.5 * (1 + math.cos(math.pi * p))
        boost = boost or {}
        for group in self.groups():
            base = self.base_lrs.get(group["name"], 0.0)
            factor = means_final**p if group["name"] == "means" else cosine
            group["lr"] = base * factor * boost.get(group["name"], 1.0)

    def lr(self, name: str) -> float:
        for group in self.groups():
            if group["name"] == name:
                return float(group["lr"])
        return 0.0

    # --- row surgery ---------------------------------------------------------------------------
    def _replace(self, name: str, new: torch.Tensor, state_fn) -> None:
        old = self.table[name]
        param = nn.Parameter(new.detach().clone(), requires_grad=True)
        for group in self.adam.param_groups:
            if group["params"][0] is old:
                state = self.adam.state.pop(old, None)
                group["params"][0] = param
                if state:
                    self.adam.state[param] = {
                        k: (state_fn(v) if torch.is_tensor(v) and v.dim() > 0 else v)
                        for k, v in state.items()
                    }
                break
        self.table.params[name] = param
        self.table.rows_changed()

    def append(self, rows: dict[str, torch.Tensor]) -> None:
        """Append rows (every column must be given) with zero Adam moments."""
        missing = set(self.table.names()) - set(rows)
        if missing:
            raise ValueError(f"append() needs every column; missing {sorted(missing)}")
        n_new = next(iter(rows.values())).shape[0]
        if n_new == 0:
            return
        for name in self.table.names():
            cur = self.table[name]
            new = torch.cat([cur.detach(), rows[name].to(cur.dtype)], dim=0)
            if name in self.table.trainable_names():
                self._replace(
                    name, new, lambda v, n=n_new: torch.cat([v, v.new_zeros((n,) + v.shape[1:])], dim=0)
                )
            else:
                self.table.set_column(name, new)

    def keep(self, mask: torch.Tensor) -> None:
        """Keep the rows where ``mask`` is true (pruning)."""
        if bool(mask.all()):
            return
        for name in self.table.names():
            cur = self.table[name]
            if name in self.table.trainable_names():
                self._replace(name, cur.detach()[mask], lambda v: v[mask])
            else:
                self.table.set_column(name, cur.detach()[mask])

    @torch.no_grad()
    def freeze_rows(self, name: str, rows: torch.Tensor) -> None:
        """Zero this step's gradient of ``rows`` of a column: with zero moments they stay exactly put."""
        if name not in self.table or self.table[name].grad is None:
            return
        grad = self.table[name].grad
        if rows.dtype == torch.bool:  # a mask: one pass, where indexing by it gathers its rows first
            grad.masked_fill_(rows.reshape(-1, *([1] * (grad.dim() - 1))), 0)
        else:
            grad[rows] = 0

    # --- proximal L1 ---------------------------------------------------------------------------
    @torch.no_grad()
    def soft_threshold(self, name: str, strength: float) -> None:
        """``x <- sign(x) max(|x| - lr * strength, 0)``: the proximal step of an L1 penalty; exact zeros.

        With Adam every coefficient moves by about ``lr`` per step when its gradient keeps one sign
        and much less when the gradient is noise, so ``strength`` < 1 zeroes the coefficients whose
        gradient has no consistent direction (static regions) and spares the rest.
        """
        if name not in self.table or strength <= 0:
            return
        param = self.table[name]
        thr = self.lr(name) * strength
        # x - clamp(x, -thr, thr) is sign(x) max(|x| - thr, 0) (to the sign of a zero) in two passes
        param.sub_(param.clamp(-thr, thr))

    @torch.no_grad()
    def zero_rows(self, name: str, rows: torch.Tensor) -> None:
        """Set ``rows`` of a column and its Adam moments to zero."""
        param = self.table[name]
        param[rows] = 0
        state = self.adam.state.get(param)
        if state:
            for key in ("exp_avg", "exp_avg_sq"):
                if key in state:
                    state[key][rows] = 0

    # --- state for checkpoints -----------------------------------------------------------------
    def table_state(self) -> dict[str, dict[str, torch.Tensor]]:
        out = {}
        for group in self.adam.param_groups:
            state = self.adam.state.get(group["params"][0])
            if state:
                out[group["name"]] = state
        return out

    def load_table_state(self, states: dict[str, dict[str, torch.Tensor]]) -> None:
        for group in self.adam.param_groups:
            s = states.get(group["name"])
            if s is not None:
                p = group["params"][0]
                self.adam.state[p] = {k: v.to(p.device) for k, v in s.items()}

    @torch.no_grad()
    def replace_dense(self, old: torch.Tensor, new: nn.Parameter) -> None:
        """Put ``new`` (grown along any dimension) in ``old``'s place; its Adam moments keep the old
        values where ``old`` had them and start at zero in the new part."""

        def grow(value: torch.Tensor) -> torch.Tensor:
            padded = value.new_zeros(new.shape)
            padded[tuple(slice(0, n) for n in old.shape)] = value
            return padded

        self._swap_dense(old, new, grow)

    @torch.no_grad()
    def select_dense(self, old: torch.Tensor, new: nn.Parameter, dim: int, index: torch.Tensor) -> None:
        """Put ``new`` (``old.index_select(dim, index)``, zero-padded along ``dim`` where ``new`` is
        longer) in ``old``'s place; its Adam moments are sliced and padded the same way (the kept
        entries keep theirs: a window moving over a stream)."""

        def select(value: torch.Tensor) -> torch.Tensor:
            chosen = value.index_select(dim, index.to(value.device))
            out = chosen.new_zeros(new.shape)
            out.narrow(dim, 0, chosen.shape[dim]).copy_(chosen)
            return out

        self._swap_dense(old, new, select)

    def _swap_dense(self, old: torch.Tensor, new: nn.Parameter, moments) -> None:
        """``new`` in ``old``'s place in the dense optimizer; ``moments`` maps each of ``old``'s
        per-element Adam tensors to ``new``'s shape (scalars such as the step are kept)."""
        if self.dense is None:
            return
        for group in self.dense.param_groups:
            for i, p in enumerate(group["params"]):
                if p is not old:
                    continue
                group["params"][i] = new
                state = self.dense.state.pop(old, None)
                if state:
                    self.dense.state[new] = {
                        key: moments(value) if torch.is_tensor(value) and value.shape == old.shape else value
                        for key, value in state.items()
                    }
                return

    def dense_state(self) -> dict[str, dict[str, torch.Tensor]]:
        """Adam state of the dense modules, keyed ``"<group>.<i>"`` (i: the parameter's place in it)."""
        out = {}
        if self.dense is not None:
            for group in self.dense.param_groups:
                for i, p in enumerate(group["params"]):
                    state = self.dense.state.get(p)
                    if state:
                        out[f"{group['name']}.{i}"] = state
        return out

    def load_dense_state(self, states: dict[str, dict[str, torch.Tensor]]) -> None:
        if self.dense is None:
            return
        for group in self.dense.param_groups:
            for i, p in enumerate(group["params"]):
                s = states.get(f"{group['name']}.{i}")
                if s is not None:
                    self.dense.state[p] = {k: v.to(p.device) for k, v in s.items()}
