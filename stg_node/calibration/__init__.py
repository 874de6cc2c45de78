"""Rig calibration: intrinsics and extrinsics of several cameras from views of a ChArUco board.

- :mod:`.rig`: ``rig.json`` (read/write, checked): the format every rig-aware part reads.
- :mod:`.board`: the board's geometry, a printable image, detection (OpenCV's aruco module).
- :mod:`.solve`: per-camera intrinsics, extrinsics through shared sightings, bundle adjustment.
- :mod:`.capture`: videos or image folders of a rig -> synchronised detections -> a rig.
- :mod:`.synthetic`: board captures rendered with known truth (the tests and the benchmark).

``stg-calibrate`` (stg_node/cli/calibrate.py) runs it; docs/RIGS.md is the guide.
"""

from stg_node.calibration.rig import Rig, RigCamera, RigError, read_rig, write_rig

__all__ = ["Rig", "RigCamera", "RigError", "read_rig", "write_rig"]
