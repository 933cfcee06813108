"""sensor_msgs/Image depth images <-> numpy and back-projection to an organized cloud,
without cv_bridge and without rclpy.

Depth drivers publish depth images by default (clouds only on request): OpenNI and Azure
Kinect as 16UC1 millimetres, RealSense as 16UC1 millimetres (`depth/image_rect_raw`),
some as 32FC1 metres; 0 or NaN is "no return". Rows may be padded (`step` larger than
width x bytes per pixel) and the data may be big-endian. Works on any object with the
Image / CameraInfo attributes (rclpy messages and rosbags dataclasses alike).
"""
from __future__ import annotations

import numpy as np

# encoding -> (numpy dtype, metres per unit)
DEPTH_ENCODINGS = {'16UC1': ('u2', 0.001), 'mono16': ('u2', 0.001), '32FC1': ('f4', 1.0)}


class DepthDecodeError(ValueError):
    """A depth image or camera info that cannot be used; the text says why."""


def decode_depth(msg) -> np.ndarray:
    """(H, W) float32 depth in metres of a depth Image, NaN where there is no return."""
    encoding = str(msg.encoding)
    if encoding not in DEPTH_ENCODINGS:
        raise DepthDecodeError(f'depth image encoding {encoding!r} is not supported '
                               f'(supported: {", ".join(DEPTH_ENCODINGS)})')
    kind, scale = DEPTH_ENCODINGS[encoding]
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    item = np.dtype(kind).itemsize
    if height == 0 or width == 0:
        return np.empty((height, width), dtype=np.float32)
    if step < width * item:
        raise DepthDecodeError(f'step {step} is smaller than width * {item} bytes ({width * item})')
    buffer = msg.data
    buffer = np.frombuffer(buffer if isinstance(buffer, (bytes, bytearray, memoryview))
                           else np.asarray(buffer, dtype=np.uint8), dtype=np.uint8)
    needed = step * (height - 1) + width * item
    if buffer.size < needed:
        raise DepthDecodeError(f'depth image data is truncated: {buffer.size} bytes for {height}x{width} '
                               f'{encoding} with step {step} (need {needed})')
    dtype = np.dtype(kind).newbyteorder('>' if msg.is_bigendian else '<')
    rows = np.lib.stride_tricks.as_strided(buffer, shape=(height, width * item), strides=(step, 1))
    depth = np.ascontiguousarray(rows).view(dtype).reshape(height, width).astype(np.float32) * np.float32(scale)
    depth[~(depth > 0)] = np.nan        # 0 (and NaN, negative) = no return
    return depth


def intrinsics_of(info) -> tuple:
    """(fx, fy, cx, cy) in pixels from a CameraInfo's K (row-major 3 x 3)."""
    k = np.asarray(info.k, dtype=np.float64).reshape(-1)
    if k.size != 9 or not (k[0] > 0 and k[4] > 0):
        raise DepthDecodeError('camera_info has no usable K (fx and fy must be positive)')
    return float(k[0]), float(k[4]), float(k[2]), float(k[5])


def back_project(depth: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """(H, W) depth in metres -> (H, W, 3) float32 organized cloud in the optical frame
    (x right, y down, z forward), NaN where depth is NaN. Lens distortion is not undone:
    depth drivers publish rectified or nearly distortion-free depth."""
    height, width = depth.shape
    u = (np.arange(width, dtype=np.float32) - np.float32(cx)) / np.float32(fx)
    v = (np.arange(height, dtype=np.float32) - np.float32(cy)) / np.float32(fy)
    points = np.empty((height, width, 3), dtype=np.float32)
    points[..., 0] = depth * u[None, :]
    points[..., 1] = depth * v[:, None]
    points[..., 2] = depth
    return points


def depth_to_cloud(image, info) -> np.ndarray:
    """(H, W, 3) organized cloud of a depth Image with its CameraInfo (sizes must agree)."""
    depth = decode_depth(image)
    if (int(info.height), int(info.width)) not in ((0, 0), depth.shape):
        raise DepthDecodeError(f'camera_info is {info.height}x{info.width} but the depth image is '
                               f'{depth.shape[0]}x{depth.shape[1]}')
    return back_project(depth, *intrinsics_of(info))


def encode_depth(depth: np.ndarray, encoding: str = '16UC1', pad_bytes: int = 0,
                 bigendian: bool = False) -> tuple:
    """Pack (H, W) metres (NaN = no return) as Image payload: (height, width, step, data).

    For tests and `skel-extract simulate --depth-image`; `pad_bytes` pads every row."""
    kind, scale = DEPTH_ENCODINGS[encoding]
    values = np.nan_to_num(np.asarray(depth, dtype=np.float64) / scale, nan=0.0)
    if kind == 'u2':
        values = np.clip(np.round(values), 0, 65535)
    typed = values.astype(np.dtype(kind).newbyteorder('>' if bigendian else '<'))
    height, width = typed.shape
    rows = typed.view(np.uint8).reshape(height, -1)
    padded = np.zeros((height, rows.shape[1] + pad_bytes), dtype=np.uint8)
    padded[:, :rows.shape[1]] = rows
    return height, width, padded.shape[1], padded.tobytes()
