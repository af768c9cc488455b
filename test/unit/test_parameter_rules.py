"""What a node gets from ``--params-file`` and ``-p``: rcl's and rclpy's rules, without ROS.

Every expected value below is derived from rcl 9.2 (Jazzy) and rclpy 7.1 by hand; the comment
of each case names the functions whose rule decides it:

- rcl ``arguments.c`` ``rcl_parse_arguments``: ``-p`` and ``--params-file`` fill ONE
  ``rcl_params_t`` in command-line order; ``_rcl_parse_param_rule``: a bare ``-p`` is stored
  under the node key ``/**``, ``-p node:name:=v`` under ``node`` (no slash added);
- rcl_yaml_param_parser ``find_node`` / ``find_parameter``: a key or a parameter seen again is
  reused in place, so it keeps the position where it FIRST appeared; ``parse_value``: a value
  overwrites only the slot of its own type; an empty sequence sets no slot (NOT_SET);
  ``get_value``: how a scalar is typed; ``_validate_name``: which node keys are allowed;
- rclpy ``node.cpp`` ``_populate_node_parameters_from_rcl_params``: a node walks the keys in
  table order, adds a leading ``/``, turns ``/*`` into ``(/\\w+)`` and ``regex_match``es its
  fully qualified name; later keys overwrite earlier ones; ``_parameter_from_rcl_variant``
  reads the slots in the order bool, integer, double, string, arrays; ``Node::get_parameters``:
  global arguments first, then the node's own.
"""
from __future__ import annotations

from pathlib import Path
import textwrap

import pytest

from rcbf_ros.parameters.arguments import (
    parameter_overrides,
    parse_ros_arguments,
    RosArgumentError,
)
from rcbf_ros.parameters.rules import load_params, ParamRules, scalar_value

SIM = '/simulator'
FILE_WILDCARD_THEN_NODE = """
/**:
  ros__parameters:
    max_steps: 1000
    shared: 1
/simulator:
  ros__parameters:
    max_steps: 2000
"""
FILE_NODE_THEN_WILDCARD = """
/simulator:
  ros__parameters:
    max_steps: 2000
/**:
  ros__parameters:
    max_steps: 1000
"""
LAUNCH_ROS_WILDCARD_DICT = """
/**:
  ros__parameters:
    max_steps: 10
"""
LAUNCH_ROS_NODE_DICT = """
/simulator:
  ros__parameters:
    max_steps: 10
"""


def command_line(tmp_path: Path, words: list[str]) -> list[str]:
    """``--ros-args`` of ``words``: ``@<yaml>`` a params file holding it, else a ``-p`` rule."""
    argv = ['--ros-args']
    for index, word in enumerate(words):
        if word.startswith('@'):
            path = tmp_path / f'p{index}_{abs(hash(word))}.yaml'
            path.write_text(textwrap.dedent(word[1:]))
            argv += ['--params-file', str(path)]
        else:
            argv += ['-p', word]
    return argv


def _overrides(tmp_path: Path, words: list[str], fully_qualified: str = SIM,
               node_words: list[str] | None = None) -> dict:
    """What a node ``fully_qualified`` gets from the command line of ``words``."""
    tables = [parse_ros_arguments(command_line(tmp_path, words))]
    if node_words is not None:
        tables.append(parse_ros_arguments(['--ros-args'] + [
            w for word in node_words for w in ('-p', word)]))
    return parameter_overrides(tables, fully_qualified)


CASES = {
    # _rcl_parse_param_rule puts a bare -p under /**; find_node reuses the file's /** key, which
    # was opened before /simulator, so the node's own section (walked later) wins.
    'bare -p loses to the node section': (
        ['@' + FILE_WILDCARD_THEN_NODE, 'max_steps:=120'], 'max_steps', 2000),
    # -p simulator:... is the key 'simulator', not '/simulator': a new key after the file's.
    'node -p after the file wins': (
        ['@' + FILE_WILDCARD_THEN_NODE, 'simulator:max_steps:=120'], 'max_steps', 120),
    # The same key opened before the file's keys is walked first and loses.
    'node -p before the file loses': (
        ['simulator:max_steps:=120', '@' + FILE_WILDCARD_THEN_NODE], 'max_steps', 2000),
    # /** opened after /simulator: the wildcard is walked last and wins.
    'a later /** wins over the node section': (
        ['@' + FILE_NODE_THEN_WILDCARD], 'max_steps', 1000),
    'bare -p wins when /** came after the node section': (
        ['@' + FILE_NODE_THEN_WILDCARD, 'max_steps:=120'], 'max_steps', 120),
    # launch_ros writes a dict under /** when the node has no namespace: it lands in the /**
    # key the first file opened, before /simulator, and loses ...
    'a /** file after the config loses': (
        ['@' + FILE_WILDCARD_THEN_NODE, '@' + LAUNCH_ROS_WILDCARD_DICT], 'max_steps', 2000),
    # ... and under the node's name when it has one: the /simulator key, overwritten in place.
    'a /simulator file after the config wins': (
        ['@' + FILE_WILDCARD_THEN_NODE, '@' + LAUNCH_ROS_NODE_DICT], 'max_steps', 10),
    'untouched keys stay': (
        ['@' + FILE_WILDCARD_THEN_NODE, 'simulator:max_steps:=120'], 'shared', 1),
    # parse_value with an empty sequence sets no slot: NOT_SET (None) ...
    'an empty list is NOT_SET': (['@/simulator:\n  ros__parameters:\n    g: []\n'], 'g', None),
    # ... and under a key that already holds a value, the value stays.
    'an empty list keeps an earlier value of the same key': (
        ['@/**:\n  ros__parameters:\n    g: [1.0]\n', 'g:=[]'], 'g', [1.0]),
    # Under a later key the NOT_SET entry overwrites in rclpy's dict.
    'an empty list under a later key unsets': (
        ['@/**:\n  ros__parameters:\n    g: [1.0]\n', 'simulator:g:=[]'], 'g', None),
    # parse_value writes the integer slot and leaves the double one; rclpy reads bool, then
    # integer, then double: the older integer wins within one key ...
    'another type in the same key keeps the earlier slot': (
        ['x:=5', 'x:=1.5'], 'x', 5),
    'the same type in the same key is overwritten': (['x:=5', 'x:=7'], 'x', 7),
    # ... while a later key overwrites whatever type.
    'another type under a later key wins': (['x:=5', 'simulator:x:=1.5'], 'x', 1.5),
    # _validate_name allows the node names * and **; rclpy adds the leading /.
    'key *': (['@"*":\n  ros__parameters: {w: 1}\n'], 'w', 1),
    'key **': (['@"**":\n  ros__parameters: {w: 2}\n'], 'w', 2),
    'key /*': (['@/*:\n  ros__parameters: {w: 3}\n'], 'w', 3),
    'key /**/simulator': (['@/**/simulator:\n  ros__parameters: {w: 4}\n'], 'w', 4),
    'key without a slash': (['@simulator:\n  ros__parameters: {w: 5}\n'], 'w', 5),
    'key of another node': (['@/other:\n  ros__parameters: {w: 6}\n'], 'w', 'absent'),
    # parse_key joins nested parameter maps with dots, nested node maps with slashes.
    'nested parameters': (['@/simulator:\n  ros__parameters: {a: {b: {c: 1}}}\n'], 'a.b.c', 1),
    # parse_key renames the placeholder of a nested map's first key in place, so a second file
    # writing o.x adds a second entry named o.x after the first; -p o.x finds the FIRST
    # (find_parameter) and rclpy's dict keeps the LAST: the second file's value.
    'a nested name written twice keeps the later file against -p': (
        ['@/**:\n  ros__parameters: {o: {x: 1}}\n', '@/**:\n  ros__parameters: {o: {x: 2}}\n',
         'o.x:=3'], 'o.x', 2),
}


@pytest.mark.parametrize('words, name, expected', CASES.values(), ids=list(CASES))
def test_what_a_node_gets(tmp_path, words, name, expected):
    overrides = _overrides(tmp_path, words)
    assert overrides.get(name, 'absent') == expected


WILDCARD_KEYS = [
    # rclpy's regex: /* is one token, /** any number, a missing leading / is added.
    ('/*', '/simulator', True), ('/*', '/ns/simulator', False), ('*', '/simulator', True),
    ('/**', '/ns/simulator', True), ('**', '/a/b/c', True), ('/ns/*', '/ns/simulator', True),
    ('/ns/*', '/simulator', False), ('/**/simulator', '/a/b/simulator', True),
    ('/**/simulator', '/simulator', True), ('ns/simulator', '/ns/simulator', True),
    ('/simulator', '/simulator_2', False),
]
REFUSED_KEYS = ['/sim*', 'sim*', '/ns*/simulator', '/a//b', '/1abc']


@pytest.mark.parametrize('key, fully_qualified, applies', WILDCARD_KEYS)
def test_wildcard_keys(tmp_path, key, fully_qualified, applies):
    words = [f'@"{key}":\n  ros__parameters: {{w: 1}}\n']
    assert ('w' in _overrides(tmp_path, words, fully_qualified)) == applies


@pytest.mark.parametrize('key', REFUSED_KEYS)
def test_keys_rcl_refuses(tmp_path, key):
    # _validate_name: wildcards only as whole tokens; node and namespace tokens are names.
    path = tmp_path / 'p.yaml'
    path.write_text(f'"{key}":\n  ros__parameters: {{w: 1}}\n')
    with pytest.raises(RosArgumentError, match=str(path)):
        parse_ros_arguments(['--ros-args', '--params-file', str(path)])


def test_the_nodes_own_arguments_come_after_the_global_ones(tmp_path):
    # Node::get_parameters: the global table first, then the node's cli_args, one dict.
    overrides = _overrides(tmp_path, ['simulator:x:=1', 'y:=1'], node_words=['x:=2'])
    assert overrides == {'x': 2, 'y': 1}


SCALARS = [
    # get_value: booleans, then strtoll(base 0), then .nan/.inf or strtod, else a string.
    ('true', 'bool', True), ('On', 'bool', True), ('n', 'bool', False), ('3', 'integer', 3),
    ('010', 'integer', 8), ('0x1A', 'integer', 26), ('08', 'double', 8.0),
    ('1e3', 'double', 1000.0), ('.5', 'double', 0.5), ('-.inf', 'double', float('-inf')),
    ('inf', 'double', float('inf')), ('1e999', 'string', '1e999'),
    ('99999999999999999999', 'double', 1e20), ('null', 'string', 'null'),
    ('~', 'string', '~'), ('1_000', 'string', '1_000'), ('a b', 'string', 'a b'),
]


@pytest.mark.parametrize('text, slot, value', SCALARS)
def test_scalars_are_typed_as_rcl_types_them(text, slot, value):
    assert scalar_value(text) == (slot, value)


def test_quoted_and_str_tagged_scalars_are_strings(tmp_path):
    words = ['@/**:\n  ros__parameters: {a: "5", b: !!str true, c: \'1e3\'}\n']
    assert _overrides(tmp_path, words) == {'a': '5', 'b': 'true', 'c': '1e3'}


@pytest.mark.parametrize('content, problem', [
    ('/**:\n  ros__parameters: {x: [1, 2.5]}\n', 'one type'),
    ('/**:\n  ros__parameters: {x: }\n', 'no value'),
    ('/**:\n  ros__parameters: {x: &a 1, y: *a}\n', 'aliases'),
    ('/**:\n  x: 1\n', 'has no ros__parameters'),
    ('- 1\n', 'top level must map node names'),
])
def test_files_rcl_refuses(tmp_path, content, problem):
    path = tmp_path / 'p.yaml'
    path.write_text(content)
    with pytest.raises(RosArgumentError, match=problem):
        parse_ros_arguments(['--ros-args', '--params-file', str(path)])


def test_load_params_leaves_out_what_has_no_value(tmp_path):
    path = tmp_path / 'p.yaml'
    path.write_text('/**:\n  ros__parameters: {a: [], b: [1.0]}\n'
                    '/simulator:\n  ros__parameters: {b: [2.0]}\n')
    assert load_params(path, 'simulator') == {'b': [2.0]}
    assert load_params(path, 'other') == {'b': [1.0]}


def test_the_table_keeps_first_appearance_order():
    rules = ParamRules()
    rules.add_rule('/**', 'a', '1')
    rules.add_rule('simulator', 'a', '2')
    rules.add_rule('/**', 'a', '3')
    assert list(rules.sections()) == ['/**', 'simulator']
    assert rules.values_for(SIM) == {'a': 2}
