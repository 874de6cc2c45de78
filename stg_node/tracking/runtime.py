"""Network runners: a model file in, a callable ``runner(input) -> list of output arrays`` out.

- :class:`TfliteRunner`: a ``.tflite`` file under LiteRT (``ai-edge-litert``, Google's TFLite
  runtime; XNNPACK on the CPU). Outputs are returned in the model's declared order.
- :class:`OnnxRunner`: an ``.onnx`` file under OpenCV's dnn module (no extra dependency).

Both set their thread count from :mod:`stg_node.threads` unless told otherwise.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from stg_node.threads import resolve_threads

log = logging.getLogger(__name__)


class RunnerError(RuntimeError):
    """A network file cannot be loaded or run; the message names the file and the fix."""


class TfliteRunner:
    """Runs a TFLite network with LiteRT; ``runner(x)`` feeds ``x`` to the first input."""

    def __init__(self, path: str | Path, threads: int | None = None):
        self.path = Path(path)
        if not self.path.is_file():
            raise RunnerError(f"TFLite network {self.path} does not exist")
        try:
            from ai_edge_litert.interpreter import Interpreter
        except ImportError as exc:
            raise RunnerError(
                "ai-edge-litert is not installed; it runs the BlazePose networks. Install it with "
                "`pip install ai-edge-litert` (setup.sh does), or use an ONNX pose model instead"
            ) from exc
        try:
            self._interpreter = Interpreter(model_path=str(self.path), num_threads=resolve_threads(threads))
            self._interpreter.allocate_tensors()
        except (ValueError, RuntimeError) as exc:
            raise RunnerError(f"LiteRT cannot load {self.path}: {exc}") from exc
        self._input = self._interpreter.get_input_details()[0]
        self._outputs = [d["index"] for d in self._interpreter.get_output_details()]
        self.input_shape = tuple(int(v) for v in self._input["shape"])

    def __call__(self, tensor: np.ndarray) -> list[np.ndarray]:
        tensor = np.ascontiguousarray(tensor, dtype=self._input["dtype"])
        if tensor.shape != self.input_shape:
            raise ValueError(f"{self.path.name} takes input {self.input_shape}, got {tensor.shape}")
        self._interpreter.set_tensor(self._input["index"], tensor)
        self._interpreter.invoke()
        return [self._interpreter.get_tensor(index) for index in self._outputs]


class OnnxRunner:
    """Runs an ONNX network with OpenCV's dnn module; ``runner(x)`` with x in NCHW float32."""

    def __init__(self, path: str | Path, threads: int | None = None):
        import cv2

        self.path = Path(path)
        if not self.path.is_file():
            raise RunnerError(f"ONNX network {self.path} does not exist")
        try:
            self._net = cv2.dnn.readNetFromONNX(str(self.path))
        except cv2.error as exc:
            raise RunnerError(f"OpenCV cannot load the ONNX network {self.path}: {exc}") from exc
        self._names = list(self._net.getUnconnectedOutLayersNames())
        cv2.setNumThreads(resolve_threads(threads))

    @property
    def output_names(self) -> list[str]:
        return list(self._names)

    def __call__(self, tensor: np.ndarray) -> list[np.ndarray]:
        import cv2

        self._net.setInput(np.ascontiguousarray(tensor, dtype=np.float32))
        try:
            outputs = self._net.forward(self._names)
        except cv2.error as exc:
            raise RunnerError(
                f"OpenCV failed to run {self.path.name} on input {tensor.shape}: {exc}"
            ) from exc
        return [np.asarray(o) for o in outputs]
