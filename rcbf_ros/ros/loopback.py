"""Pin Eclipse Cyclone DDS to the loopback interface.

Every participant this package creates on these machines (tests, CI, benchmarks, the launch
command) must stay on the machine: the interface with address 127.0.0.1, no multicast, unicast
discovery of peers on 127.0.0.1. Cyclone reads ``CYCLONEDDS_URI`` once, when the first participant
is created, so ``ensure_loopback()`` must run before that (it is idempotent and never overrides a
URI the user set on purpose unless ``force=True``).

What the configuration cannot do: Cyclone (0.10 and 11, ``ddsi_udp_create_conn``) binds its
unicast RECEIVE sockets (one for discovery, one for data, per domain) to the wildcard address
0.0.0.0 whatever the configuration says; only its transmit socket binds to 127.0.0.1.
:func:`pin_wildcard_sockets_to_loopback` closes that gap on Linux by binding those sockets to the
loopback device (``SO_BINDTODEVICE``), so that they only receive what arrives on ``lo``.
"""
from __future__ import annotations

from dataclasses import dataclass
import os
import socket
import struct
from typing import Iterable, MutableMapping

LOOPBACK_DEVICE = 'lo'
"""Linux's loopback interface (``SO_BINDTODEVICE`` target)."""

WRITER_LINGER = '200 ms'
"""How long a deleted reliable writer waits for acknowledgements of its last samples.

Cyclone's default (1 s) is per writer and in sequence: a node stopping right after a sibling
was killed waits that long on EVERY writer the dead process read, for acknowledgements that will
never come (its participant lease has not run out yet). A live reader on loopback acknowledges
within milliseconds."""

LOOPBACK_CYCLONEDDS_URI = (
    '<CycloneDDS><Domain id="any"><General>'
    '<Interfaces><NetworkInterface address="127.0.0.1"/></Interfaces>'
    '<AllowMulticast>false</AllowMulticast>'
    '</General><Discovery>'
    '<Peers><Peer address="127.0.0.1"/></Peers>'
    '<ParticipantIndex>auto</ParticipantIndex>'
    '<MaxAutoParticipantIndex>60</MaxAutoParticipantIndex>'
    '</Discovery><Internal>'
    f'<WriterLingerDuration>{WRITER_LINGER}</WriterLingerDuration>'
    '</Internal></Domain></CycloneDDS>'
)


def ensure_loopback(environ: MutableMapping[str, str] | None = None, *,
                    force: bool = False) -> str:
    """Set ``CYCLONEDDS_URI`` to the loopback configuration (unless already set).

    Args:
        environ: the environment to modify (``os.environ`` by default; pass a copy for a
            child process).
        force: replace a URI that is already set.

    Returns:
        The URI now in effect.
    """
    env = os.environ if environ is None else environ
    if force or not env.get('CYCLONEDDS_URI'):
        env['CYCLONEDDS_URI'] = LOOPBACK_CYCLONEDDS_URI
    return env['CYCLONEDDS_URI']


@dataclass(frozen=True)
class UdpSocket:
    """One row of ``/proc/net/udp``."""

    inode: int
    """Socket inode (``socket:[<inode>]`` in ``/proc/<pid>/fd``)."""
    address: str
    """Local IPv4 address, dotted (``0.0.0.0``: the wildcard)."""
    port: int
    """Local port."""


def parse_proc_net_udp(text: str) -> list[UdpSocket]:
    """The sockets listed in ``/proc/net/udp`` text (addresses are in host byte order)."""
    sockets = []
    for line in text.splitlines()[1:]:
        fields = line.split()
        if len(fields) < 10:
            continue
        address, port = fields[1].split(':')
        dotted = socket.inet_ntoa(struct.pack('=I', int(address, 16)))
        sockets.append(UdpSocket(inode=int(fields[9]), address=dotted, port=int(port, 16)))
    return sockets


def own_socket_fds(pid: int | str = 'self') -> dict[int, int]:
    """Socket inode -> file descriptor, for every socket process ``pid`` holds open."""
    found = {}
    directory = f'/proc/{pid}/fd'
    for name in os.listdir(directory):
        try:
            target = os.readlink(f'{directory}/{name}')
        except OSError:  # closed meanwhile
            continue
        if target.startswith('socket:['):
            found[int(target[8:-1])] = int(name)
    return found


def own_udp_sockets(pid: int | str = 'self') -> list[tuple[UdpSocket, int]]:
    """The IPv4 UDP sockets of process ``pid`` with their file descriptors."""
    fds = own_socket_fds(pid)
    with open(f'/proc/{pid}/net/udp', encoding='ascii') as stream:
        rows = parse_proc_net_udp(stream.read())
    return [(row, fds[row.inode]) for row in rows if row.inode in fds]


def pin_wildcard_sockets_to_loopback(skip_inodes: Iterable[int] = ()) -> list[UdpSocket]:
    """Bind this process's UDP sockets on 0.0.0.0 to the loopback device (Linux).

    Meant for the sockets a Cyclone participant just opened (pass the inodes that existed
    before it as ``skip_inodes``). Unprivileged processes may do this since Linux 5.7.

    Returns:
        The wildcard sockets that could not be pinned (not Linux, an older kernel, or already
        bound to another device).
    """
    option = getattr(socket, 'SO_BINDTODEVICE', None)
    skip = set(skip_inodes)
    try:
        candidates = [(row, fd) for row, fd in own_udp_sockets()
                      if row.address == '0.0.0.0' and row.inode not in skip]
    except OSError:  # no /proc
        return []
    failed = []
    for row, fd in candidates:
        sock = socket.socket(fileno=fd)
        try:
            if option is None:
                raise OSError('SO_BINDTODEVICE is not available')
            sock.setsockopt(socket.SOL_SOCKET, option, LOOPBACK_DEVICE.encode())
        except OSError:
            failed.append(row)
        finally:
            sock.detach()  # the descriptor stays Cyclone's
    return failed


def bound_device(fd: int) -> str:
    """The device a socket is bound to (``''``: none)."""
    sock = socket.socket(fileno=fd)
    try:
        raw = sock.getsockopt(socket.SOL_SOCKET, socket.SO_BINDTODEVICE, 16)
    finally:
        sock.detach()
    return raw.split(b'\0', 1)[0].decode()
