"""sensor_msgs/PointCloud2 <-> numpy, without sensor_msgs_py and without rclpy.

Works on any object with the PointCloud2 attributes (rclpy messages and rosbags
dataclasses alike). Depth drivers differ in point_step (16, 20, 32, ...), float width,
padding and organisation, so x, y and z are read by their field offsets with one strided
numpy view: no Python loop over points.
"""
from __future__ import annotations

import numpy as np

from ..core.point_sets import finite_rows

# sensor_msgs/PointField datatypes
INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64 = range(1, 9)
_FLOAT_TYPES = {FLOAT32: 'f4', FLOAT64: 'f8'}
_DATATYPE_SIZES = {INT8: 1, UINT8: 1, INT16: 2, UINT16: 2, INT32: 4, UINT32: 4, FLOAT32: 4, FLOAT64: 8}


class CloudDecodeError(ValueError):
    """A PointCloud2 message that cannot be read as x, y, z points; the text says why."""


def decode_xyz(msg, dtype=np.float32) -> np.ndarray:
    """(height * width, 3) points (float32 unless `dtype` says otherwise) of a PointCloud2,
    in row-major pixel order.

    Invalid points (NaN / inf) are kept, so an organized cloud keeps its layout; use
    `finite_points` to drop them. Raises CloudDecodeError on missing x/y/z fields,
    unsupported field types, inconsistent sizes or truncated data.
    """
    width, height, point_step = int(msg.width), int(msg.height), int(msg.point_step)
    n_points = width * height
    fields = {f.name: f for f in msg.fields}
    missing = [name for name in ('x', 'y', 'z') if name not in fields]
    if missing:
        present = ', '.join(fields) or 'none'
        raise CloudDecodeError(f'PointCloud2 has no field {"/".join(missing)} (fields: {present})')
    if n_points == 0:
        return np.empty((0, 3), dtype=dtype)
    endian = '>' if msg.is_bigendian else '<'
    formats, offsets = [], []
    for name in ('x', 'y', 'z'):
        field = fields[name]
        if field.datatype not in _FLOAT_TYPES:
            raise CloudDecodeError(f'field {name} has datatype {field.datatype}; '
                                   'only FLOAT32 (7) and FLOAT64 (8) are supported')
        end = field.offset + _DATATYPE_SIZES[field.datatype]
        if end > point_step:
            raise CloudDecodeError(f'field {name} (offset {field.offset}) does not fit in '
                                   f'point_step {point_step}')
        formats.append(endian + _FLOAT_TYPES[field.datatype])
        offsets.append(field.offset)
    row_step = int(msg.row_step) if int(msg.row_step) > 0 else width * point_step
    if row_step < width * point_step:
        raise CloudDecodeError(f'row_step {row_step} is smaller than width * point_step '
                               f'({width} * {point_step})')
    data = msg.data
    buffer = data if isinstance(data, (bytes, bytearray, memoryview)) else np.asarray(data, dtype=np.uint8)
    buffer = np.frombuffer(buffer, dtype=np.uint8)
    needed = row_step * (height - 1) + width * point_step
    if buffer.size < needed:
        raise CloudDecodeError(f'PointCloud2 data is truncated: {buffer.size} bytes for '
                               f'{height}x{width} points of {point_step} bytes (need {needed})')
    record_type = np.dtype({'names': ['x', 'y', 'z'], 'formats': formats, 'offsets': offsets,
                      'itemsize': point_step})
    rows = np.lib.stride_tricks.as_strided(buffer, shape=(height, width * point_step),
                                           strides=(row_step, 1))
    records = np.ascontiguousarray(rows).view(record_type).reshape(-1)
    points = np.empty((n_points, 3), dtype=dtype)
    points[:, 0], points[:, 1], points[:, 2] = records['x'], records['y'], records['z']
    return points


def finite_points(points: np.ndarray) -> np.ndarray:
    """Drop rows with any NaN or inf coordinate: (N, 3) -> (K, 3)."""
    return points[finite_rows(points)]


def xyz_cloud_fields(float64: bool = False) -> list:
    """(name, offset, datatype, count) of an x, y, z cloud, float32 or float64."""
    size, datatype = (8, FLOAT64) if float64 else (4, FLOAT32)
    return [(name, size * i, datatype, 1) for i, name in enumerate('xyz')]


def encode_xyz(points: np.ndarray, point_step: int = 16, float64: bool = False) -> tuple:
    """Pack (H, W, 3) or (N, 3) points as PointCloud2 payload: float32 x, y, z padded to
    point_step bytes (OpenNI-style), or with float64 packed float64 (point_step 24).

    Returns (height, width, point_step, row_step, data bytes, is_dense). An (N, 3) array
    gives an unorganized cloud (height 1).
    """
    points = np.asarray(points, dtype=np.float64 if float64 else np.float32)
    if points.ndim == 2:
        points = points[None]
    if points.ndim != 3 or points.shape[2] != 3:
        raise ValueError(f'points must be (N, 3) or (H, W, 3), got {points.shape}')
    height, width = points.shape[:2]
    if float64:
        point_step = 24
    elif point_step % 4 or point_step < 12:
        raise ValueError('point_step must be a multiple of 4 and at least 12')
    packed = np.zeros((height, width, point_step // points.itemsize), dtype=points.dtype.newbyteorder('<'))
    packed[..., :3] = points
    is_dense = bool(np.isfinite(points).all())
    return height, width, point_step, width * point_step, packed.tobytes(), is_dense


def pointcloud2(cloud_type, field_type, header, points: np.ndarray, point_step: int = 16,
                float64: bool = False, data_as_array: bool = False):
    """The one PointCloud2 builder: a message of cloud_type with fields of field_type (the
    rclpy classes, or the rosbags typestore's), its header, and the points encoded by
    encode_xyz. data_as_array: the payload as a uint8 numpy array (rosbags), else bytes."""
    height, width, point_step, row_step, data, is_dense = encode_xyz(points, point_step, float64)
    fields = [field_type(name=n, offset=o, datatype=d, count=c) for n, o, d, c in xyz_cloud_fields(float64)]
    return cloud_type(header=header, height=height, width=width, fields=fields, is_bigendian=False,
                      point_step=point_step, row_step=row_step, is_dense=is_dense,
                      data=np.frombuffer(data, dtype=np.uint8) if data_as_array else data)
