"""The ESDF builder refreshes into the output arrays of fields nobody holds any more, and never
into those of a field (or a view of one of its arrays) still in use: a planner holding a field
while the mapping thread refreshes must see it unchanged."""

from __future__ import annotations

import gc

import numpy as np

from onboard.mapping import EsdfBuilder, OccupancyMap, OccupancyParams


def _random_map(seed: int) -> OccupancyMap:
    rng = np.random.default_rng(seed)
    om = OccupancyMap(OccupancyParams(size_m=(2.4, 2.0, 1.6)), center=np.zeros(3))
    _fill(om, rng)
    return om


def _fill(om: OccupancyMap, rng: np.random.Generator) -> None:
    u = rng.random(om.shape)
    om.logodds[...] = np.where(u < 0.05, 2.0, np.where(u < 0.6, -1.0, -100.0))
    om.surf[:, :3] = rng.uniform(-0.05, 0.05, size=(om.surf.shape[0], 3))
    om.surf[:, 3] = rng.integers(0, 3, size=om.surf.shape[0])


def _address(a: np.ndarray) -> int:
    return int(a.__array_interface__["data"][0])


def test_fields_nobody_holds_give_their_arrays_to_the_next_refresh() -> None:
    om = _random_map(0)
    b = EsdfBuilder()
    seen: set[int] = set()
    for _ in range(12):
        f = b.build(om, inflate_m=0.1)
        seen.add(_address(f.values))
        del f
        gc.collect()
    assert len(seen) == 1  # one buffer set, reused every time
    assert b.new_sets == 1


def test_the_builder_counts_the_buffer_sets_it_had_to_allocate() -> None:
    om = _random_map(2)
    b = EsdfBuilder()
    held = [b.build(om, inflate_m=0.1) for _ in range(5)]  # each still held: a new set each
    assert b.new_sets == 5
    del held
    gc.collect()
    for _ in range(4):
        b.build(om, inflate_m=0.1)
        gc.collect()
    assert b.new_sets == 5  # the pooled ones came back


def test_a_field_or_any_view_of_it_still_held_is_never_overwritten() -> None:
    rng = np.random.default_rng(1)
    om = _random_map(1)
    b = EsdfBuilder()
    held = b.build(om, inflate_m=0.1)
    planning = held.inflated(0.1)
    copies = {
        "values": held.values.copy(),
        "planning": planning.values.copy(),
        "known": None if held.known is None else held.known.copy(),
        "occupied": held.occupied.copy(),
    }
    # only views of arrays of other fields, no field object
    f2 = b.build(om, inflate_m=0.1)
    v2 = f2.values[1:3]
    k2 = f2.known
    copy2 = (v2.copy(), None if k2 is None else k2.copy())
    del f2
    gc.collect()
    for _ in range(8):  # the map changes; refreshes must go to other buffers
        _fill(om, rng)
        fresh = EsdfBuilder().build(om, inflate_m=0.1)
        got = b.build(om, inflate_m=0.1)
        np.testing.assert_array_equal(got.values, fresh.values)  # same result as a new builder
        np.testing.assert_array_equal(got.inflated(0.1).values, fresh.inflated(0.1).values)
        del got, fresh
        gc.collect()
    for name, a in (("values", held.values), ("planning", planning.values)):
        want = copies[name]
        assert want is not None
        np.testing.assert_array_equal(a, want)
    assert held.known is not None and copies["known"] is not None
    np.testing.assert_array_equal(held.known, copies["known"])
    occupied = copies["occupied"]
    assert occupied is not None
    np.testing.assert_array_equal(held.occupied, occupied)
    np.testing.assert_array_equal(v2, copy2[0])
    assert k2 is not None and copy2[1] is not None
    np.testing.assert_array_equal(k2, copy2[1])
    # what is given out cannot be written
    for a in (held.values, planning.values, held.occupied, held.known, v2):
        assert not a.flags.writeable
