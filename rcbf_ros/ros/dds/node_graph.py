"""A node's view of the ROS graph, as rclpy's Node queries it (the graph half of
:class:`.node.Node`).

Topics and endpoints come from DDS discovery (Cyclone's built-in topics, local endpoints
included); which node owns an endpoint, and which nodes exist, from ``ros_discovery_info``
(:mod:`.graph`).
"""
from __future__ import annotations

from typing import Any

from cyclonedds.builtin import (
    BuiltinDataReader,
    BuiltinTopicDcpsPublication,
    BuiltinTopicDcpsSubscription,
)
from cyclonedds.core import InstanceState, ReadCondition, SampleState, ViewState

from rcbf_ros.ros.dds import messages
from rcbf_ros.ros.dds.context import delete_entity
from rcbf_ros.ros.dds.endpoints import TopicEndpointInfo, TopicEndpointTypeEnum
from rcbf_ros.ros.dds.graph import node_of_endpoint
from rcbf_ros.ros.dds.qos import from_cyclone_qos


class NodeGraph:
    """Graph queries of a node (rclpy's Node methods); the node has ``context`` and
    ``resolve_topic_name``."""

    def _init_graph_queries(self) -> None:
        """No built-in topic readers yet (created on the first query)."""
        self._builtin_readers: list[tuple[BuiltinDataReader, ReadCondition, ReadCondition]] \
            | None = None
        self._endpoint_cache: dict[Any, list[Any]] = {}

    def _close_graph_queries(self) -> None:
        """Delete the built-in topic readers (idempotent)."""
        for reader, alive_condition, unread_condition in self._builtin_readers or ():
            delete_entity(alive_condition)
            delete_entity(unread_condition)
            delete_entity(reader)
        self._builtin_readers = None
        self._endpoint_cache = {}

    def _alive_endpoints(self, kinds: tuple[Any, ...] = (
            BuiltinTopicDcpsPublication, BuiltinTopicDcpsSubscription)) -> list[Any]:
        """Discovered (alive) endpoints of the given built-in topic kinds, local ones included.

        Reading them all converts every endpoint's QoS in Python (about 0.4 ms each), so the
        list of a kind is kept until discovery reports a change (an unread sample: a new
        endpoint, or one that went away).
        """
        if self._builtin_readers is None:
            alive = SampleState.Any | ViewState.Any | InstanceState.Alive
            unread = SampleState.NotRead | ViewState.Any | InstanceState.Any
            self._builtin_readers = []
            for kind in (BuiltinTopicDcpsPublication, BuiltinTopicDcpsSubscription):
                reader = BuiltinDataReader(self.context.participant, kind)
                self._builtin_readers.append(
                    (reader, ReadCondition(reader, alive), ReadCondition(reader, unread)))
            self._endpoint_cache = {}
        endpoints = []
        for kind, (reader, alive_condition, unread_condition) in zip(
                (BuiltinTopicDcpsPublication, BuiltinTopicDcpsSubscription),
                self._builtin_readers):
            if kind not in kinds:
                continue
            read = self.context.read_builtin
            changed = read(reader, unread_condition, 64)  # any will do
            if changed or kind not in self._endpoint_cache:
                self._endpoint_cache[kind] = read(reader, alive_condition, 100000)
            endpoints.extend(self._endpoint_cache[kind])
        return endpoints

    def get_topic_names_and_types(self, no_demangle: bool = False) -> list[tuple[str, list[str]]]:
        """``[(topic, [type, ...]), ...]`` of every ROS topic seen by DDS discovery, sorted."""
        topics: dict[str, set[str]] = {}
        for endpoint in self._alive_endpoints():
            if no_demangle:
                topics.setdefault(endpoint.topic_name, set()).add(endpoint.type_name)
            elif endpoint.topic_name.startswith('rt/'):
                topics.setdefault(endpoint.topic_name[2:], set()).add(
                    messages.ros_type_name(endpoint.type_name))
        return sorted((name, sorted(types)) for name, types in topics.items())

    def get_publishers_info_by_topic(self, topic_name: str,
                                     no_mangle: bool = False) -> list[TopicEndpointInfo]:
        """Publishers of ``topic_name`` (expanded, not remapped, as rclpy does) in the graph."""
        return self._endpoints_info(topic_name, no_mangle, TopicEndpointTypeEnum.PUBLISHER)

    def get_subscriptions_info_by_topic(self, topic_name: str,
                                        no_mangle: bool = False) -> list[TopicEndpointInfo]:
        """Subscriptions of ``topic_name`` (expanded, not remapped) in the graph."""
        return self._endpoints_info(topic_name, no_mangle, TopicEndpointTypeEnum.SUBSCRIPTION)

    def _endpoints_info(self, topic_name: str, no_mangle: bool,
                        kind: TopicEndpointTypeEnum) -> list[TopicEndpointInfo]:
        dds_name = topic_name if no_mangle else 'rt' + self.resolve_topic_name(
            topic_name, only_expand=True)
        is_reader = kind == TopicEndpointTypeEnum.SUBSCRIPTION
        builtin = BuiltinTopicDcpsSubscription if is_reader else BuiltinTopicDcpsPublication
        endpoints = [e for e in self._alive_endpoints((builtin,)) if e.topic_name == dds_name]
        participants = self.context.graph.participants() if endpoints else {}
        infos = []
        for e in endpoints:
            name, namespace = node_of_endpoint(
                participants=participants, participant_gid=e.participant_key.bytes,
                endpoint_gid=e.key.bytes, is_reader=is_reader)
            infos.append(TopicEndpointInfo(
                node_name=name, node_namespace=namespace,
                topic_type=messages.ros_type_name(e.type_name), endpoint_type=kind,
                endpoint_gid=list(e.key.bytes), qos_profile=from_cyclone_qos(e.qos)))
        return infos

    def get_node_names(self) -> list[str]:
        """Names of every node in the ROS graph (``ros_discovery_info``), this one included."""
        return [name for name, _ in self.get_node_names_and_namespaces()]

    def get_node_names_and_namespaces(self) -> list[tuple[str, str]]:
        """``[(name, namespace), ...]`` of every node in the ROS graph, as rclpy's."""
        return self.context.graph.node_names_and_namespaces()

    def count_publishers(self, topic_name: str) -> int:
        """Alive publishers of ``topic_name`` (resolved for this node) in the DDS graph."""
        return self._count(topic_name, BuiltinTopicDcpsPublication)

    def count_subscribers(self, topic_name: str) -> int:
        """Alive subscriptions of ``topic_name`` (resolved for this node) in the DDS graph."""
        return self._count(topic_name, BuiltinTopicDcpsSubscription)

    def _count(self, topic_name: str, kind: Any) -> int:
        dds_name = 'rt' + self.resolve_topic_name(topic_name)
        return sum(1 for e in self._alive_endpoints((kind,)) if e.topic_name == dds_name)
