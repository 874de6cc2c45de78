"""The pure-PyTorch rasterizer: the oracle the fast backends are tested against.

Written for clarity, not speed: projection is a handful of batched tensor expressions and
rasterization evaluates every (pixel, Gaussian) pair that can matter, densely, with autograd
doing the backward. It follows exactly the rules of the C++ kernels (constants.py), but none
of their tricks: no tiles, no hand-written gradients, no division-based transmittance.

Memory stays bounded: pixels are processed in square blocks, each block only looks at the
Gaussians whose screen box overlaps it, and those are taken in depth-ordered chunks of at
most ``TORCH_MAX_PAIRS`` pairs, carrying transmittance from chunk to chunk. With gradients,
each block is checkpointed (recomputed during backward), so the autograd graph never holds
more than one block's pairs.

Projection runs in float64 whatever the input dtype (extreme scales or a centre on the near
plane would overflow float32 covariances); its outputs are cast back to the input dtype, so a
float32 render composites in float32 exactly as the C++ backend does.
"""

from __future__ import annotations

import torch
from torch.utils.checkpoint import checkpoint

from . import constants as K_
from .backend import TwoStageBackend, plane_in_dtype
from .types import AbsGradHolder, Projection, RenderRequest, RenderStats


class _CompensationSqrt(torch.autograd.Function):
    """sqrt(max(x, 0)) with the gradient 0.5 / (sqrt(x) + eps): finite for degenerate Gaussians."""

    @staticmethod
    def forward(ctx, ratio):
        out = ratio.clamp_min(0.0).sqrt()
        ctx.save_for_backward(ratio, out)
        return out

    @staticmethod
    def backward(ctx, grad):
        ratio, out = ctx.saved_tensors
        return torch.where(ratio > 0, grad * 0.5 / (out + K_.COMPENSATION_GRAD_EPS), torch.zeros_like(grad))


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """[N, 4] wxyz (any norm; zero -> identity) -> [N, 3, 3] rotation matrices."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(K_.QUAT_NORM_EPS)
    w, x, y, z = q.unbind(-1)
    rot = torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    )
    return rot.reshape(quats.shape[:-1] + (3, 3))


def project(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    *,
    near_plane: float = K_.NEAR_PLANE,
    far_plane: float = K_.FAR_PLANE,
    eps2d: float = K_.LOW_PASS_EPS2D,
    radius_clip: float = 0.0,
    antialiased: bool = False,
) -> Projection:
    """EWA projection of 3D Gaussians into the image (see the module docstring)."""
    dtype = means.dtype
    work = torch.float64
    m = means.to(work)
    s = scales.to(work)
    o = opacities.to(work)
    vm = viewmat.detach().to(device=means.device, dtype=work)
    Kd = K.detach().to(device=means.device, dtype=work)
    R, t = vm[:3, :3], vm[:3, 3]
    fx, fy, cx, cy = Kd[0, 0], Kd[1, 1], Kd[0, 2], Kd[1, 2]

    rot = quat_to_rotmat(quats.to(work))
    M = rot * s[:, None, :]
    cov = M @ M.transpose(1, 2)
    p = m @ R.T + t
    cov_c = R @ cov @ R.T

    pz = p[:, 2]
    in_depth = (pz >= near_plane) & (pz <= far_plane)
    z = torch.where(in_depth, pz, torch.ones_like(pz))
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    lim_xp = (width - cx) / fx + K_.FRUSTUM_MARGIN * tan_x
    lim_xn = cx / fx + K_.FRUSTUM_MARGIN * tan_x
    lim_yp = (height - cy) / fy + K_.FRUSTUM_MARGIN * tan_y
    lim_yn = cy / fy + K_.FRUSTUM_MARGIN * tan_y
    tx = z * torch.clamp(p[:, 0] / z, min=-lim_xn, max=lim_xp)
    ty = z * torch.clamp(p[:, 1] / z, min=-lim_yn, max=lim_yp)
    zero = torch.zeros_like(z)
    J = torch.stack([fx / z, zero, -fx * tx / (z * z), zero, fy / z, -fy * ty / (z * z)], dim=-1).reshape(
        -1, 2, 3
    )
    cov2d = J @ cov_c @ J.transpose(1, 2)
    a = cov2d[:, 0, 0]
    b = 0.5 * (cov2d[:, 0, 1] + cov2d[:, 1, 0])
    c = cov2d[:, 1, 1]
    det0 = a * c - b * b
    a1, c1 = a + eps2d, c + eps2d
    det1 = a1 * c1 - b * b
    ok = in_depth & (det1 > 0) & torch.isfinite(det1)
    det1s = torch.where(ok, det1, torch.ones_like(det1))
    conics = torch.stack([c1 / det1s, -b / det1s, a1 / det1s], dim=-1)
    if antialiased:
        comp = _CompensationSqrt.apply(torch.where(ok, det0 / det1s, torch.zeros_like(det0)))
        opac_eff = o * comp
    else:
        opac_eff = o
    means2d = torch.stack([fx * (p[:, 0] / z) + cx, fy * (p[:, 1] / z) + cy], dim=-1)

    with torch.no_grad():
        oe = opac_eff.detach()
        visible = ok & (oe >= K_.ALPHA_MIN)
        extent = torch.sqrt(2.0 * torch.log(oe.clamp_min(K_.ALPHA_MIN) / K_.ALPHA_MIN))
        extent = extent.clamp(max=K_.SIGMA_EXTENT_MAX)
        rx = torch.ceil(extent * a1.clamp_min(0).sqrt())
        ry = torch.ceil(extent * c1.clamp_min(0).sqrt())
        visible &= ~((rx <= radius_clip) & (ry <= radius_clip))
        mx, my = means2d[:, 0].detach(), means2d[:, 1].detach()
        # gsplat's image test: culled when [mean - radius, mean + radius] misses (0, W) x (0, H).
        visible &= (mx + rx > 0) & (mx - rx < width) & (my + ry > 0) & (my - ry < height)
        # Pixels whose centre (j + 0.5) lies within the radius; empty for a visible Gaussian
        # that reaches less than half a pixel into the image.
        x0 = torch.ceil(mx - rx - 0.5).clamp_min(0)
        x1 = torch.floor(mx + rx - 0.5).clamp_max(width - 1)
        y0 = torch.ceil(my - ry - 0.5).clamp_min(0)
        y1 = torch.floor(my + ry - 0.5).clamp_max(height - 1)
        bbox = torch.stack([x0, x1, y0, y1], dim=-1)
        covers = visible & (x0 <= x1) & (y0 <= y1)
        bbox = torch.where(
            covers[:, None], bbox, torch.tensor([0.0, -1.0, 0.0, -1.0], dtype=work, device=bbox.device)
        )
        bbox = bbox.clamp(-1, max(width, height)).to(torch.int32)
        radii = torch.stack([rx, ry], dim=-1).clamp(0, K_.RADIUS_REPORT_MAX)
        radii = torch.where(visible[:, None], radii, torch.zeros_like(radii)).to(torch.int32)

    vis = visible[:, None]
    return Projection(
        means2d=torch.where(vis, means2d, torch.zeros_like(means2d)).to(dtype),
        conics=torch.where(vis, conics, torch.zeros_like(conics)).to(dtype),
        depths=torch.where(visible, pz, torch.zeros_like(pz)).to(dtype),
        opacities=torch.where(visible, opac_eff, torch.zeros_like(opac_eff)).to(dtype),
        radii=radii,
        bbox=bbox,
        visible=visible,
    )


class _PairMeans(torch.autograd.Function):
    """means2d[index] broadcast over the pixels of a block, recording AbsGS statistics.

    The backward receives one gradient per (pixel, Gaussian) pair; it returns their sum (the
    ordinary gradient) and adds the sum of their absolute values to ``holder.tensor.absgrad``.
    """

    @staticmethod
    def forward(ctx, means2d, index, pixels, holder):
        ctx.save_for_backward(index)
        ctx.n = means2d.shape[0]
        ctx.holder = holder
        return means2d.index_select(0, index).unsqueeze(0).expand(pixels, -1, -1)

    @staticmethod
    def backward(ctx, grad):
        (index,) = ctx.saved_tensors
        grad_sum = torch.zeros((ctx.n, 2), dtype=grad.dtype, device=grad.device)
        grad_sum.index_add_(0, index, grad.sum(0))
        if ctx.holder is not None:
            ctx.holder.add_absgrad(index, grad.abs().sum(0))
        return grad_sum, None, None, None


def count_intersections(proj: Projection) -> int:
    """Tile intersections the tiled backends will process (for info parity)."""
    b = proj.bbox[proj.drawn()].to(torch.int64)
    if b.numel() == 0:
        return 0
    ts = K_.TILE_SIZE
    nx = b[:, 1] // ts - b[:, 0] // ts + 1
    ny = b[:, 3] // ts - b[:, 2] // ts + 1
    return int((nx * ny).sum())


def _composite_block(
    means2d, conics, opacities, colors, bbox, sel, xs, ys, max_pairs, holder, use_pairs
) -> tuple[torch.Tensor, torch.Tensor]:
    """Blend the depth-sorted Gaussians `sel` over the pixels (xs, ys): (colour [P, C], T [P])."""
    dtype, device = colors.dtype, colors.device
    px = xs.to(dtype) + 0.5
    py = ys.to(dtype) + 0.5
    P = xs.numel()
    acc = torch.zeros((P, colors.shape[1]), dtype=dtype, device=device)
    T = torch.ones(P, dtype=dtype, device=device)
    done = torch.zeros(P, dtype=torch.bool, device=device)
    chunk = max(1, max_pairs // P)
    for start in range(0, sel.numel(), chunk):
        g = sel[start : start + chunk]
        if use_pairs:
            m2 = _PairMeans.apply(means2d, g, P, holder)
            dx = m2[..., 0] - px[:, None]
            dy = m2[..., 1] - py[:, None]
        else:
            m2 = means2d[g]
            dx = m2[None, :, 0] - px[:, None]
            dy = m2[None, :, 1] - py[:, None]
        con = conics[g]
        ca, cb, cc = con[None, :, 0], con[None, :, 1], con[None, :, 2]
        sigma = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
        alpha = torch.clamp(opacities[g][None, :] * torch.exp(-sigma), max=K_.ALPHA_MAX)
        with torch.no_grad():
            gb = bbox[g].to(torch.int64)
            inside = (
                (xs[:, None] >= gb[None, :, 0])
                & (xs[:, None] <= gb[None, :, 1])
                & (ys[:, None] >= gb[None, :, 2])
                & (ys[:, None] <= gb[None, :, 3])
            )
            valid = inside & (sigma >= 0) & (alpha >= K_.ALPHA_MIN) & ~done[:, None]
            a_valid = torch.where(valid, alpha, torch.zeros_like(alpha))
            # Transmittance after each candidate if every valid one were blended; the first
            # that would take it to TRANSMITTANCE_MIN or below stops the pixel (and is not
            # blended), as gsplat's `next_T <= 1e-4f` does.
            t_after = torch.cumprod(torch.cat([T.detach()[:, None], 1 - a_valid], dim=1), dim=1)[:, 1:]
            blend = valid & (t_after > K_.TRANSMITTANCE_MIN)
            stopped = (valid & (t_after <= K_.TRANSMITTANCE_MIN)).any(dim=1)
        a_blend = torch.where(blend, alpha, torch.zeros_like(alpha))
        trans = torch.cumprod(torch.cat([T[:, None], 1 - a_blend], dim=1), dim=1)
        # An explicit multiply-sum, not a matmul: tiny BLAS calls wake OpenBLAS's own thread
        # pool, which on a busy small machine costs far more than the arithmetic.
        acc = acc + ((a_blend * trans[:, :-1]).unsqueeze(-1) * colors[g].unsqueeze(0)).sum(dim=1)
        T = trans[:, -1]
        done = done | stopped
    return acc, T


def _block_lists(bbox, ids, width, height, block_size):
    """Per pixel block, the Gaussians (``ids`` order kept) whose box overlaps it, as a flat
    list and offsets: a vectorised counting sort, O(overlaps) instead of O(blocks * N)."""
    device = ids.device
    blocks_x = -(-width // block_size)
    blocks_y = -(-height // block_size)
    bx0, bx1 = bbox[:, 0] // block_size, bbox[:, 1] // block_size
    by0, by1 = bbox[:, 2] // block_size, bbox[:, 3] // block_size
    nbx = bx1 - bx0 + 1
    counts = nbx * (by1 - by0 + 1)
    owner = torch.repeat_interleave(torch.arange(ids.numel(), device=device), counts)
    first = torch.cumsum(counts, 0) - counts
    local = torch.arange(owner.numel(), device=device) - first[owner]
    block = (by0[owner] + local // nbx[owner]) * blocks_x + bx0[owner] + local % nbx[owner]
    order = torch.sort(block, stable=True).indices
    members = ids[owner[order]]
    per_block = torch.bincount(block, minlength=blocks_x * blocks_y)
    starts = torch.zeros(blocks_x * blocks_y + 1, dtype=torch.int64, device=device)
    starts[1:] = torch.cumsum(per_block, 0)
    return members, starts.tolist()


def default_block_size(width: int, height: int, n_visible: int) -> int:
    """Pixel block edge balancing pair work (~10 ns each) against per-block Python overhead
    (~200 us): pairs grow like n_visible * B^2, blocks like W * H / B^2."""
    edge = (2e4 * width * height / max(n_visible, 1)) ** 0.25
    return int(min(max(round(edge), 4), 256))


def rasterize(
    proj: Projection,
    colors: torch.Tensor,
    width: int,
    height: int,
    *,
    holder=None,
    block_size: int | None = None,
    max_pairs: int = K_.TORCH_MAX_PAIRS,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite the projected Gaussians front to back: (image [H, W, C], alpha [H, W, 1]).

    The image has no background (the caller adds ``(1 - alpha) * background``). When
    gradients are needed every block is checkpointed (recomputed in backward), so memory
    stays bounded by one block's pairs instead of growing with the whole image.
    """
    device, dtype = colors.device, colors.dtype
    C = colors.shape[1]
    vis_idx = torch.nonzero(proj.drawn()).squeeze(1)
    order = torch.sort(proj.depths.detach()[vis_idx], stable=True).indices
    sorted_ids = vis_idx[order]
    if block_size is None:
        block_size = default_block_size(width, height, sorted_ids.numel())
    members, starts = _block_lists(
        proj.bbox[sorted_ids].to(torch.int64), sorted_ids, width, height, block_size
    )
    blocks_x = -(-width // block_size)
    tensors = (proj.means2d, proj.conics, proj.opacities, colors)
    needs_grad = torch.is_grad_enabled() and any(t.requires_grad for t in tensors)
    use_pairs = holder is not None or proj.means2d.requires_grad

    rows = []
    for by0 in range(0, height, block_size):
        by1 = min(by0 + block_size, height) - 1
        row_blocks = []
        for bx0 in range(0, width, block_size):
            bx1 = min(bx0 + block_size, width) - 1
            bh, bw = by1 - by0 + 1, bx1 - bx0 + 1
            block = (by0 // block_size) * blocks_x + bx0 // block_size
            sel = members[starts[block] : starts[block + 1]]
            if sel.numel() == 0:
                row_blocks.append(
                    (
                        torch.zeros((bh, bw, C), dtype=dtype, device=device),
                        torch.ones((bh, bw), dtype=dtype, device=device),
                    )
                )
                continue
            ys, xs = torch.meshgrid(
                torch.arange(by0, by1 + 1, device=device),
                torch.arange(bx0, bx1 + 1, device=device),
                indexing="ij",
            )
            args = (*tensors, proj.bbox, sel, xs.reshape(-1), ys.reshape(-1), max_pairs, holder, use_pairs)
            if needs_grad:
                acc, T = checkpoint(_composite_block, *args, use_reentrant=False)
            else:
                acc, T = _composite_block(*args)
            row_blocks.append((acc.reshape(bh, bw, C), T.reshape(bh, bw)))
        rows.append(
            (
                torch.cat([blk[0] for blk in row_blocks], dim=1),
                torch.cat([blk[1] for blk in row_blocks], dim=1),
            )
        )
    image = torch.cat([r[0] for r in rows], dim=0)
    T_final = torch.cat([r[1] for r in rows], dim=0)
    if needs_grad and not image.requires_grad:
        # Nothing was visible: keep the outputs in the graph (zero gradients), as the other
        # backends' autograd Functions do, so a training step never fails on an empty view.
        anchor = sum(t.sum() for t in tensors if t.requires_grad) * 0.0
        image, T_final = image + anchor, T_final + anchor
    return image, (1.0 - T_final)[..., None]


class TorchBackend(TwoStageBackend):
    """The reference as a backend: any device, the inputs' dtype (float64 for gradcheck)."""

    name = "torch"
    device_type = None
    description = "pure PyTorch reference"

    def project(self, request: RenderRequest, tensors, stats: RenderStats) -> Projection:
        o = request.options
        dtype = tensors[0].dtype
        return project(
            *tensors,
            request.viewmat,
            request.K,
            request.width,
            request.height,
            near_plane=plane_in_dtype(o.near_plane, dtype),
            far_plane=plane_in_dtype(o.far_plane, dtype),
            eps2d=o.eps2d,
            radius_clip=o.radius_clip,
            antialiased=o.antialiased,
        )

    def rasterize(
        self,
        request: RenderRequest,
        projection: Projection,
        colors: torch.Tensor,
        holder: AbsGradHolder | None,
        stats: RenderStats,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        stats.n_intersections = count_intersections(projection)
        return rasterize(projection, colors, request.width, request.height, holder=holder)


BACKEND = TorchBackend()
