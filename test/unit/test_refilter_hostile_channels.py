"""``rcbf_ros refilter`` on bags that hold more than the filter reads, or one bad message: the
run goes on as the node would. Bags are written here with the mcap library's own writer (not
ours), so their channels can carry what our writer refuses: a schema name that is not
``pkg/msg/Type``, a JSON message encoding."""
from __future__ import annotations

import json
from pathlib import Path

from mcap.writer import Writer
import numpy as np
import pytest
from rosbags.typesys import get_typestore, Stores

from rcbf_ros.bag import read_bag
from rcbf_ros.bag.refilter import main, refilter_bag, RefilterError

STORE = get_typestore(Stores.ROS2_JAZZY)
ARRAY = STORE.types['std_msgs/msg/Float64MultiArray']
LAYOUT = STORE.types['std_msgs/msg/MultiArrayLayout']
DIMENSION = STORE.types['std_msgs/msg/MultiArrayDimension']
ARRAY_DEFINITION = (
    b'std_msgs/MultiArrayLayout layout\nfloat64[] data\n' + b'=' * 80 + b'\n'
    b'MSG: std_msgs/MultiArrayLayout\nMultiArrayDimension[] dim\nuint32 data_offset\n'
    + b'=' * 80 + b'\nMSG: std_msgs/MultiArrayDimension\nstring label\nuint32 size\n'
    b'uint32 stride\n')
T0 = 1_700_000_000_000_000_000
STEPS = 20
PARAMS = 'unicycle'


def array(label: str, values) -> bytes:
    values = np.asarray(values, dtype=np.float64)
    return bytes(STORE.serialize_cdr(ARRAY(
        layout=LAYOUT(dim=[DIMENSION(label=label, size=values.size, stride=values.size)],
                      data_offset=0), data=values), ARRAY.__msgtype__))


def write_bag(directory: Path, *, extra: tuple[str, str, str] | None = None,
              proposal: dict[int, bytes] | None = None,
              state: dict[int, bytes] | None = None) -> Path:
    """A unicycle run of STEPS states and proposals (20 ms apart) in ``directory``; ``extra``
    (schema name, schema encoding, message encoding) adds a topic ``/extra`` beside them;
    ``proposal`` / ``state`` replace the message of step k by other bytes."""
    directory.mkdir(parents=True)
    with open(directory / f'{directory.name}_0.mcap', 'wb') as stream:
        writer = Writer(stream)
        writer.start('ros2', 'test')
        schema = writer.register_schema('std_msgs/msg/Float64MultiArray', 'ros2msg',
                                        ARRAY_DEFINITION)
        states = writer.register_channel('/state', 'cdr', schema)
        proposals = writer.register_channel('/cmd_proposed', 'cdr', schema)
        other = None
        if extra is not None:
            name, schema_encoding, message_encoding = extra
            other = writer.register_channel('/extra', message_encoding, writer.register_schema(
                name, schema_encoding, b'float64 x\n'))
        for k in range(STEPS):
            t = T0 + k * 20_000_000
            writer.add_message(states, t, (state or {}).get(
                k, array('state', [-2.4 + 0.03 * k, 0.0, 0.0])), t)
            writer.add_message(proposals, t + 1, (proposal or {}).get(
                k, array('u', [1.0, 0.05])), t + 1)
            if other is not None:
                data = (json.dumps({'x': k}).encode() if message_encoding == 'json'
                        else b'\x00\x01\x00\x00' + bytes(8))
                writer.add_message(other, t + 2, data, t + 2)
        writer.finish()
    return directory


def answers(bag: Path) -> list:
    return [item for item in read_bag(bag) if item.topic == '/refilter/cmd_safe']


@pytest.mark.parametrize('extra', [('a/b/c/d', 'ros2msg', 'cdr'), ('..', 'ros2msg', 'cdr'),
                                   ('pkg/msg/T/', 'ros2msg', 'cdr'),
                                   ('std_msgs/msg/Float64', 'ros2msg', 'json')],
                         ids=['four_parts', 'dots', 'trailing_slash', 'json_encoding'])
def test_a_topic_the_output_cannot_hold_is_left_out_and_named(tmp_path, extra):
    source = write_bag(tmp_path / 'run', extra=extra)
    summary = refilter_bag(source, tmp_path / 'out', PARAMS)
    assert list(summary.not_copied) == ['/extra']
    assert summary.not_copied_messages == STEPS
    assert len(answers(tmp_path / 'out')) == STEPS
    copied = {item.topic for item in read_bag(tmp_path / 'out')}
    assert '/extra' not in copied and {'/state', '/cmd_proposed'} <= copied
    assert 'not copied: 20 messages of 1 topics: /extra' in summary.format()


@pytest.mark.parametrize('bad', [array('u', []), array('u', [1.0]), array('u', [1, 2, 3]),
                                 b'\x00\x01\x00\x00\xff'],
                         ids=['empty', 'short', 'long', 'undecodable'])
def test_one_bad_proposal_mid_bag_is_answered_with_the_fail_safe_and_the_run_goes_on(
        tmp_path, bad):
    source = write_bag(tmp_path / 'run', proposal={10: bad})
    summary = refilter_bag(source, tmp_path / 'out', PARAMS)
    written = answers(tmp_path / 'out')
    assert summary.proposals == STEPS and len(written) == STEPS
    assert summary.skipped_total == 1 and summary.processed == STEPS - 1
    assert summary.fail_safe_answers.get('proposal') == 1


def test_one_bad_state_mid_bag_is_a_bad_state_and_the_run_goes_on(tmp_path):
    source = write_bag(tmp_path / 'run', state={10: array('state', [1.0, 2.0])})
    summary = refilter_bag(source, tmp_path / 'out', PARAMS)
    assert len(answers(tmp_path / 'out')) == STEPS
    assert summary.skipped_total == 1  # the proposal at the bad state: the fail-safe
    assert any('bad state' in reason for reason in summary.skipped)


@pytest.mark.parametrize('which', ['proposal', 'state'])
def test_a_bad_first_message_stops_the_run_in_one_line_and_leaves_no_bag(tmp_path, capsys,
                                                                        which):
    bad = {0: array('u', [1.0])} if which == 'proposal' else {0: array('state', [1.0])}
    source = write_bag(tmp_path / 'run', **{which: bad})
    with pytest.raises(RefilterError, match='another system'):
        refilter_bag(source, tmp_path / 'out', PARAMS)
    assert not (tmp_path / 'out').exists()
    assert main([str(source), str(tmp_path / 'out2'), '--params-file', PARAMS]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
