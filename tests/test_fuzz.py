"""Fuzzing the decoder and the dispatcher with hypothesis (docs/security.md).

Properties: no exception escapes, every message is decoded or dropped with a
documented reason, the engine's state stays consistent (bounded tables,
tracks and persons that agree, finite joints), and every message handed to
the engine is applied or counted. ``bench/fuzz.py`` runs the same properties
much longer and reports how many inputs were tried.
"""

from __future__ import annotations

import pytest

hypothesis = pytest.importorskip("hypothesis", reason="pip install -e '.[test]' (hypothesis)")
from hypothesis import HealthCheck, given, settings, strategies as st  # noqa: E402

from stage.testing.fuzz import EngineUnderTest, check_decoder, datagrams  # noqa: E402

FAST = settings(max_examples=300, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


@FAST
@given(datagrams())
def test_the_decoder_never_raises_and_accounts_for_every_message(data):
    check_decoder(data)


@FAST
@given(st.binary(max_size=200))
def test_the_decoder_survives_raw_bytes(data):
    check_decoder(data)


SOURCES = [("127.0.0.1", 5000), ("127.0.0.1", 5001), ("127.0.0.2", 5000), ("10.0.0.1", 7000)]


@settings(max_examples=60, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(st.lists(st.tuples(datagrams(), st.sampled_from(SOURCES),
                          st.sampled_from([0.0, 0.001, 0.033, 0.5, 2.0])), max_size=40))
def test_the_engine_stays_consistent_and_counts_every_message(steps):
    sut = EngineUnderTest()
    for data, source, dt in steps:
        sut.feed(data, source, dt)
        sut.check()
