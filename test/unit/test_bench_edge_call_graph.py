"""The call-graph benchmark of the filter's path counts stops, files and returns as its
docstring says, in each of its views."""
from __future__ import annotations

from pathlib import Path

from benchmark_modules import load_benchmark

import rcbf_ros
from rcbf_ros.messages import conversions

bench = load_benchmark('edge_call_graph')
PACKAGE = Path(rcbf_ros.__file__).resolve().parent


def test_a_call_into_another_file_and_back_is_three_stops_in_two_files():
    data = conversions.sections_to_cdr({'u': [1.0, 2.0]})
    views = bench._trace(lambda: conversions.sections_from_cdr(data), PACKAGE)
    expected = ['messages/conversions.py', 'messages/cdr.py', 'messages/conversions.py']
    assert views == {view: expected for view in bench.VIEWS}
    assert bench._figures(expected) == (3, 2, 1)


def test_the_views_fold_what_lies_below_a_decision_and_a_hand_off():
    """From the node's file, a call into conversions that calls cdr is one hand-off; below
    an opaque function, everything is that function's file."""
    data = conversions.sections_to_cdr({'u': [1.0, 2.0]})
    code = compile('def handler():\n    return sections_from_cdr(data)\n',
                   str(PACKAGE / bench.NODE_FILE), 'exec')
    scope = {'sections_from_cdr': conversions.sections_from_cdr, 'data': data}
    exec(code, scope)  # a function whose frames are in the node's file
    views = bench._trace(scope['handler'], PACKAGE)
    assert views['every file'] == [bench.NODE_FILE, 'messages/conversions.py',
                                   'messages/cdr.py', 'messages/conversions.py',
                                   bench.NODE_FILE]
    assert views['hand-offs'] == [bench.NODE_FILE, 'messages/conversions.py', bench.NODE_FILE]


def test_the_decision_and_all_below_it_is_one_stop():
    data = conversions.sections_to_cdr({'u': [1.0, 2.0]})
    file, name = bench.OPAQUE[0]
    code = compile(f'def {name}():\n    return sections_from_cdr(data)\n',
                   str(PACKAGE / file), 'exec')
    scope = {'sections_from_cdr': conversions.sections_from_cdr, 'data': data}
    exec(code, scope)
    views = bench._trace(scope[name], PACKAGE)
    assert views['decide as one stop'] == [file]
    assert views['every file'] == [file, 'messages/conversions.py', 'messages/cdr.py',
                                   'messages/conversions.py', file]
