"""Bags: MCAP in the rosbag2 layout, written, read with every chunk checked, and recovered
after a killed recorder; a pure library (no DDS), shared by the recorder, replay and refilter."""
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
    TopicInfo,
)
from rcbf_ros.bag.recover import check_bag, FileRecovery, recover_bag, recover_file, reindex_bag
from rcbf_ros.bag.scan import BagError, BagNotFoundError, McapScan
from rcbf_ros.bag.writer import BagWriter, BagWriterConfig, TopicRecord, write_metadata_yaml

__all__ = [
    'BagError', 'BagInfo', 'BagMessage', 'BagNotFoundError', 'BagWriter', 'BagWriterConfig',
    'FileRecovery', 'INFINITE_DURATION_NS', 'McapScan', 'RecordedQos', 'TopicInfo',
    'TopicRecord', 'bag_info', 'check_bag', 'dump_offered_qos_profiles', 'mcap_files',
    'parse_offered_qos_profiles', 'read_bag', 'read_bag_messages', 'recover_bag',
    'recover_file', 'reindex_bag', 'write_metadata_yaml',
]
