"""A live show sets start-up's objects aside from the cyclic garbage collector
(stage.app.heap): a full collection then walks only what the show made since."""

from __future__ import annotations

import argparse
import gc

import pytest

from stage.app.heap import freeze_start_up, thaw
from stage.app.options import ShowOptions
from stage.app.show import Show


@pytest.fixture(autouse=True)
def _unfrozen():
    gc.unfreeze()
    yield
    gc.unfreeze()


class _Node:
    def __init__(self) -> None:
        self.other = self   # a reference cycle: only the cyclic collector frees it


def test_freezing_sets_aside_what_lives_now_and_still_collects_what_comes_later():
    kept = _Node()
    frozen = freeze_start_up()
    assert frozen == gc.get_freeze_count() > 0
    assert not any(o is kept for o in gc.get_objects())   # no longer walked
    before = gc.get_freeze_count()
    _Node()                                               # garbage made after the freeze
    assert gc.collect() >= 1                              # ...is still found and freed
    assert gc.get_freeze_count() == before                # nothing new was frozen
    thaw()
    assert gc.get_freeze_count() == 0
    assert any(o is kept for o in gc.get_objects())


def _live(**kw) -> ShowOptions:
    return ShowOptions(host="127.0.0.1", port=0, plugins=False, self_healing=False,
                       health=False, **kw)


def test_a_live_show_freezes_after_start_up_and_thaws_when_it_stops():
    show = Show(_live(freeze_heap=True)).start()
    try:
        assert gc.get_freeze_count() > 0
        # the engine, built at start-up, is among the objects set aside
        assert not any(o is show.engine for o in gc.get_objects())
    finally:
        show.stop()
    assert gc.get_freeze_count() == 0


def test_the_library_default_leaves_the_collector_alone():
    show = Show(_live()).start()
    try:
        assert gc.get_freeze_count() == 0
    finally:
        show.stop()


def test_the_commands_freeze_their_shows():
    from stage.cli.common import show_options
    args = argparse.Namespace(view=[], duration=None, no_self_healing=False, no_plugins=True,
                              fused=None)
    assert show_options(args).freeze_heap is True
