"""Float64MultiArray sections: labels that would make two sections share a name, or that
could not be printed on one line of a log or a diagnostic, are refused with the dimension."""
from __future__ import annotations

import numpy as np
import pytest

from rcbf_ros.ros.conversions import MAX_LABEL_CHARS, msg_to_sections, sections_to_msg
from rcbf_ros.ros.runtime import get_message


def _array(labels_sizes: list[tuple[str, int]]) -> object:
    message = get_message('std_msgs/msg/Float64MultiArray')()
    dim = get_message('std_msgs/msg/MultiArrayDimension')
    message.layout.dim = [dim(label=label, size=size, stride=size)
                          for label, size in labels_sizes]
    message.data = [float(k) for k in range(sum(size for _, size in labels_sizes))]
    return message


def test_sections_round_trip():
    sections = msg_to_sections(sections_to_msg({'u': [1.0, 2.0], 'state': [3.0, 4.0, 5.0]}))
    assert list(sections) == ['u', 'state']
    np.testing.assert_array_equal(sections['state'], [3.0, 4.0, 5.0])


def test_unlabelled_dimension_takes_the_default_label():
    assert list(msg_to_sections(_array([('', 2)]), default_label='u')) == ['u']


@pytest.mark.parametrize('labels, words', [
    ([('u', 1), ('u', 1)], ["'u'", 'repeated']),
    ([('', 1), ('u', 1)], ["'u'", 'repeated']),               # unlabelled is u here
    ([('u', 1), ('x' * (MAX_LABEL_CHARS + 1), 1)], ['dim[1]', 'characters']),
    ([('u\nstate', 2)], ['dim[0]', 'not printable', r'\n']),
    ([('u\x00', 2)], ['dim[0]', 'not printable']),
])
def test_bad_labels_are_refused_naming_the_dimension(labels, words):
    with pytest.raises(ValueError) as info:
        msg_to_sections(_array(labels), default_label='u')
    text = str(info.value)
    assert all(word in text for word in words), text
    assert '\n' not in text and len(text) < 200


def test_replacement_characters_are_printable_labels():
    assert list(msg_to_sections(_array([('u\ufffd', 2)]))) == ['u\ufffd']
