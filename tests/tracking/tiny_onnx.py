"""Hand-encoded ONNX files for tests: a network whose output is known, without the onnx package.

An ONNX model is a protobuf ``ModelProto``; this writes the few messages a small graph needs
(field numbers from onnx/onnx.proto) in protobuf's wire format: varints and length-delimited
fields. :func:`dot_heatmap_model` builds a COCO-17 "pose network": 4x4 average pooling, then a
1x1 convolution that copies input channel c (R, G, B) into the heatmaps of keypoints whose index
is c mod 3, so a bright red dot in the crop is where keypoints 0, 3, 6, ... are found.
"""

from __future__ import annotations

import numpy as np

_FLOAT = 1  # TensorProto.DataType.FLOAT
_ATTR_INT, _ATTR_INTS = 2, 7  # AttributeProto.AttributeType


def _varint(value: int) -> bytes:
    out = bytearray()
    value &= (1 << 64) - 1
    while True:
        byte = value & 0x7F
        value >>= 7
        if value:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def _key(field: int, wire: int) -> bytes:
    return _varint((field << 3) | wire)


def _int(field: int, value: int) -> bytes:
    return _key(field, 0) + _varint(value)


def _bytes(field: int, payload: bytes) -> bytes:
    return _key(field, 2) + _varint(len(payload)) + payload


def _str(field: int, text: str) -> bytes:
    return _bytes(field, text.encode())


def _tensor(name: str, array: np.ndarray) -> bytes:
    array = np.ascontiguousarray(array, dtype="<f4")
    dims = b"".join(_int(1, d) for d in array.shape)
    return dims + _int(2, _FLOAT) + _str(8, name) + _bytes(9, array.tobytes())


def _value_info(name: str, shape: tuple[int, ...]) -> bytes:
    dims = b"".join(_bytes(1, _int(1, d)) for d in shape)  # Dimension.dim_value
    tensor_type = _int(1, _FLOAT) + _bytes(2, dims)  # TypeProto.Tensor: elem_type, shape
    return _str(1, name) + _bytes(2, _bytes(1, tensor_type))  # ValueInfoProto: name, type


def _attr_ints(name: str, values: list[int]) -> bytes:
    return _str(1, name) + b"".join(_int(8, v) for v in values) + _int(20, _ATTR_INTS)


def _node(op: str, inputs: list[str], outputs: list[str], attributes: list[bytes] = ()) -> bytes:
    body = b"".join(_str(1, i) for i in inputs) + b"".join(_str(2, o) for o in outputs)
    body += _str(3, f"{op}_{outputs[0]}") + _str(4, op)
    return body + b"".join(_bytes(5, a) for a in attributes)


def model_bytes(nodes, initializers, inputs, outputs, opset: int = 13) -> bytes:
    graph = b"".join(_bytes(1, n) for n in nodes) + _str(2, "tiny")
    graph += b"".join(_bytes(5, _tensor(name, array)) for name, array in initializers)
    graph += b"".join(_bytes(11, _value_info(name, shape)) for name, shape in inputs)
    graph += b"".join(_bytes(12, _value_info(name, shape)) for name, shape in outputs)
    opset_id = _str(1, "") + _int(2, opset)
    return _int(1, 8) + _str(2, "stg_node-tests") + _bytes(7, graph) + _bytes(8, opset_id)


def dot_heatmap_model(
    path, width: int = 192, height: int = 256, stride: int = 4, keypoints: int = 17
) -> None:
    """Write the COCO-17 heatmap network described in the module docstring."""
    weight = np.zeros((keypoints, 3, 1, 1), np.float32)
    for k in range(keypoints):
        weight[k, k % 3, 0, 0] = 1.0
    nodes = [
        _node(
            "AveragePool",
            ["input"],
            ["pooled"],
            [_attr_ints("kernel_shape", [stride, stride]), _attr_ints("strides", [stride, stride])],
        ),
        _node("Conv", ["pooled", "weight"], ["heatmaps"], [_attr_ints("kernel_shape", [1, 1])]),
    ]
    data = model_bytes(
        nodes,
        [("weight", weight)],
        [("input", (1, 3, height, width))],
        [("heatmaps", (1, keypoints, height // stride, width // stride))],
    )
    with open(path, "wb") as fh:
        fh.write(data)
