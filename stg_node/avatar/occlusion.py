"""What the posed body casts on itself: an ambient-occlusion term for the avatar's shading.

:mod:`shading` lights each Gaussian by the irradiance of its world normal, as if the rest of the
body were not there: an arm held across the chest leaves the chest as bright as ever, and a colour
learned where the arm hung by the side cannot know better. This module darkens each Gaussian by
the share of its sky the posed body covers, cheaply enough to run on every frame of a live render:

- **Occluders**: the body as a set of spheres (Ren et al. 2006 approximate a character by spheres
  for soft shadows; so do games' capsule occlusion), fitted once to the canonical body (the big
  pose): per bone, the vertices it dominates are cut along their principal axis into one to
  ``MAX_SPHERES_PER_BONE`` chunks about as long as the limb is thick, each a sphere at the chunk's
  centroid with the chunk's median distance to the axis as radius. Posed rigidly by their bone's
  transform: no gradient (they are the body's, as the joint shrink is).
- **Occlusion of one sphere**: a sphere of radius ``r`` whose centre is at distance ``d`` in
  direction ``l`` covers the cosine-weighted share ``F = max(0, n . l) (r / d)^2`` of a
  point's hemisphere around normal ``n`` (its form factor, exact while it is above the horizon;
  ``r / d`` capped at 1). The spheres of the Gaussian's own bone and the bones next to it
  (parent, children) are left out: they are the surface it lies on. Together: ``V = prod_s (1 -
  F_s)``, the visible share.
- **Shading**: the irradiance is multiplied by ``1 - k + k V``, with a strength ``k`` in [0, 1]
  learned with the light (starting at ``INITIAL_STRENGTH``), so a clip whose images show no
  occlusion can turn the term off.

Cost: (Gaussians x spheres) distances per frame, about 60 spheres. On float32 CPU tensors one C++
pass per Gaussian (``csrc/sphere_occlusion.cpp``, eight spheres a vector, no (M, S) temporaries:
about 30x the torch blocks, 0.6 ms for 20k Gaussians on one thread), so the term runs exactly on every
frame of training and of a live render, with no cache and nothing stale; :func:`sphere_visibility`
is the torch reference (other devices, float64, no compiler, ``STG_AVATAR_KERNELS=torch``) it is
tested against.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from stg_node.avatar.kernels import use_kernels
from stg_node.splat.build import load_kernels

MAX_SPHERES_PER_BONE = 4
INITIAL_STRENGTH = 0.5
ROW_BLOCK = 256  # Gaussians per block of the torch visibility computation on a CPU
DEVICE_ROW_BLOCK = 65_536  # ... and on other devices (a block's (rows, S) temporaries: ~18 MB each)
_MIN_VERTICES = 4


def fit_spheres(
    vertices: torch.Tensor, weights: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Spheres approximating the body: (centres (S, 3), radii (S,), bone (S,)) from its canonical
    ``vertices`` (V, 3) and skinning ``weights`` (V, J) (module doc)."""
    vertices = vertices.detach().to(torch.float64).cpu()
    dominant = weights.detach().cpu().argmax(dim=1)
    centres, radii, bones = [], [], []
    for bone in range(weights.shape[1]):
        pts = vertices[dominant == bone]
        if pts.shape[0] < _MIN_VERTICES:
            continue
        mean = pts.mean(dim=0)
        _, _, vt = torch.linalg.svd(pts - mean, full_matrices=False)
        axis = vt[0]
        t = (pts - mean) @ axis
        perp = (pts - mean) - t[:, None] * axis
        thickness = float(perp.norm(dim=1).median())
        length = float(t.max() - t.min())
        count = int(min(MAX_SPHERES_PER_BONE, max(1, round(length / max(2.0 * thickness, 1e-6)))))
        edges = torch.linspace(float(t.min()), float(t.max()) + 1e-9, count + 1, dtype=torch.float64)
        for lo, hi in zip(edges[:-1], edges[1:], strict=True):
            chunk = (t >= lo) & (t < hi)
            if int(chunk.sum()) < _MIN_VERTICES:
                continue
            centre = pts[chunk].mean(dim=0)
            along = (pts[chunk] - centre) @ axis
            across = (pts[chunk] - centre) - along[:, None] * axis
            centres.append(centre)
            radii.append(float(across.norm(dim=1).median()))
            bones.append(bone)
    if not centres:
        raise ValueError("no bone dominates enough vertices to fit an occluder sphere")
    return (
        torch.stack(centres).to(torch.float32),
        torch.tensor(radii, dtype=torch.float32),
        torch.tensor(bones, dtype=torch.long),
    )


def sphere_visibility(
    points: torch.Tensor,
    normals: torch.Tensor,
    centres: torch.Tensor,
    radii: torch.Tensor,
    counts: torch.Tensor | None = None,
) -> torch.Tensor:
    """(M,) the visible share of each point's hemisphere (unit ``normals`` (M, 3)) past spheres
    ``centres`` (S, 3) / ``radii`` (S,): ``prod_s (1 - max(0, n . l_s) min(1, r_s / d_s)^2)``.
    ``counts`` (M, S) bool: which spheres count for which point (None: all)."""
    # all (M, S) terms from matrix products: no (M, S, 3) tensor (3.5x faster at 11k x 71)
    toward = normals @ centres.T - (points * normals).sum(dim=1, keepdim=True)  # n . (c - p)
    dist2 = (
        points.square().sum(dim=1, keepdim=True)
        + centres.square().sum(dim=1)[None]
        - 2.0 * points @ centres.T
    ).clamp_min(1e-12)
    cosine = (toward * dist2.rsqrt()).clamp(0.0, 1.0)
    covered = cosine * (radii.square()[None] / dist2).clamp(max=1.0)
    if counts is not None:
        covered = covered * counts
    return (1.0 - covered).prod(dim=1)


class BodyOcclusion(nn.Module):
    """The body's occluder spheres (canonical, per bone) and the learned strength of the term."""

    def __init__(self):
        super().__init__()
        self.register_buffer("centres", torch.zeros(0, 3))
        self.register_buffer("radii", torch.zeros(0))
        self.register_buffer("bones", torch.zeros(0, dtype=torch.long))
        self.register_buffer("counts", torch.zeros(0, 0, dtype=torch.bool))  # (J, S): bone -> spheres it sees
        logit = math.log(INITIAL_STRENGTH / (1.0 - INITIAL_STRENGTH))
        self.strength_logit = nn.Parameter(torch.tensor([logit]))
        self._mask_cache: tuple | None = None

    @property
    def fitted(self) -> bool:
        return self.centres.shape[0] > 0

    def fit(self, vertices: torch.Tensor, weights: torch.Tensor, parents: list[int]) -> None:
        """Fit the spheres to the canonical body and note which bones' spheres each bone counts
        (all but its own, its parent's and its children's)."""
        centres, radii, bones = fit_spheres(vertices, weights)
        joints = weights.shape[1]
        near = torch.eye(joints, dtype=torch.bool)
        for child, parent in enumerate(parents):
            if 0 <= parent < joints:
                near[child, parent] = near[parent, child] = True
        device = self.strength_logit.device
        self.centres = centres.to(device)
        self.radii = radii.to(device)
        self.bones = bones.to(device)
        self.counts = (~near[:, bones]).to(device)

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # the sphere count is the body's: take the stored buffers' shapes before copying them
        for name in ("centres", "radii", "bones", "counts"):
            stored = state_dict.get(prefix + name)
            if stored is not None:
                dtype = getattr(self, name).dtype
                setattr(self, name, torch.zeros(stored.shape, dtype=dtype, device=self.strength_logit.device))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def strength(self) -> torch.Tensor:
        return torch.sigmoid(self.strength_logit)

    @torch.no_grad()
    def visibility(
        self, points: torch.Tensor, normals: torch.Tensor, bone: torch.Tensor, transforms: torch.Tensor
    ) -> torch.Tensor:
        """(M,) visible share at posed ``points`` (M, 3) with world ``normals`` (M, 3) of Gaussians
        dominated by ``bone`` (M,), the spheres posed by the bone ``transforms`` (J, 4, 4)."""
        if not self.fitted:
            return torch.ones(points.shape[0], dtype=points.dtype, device=points.device)
        rigid = transforms[self.bones].to(points.dtype)
        centres = (rigid[:, :3, :3] @ self.centres.to(points.dtype)[:, :, None]).squeeze(2) + rigid[:, :3, 3]
        radii = self.radii.to(points.dtype)
        points, normals = points.detach(), normals.detach()
        if points.shape[0] and use_kernels(points, normals, centres):
            return load_kernels().ops.sphere_visibility(
                points.contiguous(),
                normals.contiguous(),
                bone.to(torch.int64).contiguous(),
                centres.contiguous(),
                radii.square().contiguous(),
                self._mask(),
                torch.get_num_threads(),
            )
        # in blocks of rows: on a CPU small (block, S) temporaries come from the allocator's cache,
        # where whole (M, S) ones were fresh pages each frame (measured 20x slower on the loaded 2-core
        # box); on a GPU large blocks, as every block costs its own kernel launches
        block = ROW_BLOCK if points.device.type == "cpu" else DEVICE_ROW_BLOCK
        return (
            torch.cat(
                [
                    sphere_visibility(
                        points[lo : lo + block],
                        normals[lo : lo + block],
                        centres,
                        radii,
                        self.counts[bone[lo : lo + block]],
                    )
                    for lo in range(0, points.shape[0], block)
                ]
            )
            if points.shape[0]
            else points.new_ones(0)
        )

    def _mask(self) -> torch.Tensor:
        """``counts`` as the kernel's float32 (J, S) 0/1 weights, converted once per fit or load."""
        cached = self._mask_cache  # (the counts tensor itself, its version, the mask): no id() reuse
        if cached is None or cached[0] is not self.counts or cached[1] != self.counts._version:
            cached = (self.counts, self.counts._version, self.counts.to(torch.float32).contiguous())
            self._mask_cache = cached
        return cached[2]

    def factor(self, visible: torch.Tensor) -> torch.Tensor:
        """(M, 1) what the irradiance is multiplied by: ``1 - k + k V``."""
        k = self.strength().to(visible.dtype)
        return (1.0 - k + k * visible)[:, None]
