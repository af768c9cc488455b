"""Inputs that no file can exhaust: YAML from outside (params files, a bag's metadata.yaml and
QoS strings, launch values) and MCAP chunks are refused at their limits, before the bytes they
would cost are read or made, with one line and exit status 2, under a memory ceiling.

The crafted files are small on disk and expand into gigabytes (:mod:`hostile_files`). The
command-line cases run as a child with its address space capped at :data:`CEILING`, so a
reader that would take more fails (MemoryError) instead of taking the machine, and its peak
RSS is checked too."""
from __future__ import annotations

import functools
import os
from pathlib import Path
import re
import sys

from hostile_files import (
    alias_bomb,
    CHUNK_OFFSET,
    chunk_record,
    deep_params,
    huge_params,
    lz4_zeros,
    mcap_with_chunk,
    MIB,
    run_measured,
    zstd_zeros,
)
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.writer import Writer
import pytest
import yaml
import zstandard

from rcbf_ros.bag import bag_info, BagError, BagWriter, BagWriterConfig, recover_file
from rcbf_ros.bag.scan import MAX_CHUNK_BYTES, MAX_RECORD_BYTES, McapScan
from rcbf_ros.launch.table import typed_value
from rcbf_ros.parameters import bounded_yaml
from rcbf_ros.parameters.rules import (
    load_params,
    MAX_PARAMS_FILE_BYTES,
    ParamRules,
    ParamsFileError,
)
from rcbf_ros.ros import replay_node

CEILING = 512 * MIB
"""The memory every reader stays under, whatever the file (address space and peak RSS)."""
BOMB_MIB = 1024
"""What the bombs expand to: twice the ceiling."""


def _cli(*argv: str, address_space: int = CEILING) -> tuple[int, str, str, int]:
    env = {**os.environ, 'PYTHONPATH': os.pathsep.join(sys.path)}
    return run_measured([sys.executable, *argv], address_space=address_space, env=env)


def _one_line(status: int, err: str, pattern: str, peak: int) -> None:
    assert status == 2, err
    assert len(err.strip().splitlines()) == 1, err
    assert re.search(pattern, err), err
    assert 'Traceback' not in err
    assert peak < CEILING, f'peak RSS {peak / MIB:.0f} MiB'


# -- bounded YAML ----------------------------------------------------------------------------

def test_alias_bomb_stops_at_the_alias_that_crosses_the_node_limit() -> None:
    with pytest.raises(bounded_yaml.YAMLLimitError, match=r'^bomb: line 7: more than 1000000 '):
        bounded_yaml.safe_load(alias_bomb(), source='bomb')


def test_aliases_refused_where_the_writer_makes_none() -> None:
    with pytest.raises(bounded_yaml.YAMLLimitError, match=r'line 2: the alias \*x is not'):
        bounded_yaml.safe_load('a: &x 1\nb: *x\n', source='m', allow_aliases=False)
    assert bounded_yaml.safe_load('a: &x 1\nb: *x\n', source='m') == {'a': 1, 'b': 1}


@pytest.mark.parametrize('tag', ['!!python/object/apply:os.system', '!!python/name:os.system',
                                 '!local', '!<tag:example.com,2000:x>'])
def test_tags_outside_the_core_schema_are_refused(tag: str) -> None:
    with pytest.raises(bounded_yaml.YAMLLimitError, match=r'line 2: the tag .* not allowed'):
        bounded_yaml.safe_load(f'a: 1\nb: {tag} ["true"]\n', source='t')


def test_core_tags_are_read_as_yaml_reads_them() -> None:
    text = 'a: !!str 1\nb: !!float 2\nc: !!int "3"\nd: !!seq [1]\n'
    assert bounded_yaml.safe_load(text, source='t') == yaml.safe_load(text)


@st.composite
def _anchored_documents(draw: st.DrawFn) -> tuple[str, int, int]:
    """A document of anchored lists, each holding scalars, aliases of earlier lists and
    nested lists; with its node count (aliases as what they repeat) and depth, worked out on
    the Python side."""
    lines = []
    sizes: list[tuple[int, int]] = []  # (nodes, height) of each anchored list
    for i in range(draw(st.integers(1, 6))):
        items, nodes, height = [], 1, 1
        for _ in range(draw(st.integers(0, 5))):
            kind = draw(st.sampled_from(['scalar', 'alias', 'nest']))
            if kind == 'alias' and sizes:
                j = draw(st.integers(0, len(sizes) - 1))
                items.append(f'*a{j}')
                nodes += sizes[j][0]
                height = max(height, 1 + sizes[j][1])
            elif kind == 'nest':
                levels = draw(st.integers(1, 4))
                items.append('[' * levels + '0' + ']' * levels)
                nodes += levels + 1
                height = max(height, 1 + levels)
            else:
                items.append('0')
                nodes += 1
        sizes.append((nodes, height))
        lines.append(f'k{i}: &a{i} [{", ".join(items)}]')
    document = '\n'.join(lines)
    return document, 1 + sum(n + 1 for n, _ in sizes), 1 + max(h for _, h in sizes)


@settings(max_examples=200, deadline=None)
@given(_anchored_documents(), st.integers(1, 400), st.integers(1, 8))
def test_node_and_depth_limits_count_what_aliases_repeat(
        case: tuple[str, int, int], max_nodes: int, max_depth: int) -> None:
    document, nodes, depth = case
    within = nodes <= max_nodes and depth <= max_depth
    try:
        bounded_yaml.check(document, source='d', max_nodes=max_nodes, max_depth=max_depth)
    except bounded_yaml.YAMLLimitError:
        assert not within, (document, nodes, depth)
    else:
        assert within, (document, nodes, depth)


def test_a_file_is_read_no_further_than_its_limit(tmp_path: Path) -> None:
    huge = huge_params(tmp_path / 'huge.yaml', 2**40)  # 1 TiB, a hole: reading it whole fails
    with pytest.raises(bounded_yaml.YAMLLimitError, match=r'larger than the 1000-byte limit'):
        bounded_yaml.read_limited(huge, max_bytes=1000, what='test file')


def test_launch_values_past_a_limit_stay_text() -> None:
    deep = '[' * 100_000 + ']' * 100_000
    assert typed_value(deep) == deep
    assert typed_value('[1, 2]') == [1, 2]


@pytest.mark.parametrize('text, line, first, key', [
    ('a: 1\nb: 2\na: 3\n', 3, 1, 'a'),
    ('{a: 1, a: 2}\n', 1, 1, 'a'),
    ('n:\n  ros__parameters:\n    alpha: 2.0\n    alpha: 0.001\n', 4, 3, 'alpha'),
    ('/**:\n  ros__parameters: {x: 1}\n/**:\n  ros__parameters: {y: 1}\n', 3, 1, '/**')])
def test_a_key_given_twice_in_one_mapping_is_refused_naming_both_lines(
        text: str, line: int, first: int, key: str) -> None:
    with pytest.raises(bounded_yaml.YAMLLimitError) as refused:
        bounded_yaml.check(text, source='f')
    assert str(refused.value) == (f'f: line {line}: the key {key!r} is given twice in one '
                                  f'mapping (lines {first} and {line}; YAML keys are unique)')


@given(st.lists(st.sampled_from(['a', 'b', 'c', 'd']), min_size=1, max_size=6),
       st.booleans())
def test_keys_are_refused_exactly_when_one_mapping_repeats_one(keys: list[str],
                                                               nested: bool) -> None:
    """Oracle: a repeat in the list of one mapping's keys; the same keys in sibling and
    nested mappings are never a repeat."""
    body = ''.join(f'{key}: {index}\n' for index, key in enumerate(keys))
    text = (''.join(f'm{i}:\n' + ''.join(f'  {line}\n' for line in body.splitlines())
                    for i in range(2)) if nested else body)
    repeated = len(set(keys)) < len(keys)
    if repeated:
        with pytest.raises(bounded_yaml.YAMLLimitError, match='given twice in one mapping'):
            bounded_yaml.check(text, source='f')
    else:
        bounded_yaml.check(text, source='f')
        assert yaml.safe_load(text) is not None


# -- params files ----------------------------------------------------------------------------

def test_deep_params_file_refused_naming_file_line_and_limit(tmp_path: Path) -> None:
    path = tmp_path / 'deep.yaml'
    path.write_text(deep_params(10_000))
    with pytest.raises(ParamsFileError, match=r"deep\.yaml': line 4: nested deeper than 64 "):
        load_params(path, 'safety_filter')


def test_huge_params_file_refused_before_it_is_read(tmp_path: Path) -> None:
    path = huge_params(tmp_path / 'huge.yaml', 2**40)
    with pytest.raises(ParamsFileError, match=f'larger than the {MAX_PARAMS_FILE_BYTES}-byte'):
        load_params(path, 'safety_filter')


def test_python_tag_in_params_file_names_the_tag(tmp_path: Path) -> None:
    path = tmp_path / 'tag.yaml'
    path.write_text('/**:\n  ros__parameters:\n    system: !!python/object/apply:os.system '
                    '["true"]\n')
    with pytest.raises(ParamsFileError, match=r"tag\.yaml': line 3: the tag "
                                              r'!!python/object/apply:os\.system is not'):
        load_params(path, 'safety_filter')


def test_a_params_file_naming_a_parameter_twice_is_read_as_ros2_reads_it_and_reported(
        tmp_path: Path) -> None:
    """rcl's parser (rcl_yaml_param_parser) lets the later value of a repeated key replace the
    earlier; a params file is read the same way, on every runtime, and the repeat reported."""
    path = tmp_path / 'twice.yaml'
    path.write_text('/**:\n  ros__parameters:\n    alpha: 2.0\n    alpha: 0.001\n')
    assert load_params(path, 'safety_filter') == {'alpha': 0.001}
    rules = ParamRules()
    rules.add_file(path)
    assert len(rules.repeated_keys) == 1
    assert re.search(r"twice\.yaml': line 4: the key 'alpha' is given twice in one mapping "
                     r'\(lines 3 and 4;', rules.repeated_keys[0])


@pytest.mark.parametrize('case', ['huge', 'deep', 'tag'])
def test_node_with_hostile_params_file_exits_2_with_one_line(case: str, tmp_path: Path) -> None:
    path = tmp_path / f'{case}.yaml'
    if case == 'huge':
        huge_params(path, 2**40)
    elif case == 'deep':
        path.write_text(deep_params(10_000))
    else:
        path.write_text('/**:\n  ros__parameters:\n    bag: !!python/name:os.system\n')
    status, _, err, peak = _cli('-m', 'rcbf_ros.ros.replay_node', '--ros-args',
                                '--params-file', str(path))
    _one_line(status, err, {'huge': f'larger than the {MAX_PARAMS_FILE_BYTES}-byte limit',
                            'deep': 'line 4: nested deeper than 64 levels',
                            'tag': 'line 3: the tag !!python/name:os.system'}[case], peak)
    assert str(path) in err


# -- bags: metadata.yaml and QoS strings -----------------------------------------------------

@functools.cache
def _lz4_bomb() -> bytes:
    return lz4_zeros(BOMB_MIB)


def _alias_bag(tmp_path: Path) -> Path:
    bag = tmp_path / 'alias_bag'
    bag.mkdir()
    (bag / 'metadata.yaml').write_text(alias_bomb())
    (bag / 'alias_bag_0.mcap').write_bytes(b'')
    return bag


def test_bag_check_alias_bomb_metadata_exits_2(tmp_path: Path) -> None:
    bag = _alias_bag(tmp_path)
    status, _, err, peak = _cli('-m', 'rcbf_ros.bag', 'check', str(bag))
    _one_line(status, err, r'metadata\.yaml: line 2: the alias \*a0 is not allowed', peak)


def test_refilter_alias_bomb_metadata_exits_2(tmp_path: Path) -> None:
    bag = _alias_bag(tmp_path)
    status, _, err, peak = _cli('-m', 'rcbf_ros.bag.refilter', str(bag), str(tmp_path / 'out'),
                                '--params-file', 'unicycle', address_space=0)
    _one_line(status, err, r'metadata\.yaml: line 2: the alias \*a0', peak)
    assert not (tmp_path / 'out').exists()


def test_replay_alias_bomb_metadata_exits_2(tmp_path: Path, ros_domain_id: int,
                                            monkeypatch: pytest.MonkeyPatch,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    bag = _alias_bag(tmp_path)
    monkeypatch.setenv('ROS_DOMAIN_ID', str(ros_domain_id))
    status = replay_node.main(['replay', '--ros-args', '-p', f'bag:={bag}',
                               '-p', 'linger_s:=0.0'])
    err = capsys.readouterr().err
    assert status == 2, err
    assert len(err.strip().splitlines()) == 1, err
    assert re.search(r'metadata\.yaml: line 2: the alias \*a0 is not allowed', err), err


def test_metadata_past_its_size_limit_is_a_bag_error(tmp_path: Path) -> None:
    bag = _alias_bag(tmp_path)
    with open(bag / 'metadata.yaml', 'r+b') as stream:
        stream.truncate(2**40)
    with pytest.raises(BagError, match=r'metadata\.yaml: larger than the 16777216-byte limit'):
        bag_info(bag)


def test_alias_bomb_in_a_channels_qos_string_is_a_bag_error(tmp_path: Path) -> None:
    path = tmp_path / 'qos.mcap'
    with open(path, 'wb') as stream:
        writer = Writer(stream)
        writer.start(profile='ros2', library='test')
        schema = writer.register_schema(name='std_msgs/msg/Empty', encoding='ros2msg', data=b'')
        writer.register_channel(topic='/x', message_encoding='cdr', schema_id=schema,
                                metadata={'offered_qos_profiles': alias_bomb()})
        writer.finish()
    with pytest.raises(BagError, match=r"qos\.mcap: channel '/x': offered_qos_profiles: line "
                                       r'2: the alias \*a0 is not allowed'):
        bag_info(path)


# -- bags: chunks ----------------------------------------------------------------------------

CHUNK_CASES = {
    # name: (compression, compressed data, stated size, what the line says)
    'lz4 bomb': ('lz4', _lz4_bomb, 1000, 'decompresses to more than the 1000 bytes it states'),
    'zstd bomb': ('zstd', lambda: zstd_zeros(BOMB_MIB), 1000,
                  'decompresses to more than the 1000 bytes it states'),
    'zstd bomb within the cap': ('zstd', lambda: zstd_zeros(BOMB_MIB), MAX_CHUNK_BYTES,
                                 f'decompresses to more than the {MAX_CHUNK_BYTES} bytes'),
    'lz4 bomb within the cap': ('lz4', _lz4_bomb, MAX_CHUNK_BYTES,
                                f'decompresses to more than the {MAX_CHUNK_BYTES} bytes'),
    'zstd states 4 GiB': ('zstd', lambda: zstd_zeros(4095), 4095 * MIB,
                          f'states {4095 * MIB} uncompressed bytes, more than the '
                          f'{MAX_CHUNK_BYTES}-byte limit of a chunk'),
    'lz4 states less than it holds': ('lz4', lambda: lz4_zeros(8), 8 * MIB - 1,
                                      f'decompresses to more than the {8 * MIB - 1} bytes'),
    'zstd states more than it holds': ('zstd', lambda: zstandard.compress(bytes(100)), MIB,
                                       'decompresses to 100 bytes, not the 1048576 it states'),
    'lz4 frame cut short': ('lz4', lambda: lz4_zeros(8)[:-4], 8 * MIB,
                            'its lz4 frame ends after'),
    'none states more than it holds': ('', lambda: bytes(100), 200,
                                       'decompresses to 100 bytes, not the 200 it states'),
}


def _bomb_file(tmp_path: Path, case: str) -> Path:
    compression, data, size, _ = CHUNK_CASES[case]
    return mcap_with_chunk(tmp_path / 'bomb.mcap',
                           chunk_record(data(), compression=compression, uncompressed_size=size))


@pytest.mark.parametrize('case', sorted(CHUNK_CASES))
def test_hostile_chunk_refused_in_process(case: str, tmp_path: Path) -> None:
    path = _bomb_file(tmp_path, case)
    assert path.stat().st_size < 5 * MIB
    with pytest.raises(BagError) as raised:
        McapScan(path).verify()
    message = str(raised.value)
    assert message.startswith(f'{path}: chunk at offset {CHUNK_OFFSET}: '), message
    assert CHUNK_CASES[case][3] in message
    assert '\n' not in message


@pytest.mark.parametrize('case', ['lz4 bomb', 'zstd bomb within the cap', 'zstd states 4 GiB'])
def test_bag_check_of_a_bomb_exits_2_under_the_ceiling(case: str, tmp_path: Path) -> None:
    path = _bomb_file(tmp_path, case)
    status, _, err, peak = _cli('-m', 'rcbf_ros.bag', 'check', str(path))
    _one_line(status, err, re.escape(f'{path}: chunk at offset {CHUNK_OFFSET}: '
                                     f'{CHUNK_CASES[case][3]}'), peak)


def test_refilter_of_a_bomb_exits_2_under_the_ceiling(tmp_path: Path) -> None:
    path = _bomb_file(tmp_path, 'lz4 bomb')
    status, _, err, peak = _cli('-m', 'rcbf_ros.bag.refilter', str(path), str(tmp_path / 'o'),
                                '--params-file', 'unicycle', address_space=0)
    _one_line(status, err, re.escape(f'chunk at offset {CHUNK_OFFSET}: decompresses to more'),
              peak)


def test_recover_leaves_a_bomb_out_under_the_ceiling(tmp_path: Path) -> None:
    path = _bomb_file(tmp_path, 'lz4 bomb within the cap')
    status, out, err, peak = _cli('-m', 'rcbf_ros.bag', 'recover', str(path))
    assert status == 0, err
    assert f'chunk at offset {CHUNK_OFFSET}: decompresses to more than' in out
    assert peak < CEILING, f'peak RSS {peak / MIB:.0f} MiB'
    assert McapScan(path).verify().message_count == 0
    assert (tmp_path / 'bomb.mcap.orig').stat().st_size > 0  # the original is kept


def test_a_record_past_its_limit_is_never_read(tmp_path: Path) -> None:
    path = mcap_with_chunk(tmp_path / 'long.mcap', chunk_record(
        b'', compression='', uncompressed_size=0))
    # The chunk's length field says 1 TiB; the file is made that long with a hole.
    with open(path, 'r+b') as stream:
        stream.seek(CHUNK_OFFSET + 1)
        stream.write((2**40).to_bytes(8, 'little'))
        stream.truncate(CHUNK_OFFSET + 9 + 2**40 + 64)
    with pytest.raises(BagError, match=f'chunk record at offset {CHUNK_OFFSET} is 1099511627776 '
                                       f'bytes, more than the {MAX_RECORD_BYTES}-byte limit'):
        McapScan(path).verify()
    recovery = recover_file(path, keep_original=False)
    assert any('more than the' in problem for problem in recovery.problems)


def test_a_real_bag_still_reads(tmp_path: Path) -> None:
    for compression in ('zstd', 'lz4', 'none'):
        directory = tmp_path / compression
        with BagWriter(directory, config=BagWriterConfig(compression=compression)) as bag:
            bag.add_topic('/state', 'std_msgs/msg/Float64MultiArray')
            for i in range(500):
                bag.write_message('/state', {'data': [float(i)] * 50}, 10**18 + i)
        assert bag_info(directory).message_count == 500


# -- replay: a bag larger than memory, small on disk -----------------------------------------

def test_replay_streams_a_bag_larger_than_its_memory(tmp_path: Path, ros_domain_id: int) -> None:
    """80 messages of 8 MB (640 MB, over the ceiling) that compress to a few hundred KiB: the
    replay holds one at a time, so it plays them all under the ceiling."""
    bag = tmp_path / 'big'
    size, count = 8 * MIB, 80
    header = b'\x00\x01\x00\x00' + b'\x00' * 12 + size.to_bytes(4, 'little')
    with BagWriter(bag) as writer:
        writer.add_topic('/blob', 'std_msgs/msg/UInt8MultiArray')
        for k in range(count):
            writer.write('/blob', header + bytes([k]) * size, 1_700_000_000_000_000_000 + k)
    assert count * size > CEILING
    env = {**os.environ, 'PYTHONPATH': os.pathsep.join(sys.path),
           'ROS_DOMAIN_ID': str(ros_domain_id)}
    status, out, err, peak = run_measured(
        [sys.executable, '-m', 'rcbf_ros.ros.replay_node', '--ros-args', '-p', f'bag:={bag}',
         '-p', 'linger_s:=0.0'], address_space=CEILING, env=env)
    assert status == 0, err
    assert f'replaying {count} messages' in out + err
    assert f'replay finished: {count} messages published' in out + err
    assert 'Traceback' not in err
    assert peak < CEILING, f'peak RSS {peak / MIB:.0f} MiB'
