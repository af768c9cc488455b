"""Bags: MCAP in the rosbag2 layout (writer, reader, QoS records). Pure library, no DDS."""
from __future__ import annotations

from rcbf_ros.bag.qos import (
    dump_offered_qos_profiles,
    INFINITE_DURATION_NS,
    parse_offered_qos_profiles,
    RecordedQos,
)
from rcbf_ros.bag.reader import (
    bag_info,
    BagInfo,
    BagMessage,
    mcap_files,
    read_bag,
    read_bag_messages,
    reindex_bag,
    TopicInfo,
)
from rcbf_ros.bag.writer import BagWriter, BagWriterConfig, TopicRecord, write_metadata_yaml

__all__ = [
    'BagInfo', 'BagMessage', 'BagWriter', 'BagWriterConfig', 'INFINITE_DURATION_NS',
    'RecordedQos', 'TopicInfo', 'TopicRecord', 'bag_info', 'dump_offered_qos_profiles',
    'mcap_files', 'parse_offered_qos_profiles', 'read_bag', 'read_bag_messages',
    'reindex_bag', 'write_metadata_yaml',
]
