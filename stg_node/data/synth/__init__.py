"""The synthetic benchmark with ground truth (``stg-synth``): see docs/SYNTH.md.

An open SMPL-format body driven by procedural SMPL motions, with garment dynamics that
skinning cannot explain, rendered by an independent z-buffered mesh rasterizer from a fixed
training camera and a ring of held-out cameras, and written in ZJU-MoCap's original layout.

Modules: ``motions`` (SMPL motion sequences) and ``joint_limits``; ``garment`` (cloth
dynamics); ``mesh_raster`` (the ground-truth renderer); ``cameras`` (the rig); ``writer``
(the ZJU-MoCap layout and ``synth.json``); ``generate`` (the pipeline); ``dataset``
(:func:`open_synth`: the generated folder through the ZJU-MoCap loader).
"""

from stg_node.data.synth.dataset import open_synth, synth_split
from stg_node.data.synth.garment import GarmentParams
from stg_node.data.synth.generate import SynthConfig, SynthResult, generate, render_schedule, split_spec
from stg_node.data.synth.motions import DEFAULT_MOTION, MOTIONS, MotionSequence, make_motion
from stg_node.data.synth.writer import METADATA_FILE, read_metadata

__all__ = [
    "DEFAULT_MOTION",
    "METADATA_FILE",
    "MOTIONS",
    "GarmentParams",
    "MotionSequence",
    "SynthConfig",
    "SynthResult",
    "generate",
    "make_motion",
    "open_synth",
    "read_metadata",
    "render_schedule",
    "split_spec",
    "synth_split",
]
