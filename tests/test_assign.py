"""Formation assignment of the ground station: templates, validation, Hungarian slots, epochs."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from gcs.formations import (
    YAW_TIE_M_PER_DRONE,
    FormationAssigner,
    FormationError,
    best_yaw,
    brute_force_slots,
    check_points,
    formation_errors,
    hungarian_slots,
    load_template,
    place,
)
from onboard.comm.wire import GCS_ID, WIRE_VERSION, Command, Envelope, decode, encode
from onboard.config import config_dir

NEW_SHAPES = ["rectangle-4", "rectangle-6", "rectangle-7", "line-4", "line-7", "arrow-5",
              "arrow-7", "pyramid-5", "octahedron-6", "bipyramid-7"]  # fmt: skip


class FakeClock:
    def __init__(self, t: float = 1.7e9) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def _positions(pts: np.ndarray, ids: list[int] | None = None) -> dict[int, np.ndarray]:
    ids = list(range(len(pts))) if ids is None else ids
    return {d: p for d, p in zip(ids, pts, strict=True)}


@pytest.mark.parametrize("name", NEW_SHAPES)
def test_new_shapes_load_and_keep_the_drone_spacing(name: str) -> None:
    f = load_template(name)
    assert f.points.shape == (int(name.rsplit("-", 1)[1]), 3)
    check_points(f.points, f.n, 1.2, name)  # every shipped shape keeps >= 1.2 m


def test_three_d_shapes_are_three_d() -> None:
    for name in ("pyramid-5", "octahedron-6", "bipyramid-7"):
        z = load_template(name).points[:, 2]
        assert np.ptp(z) > 0.5, name


@pytest.mark.parametrize("n", [2, 3, 4, 5, 6, 7])
def test_hungarian_equals_brute_force(n: int) -> None:
    rng = np.random.default_rng(100 + n)
    for _ in range(20):
        a = rng.uniform(-5, 5, (n, 3))
        b = rng.uniform(-5, 5, (n, 3))
        slots, cost = hungarian_slots(a, b)
        bslots, bcost = brute_force_slots(a, b)
        assert sorted(slots.tolist()) == list(range(n))  # a permutation
        assert cost == pytest.approx(bcost, rel=1e-12, abs=1e-12)
        assert float(np.linalg.norm(a - b[slots], axis=1).sum()) == pytest.approx(cost)


def test_assignment_places_the_template_at_the_swarm_with_scale_and_yaw() -> None:
    clock = FakeClock()
    asg = FormationAssigner(clock, lead_s=2.0)
    tpl = load_template("hexagon-7")
    # the drones already fly the hexagon, turned 90 degrees, shifted, scaled 1.5 and shuffled
    truth = place(tpl.points, (10.0, -3.0, 1.5), 1.5, math.pi / 2)
    perm = np.random.default_rng(1).permutation(7)
    ids = [3, 9, 1, 4, 5, 8, 2]
    positions = _positions(truth[perm], ids)
    a = asg.assign("hexagon-7", positions, scale=1.5, yaw_rad=math.pi / 2)
    assert np.allclose(a.center_m, (10.0, -3.0, 1.5))
    assert a.cost_m == pytest.approx(0.0, abs=1e-9)
    for d, k in zip(ids, perm, strict=True):
        assert a.slots[d] == k
    assert a.effective_s == pytest.approx(clock.t + 2.0)
    e = formation_errors(positions, a.slots, a.points_m)
    assert e is not None and e[0] == pytest.approx(0.0, abs=1e-9) and e[1] < 1e-12
    # the wire action carries the placed shape about its centroid; it passes the wire checks
    w = a.to_wire()
    assert w.scale == 1.0 and w.yaw_rad == 0.0 and w.epoch == a.epoch
    assert np.allclose(np.asarray(w.points_m), a.points_m - a.points_m.mean(axis=0))
    env = Envelope(WIRE_VERSION, GCS_ID, 1, 0, clock.t, 10.0, Command(1, ids, clock.t, w))
    back = decode(encode(env)).body
    assert isinstance(back, Command) and back.action == w


def test_assignment_mid_flight_takes_the_nearest_slots() -> None:
    """A line of 4 flying along x re-shapes into a rectangle: each drone takes the corner on
    its side, and the total distance is the brute-force optimum."""
    asg = FormationAssigner(FakeClock())
    line = place(load_template("line-4").points, (5.0, 0.0, 1.0), 1.0, 0.0)
    positions = _positions(line)
    a = asg.assign("rectangle-4", positions)
    _, best = brute_force_slots(line, a.points_m)
    assert a.cost_m == pytest.approx(best)
    for d, s in a.slots.items():  # each drone's slot is on its own side of the x axis
        assert np.sign(a.points_m[s][1]) == np.sign(positions[d][1])


def _total(tpl: np.ndarray, pos: np.ndarray, yaw: float) -> float:
    return hungarian_slots(pos, place(tpl, pos.mean(axis=0), 1.0, yaw))[1]


def test_without_a_yaw_the_turn_of_least_travel() -> None:
    """A hexagon re-shaping into the rectangle travels least with the rectangle turned by 30
    or 90 degrees (4.67 m against 8.25 m as written); no turn on a fine grid is nearer."""
    asg = FormationAssigner(FakeClock())
    hexagon = place(load_template("hexagon-7").points, (5.0, 2.0, 1.5), 1.0, 0.0)
    a = asg.assign("rectangle-7", _positions(hexagon), yaw_rad=None)
    rect = load_template("rectangle-7").points
    assert min(abs(abs(a.yaw_rad) - math.radians(d)) for d in (30.0, 90.0, 150.0)) < 1e-3
    assert a.cost_m == pytest.approx(4.665, abs=1e-3)
    assert _total(rect, hexagon, 0.0) == pytest.approx(8.251, abs=1e-3)
    # no turn on a fine grid is nearer by more than the tie (the file's hexagon is rounded to
    # 4 decimals: 90 degrees is 0.2 mm nearer than 30), and none nearby is nearer at all
    grid = [_total(rect, hexagon, math.radians(k / 10.0)) for k in range(3600)]
    assert a.cost_m <= min(grid) + YAW_TIE_M_PER_DRONE * 7
    for d in (-0.1, -0.01, 0.01, 0.1):
        assert a.cost_m <= _total(rect, hexagon, a.yaw_rad + math.radians(d)) + 1e-9
    # the slots are those of the placed points, and the wire carries the turned shape
    assert np.allclose(a.points_m, place(rect, hexagon.mean(axis=0), 1.0, a.yaw_rad))
    w = a.to_wire()
    assert np.allclose(np.asarray(w.points_m), a.offsets_m) and w.yaw_rad == 0.0
    # a yaw given is kept
    b = asg.assign("rectangle-7", _positions(hexagon), yaw_rad=0.0)
    assert b.yaw_rad == 0.0 and b.cost_m == pytest.approx(8.251, abs=1e-3)


@pytest.mark.parametrize("name", ["arrow-7", "line-4", "bipyramid-7", "heart-10"])
def test_best_yaw_finds_a_turned_swarm(name: str) -> None:
    """Drones standing in the shape turned by any angle (shuffled) get that angle back, or one
    of the shape's symmetric turns: no travel at all."""
    tpl = load_template(name).points
    rng = np.random.default_rng(7)
    for yaw in (0.3, -2.0, 2.9, math.radians(137.4)):
        pos = place(tpl, (1.0, -4.0, 2.0), 1.3, yaw)[rng.permutation(len(tpl))]
        got = best_yaw(tpl, pos, pos.mean(axis=0), 1.3)
        assert -math.pi < got <= math.pi
        placed = place(tpl, pos.mean(axis=0), 1.3, got)
        assert hungarian_slots(pos, placed)[1] == pytest.approx(0.0, abs=2e-3 * len(tpl))


def test_best_yaw_keeps_the_template_as_written_on_a_tie() -> None:
    """A swarm already in a symmetric shape (the hexagon: six turns fit it exactly, the
    rectangle: two) keeps the shape unturned, exactly, whatever the order of the drones; and
    within a degree where each drone is off by up to 3 cm (the real stack's hovers fitted the
    hexagon a little better turned by 60 degrees)."""
    rng = np.random.default_rng(3)
    for name in ("hexagon-7", "rectangle-7", "rectangle-4", "octahedron-6"):
        tpl = load_template(name).points
        pos = place(tpl, (3.0, 3.0, 1.0), 1.0, 0.0)[::-1]
        assert best_yaw(tpl, pos, pos.mean(axis=0), 1.0) == 0.0, name
        for _ in range(10):
            noisy = pos + rng.uniform(-0.03, 0.03, pos.shape)
            got = best_yaw(tpl, noisy, noisy.mean(axis=0), 1.0)
            assert abs(got) < math.radians(1.0), (name, math.degrees(got))


def test_subset_with_drones() -> None:
    asg = FormationAssigner(FakeClock())
    positions = _positions(np.array([[i * 2.0, 0.0, 1.0] for i in range(7)]))
    a = asg.assign("triangle-3", positions, drones=[6, 2, 4])
    assert sorted(a.slots) == [2, 4, 6]
    assert sorted(a.slots.values()) == [0, 1, 2]
    assert np.allclose(a.center_m, [8.0, 0.0, 1.0])


def test_epochs_increase_and_errors_use_none() -> None:
    clock = FakeClock()
    asg = FormationAssigner(clock)
    positions = _positions(place(load_template("hexagon-7").points, (0, 0, 1), 1.0, 0.0))
    e1 = asg.assign("hexagon-7", positions).epoch
    e2 = asg.assign("hexagon-7", positions).epoch  # same clock: still a new epoch
    assert e2 > e1
    with pytest.raises(FormationError):
        asg.assign("triangle-3", positions)
    assert asg.last_epoch == e2 and asg.last is not None and asg.last.epoch == e2
    asg.observe_epoch(e2 + 1000)  # seen on the bus (a drone's state)
    e3 = asg.assign("hexagon-7", positions).epoch
    assert e3 > e2 + 1000
    # a restarted ground station (new assigner, later clock) still issues newer epochs
    clock.t += 5.0
    assert FormationAssigner(clock).assign("hexagon-7", positions).epoch > e2


def _hex_positions() -> dict[int, np.ndarray]:
    return _positions(place(load_template("hexagon-7").points, (0, 0, 1), 1.0, 0.0))


def test_wrong_count() -> None:
    with pytest.raises(FormationError, match=r"has 4 points but 7 drones"):
        FormationAssigner(FakeClock()).assign("tetrahedron-4", _hex_positions())
    with pytest.raises(FormationError, match=r"has 7 points but 3 drones"):
        FormationAssigner(FakeClock()).assign("hexagon-7", _hex_positions(), drones=[0, 1, 2])


def test_nan_in_file(tmp_path: Path) -> None:
    f = tmp_path / "bad.yaml"
    f.write_text("points: [[0, 0, 0], [1, .nan, 0], [0, 2, 0]]\n")
    with pytest.raises(FormationError, match=r"bad\.yaml"):
        FormationAssigner(FakeClock()).assign(f, _positions(np.eye(3)))


def test_nan_points_named() -> None:
    with pytest.raises(FormationError, match=r"points \[1\] are not finite"):
        check_points(np.array([[0, 0, 0], [np.nan, 0, 0], [2, 0, 0]]), 3, 0.8)


def test_duplicate_and_too_close_points(tmp_path: Path) -> None:
    dup = tmp_path / "dup.json"
    dup.write_text('{"points": [[0, 0, 0], [2, 0, 0], [0, 0, 0]]}')
    with pytest.raises(FormationError, match=r"points 0 and 2 coincide"):
        FormationAssigner(FakeClock()).assign(dup, _positions(np.eye(3) * 3))
    # hexagon-7 has its nearest points 2 m apart: scaled by 0.3 they are 0.6 m < 0.8 m
    with pytest.raises(FormationError, match=r"are 0\.600 m apart, closer than the drone spacing"):
        FormationAssigner(FakeClock()).assign("hexagon-7", _hex_positions(), scale=0.3)
    FormationAssigner(FakeClock(), min_spacing_m=0.5).assign(
        "hexagon-7", _hex_positions(), scale=0.3
    )


def test_unknown_name_and_unreadable_file(tmp_path: Path) -> None:
    with pytest.raises(FormationError, match=r"no file named 'no-such-shape'.*hexagon-7"):
        load_template("no-such-shape")
    missing = tmp_path / "missing.yaml"
    with pytest.raises(FormationError, match=r"missing\.yaml.*cannot read"):
        load_template(missing)
    garbage = tmp_path / "garbage.yaml"
    garbage.write_text("points: [[0, 0, 0], [1, 0\n")
    with pytest.raises(FormationError, match=r"invalid YAML"):
        load_template(garbage)
    wrong = tmp_path / "wrong.yaml"
    wrong.write_text("pointz: [[0, 0, 0], [1, 0, 0]]\n")
    with pytest.raises(FormationError, match=r"pointz"):
        load_template(wrong)
    assert (config_dir() / "formations" / "hexagon-7.yaml").is_file()


def test_bad_scale_yaw_drones_positions() -> None:
    a = FormationAssigner(FakeClock())
    for scale in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(FormationError, match="scale"):
            a.assign("hexagon-7", _hex_positions(), scale=scale)
    with pytest.raises(FormationError, match="yaw"):
        a.assign("hexagon-7", _hex_positions(), yaw_rad=math.nan)
    with pytest.raises(FormationError, match=r"drones \[42\] are not up"):
        a.assign("triangle-3", _hex_positions(), drones=[0, 1, 42])
    with pytest.raises(FormationError, match="twice"):
        a.assign("triangle-3", _hex_positions(), drones=[0, 1, 1])
    pos = _hex_positions()
    pos[3] = np.array([np.nan, 0.0, 1.0])
    with pytest.raises(FormationError, match=r"drones \[3\] are not finite"):
        a.assign("hexagon-7", pos)
    with pytest.raises(FormationError, match="none is up"):
        a.assign("hexagon-7", {})


def test_per_drone_errors_are_the_terms_of_e_dist() -> None:
    from gcs.formations import per_drone_errors

    tpl = load_template("hexagon-7").points
    cur = place(tpl, (1.0, 2.0, 1.0), 2.0, 0.3)  # a similar copy: no error
    slots = {d: d for d in range(7)}
    assert max(per_drone_errors(_positions(cur), slots, tpl).values()) < 1e-9
    cur[3] += (0.5, 0.0, 0.0)  # one drone off its slot
    per = per_drone_errors(_positions(cur), slots, tpl)
    e = formation_errors(_positions(cur), slots, tpl)
    assert e is not None and max(per, key=lambda d: per[d]) == 3
    assert math.sqrt(sum(v * v for v in per.values())) == pytest.approx(e[0])
    assert per_drone_errors({0: cur[0]}, slots, tpl) == {}
