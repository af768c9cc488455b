"""LaserScan, PointCloud2 and Range test messages encoded by rosbags' Jazzy type store (an
encoder that is not the reader under test)."""
from __future__ import annotations

import math

import numpy as np

from rcbf_ros.messages import sensor
from rcbf_ros.messages.typestore import jazzy_typestore

STORE = jazzy_typestore()
T = STORE.types
FLOAT32_MAX = float(np.finfo(np.float32).max)


def header(frame_id: str = 'laser', sec: int = 12, nanosec: int = 345):
    return T['std_msgs/msg/Header'](
        stamp=T['builtin_interfaces/msg/Time'](sec=sec, nanosec=nanosec), frame_id=frame_id)


def scan_bytes(ranges, *, angle_min=0.0, increment=0.1, range_min=0.1, range_max=10.0,
                frame_id='laser', little_endian=True, intensities=None) -> bytes:
    ranges = np.asarray(ranges, dtype=np.float32)
    angle_max = angle_min + increment * max(len(ranges) - 1, 0)
    if math.isfinite(angle_max):   # a float32 field: a finite sum past its range is its limit
        angle_max = max(min(angle_max, FLOAT32_MAX), -FLOAT32_MAX)
    msg = T[sensor.LASER_SCAN](
        header=header(frame_id), angle_min=angle_min,
        angle_max=angle_max, angle_increment=increment,
        time_increment=0.0, scan_time=0.1, range_min=range_min, range_max=range_max,
        ranges=ranges,
        intensities=np.asarray(intensities if intensities is not None else [], np.float32))
    return bytes(STORE.serialize_cdr(msg, sensor.LASER_SCAN, little_endian=little_endian))


def cloud_bytes(points: np.ndarray, *, dtype='<f4', layout=('x', 'y', 'z'), pad: int = 0,
                 height: int = 1, row_pad: int = 0, frame_id='base_link',
                 little_endian=True, fields=None, data_cut: int = 0) -> bytes:
    """A cloud of (N, 3) ``points`` with its fields in ``layout`` order, ``pad`` bytes after
    the coordinates of each point and ``row_pad`` bytes after each row."""
    item = np.dtype(dtype)
    names = list(layout) + ([f'_pad{k}' for k in range(pad)])
    formats = [item] * len(layout) + [np.uint8] * pad
    record = np.dtype({'names': names, 'formats': formats})
    n = len(points)
    width = n // height
    table = np.zeros(n, dtype=record)
    for k, axis in enumerate('xyz'):
        if axis in layout:
            table[axis] = points[:, k]
    rows = table.view(np.uint8).reshape(height, width * record.itemsize)
    rows = np.concatenate([rows, np.full((height, row_pad), 7, np.uint8)], axis=1)
    data = rows.ravel()
    if data_cut:
        data = data[:-data_cut]
    datatype = sensor.FLOAT32 if item.itemsize == 4 else sensor.FLOAT64
    field = T['sensor_msgs/msg/PointField']
    if fields is None:
        fields = [field(name=name, offset=record.fields[name][1], datatype=datatype, count=1)
                  for name in layout]
    msg = T[sensor.POINT_CLOUD2](
        header=header(frame_id), height=height, width=width, fields=fields,
        is_bigendian=item.byteorder == '>', point_step=record.itemsize,
        row_step=width * record.itemsize + row_pad, data=data, is_dense=False)
    return bytes(STORE.serialize_cdr(msg, sensor.POINT_CLOUD2, little_endian=little_endian))


def range_bytes(reading: float, *, field_of_view: float = 0.5, min_range: float = 0.02,
                max_range: float = 4.0, frame_id: str = 'sonar',
                little_endian: bool = True) -> bytes:
    msg = T[sensor.RANGE](header=header(frame_id), radiation_type=0,
                          field_of_view=field_of_view, min_range=min_range,
                          max_range=max_range, range=reading, variance=0.0)
    return bytes(STORE.serialize_cdr(msg, sensor.RANGE, little_endian=little_endian))
