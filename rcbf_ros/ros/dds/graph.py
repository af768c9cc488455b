"""ROS 2 graph information of the Cyclone runtime: rmw_dds_common's ``ros_discovery_info``.

DDS discovery tells which participants, readers and writers exist; which ROS node owns which
reader and writer travels in ROS 2's own topic ``ros_discovery_info`` (DDS topic name as is, no
``rt/`` prefix), type ``rmw_dds_common/msg/ParticipantEntitiesInfo``, one sample per participant:
its GID and, per node, namespace, name and the GIDs of the node's readers and writers. A GID is
the entity's 16-byte DDS GUID (``RMW_GID_STORAGE_SIZE`` is 16 in Jazzy).

As rmw_cyclonedds does, each context (one participant) writes its sample reliable, transient
local, keep-last 1 (late joiners get the current one) whenever one of its nodes or endpoints is
created or destroyed, and reads the other participants' samples keep-all, ignoring its own;
when a participant leaves DDS discovery its nodes leave the graph. This is the only traffic it
adds: nothing per message.

The reader is drained when the graph is queried, whenever this context writes, and by every
node's executor as samples arrive (each node's wait set waits on :attr:`GraphInfo.condition`),
not by a thread: samples only arrive when some process's graph changes, but a keep-all reader
left alone would keep every one of them (a client created and destroyed elsewhere, as ``ros2
param get`` does, is four samples).
"""
from __future__ import annotations

from dataclasses import dataclass, field
import threading
from typing import Any, Callable, Iterable, Mapping, Sequence

from cyclonedds._clayer import ddspy_take, ddspy_write
from cyclonedds.builtin import BuiltinDataReader, BuiltinTopicDcpsParticipant
from cyclonedds.core import InstanceState, Policy, Qos, ReadCondition, SampleState, ViewState
from cyclonedds.domain import DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic

from rcbf_ros.ros.dds import messages
from rcbf_ros.ros.dds.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    to_cyclone_qos,
    type_user_data,
)

DISCOVERY_TOPIC = 'ros_discovery_info'
"""DDS topic name of the graph information (rmw uses it as is, without ``rt/``)."""
PARTICIPANT_INFO_TYPE = 'rmw_dds_common/msg/ParticipantEntitiesInfo'
GID_SIZE = 16
"""Bytes of a GID in Jazzy (``RMW_GID_STORAGE_SIZE``): a Cyclone GUID exactly."""
WRITER_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)
"""rmw_cyclonedds' QoS of its ``ros_discovery_info`` writer."""
READER_QOS = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)
"""... and of its reader (which ignores the participant's own samples)."""
NODE_NAME_UNKNOWN = ('_NODE_NAME_UNKNOWN_', '_NODE_NAMESPACE_UNKNOWN_')
"""rmw's (name, namespace) of an endpoint of a ROS participant that no node claims (yet)."""
BARE_DDS_APP = ('_CREATED_BY_BARE_DDS_APP_', '_CREATED_BY_BARE_DDS_APP_')
"""rmw's (name, namespace) of an endpoint of a participant that is not a ROS one."""

_ANY_SAMPLE = SampleState.Any | ViewState.Any | InstanceState.Any
_TAKE_BATCH = 64


def gid_of(entity: Any) -> bytes:
    """The GID of a Cyclone entity (participant, reader, writer): its 16-byte GUID."""
    return entity.guid.bytes


@dataclass
class NodeEntities:
    """One node's entry in ``ros_discovery_info``."""

    namespace: str
    """Node namespace (``/`` or ``/a/b``)."""
    name: str
    """Node name."""
    readers: list[bytes] = field(default_factory=list)
    """GIDs of the node's DDS readers, in creation order."""
    writers: list[bytes] = field(default_factory=list)
    """GIDs of the node's DDS writers, in creation order."""


def participant_info_message(*, participant_gid: bytes,
                             nodes: Iterable[NodeEntities]) -> messages.Message:
    """The ``ParticipantEntitiesInfo`` a participant with these nodes publishes."""
    gid_type = messages.get_message('rmw_dds_common/msg/Gid')
    node_type = messages.get_message('rmw_dds_common/msg/NodeEntitiesInfo')
    return messages.get_message(PARTICIPANT_INFO_TYPE)(
        gid=gid_type(data=participant_gid),
        node_entities_info_seq=[
            node_type(node_namespace=node.namespace, node_name=node.name,
                      reader_gid_seq=[gid_type(data=gid) for gid in node.readers],
                      writer_gid_seq=[gid_type(data=gid) for gid in node.writers])
            for node in nodes])


def nodes_of_message(message: Any) -> tuple[bytes, list[NodeEntities]]:
    """Participant GID and nodes of a ``ParticipantEntitiesInfo`` (inverse of
    :func:`participant_info_message`)."""
    return bytes(message.gid.data), [
        NodeEntities(namespace=info.node_namespace, name=info.node_name,
                     readers=[bytes(gid.data) for gid in info.reader_gid_seq],
                     writers=[bytes(gid.data) for gid in info.writer_gid_seq])
        for info in message.node_entities_info_seq]


def node_of_endpoint(*, participants: Mapping[bytes, Sequence[NodeEntities]],
                     participant_gid: bytes, endpoint_gid: bytes,
                     is_reader: bool) -> tuple[str, str]:
    """(name, namespace) of the node owning an endpoint, as rmw_dds_common's graph cache says:
    the node listing its GID; :data:`NODE_NAME_UNKNOWN` if its participant is a ROS one (in
    ``participants``) but no node lists it; :data:`BARE_DDS_APP` otherwise."""
    nodes = participants.get(participant_gid)
    if nodes is None:
        return BARE_DDS_APP
    for node in nodes:
        if endpoint_gid in (node.readers if is_reader else node.writers):
            return node.name, node.namespace
    return NODE_NAME_UNKNOWN


def _is_ros_participant(qos: Qos | None) -> bool:
    """True if a participant's USER_DATA carries rmw's ``enclave=`` key."""
    user_data = qos[Policy.Userdata] if qos is not None else None
    data = getattr(user_data, 'data', b'') or b''
    return any(item.startswith(b'enclave=') for item in data.split(b';'))


class GraphInfo:
    """This context's entry in ``ros_discovery_info`` and what the others publish there.

    Node entries are changed through :meth:`add_node`, :meth:`remove_node`,
    :meth:`add_endpoint` and :meth:`remove_endpoint`; each change publishes the whole entry once.
    """

    def __init__(self, participant: DomainParticipant, *,
                 read_builtin: Callable[[Any, Any, int], list[Any]]) -> None:
        """``read_builtin(reader, condition, count)`` reads a built-in topic reader (the
        context's, which turns a signal inside Cyclone's callbacks into its exception)."""
        self.gid = gid_of(participant)
        self._read_builtin = read_builtin
        """This participant's GID."""
        self.undecodable_count = 0
        """Samples of other participants that did not decode (dropped)."""
        self._lock = threading.RLock()
        self._nodes: list[NodeEntities] = []
        self._remote: dict[bytes, list[NodeEntities]] = {}
        user_data = type_user_data(PARTICIPANT_INFO_TYPE)
        self._topic = Topic(participant, DISCOVERY_TOPIC,
                            messages.idl_struct(PARTICIPANT_INFO_TYPE))
        self._writer: DataWriter | None = DataWriter(
            participant, self._topic, qos=to_cyclone_qos(WRITER_QOS, user_data))
        self._reader: DataReader | None = DataReader(
            participant, self._topic,
            qos=to_cyclone_qos(READER_QOS, user_data) + Qos(Policy.IgnoreLocal.Participant))
        self.condition: ReadCondition | None = ReadCondition(self._reader, _ANY_SAMPLE)
        """Triggered while other participants' samples wait to be taken (:meth:`drain`)."""
        self._participants = BuiltinDataReader(participant, BuiltinTopicDcpsParticipant)
        self._alive_participants = ReadCondition(
            self._participants, SampleState.Any | ViewState.Any | InstanceState.Alive)

    # this participant's nodes ---------------------------------------------------------------
    def add_node(self, *, name: str, namespace: str) -> NodeEntities:
        """Add a node (no endpoints yet) and publish; the entry to pass to the other calls."""
        node = NodeEntities(namespace=namespace, name=name)
        with self._lock:
            self._nodes.append(node)
            self._publish()
        return node

    def remove_node(self, node: NodeEntities) -> None:
        """Remove a node with its endpoints and publish (nothing if it is not listed)."""
        with self._lock:
            if any(entry is node for entry in self._nodes):
                self._nodes = [entry for entry in self._nodes if entry is not node]
                self._publish()

    def add_endpoint(self, node: NodeEntities, gid: bytes, *, is_reader: bool) -> None:
        """List a reader's or writer's GID under ``node`` and publish."""
        with self._lock:
            (node.readers if is_reader else node.writers).append(gid)
            self._publish()

    def remove_endpoint(self, node: NodeEntities, gid: bytes, *, is_reader: bool) -> None:
        """Unlist a reader's or writer's GID and publish (nothing if it is not listed)."""
        with self._lock:
            gids = node.readers if is_reader else node.writers
            if gid in gids:
                gids.remove(gid)
                self._publish()

    def _publish(self) -> None:
        if self._writer is None:
            return
        self._take_remote()  # keeps the keep-all reader's backlog short without a thread
        data = messages.serialize_message(
            participant_info_message(participant_gid=self.gid, nodes=self._nodes))
        ret = ddspy_write(self._writer._ref, messages.dds_payload(data))
        if isinstance(ret, int) and ret < 0:
            raise RuntimeError(f'DDS write on {DISCOVERY_TOPIC} failed with code {ret}')

    # the graph ------------------------------------------------------------------------------
    def participants(self) -> dict[bytes, list[NodeEntities]]:
        """Every ROS participant in the graph (this one included), by GID in GID order, with its
        nodes in their order of creation; what rmw's graph cache holds."""
        with self._lock:
            if self._reader is None:
                return {}
            self._take_remote()
            alive = {}
            for sample in self._read_builtin(self._participants, self._alive_participants,
                                             100000):
                alive[sample.key.bytes] = _is_ros_participant(sample.qos)
            self._remote = {gid: nodes for gid, nodes in self._remote.items() if gid in alive}
            known = {gid: [] for gid, ros in alive.items() if ros and gid != self.gid}
            known.update(self._remote)
            known[self.gid] = [NodeEntities(n.namespace, n.name, list(n.readers),
                                            list(n.writers)) for n in self._nodes]
            return dict(sorted(known.items()))

    def node_names_and_namespaces(self) -> list[tuple[str, str]]:
        """(name, namespace) of every node in the graph, as rclpy's
        ``get_node_names_and_namespaces``."""
        return [(node.name, node.namespace)
                for nodes in self.participants().values() for node in nodes]

    def drain(self) -> None:
        """Take the other participants' samples that arrived (their entries kept, the samples
        freed)."""
        with self._lock:
            if self._reader is not None:
                self._take_remote()

    def _take_remote(self) -> None:
        while True:
            samples = ddspy_take(self._reader._ref, _ANY_SAMPLE, _TAKE_BATCH)
            if isinstance(samples, int):
                raise RuntimeError(f'DDS take on {DISCOVERY_TOPIC} failed with code {samples}')
            for data, info in samples:
                if not info.valid_data:
                    continue
                try:
                    message = messages.deserialize_message(data, PARTICIPANT_INFO_TYPE)
                except messages.DeserializationError:
                    self.undecodable_count += 1
                    continue
                gid, nodes = nodes_of_message(message)
                if gid != self.gid:
                    self._remote[gid] = nodes
            if len(samples) < _TAKE_BATCH:
                return

    def close(self) -> None:
        """Delete the DDS entities (idempotent); the participant's nodes are gone by then."""
        with self._lock:
            for entity in (self._alive_participants, self._participants, self.condition,
                           self._reader, self._writer, self._topic):
                if entity is not None:
                    entity.__del__()
            self._reader = self._writer = self.condition = None
            self._alive_participants = self._participants = self._topic = None
