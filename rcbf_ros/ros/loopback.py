"""Pin Eclipse Cyclone DDS to the loopback interface.

Every participant this package creates on these machines (tests, CI, benchmarks, the launch
command) must stay on the machine: interface ``lo``, no multicast, unicast discovery of peers on
127.0.0.1. Cyclone reads ``CYCLONEDDS_URI`` once, when the first participant is created, so
``ensure_loopback()`` must run before that (it is idempotent and never overrides a URI the user
set on purpose unless ``force=True``).
"""
from __future__ import annotations

import os
from typing import MutableMapping

LOOPBACK_CYCLONEDDS_URI = (
    '<CycloneDDS><Domain id="any"><General>'
    '<Interfaces><NetworkInterface name="lo"/></Interfaces>'
    '<AllowMulticast>false</AllowMulticast>'
    '</General><Discovery>'
    '<Peers><Peer address="127.0.0.1"/></Peers>'
    '<ParticipantIndex>auto</ParticipantIndex>'
    '<MaxAutoParticipantIndex>60</MaxAutoParticipantIndex>'
    '</Discovery></Domain></CycloneDDS>'
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
