"""PointCloud2 decoding across driver layouts."""
from types import SimpleNamespace

import numpy as np
import pytest

from skel_extract_ros.codecs.pointcloud import CloudDecodeError, decode_xyz, encode_xyz, finite_points


def make_msg(points, point_step=16, dtype='<f4', offsets=(0, 4, 8), height=1, big_endian=False,
             row_padding=0, extra_field=None):
    points = np.asarray(points, dtype=np.float64)
    n = len(points)
    width = n // height
    itemsize = np.dtype(dtype).itemsize
    record = np.zeros((n, point_step), dtype=np.uint8)
    for axis, offset in enumerate(offsets):
        record[:, offset:offset + itemsize] = points[:, axis].astype(dtype).view(np.uint8).reshape(n, itemsize)
    rows = record.reshape(height, width * point_step)
    rows = np.concatenate([rows, np.full((height, row_padding), 0xAB, np.uint8)], axis=1)
    datatype = 7 if itemsize == 4 else 8
    fields = [SimpleNamespace(name=name, offset=o, datatype=datatype, count=1)
              for name, o in zip('xyz', offsets)]
    if extra_field:
        fields.append(SimpleNamespace(name=extra_field[0], offset=extra_field[1], datatype=7, count=1))
    return SimpleNamespace(width=width, height=height, point_step=point_step,
                           row_step=width * point_step + row_padding, fields=fields,
                           is_bigendian=big_endian, data=rows.tobytes())


POINTS = np.random.default_rng(0).normal(size=(12, 3))


@pytest.mark.parametrize('point_step', [12, 16, 20, 32])
def test_float32_layouts(point_step):
    np.testing.assert_allclose(decode_xyz(make_msg(POINTS, point_step)), POINTS, rtol=1e-6)


def test_float64_and_big_endian_and_row_padding():
    np.testing.assert_allclose(decode_xyz(make_msg(POINTS, 32, '<f8', (0, 8, 16))), POINTS, rtol=1e-6)
    np.testing.assert_allclose(decode_xyz(make_msg(POINTS, 16, '>f4', big_endian=True)), POINTS, rtol=1e-6)
    np.testing.assert_allclose(decode_xyz(make_msg(POINTS, 16, height=3, row_padding=8)), POINTS, rtol=1e-6)


def test_shuffled_offsets_and_rgb_field():
    msg = make_msg(POINTS, 32, offsets=(8, 0, 4), extra_field=('rgb', 16))
    np.testing.assert_allclose(decode_xyz(msg), POINTS, rtol=1e-6)


def test_organized_nan_cloud_keeps_layout():
    points = POINTS.copy()
    points[[1, 5]] = np.nan
    decoded = decode_xyz(make_msg(points, 16, height=3))
    assert decoded.shape == (12, 3)
    assert len(finite_points(decoded)) == 10


def test_errors_are_specific():
    msg = make_msg(POINTS)
    msg.fields = msg.fields[:2]
    with pytest.raises(CloudDecodeError, match='no field z'):
        decode_xyz(msg)
    msg = make_msg(POINTS)
    msg.data = msg.data[:-5]
    with pytest.raises(CloudDecodeError, match='truncated'):
        decode_xyz(msg)
    msg = make_msg(POINTS)
    msg.point_step = 8
    with pytest.raises(CloudDecodeError, match='does not fit'):
        decode_xyz(msg)
    msg = make_msg(POINTS)
    msg.fields[0].datatype = 2
    with pytest.raises(CloudDecodeError, match='datatype'):
        decode_xyz(msg)


def test_empty_cloud():
    msg = make_msg(POINTS)
    msg.width, msg.data = 0, b''
    assert decode_xyz(msg).shape == (0, 3)


def test_encode_round_trip():
    organized = np.random.default_rng(1).normal(size=(4, 5, 3)).astype(np.float32)
    height, width, step, row_step, data, dense = encode_xyz(organized)
    msg = SimpleNamespace(width=width, height=height, point_step=step, row_step=row_step,
                          is_bigendian=False, data=data,
                          fields=[SimpleNamespace(name=n, offset=o, datatype=7, count=1)
                                  for n, o in zip('xyz', (0, 4, 8))])
    np.testing.assert_array_equal(decode_xyz(msg).reshape(4, 5, 3), organized)
    assert dense
