"""The silhouette term of the SMPL fit: the posed mesh should cover the person's mask, and no more.

Keypoints say where a dozen joints are; they say little about how the body is turned about the
vertical (a side view and a front view put the hips and shoulders at nearly the same points) or
how a limb is twisted. The person's mask does: its width, the arms' outline. This module turns a
mask into residual rows the Levenberg-Marquardt fit (fitting.py) can use, without a renderer:

- :class:`MeshSamples`: a fixed, evenly spread subset of the body's vertices (a few hundred of
  7k-14k), skinned with the body package's own forward kinematics and skinning, as
  :class:`~stg_node.tracking.body_points.BodyKeypoints` does for the keypoints;
- :class:`MaskTarget`: from one mask, the distance (pixels) from every pixel to the nearest mask
  pixel (0 inside; ``cv2.distanceTransform``) and points spread along the mask's outline;
- :func:`silhouette_residuals`: two chamfer halves, in units of the fit's 2D residual unit:
  every projected vertex's distance to the mask (a vertex outside the person's mask is wrong
  whatever the pose, since every vertex of a closed mesh projects inside its own silhouette),
  and every outline point's distance to the nearest projected vertex (a mask part no vertex
  reaches is a limb in the wrong place). Each half is averaged over its samples and given the
  configured weight, so the balance with the keypoints does not depend on how many samples there
  are; each distance passes through a Cauchy-shaped cap, so a mask that wrongly holds a chair or
  a second person pulls gently, not without bound.

Self-occlusion needs no visibility test: both halves hold for any closed mesh's projection, front
or back facing. The sampled vertices leave gaps of a few pixels between them, which sets the
floor of the outline half (a fit is not pushed to close them: the cap is flat near zero).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from stg_node.body import BodyModel, lbs

DTYPE = torch.float64


def spread_vertices(vertices: np.ndarray, count: int) -> np.ndarray:
    """Indices of ``count`` vertices spread evenly over the mesh (farthest-point sampling from the
    top of the head: deterministic, and no body part left without samples)."""
    vertices = np.asarray(vertices, dtype=np.float64)
    if count >= len(vertices):
        return np.arange(len(vertices))
    chosen = [int(np.argmax(vertices[:, 1]))]
    distance = np.linalg.norm(vertices - vertices[chosen[0]], axis=1)
    for _ in range(count - 1):
        nxt = int(np.argmax(distance))
        chosen.append(nxt)
        distance = np.minimum(distance, np.linalg.norm(vertices - vertices[nxt], axis=1))
    return np.asarray(chosen, dtype=np.int64)


class MeshSamples(torch.nn.Module):
    """``local(betas, rotations) -> (B, V, 3)``: sampled mesh vertices in model space (before Rh, Th)
    from (B, 24, 3, 3) local joint rotations; pose-corrective blend shapes left out (as for the
    keypoints: millimetres)."""

    def __init__(self, body: BodyModel, count: int):
        super().__init__()
        if count < 1:
            raise ValueError(f"the silhouette needs at least one mesh sample, got {count}")
        with torch.no_grad():
            template = body.v_template.double()
            self.vertex_ids = torch.as_tensor(spread_vertices(template.numpy(), count))
            self.register_buffer("template", template[self.vertex_ids])
            self.register_buffer("shapedirs", body.shapedirs.double()[self.vertex_ids])
            self.register_buffer("weights", body.weights.double()[self.vertex_ids])
            regressor = body.J_regressor.double()
            self.register_buffer("joint_template", regressor @ template)
            self.register_buffer(
                "joint_shapedirs", torch.einsum("jv,vcs->jcs", regressor, body.shapedirs.double())
            )
        self.parents = body.parents.clone()
        self.num_betas = int(body.num_betas)

    def local(self, betas: torch.Tensor, rotations: torch.Tensor) -> torch.Tensor:
        batch = rotations.shape[0]
        betas = betas.to(DTYPE).reshape(-1, self.num_betas).expand(batch, -1)
        rest_joints = self.joint_template + torch.einsum("jcs,bs->bjc", self.joint_shapedirs, betas)
        _, transforms = lbs.rigid_chain(rotations.to(DTYPE), rest_joints, self.parents)
        rest = self.template + torch.einsum("vcs,bs->bvc", self.shapedirs, betas)
        return lbs.skin_points(rest, self.weights, transforms)


@dataclass
class MaskTarget:
    """What the fit compares the projected mesh with: one mask's outside-distance map and outline."""

    outside: torch.Tensor  # (H, W) pixels from each pixel to the nearest mask pixel, 0 inside
    outline: torch.Tensor  # (M, 2) x, y pixel centres spread along the mask's outer boundary
    area_px: int

    @classmethod
    def from_mask(cls, mask: np.ndarray, outline_points: int) -> MaskTarget | None:
        """None when the mask is empty (nothing to compare with)."""
        mask = np.asarray(mask)
        if mask.ndim != 2:
            raise ValueError(f"the silhouette needs an (H, W) mask, got shape {mask.shape}")
        inside = (mask > 0).astype(np.uint8)
        area = int(inside.sum())
        if area == 0:
            return None
        outside = cv2.distanceTransform(1 - inside, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        contours, _ = cv2.findContours(inside, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        boundary = np.concatenate([c.reshape(-1, 2) for c in contours]).astype(np.float64)
        step = max(len(boundary) / max(outline_points, 1), 1.0)
        picked = boundary[(np.arange(min(outline_points, len(boundary))) * step).astype(int)]
        return cls(torch.as_tensor(outside, dtype=DTYPE), torch.as_tensor(picked, dtype=DTYPE), area)


def sample_map(image: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
    """Bilinear sample of an (H, W) map at (..., 2) x, y pixel centres; points outside the image
    take the nearest border value plus their distance past the border (so the outside-distance map
    keeps growing off-image)."""
    height, width = image.shape
    x = xy[..., 0].clamp(0.0, width - 1.0)
    y = xy[..., 1].clamp(0.0, height - 1.0)
    beyond = (xy[..., 0] - x).abs() + (xy[..., 1] - y).abs()
    x0 = x.floor().clamp(max=width - 2).long()
    y0 = y.floor().clamp(max=height - 2).long()
    fx, fy = x - x0, y - y0
    top = image[y0, x0] * (1 - fx) + image[y0, x0 + 1] * fx
    bottom = image[y0 + 1, x0] * (1 - fx) + image[y0 + 1, x0 + 1] * fx
    return top * (1 - fy) + bottom * fy + beyond


def capped(distance: torch.Tensor, scale: float) -> torch.Tensor:
    """A residual whose square is the Cauchy cost of ``distance`` (>= 0): ~distance near 0, grows
    only logarithmically past ``scale``."""
    return scale * torch.log1p((distance / scale) ** 2).sqrt()


def silhouette_residuals(
    uv: torch.Tensor, target: MaskTarget, unit_px: float, weight: float, robust_units: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, V) rows for the vertices outside the mask and (B, M) rows for the outline points far
    from every vertex, from projected vertices ``uv`` (B, V, 2); each half's sum of squares is
    ``weight`` x the mean capped squared distance in 2D residual units."""
    outside = sample_map(target.outside, uv) / unit_px
    reach = torch.cdist(target.outline[None].expand(uv.shape[0], -1, -1), uv).amin(dim=2) / unit_px
    scale_v = (weight / uv.shape[1]) ** 0.5
    scale_m = (weight / max(target.outline.shape[0], 1)) ** 0.5
    return capped(outside, robust_units) * scale_v, capped(reach, robust_units) * scale_m


def inside_fraction(uv: np.ndarray, mask: np.ndarray) -> float:
    """Share of projected points (N, 2) that land on a mask pixel (points off the image count as
    outside): how well a mesh covers the person, the benchmark's mesh-in-mask figure."""
    uv = np.asarray(uv, dtype=np.float64)
    height, width = mask.shape[:2]
    col = np.floor(uv[:, 0] + 0.5).astype(np.int64)
    row = np.floor(uv[:, 1] + 0.5).astype(np.int64)
    on = (col >= 0) & (col < width) & (row >= 0) & (row < height)
    hit = np.zeros(len(uv), dtype=bool)
    hit[on] = mask[row[on], col[on]] > 0
    return float(hit.mean()) if len(uv) else float("nan")
