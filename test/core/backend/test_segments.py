"""Which parts of the graph loops tied: the union-find and which side a tie moves."""

from __future__ import annotations

from solid_ros.core.backend.segments import MAP, ORIGIN, Segments


def test_segments_tie_and_the_fixed_side() -> None:
    segs = Segments()
    a, b, c = segs.new(), segs.new(), segs.new()
    assert segs.tied(a, ORIGIN) and not segs.tied(b, ORIGIN)
    assert segs.fixed(a) and not segs.fixed(b) and not segs.fixed(c)
    segs.join(c, b)
    assert segs.members(b) == {b, c} and not segs.tied(b, a)
    segs.join(b, a)
    assert segs.members(c) == {a, b, c} and segs.fixed(c)
    # Once the session moved into a loaded map, only the map holds still.
    segs.anchored = True
    assert not segs.fixed(a)
    d = segs.new()
    segs.join(d, MAP)
    assert segs.fixed(d) and segs.members(MAP) == {d}
