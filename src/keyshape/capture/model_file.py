"""The vendored model file ``face_landmarker.task``: what keyshape reads from it besides the tracker.

The file is a zip; ``geometry_pipeline_metadata_landmarks.binarypb`` inside holds MediaPipe's
canonical face mesh as a protobuf message, decoded here with a minimal reader (no protobuf
dependency).
"""

from __future__ import annotations

import struct
import zipfile
from importlib import resources

import numpy as np

from ..exceptions import InputError

__all__ = ["canonical_face"]


def canonical_face() -> tuple[np.ndarray, np.ndarray]:
    """MediaPipe's canonical face mesh: vertices ``(468, 3)`` in centimetres, faces ``(898, 3)``.

    Read from ``geometry_pipeline_metadata_landmarks.binarypb`` inside the vendored
    ``face_landmarker.task`` (a zip): message ``GeometryPipelineMetadata``, field 1
    ``canonical_mesh`` (``Mesh3d``: field 3 ``vertex_buffer`` as x, y, z, u, v floats;
    field 4 ``index_buffer``), decoded with a minimal protobuf reader.
    """
    model = resources.files("keyshape").joinpath("data/face_landmarker.task")
    with resources.as_file(model) as path, zipfile.ZipFile(path) as archive:
        blob = archive.read("geometry_pipeline_metadata_landmarks.binarypb")
    mesh = next(value for number, _, value in _fields(blob) if number == 1)
    floats, indices = [], []
    for number, wire, value in _fields(mesh):
        if number == 3:
            floats.extend(struct.unpack(f"<{len(value) // 4}f", value) if wire == 2 else [_as_float(value)])
        elif number == 4:
            indices.extend(_packed_varints(value) if wire == 2 else [value])
    vertices = np.array(floats, dtype=float).reshape(-1, 5)[:, :3]
    return vertices, np.array(indices, dtype=np.int64).reshape(-1, 3)


def _as_float(raw: bytes) -> float:
    return struct.unpack("<f", raw)[0]


def _varint(data: bytes, i: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        byte = data[i]
        i += 1
        value |= (byte & 0x7F) << shift
        shift += 7
        if byte < 0x80:
            return value, i


def _packed_varints(data: bytes) -> list[int]:
    out, i = [], 0
    while i < len(data):
        value, i = _varint(data, i)
        out.append(value)
    return out


def _fields(data: bytes):
    """(field number, wire type, value) of a protobuf message: varint, fixed32/64 bytes or bytes."""
    i = 0
    while i < len(data):
        key, i = _varint(data, i)
        number, wire = key >> 3, key & 7
        if wire == 0:
            value, i = _varint(data, i)
        elif wire == 1:
            value, i = data[i:i + 8], i + 8
        elif wire == 5:
            value, i = data[i:i + 4], i + 4
        elif wire == 2:
            length, i = _varint(data, i)
            value, i = data[i:i + length], i + length
        else:
            raise InputError(f"face_landmarker.task: unsupported protobuf wire type {wire}")
        yield number, wire, value
