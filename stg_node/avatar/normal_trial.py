"""Which way the shading normals point in training, decided from the clip's light ("auto").

Normals flipped towards the training camera (``camera``) let the albedo learn to undo the flips
of the training view's silhouettes and of the side facing away from the light: a body turned
away from the training orientation shows that as a gap between novel views and novel poses,
measured up to 1.3 dB under a directional room light (docs/BENCHMARKS.md, issue 21). Normals
signed by the body (``outward``, shading.outward_normals) close it there, but on a clip lit
flat they let the light grow a weak lamp towards the camera that costs novel views and poses
0.3-1 dB: how a surface faces the one training camera is confounded with what its edges do in
the image (coverage, blending), and a light along the line of sight can absorb that.

The sign matters in proportion to the light's contrast: under a uniform light every normal gets
the same shade whatever its sign. So ``auto`` trains with the camera's sign (today's training,
bit for bit, until the decision) and, at ``normal_decide_iter``, measures the learned light's
**contrast**, the standard deviation of its irradiance over all directions relative to its
mean (:func:`light_contrast`; 0 for a uniform light, whatever the light model). At or above
``normal_min_contrast`` the clip shows a light whose direction matters, and training continues
with outward normals; below it the light is weak enough that the sign cannot matter much and
the camera's sign, safe on flat light, stays. The run's summary says which and why
(:func:`report`).
"""

from __future__ import annotations

import torch

from stg_node.avatar import shading

NORMAL_SIGN_KEY = "model.normal_sign"
CONTRAST_NOTE = "normal_sign.contrast"  # Trainer.notes: the evidence, kept with the checkpoint
SEEN_CONTRAST_NOTE = "normal_sign.seen_contrast"
ITERATION_NOTE = "normal_sign.iteration"
_SAMPLES = 2048  # directions on the sphere the contrast is averaged over


def sphere_directions(count: int = _SAMPLES, device=None) -> torch.Tensor:
    """(count, 3) unit directions spread evenly over the sphere (Fibonacci lattice)."""
    return shading.sphere_directions(count, device)


@torch.no_grad()
def light_contrast(shading, seen_only: bool = False) -> float:
    """Std of the learned light's irradiance over all directions over its mean, the largest over
    RGB (0: uniform; the benchmark's room light, ambient 0.3 and one lamp 0.7: 0.48). With
    ``seen_only``, over the directions a training view faced (``Shading.seen``) only."""
    directions = sphere_directions(device=shading.reference.device)
    e = shading.light.irradiance(directions)
    if seen_only:
        faced = shading.seen_at(directions)
        if bool(faced.any()):
            e = e[faced]
    return float((e.std(dim=0) / e.mean(dim=0).clamp_min(1e-9)).max())


def choose(contrast: float, threshold: float) -> tuple[str, str]:
    """(sign, why) for a light of ``contrast`` against ``threshold`` (module doc)."""
    if contrast >= threshold:
        return "outward", (
            f"the learned light varies by {contrast:.2f} of its mean over directions (>= {threshold:g}): "
            "a directional light, whose shade outward normals carry to orientations the clip never showed"
        )
    return "camera", (
        f"the learned light varies by only {contrast:.2f} of its mean over directions (< {threshold:g}): "
        "too even for a normal's sign to matter, and outward normals would let it grow a lamp at the camera"
    )


def report(config, notes: dict) -> dict:
    """What the run chose for the training normals' sign and why (the run's summary)."""
    sign = config.model.normal_sign
    if not config.model.shading:
        return {"chose": sign, "why": "no shading: normals are not used"}
    if CONTRAST_NOTE in notes:
        _, why = choose(notes[CONTRAST_NOTE], config.normal_min_contrast)
        return {
            "chose": sign,
            "why": why,
            "iteration": int(notes.get(ITERATION_NOTE, 0)),
            "evidence": {
                "light_contrast": notes[CONTRAST_NOTE],
                **({"seen_contrast": notes[SEEN_CONTRAST_NOTE]} if SEEN_CONTRAST_NOTE in notes else {}),
            },
        }
    if sign == "auto":
        return {
            "chose": "camera",
            "why": f"not decided yet: the light is judged at iteration {config.normal_decide_iter}",
        }
    return {"chose": sign, "why": f"model.normal_sign={sign}: set by the caller"}
