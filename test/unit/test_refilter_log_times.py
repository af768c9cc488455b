"""``rcbf_ros refilter`` of a bag whose log times reach past what an answer's stamp can hold
(an MCAP log time is any uint64; builtin_interfaces/msg/Time counts seconds in an int32): the
run is refused in one line naming the topic and the log time, and no bag is left."""
from __future__ import annotations

from pathlib import Path
import tempfile

from hypothesis import given, settings
from hypothesis import strategies as st
import pytest
from test_refilter import _sections, PARAMS_A
import yaml

from rcbf_ros.bag import BagWriter, read_bag
from rcbf_ros.bag.refilter import (
    LATEST_LOG_TIME_NS,
    main,
    OUTPUT_DIAGNOSTICS_TOPIC,
    refilter_bag,
    RefilterError,
)
from rcbf_ros.messages.typestore import jazzy_typestore

FREE = [-2.4, 0.0, 0.0]
U = [1.0, 0.05]
DIAGNOSTIC_ARRAY = 'diagnostic_msgs/msg/DiagnosticArray'
LAST_SECOND = LATEST_LOG_TIME_NS - 10**9 + 1


def _bag(directory: Path, events: list[tuple[int, str]]) -> Path:
    """A bag of ``(log time ns, topic)`` events, /state (FREE) and /cmd_proposed (U)."""
    with BagWriter(directory) as bag:
        bag.add_topic('/state', 'std_msgs/msg/Float64MultiArray')
        bag.add_topic('/cmd_proposed', 'std_msgs/msg/Float64MultiArray')
        for log_time_ns, topic in events:
            body = _sections(state=FREE) if topic == '/state' else _sections(u=U)
            bag.write_message(topic, body, log_time_ns)
    return directory


_TIMES = st.one_of(st.integers(0, 2**64 - 1),
                   st.integers(LAST_SECOND, LATEST_LOG_TIME_NS + 10**9),
                   st.sampled_from([LATEST_LOG_TIME_NS, LATEST_LOG_TIME_NS + 1, 2**63 - 1,
                                    2**63, 2**64 - 1]))


@settings(max_examples=30, deadline=None)
@given(times=st.lists(_TIMES, min_size=1, max_size=4),
       control_period_s=st.sampled_from([0.0, 0.05]))
def test_every_answer_is_stamped_with_its_log_time_or_the_run_is_refused_naming_it(
        times, control_period_s):
    events = [(t, '/state') for t in times] + [(t + 1, '/cmd_proposed') for t in times
                                               if t + 1 < 2**64]
    params = dict(PARAMS_A, control_period_s=control_period_s, latency_s=0.02)
    with tempfile.TemporaryDirectory() as tmp:
        source = _bag(Path(tmp) / 'run', events)
        late = [t for t, _ in events if t > LATEST_LOG_TIME_NS]
        if late:
            with pytest.raises(RefilterError) as refused:
                refilter_bag(source, Path(tmp) / 'out' / 'bag', params)
            text = str(refused.value)
            assert '\n' not in text and f'at log time {min(late)}:' in text
            assert not (Path(tmp) / 'out').exists()
            return
        refilter_bag(source, Path(tmp) / 'out', params)
        store = jazzy_typestore()
        answers = list(read_bag(Path(tmp) / 'out', topics=[OUTPUT_DIAGNOSTICS_TOPIC]))
    assert answers
    for message in answers:
        stamp = store.deserialize_cdr(message.data, DIAGNOSTIC_ARRAY).header.stamp
        assert stamp.sec * 10**9 + stamp.nanosec == message.log_time_ns


def test_the_command_line_refuses_such_a_bag_in_one_line_exit_2(tmp_path, capsys):
    source = _bag(tmp_path / 'run', [(1_700_000_000 * 10**9, '/state'),
                                     (1_700_000_000 * 10**9 + 1, '/cmd_proposed'),
                                     (2**63, '/state'), (2**63 + 1, '/cmd_proposed')])
    params = tmp_path / 'params.yaml'
    params.write_text(yaml.safe_dump({'safety_filter': {'ros__parameters': PARAMS_A}}))
    assert main([str(source), str(tmp_path / 'out'), '--params-file', str(params)]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err == [f'rcbf_ros refilter: error: /state at log time {2**63}: later than '
                   f'{LATEST_LOG_TIME_NS} ns, the latest builtin_interfaces/msg/Time '
                   '(2038-01-19) an answer can be stamped with']
    assert not (tmp_path / 'out').exists()
