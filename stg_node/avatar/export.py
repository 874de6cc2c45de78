"""PLY export of an avatar in the standard 3DGS layout: canonical, or posed at a training frame.

Canonical: the table's centres in the big-pose canonical space, their base rotation and
opacity. Posed (``frame``): the world-space Gaussians of that training frame (its pose, its
time: spacetime offsets and temporal opacity included; Gaussians invisible at that instant
are left out). Colours: SH coefficients as stored in SH mode; in MLP mode the MLP's colour
averaged over six viewing directions, written as the DC term (a PLY holds no MLP).
"""

from __future__ import annotations

from pathlib import Path

import torch

from stg_node.avatar.model import AvatarModel, BodyState, Camera3
from stg_node.splat.constants import ALPHA_MIN
from stg_node.splat.ply import save_ply

_DIRECTIONS = torch.tensor(
    [[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=torch.float32
)


@torch.no_grad()
def canonical_colors(model: AvatarModel, poses=None) -> torch.Tensor:
    table = model.table
    n = table.num
    if model.color_mlp is None:
        from stg_node.avatar.color import SH_C0

        return (table["sh"][:, 0] * SH_C0 + 0.5).clamp(0, 1)
    from stg_node.avatar.timecode import pose_key

    key = torch.as_tensor(
        pose_key(torch.zeros(24, 3).numpy() if poses is None else poses), device=model.device
    )
    out = torch.zeros(n, 3, device=model.device)
    for d in _DIRECTIONS.to(model.device):
        out += model.color_mlp(table["means"], table["features"], key, d.expand(n, 3), model.config.sh_degree)
    return out / len(_DIRECTIONS)


@torch.no_grad()
def export_canonical(model: AvatarModel, path: Path) -> Path:
    table = model.table
    q = table["quats"] / table["quats"].norm(dim=1, keepdim=True).clamp_min(1e-12)
    if model.color_mlp is None and table["sh"].shape[1] > 1:
        return save_ply(
            path,
            table["means"],
            q,
            table.scales(),
            table.opacities(),
            sh_dc=table["sh"][:, 0],
            sh_rest=table["sh"][:, 1:],
        )
    return save_ply(path, table["means"], q, table.scales(), table.opacities(), canonical_colors(model))


@torch.no_grad()
def export_posed(model: AvatarModel, smpl, time_s: float, camera, path: Path) -> Path:
    cam = Camera3.from_camera(camera, device=model.device)
    posed = model.pose(BodyState.from_smpl(smpl, model.device), model.time_axis(time_s), cam.center)
    keep = posed.opacities >= ALPHA_MIN
    return save_ply(
        path,
        posed.means[keep],
        posed.quats[keep],
        posed.scales[keep],
        posed.opacities[keep],
        posed.colors[keep].clamp(0, 1),
    )
