"""docs/INTERFACE.md's tables, generated from the nodes' own specs (so they cannot drift).

    rcbf_ros interface-doc                                # print the generated section
    rcbf_ros interface-doc --write docs/INTERFACE.md
    rcbf_ros interface-doc --check docs/INTERFACE.md      # exit 1 when it differs

The section lies between :data:`BEGIN` and :data:`END`; the rest of the file is written by hand.
It holds every shipped system's state and command layout, ``filter_info``'s sections and status
codes, and per node (:data:`NODES`) the :class:`~rcbf_ros.node_logic.interface.NodeInterface`
that ``<node> --help`` prints. A command, not node logic: it imports every node module.
"""
from __future__ import annotations

import argparse
from dataclasses import replace
import importlib
from pathlib import Path
import sys
from typing import Sequence

from rcbf_ros.core.filter_info import INFO_SECTIONS, STATUS_CODES, UNKNOWN_STATUS
from rcbf_ros.messages.conversions import COMMAND_LAYOUTS, ODOMETRY_STATES, STATE_LAYOUTS
from rcbf_ros.node_logic.interface import NodeInterface, parameter_table, resolve, topic_table
from rcbf_ros.node_logic.safety_filter import FILTER_PARAMETERS
from rcbf_ros.parameters.bounded_yaml import read_limited

INTERFACE_DOC = 'docs/INTERFACE.md'
"""Where the generated section lives, from the repository's root."""
BEGIN = ('<!-- BEGIN interface (generated: rcbf_ros interface-doc --write '
         f'{INTERFACE_DOC}) -->')
END = '<!-- END interface -->'

NODES: tuple[tuple[str, str], ...] = (
    ('rcbf_ros.ros.safety_filter_node', 'INTERFACE'),
    ('sim_nodes.simulator_node', 'simulator_interface'),
    ('sim_nodes.nominal_controller_node', 'nominal_controller_interface'),
    ('sim_nodes.unicycle_lidar_node', 'unicycle_lidar_interface'),
    ('rcbf_ros.ros.learner_node', 'INTERFACE'),
    ('rcbf_ros.ros.policy_node', 'INTERFACE'),
    ('rcbf_ros.ros.recorder_node', 'INTERFACE'),
    ('rcbf_ros.ros.replay_node', 'INTERFACE'),
    ('rcbf_ros.ros.scene_node', 'INTERFACE'),
)
"""(module, attribute) of every node's interface, in the order of the document."""


def node_interfaces() -> list[NodeInterface]:
    """Every node's interface (the simulated systems' nodes for their default system)."""
    return [resolve(getattr(importlib.import_module(module), name), [module])
            for module, name in NODES]


def _layout(entries: Sequence[tuple[str, str]]) -> str:
    return ', '.join(f'{name} ({unit})' for name, unit in entries)


def layout_tables() -> str:
    """State and command layout per system, the filter_info sections and the status codes."""
    rows = ['| system | state x (n_x entries: name (unit)) | command u | as nav_msgs/Odometry |',
            '|---|---|---|---|']
    for system in STATE_LAYOUTS:
        odometry = ODOMETRY_STATES.get(system, 'not supported: use Float64MultiArray')
        rows.append(f'| `{system}` | {_layout(STATE_LAYOUTS[system])} | '
                    f'{_layout(COMMAND_LAYOUTS[system])} | {odometry} |')
    rows += ['', '`filter_info` (std_msgs/Float64MultiArray, labelled sections in this order; '
             'the first five always, so their `data` indexes are fixed per system; the rest '
             'when known; never NaN):', '', '| section | size | meaning |', '|---|---|---|']
    rows += [f'| `{label}` | {size} | {meaning} |' for label, size, meaning in INFO_SECTIONS]
    rows += ['', 'Status codes (`filter_info` `status`; diagnostics carry the words):', '',
             '| code | meaning |', '|---|---|']
    rows += [f'| {code} | {name} |' for name, code in STATUS_CODES.items()]
    rows.append(f'| {UNKNOWN_STATUS} | any other |')
    return '\n'.join(rows)


def _without_filter_keys(interface: NodeInterface) -> tuple[NodeInterface, bool]:
    """The interface without the safety filter's own key specs (listed once, in its table)."""
    if interface.node == 'safety_filter':
        return interface, False
    kept = tuple(p for p in interface.parameters
                 if not any(p is spec for spec in FILTER_PARAMETERS))
    return replace(interface, parameters=kept), len(kept) < len(interface.parameters)


def generated_section() -> str:
    """The generated text between :data:`BEGIN` and :data:`END` (both lines included)."""
    parts = [BEGIN, '', '### State and command layouts', '', layout_tables()]
    for full in node_interfaces():
        interface, shared = _without_filter_keys(full)
        parts += ['', f'### `{interface.node}`', '', interface.summary, '',
                  topic_table(interface), '', parameter_table(interface)]
        if shared:
            parts += ['', "Also the safety problem's keys of the params file, as "
                      '`safety_filter` lists them (system, obstacles.*, bands.*, ...).']
        parts += [''] + list(interface.notes) if interface.notes else []
    parts += ['', END]
    return '\n'.join(parts) + '\n'


MAX_DOC_BYTES = 1 << 20
"""The largest document --write and --check read (docs/INTERFACE.md holds some 35 kB)."""


def replace_section(text: str, section: str) -> str:
    """``text`` with its generated section replaced by ``section``.

    Raises:
        ValueError: the markers are missing or out of order.
    """
    start, end = text.find(BEGIN), text.find(END)
    if start < 0 or end < start:
        raise ValueError(f'no "{BEGIN}" ... "{END}" section')
    return text[:start] + section + text[end + len(END) + 1:]


def main(argv: Sequence[str] | None = None) -> int:
    """Print, write or check the generated section. Exit 1 when --check finds a difference."""
    parser = argparse.ArgumentParser(
        prog='rcbf_ros interface-doc',
        description=f'The interface tables of {INTERFACE_DOC}, generated.')
    group = parser.add_mutually_exclusive_group()
    group.add_argument('--write', metavar='FILE', help='rewrite the section in this file')
    group.add_argument('--check', metavar='FILE', help='exit 1 when the section differs')
    args = parser.parse_args(argv)
    section = generated_section()
    path = args.write or args.check
    if path is None:
        sys.stdout.write(section)
        return 0
    try:  # a regular file of a document's size: a FIFO or /dev/zero would never end
        text = read_limited(path, max_bytes=MAX_DOC_BYTES, what='document')
        updated = replace_section(text, section)
    except (OSError, ValueError) as exc:
        print(f'interface_doc: {path}: {exc}', file=sys.stderr)
        return 2
    if args.check:
        if updated != text:
            print(f'interface_doc: {path}: the interface section is out of date; run python -m '
                  f'rcbf_ros.cli.interface_doc --write {path}', file=sys.stderr)
            return 1
        return 0
    Path(path).write_text(updated, encoding='utf-8')
    return 0


if __name__ == '__main__':
    sys.exit(main())
