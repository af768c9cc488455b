"""The safety filter's topic clash rule: every name the node uses, resolved, no two alike.

:func:`rcbf_ros.node_logic.sources.topic_refusal` against an oracle of its own: the names the
node uses (the middleware's, its topics, its sources') resolved with rcl's rules
(:func:`rcbf_ros.parameters.arguments.resolve_topic_name`, the dds layer's), and refused
exactly when two resolve alike, in one line naming both.
"""
from __future__ import annotations

from itertools import combinations
from types import SimpleNamespace

from hypothesis import given, settings
from hypothesis import strategies as st
import pytest

from rcbf_ros.node_logic.safety_filter_interface import INTERFACE
from rcbf_ros.node_logic.sources import MIDDLEWARE_TOPICS, topic_refusal
from rcbf_ros.parameters.arguments import RemapRule, resolve_topic_name

OWN = tuple(topic.name for topic in INTERFACE.topics)
"""The node's own topics, as the node passes them."""
TARGETS = ('cmd_vel', '/cmd_vel', 'odom', '/odom', 'scan', '/robot/scan', '/tf', 'tf_static',
           'rosout', '/parameter_events', 'state', 'cmd_safe', '/cmd_safe', '~/cmd',
           '~/get_parameters', 'diagnostics', '/robot/cmd_vel', 'filter_info')
"""Remap targets and source topics: few enough that clashes are common."""


def _resolver(node: str, namespace: str, remaps: dict[str, str]):
    rules = [RemapRule(match, replacement) for match, replacement in remaps.items()]
    return lambda topic: resolve_topic_name(topic, node, namespace, rules)


def _sources(topics: list[str]) -> SimpleNamespace:
    """What topic_refusal reads of a SourceConfig: (name, parameters with .topic) pairs."""
    return SimpleNamespace(sources=tuple(
        (f'src{index}', SimpleNamespace(topic=topic)) for index, topic in enumerate(topics)))


@settings(max_examples=300, deadline=None)
@given(node=st.sampled_from(['safety_filter', 'filter']),
       namespace=st.sampled_from(['/', '/robot', '/a/b']),
       remaps=st.dictionaries(st.sampled_from(OWN + MIDDLEWARE_TOPICS[:4] + ('/state',)),
                              st.sampled_from(TARGETS), max_size=3),
       topics=st.lists(st.sampled_from(TARGETS), max_size=2))
def test_refused_exactly_when_two_names_resolve_alike_naming_both(node, namespace, remaps,
                                                                   topics):
    resolve = _resolver(node, namespace, remaps)
    labels = {name: name for name in (*MIDDLEWARE_TOPICS, *OWN)}
    labels.update({f'src{index}.topic': topic for index, topic in enumerate(topics)})
    resolved = {label: resolve(given) for label, given in labels.items()}
    clashes = [(a, b) for a, b in combinations(resolved, 2) if resolved[a] == resolved[b]]
    why = topic_refusal(_sources(topics), OWN, resolve)
    assert bool(why) == bool(clashes), (why, clashes)
    if why:
        assert '\n' not in why and len(why) < 400
        assert any(a in why and b in why and resolved[a] in why for a, b in clashes), why


@pytest.mark.parametrize('remaps, namespace, both', [
    ({'cmd_proposed': 'cmd_safe'}, '/', ('cmd_proposed', 'cmd_safe', '/cmd_safe')),
    ({'cmd_proposed': '/cmd_vel', 'cmd_safe': 'cmd_vel'}, '/',
     ('cmd_proposed', 'cmd_safe', '/cmd_vel')),
    ({'cmd_safe': '/robot/cmd_proposed'}, '/robot',
     ('cmd_proposed', 'cmd_safe', '/robot/cmd_proposed')),
    ({'state': '/tf'}, '/', ('/tf', 'state', '/tf')),
    ({'cmd_proposed': 'tf'}, '/', ('/tf', 'cmd_proposed', '/tf')),
    ({'cmd_safe': '/rosout'}, '/', ('/rosout', 'cmd_safe', '/rosout')),
    ({'filter_info': '~/get_parameters'}, '/',
     ('~/get_parameters', 'filter_info', '/safety_filter/get_parameters')),
    ({'/tf': '/cmd_vel', 'cmd_safe': '/cmd_vel'}, '/', ('/tf', 'cmd_safe', '/cmd_vel')),
])
def test_a_node_topic_on_another_or_on_the_middlewares_is_refused(remaps, namespace, both):
    why = topic_refusal(None, OWN, _resolver('safety_filter', namespace, remaps))
    first, second, full = both
    assert why == (f"{first} and {second} both resolve to {full}; each of the node's topics "
                   'needs its own (see the remaps and namespace)')


@pytest.mark.parametrize('remaps, namespace', [
    ({}, '/'), ({}, '/robot'), ({'cmd_proposed': '/cmd_vel_nav', 'cmd_safe': '/cmd_vel',
                                 'state': '/odom'}, '/'),
    ({'cmd_safe': '/robot/cmd_vel'}, '/robot'),
])
def test_distinct_names_pass(remaps, namespace):
    assert topic_refusal(None, OWN, _resolver('safety_filter', namespace, remaps)) == ''
