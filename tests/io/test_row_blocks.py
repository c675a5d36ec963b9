"""The row-block engine shared by simulate, fit_ramps and the level-1b writer (slicersim.io.row_blocks)."""
import numpy as np
import pytest

from slicersim.io.row_blocks import BackgroundLanes, BufferRing, RowBlocks, pipelined, rows_per_block, show_progress


def test_rows_per_block_from_the_memory_budget():
    assert rows_per_block(1000, 100, 50) == 10
    assert rows_per_block(10**9, 100, 50) == 50                       # never more than the rows
    assert rows_per_block(1000, 100, 50, reserve=500) == 5
    assert rows_per_block(1000, 100, 50, chunk=4) == 8                # a multiple of the file's chunk rows
    with pytest.raises(MemoryError, match="max_bytes 99 B is below one detector row"):
        rows_per_block(99, 100, 50)
    with pytest.raises(MemoryError, match="memory_budget"):
        rows_per_block(99, 100, 50, name="memory_budget")


def test_a_budget_below_one_row_is_a_slicersim_error_and_a_memory_error():
    """Scripts catching SlicersimError (or MemoryError) both see it."""
    from slicersim.errors import ResourceError, SlicersimError
    with pytest.raises(ResourceError) as info:
        rows_per_block(99, 100, 50)
    assert isinstance(info.value, SlicersimError) and isinstance(info.value, MemoryError)


def test_row_blocks_cover_every_row_of_every_ramp_once():
    blocks = RowBlocks(10, 4, nouter=3, progress=False)
    steps = list(blocks)
    assert len(blocks) == len(steps) == 9
    assert steps[:3] == [(0, 0, 4), (0, 4, 8), (0, 8, 10)] and steps[-1] == (2, 8, 10)
    assert show_progress(True, 1) and not show_progress(False, 100)


class _Stderr:
    def __init__(self, tty):
        self.tty = tty

    def isatty(self):
        return self.tty

    def write(self, text):
        return len(text)

    def flush(self):
        pass


@pytest.mark.parametrize("tty", [True, False])
def test_show_progress_is_the_one_meaning_of_progress(monkeypatch, tty):
    """progress=None (every default) draws a bar only when stderr is a terminal (and the pass has
    more than auto_min blocks when it is counted); True/False as given; anything else is a
    ParameterError naming progress."""
    import sys

    from slicersim.errors import ParameterError
    monkeypatch.setattr(sys, "stderr", _Stderr(tty))
    assert show_progress(None) is tty
    assert show_progress(None, 100) is tty and show_progress(None, 3) is False
    assert show_progress(True) is True and show_progress(False) is False
    assert show_progress(np.bool_(True)) is True
    for bad in ("yes", 1, 0.0):
        with pytest.raises(ParameterError, match="progress must be True or False"):
            show_progress(bad)


def test_progress_defaults_are_none_everywhere():
    """Every public progress keyword defaults to None (resolved by show_progress)."""
    import dataclasses
    import inspect

    from slicersim.campaign.plan import SurveyOptions
    from slicersim.campaign.runner import RunOptions, run_campaign
    from slicersim.etc.solve import SolveOptions
    from slicersim.products.cube import build_cube
    from slicersim.products.ramps import RunOptions as RampRunOptions
    from slicersim.reduction.campaign import reduce_dataset, reduce_file
    from slicersim.reduction.ramp_fit import FIT_DEFAULTS
    for func in (run_campaign, RunOptions.checked, build_cube, reduce_dataset, reduce_file):
        assert inspect.signature(func).parameters["progress"].default is None, func
    for cls in (SurveyOptions, SolveOptions, RampRunOptions):
        assert {f.name: f.default for f in dataclasses.fields(cls)}["progress"] is None, cls
    assert FIT_DEFAULTS["progress"] is None


def test_pipelined_stores_each_result_once_in_order():
    stored = []
    launched = []

    def launch(step):
        launched.append(step)
        return (lambda: step * 10) if step % 2 else step * 10     # device (callable) and host results mixed

    pipelined(range(5), launch, lambda step, result: stored.append((step, result)))
    assert sorted(stored) == [(i, 10 * i) for i in range(5)] and launched == list(range(5))


def test_buffer_ring_alternates_and_lanes_raise_the_first_error():
    ring = BufferRing(12, (np.uint16, np.uint8), nsets=2)
    a, b, c = ring.next((2, 3)), ring.next((3, 4)), ring.next()
    assert a[0].shape == (2, 3) and b[1].shape == (3, 4) and c[0] is ring.sets[0][0]
    assert not np.shares_memory(a[0], b[0])
    lanes = BackgroundLanes(("write",))
    lanes.submit("write", lambda: None)
    lanes.submit("write", lambda: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        lanes.finish()
