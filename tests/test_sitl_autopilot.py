"""PX4-like flight logic of the mock, stepped in simulated time without sockets.

A ``Fleet`` that is never opened runs its ticks headless; messages go through the same MAVLink
handlers as on the network (``VehicleLink.handle``), only nothing is sent.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from sitl_mock import dynamics as dyn
from sitl_mock.autopilot import AutopilotParams, LandedState, Mode, Result
from sitl_mock.fleet import Fleet, FleetConfig
from sitl_mock.mavlink_io import setpoint_from_local_ned
from sitl_mock.truth import InMemoryTruth

MAV = mavlink.MAVLink(None, 245, 190)
POS_ONLY = 8 | 16 | 32 | 64 | 128 | 256 | 2048  # position + yaw


def make_fleet(
    n: int = 1, world: Any = None, truth: Any = (), spawn: Any = None, **ap: Any
) -> Fleet:
    params: dict[str, Any] = {"boot_time_s": 0.5, **ap}
    cfg = FleetConfig(
        count=n, local_port_offset=None, autopilot=AutopilotParams(**params), spawn_enu_m=spawn
    )
    return Fleet(cfg, world, truth)


def run(
    f: Fleet,
    seconds: float,
    sp: dict[int, tuple[float, float, float]] | None = None,
    sp_rate_hz: float = 20.0,
) -> None:
    """Tick for ``seconds`` of simulated time, streaming position setpoints (local NED) to the
    vehicles in ``sp`` (index -> position) at ``sp_rate_hz``."""
    every = max(1, int(round(1.0 / (sp_rate_hz * f.dt_s))))
    for k in range(int(round(seconds / f.dt_s))):
        if sp and k % every == 0:
            for i, p in sp.items():
                f.links[i].handle(
                    MAV.set_position_target_local_ned_encode(
                        0, i + 1, 1, 1, POS_ONLY, *p, 0, 0, 0, 0, 0, 0, 0.0, 0.0
                    )
                )
        f.tick()


def local_ned(f: Fleet, i: int = 0) -> np.ndarray:
    s = f.state[i]
    est = s[dyn.S_P : dyn.S_P + 3] + s[dyn.S_E : dyn.S_E + 3] - f.spawns[i]
    return np.array([est[1], est[0], -est[2]])


def test_px4_custom_mode_encoding() -> None:
    assert Mode.HOLD.custom_mode == 0x03040000
    assert Mode.OFFBOARD.custom_mode == 0x00060000
    assert Mode.LAND.custom_mode == 0x06040000
    assert Mode.TAKEOFF.custom_mode == 0x02040000
    assert Mode.POSCTL.custom_mode == 0x00030000
    for m in Mode:
        assert Mode.from_custom_mode(m.custom_mode) is m
    assert Mode.from_main_sub(4, 0) is Mode.MISSION
    assert Mode.from_main_sub(6, 3) is Mode.OFFBOARD  # sub mode ignored outside AUTO
    assert Mode.from_main_sub(9, 0) is None


def test_arming_rules_and_preflight_disarm() -> None:
    f = make_fleet(disarm_preflight_s=3.0)
    ap = f.autopilots[0]
    assert ap.command_arm(f.t_s, True) == Result.TEMPORARILY_REJECTED  # still booting
    run(f, 0.6)
    assert ap.mode is Mode.HOLD and ap.landed
    assert ap.command_arm(f.t_s, True) == Result.ACCEPTED
    assert ap.command_arm(f.t_s, True) == Result.ACCEPTED  # already armed
    run(f, 2.0)
    assert ap.armed and f.state[0, dyn.S_P + 2] == 0.0  # idling on the ground
    run(f, 1.5)
    assert not ap.armed  # no takeoff within disarm_preflight_s
    assert ap.command_arm(f.t_s, False) == Result.ACCEPTED  # disarming when disarmed


def test_offboard_needs_a_stream_above_2hz_for_a_second() -> None:
    f = make_fleet()
    ap = f.autopilots[0]
    run(f, 0.6)
    assert ap.command_set_mode(f.t_s, Mode.OFFBOARD) == Result.TEMPORARILY_REJECTED
    run(f, 0.5, sp={0: (0.0, 0.0, -2.0)})
    assert ap.command_set_mode(f.t_s, Mode.OFFBOARD) == Result.TEMPORARILY_REJECTED  # 0.5 s
    run(f, 0.7, sp={0: (0.0, 0.0, -2.0)})
    assert ap.command_set_mode(f.t_s, Mode.OFFBOARD) == Result.ACCEPTED
    assert ap.mode is Mode.OFFBOARD
    # a 1 Hz stream is too slow
    g = make_fleet()
    run(g, 0.6)
    run(g, 3.0, sp={0: (0.0, 0.0, -2.0)}, sp_rate_hz=1.0)
    assert g.autopilots[0].command_set_mode(g.t_s, Mode.OFFBOARD) == Result.TEMPORARILY_REJECTED
    # setpoints that leave an axis uncontrolled are not a stream
    h = make_fleet()
    run(h, 0.6)
    for _ in range(40):
        h.links[0].handle(
            MAV.set_position_target_local_ned_encode(
                0, 1, 1, 1, 0xFFF, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0
            )
        )
        run(h, 0.05)
    assert h.links[0].stats.setpoints_malformed == 40 and h.links[0].stats.setpoints == 0
    assert h.autopilots[0].command_set_mode(h.t_s, Mode.OFFBOARD) == Result.TEMPORARILY_REJECTED


def test_takeoff_offboard_failsafe_land_cycle() -> None:
    f = make_fleet()
    ap = f.autopilots[0]
    run(f, 0.6)
    assert ap.command_arm(f.t_s, True) == Result.ACCEPTED
    assert ap.command_takeoff(f.t_s, None) == Result.ACCEPTED
    assert ap.mode is Mode.TAKEOFF
    run(f, 1.5)
    assert ap.landed_state() is LandedState.TAKEOFF
    run(f, 3.5)
    assert ap.mode is Mode.HOLD  # switched by itself after the climb
    assert local_ned(f)[2] == pytest.approx(-2.5, abs=0.15)
    assert ap.landed_state() is LandedState.IN_AIR
    assert ap.command_arm(f.t_s, False) == Result.TEMPORARILY_REJECTED  # in the air
    # offboard flight to a point
    run(f, 1.2, sp={0: (0.0, 0.0, -2.5)})
    assert ap.command_set_mode(f.t_s, Mode.OFFBOARD) == Result.ACCEPTED
    run(f, 6.0, sp={0: (2.0, 1.0, -3.0)})
    np.testing.assert_allclose(local_ned(f), [2.0, 1.0, -3.0], atol=0.1)
    # the stream stops: offboard for COM_OF_LOSS_T (1 s), then the failsafe (hold)
    run(f, 0.9)
    assert ap.mode is Mode.OFFBOARD and ap.failsafe is None
    run(f, 0.3)
    assert ap.mode is Mode.HOLD and ap.failsafe == "offboard_loss"
    run(f, 3.0)
    np.testing.assert_allclose(local_ned(f), [2.0, 1.0, -3.0], atol=0.15)
    # land, detect the landing, disarm 2 s later, return to the last user mode (offboard)
    assert ap.command_land(f.t_s) == Result.ACCEPTED
    run(f, 3.0)
    assert ap.landed_state() is LandedState.LANDING
    run(f, 5.0)
    assert ap.landed and not ap.armed
    assert ap.mode is Mode.OFFBOARD
    assert ap.command_arm(f.t_s, True) == Result.TEMPORARILY_REJECTED  # offboard, no stream
    assert ap.command_set_mode(f.t_s, Mode.HOLD) == Result.ACCEPTED
    assert ap.command_arm(f.t_s, True) == Result.ACCEPTED


def test_failsafe_land_and_forced_disarm() -> None:
    f = make_fleet(offboard_loss_action="land", offboard_loss_timeout_s=0.5)
    ap = f.autopilots[0]
    run(f, 0.6)
    run(f, 1.2, sp={0: (0.0, 0.0, -2.0)})
    assert ap.command_set_mode(f.t_s, Mode.OFFBOARD) == Result.ACCEPTED
    assert ap.command_arm(f.t_s, True) == Result.ACCEPTED  # arming in offboard with a stream
    run(f, 5.0, sp={0: (0.0, 0.0, -2.0)})
    assert local_ned(f)[2] == pytest.approx(-2.0, abs=0.1)
    run(f, 0.7)
    assert ap.mode is Mode.LAND and ap.failsafe == "offboard_loss"
    run(f, 8.0)
    assert not ap.armed and ap.landed
    # forced disarm in the air: the vehicle falls
    g = make_fleet()
    ap = g.autopilots[0]
    run(g, 0.6)
    ap.command_arm(g.t_s, True)
    ap.command_takeoff(g.t_s, 3.0)
    run(g, 6.0)
    assert ap.command_arm(g.t_s, False, force=True) == Result.ACCEPTED
    run(g, 2.0)
    assert g.state[0, dyn.S_P + 2] == 0.0 and not ap.armed
    assert [c.kind for c in g.collision_events()] == ["ground"]  # a hard landing


def test_position_mode_needs_rc_and_unknown_modes_are_denied() -> None:
    f = make_fleet()
    run(f, 0.6)
    ap = f.autopilots[0]
    assert ap.command_set_mode(f.t_s, Mode.POSCTL) == Result.TEMPORARILY_REJECTED
    assert ap.command_set_mode(f.t_s, Mode.MANUAL) == Result.DENIED
    assert ap.command_set_mode(f.t_s, None) == Result.DENIED
    g = make_fleet(rc_present=True)
    run(g, 0.6)
    assert g.autopilots[0].command_set_mode(g.t_s, Mode.POSCTL) == Result.ACCEPTED


def test_return_to_launch() -> None:
    f = make_fleet(rtl_return_alt_m=4.0)
    ap = f.autopilots[0]
    run(f, 0.6)
    run(f, 1.2, sp={0: (0.0, 0.0, -2.0)})
    ap.command_set_mode(f.t_s, Mode.OFFBOARD)
    ap.command_arm(f.t_s, True)
    run(f, 7.0, sp={0: (6.0, 3.0, -2.0)})
    assert ap.command_rtl(f.t_s) == Result.ACCEPTED
    run(f, 25.0)
    assert not ap.armed and ap.landed
    np.testing.assert_allclose(local_ned(f)[:2], [0.0, 0.0], atol=0.2)


# ---- setpoint decoding (type_mask, frames) ----------------------------------------------------

ORIGIN = np.array([10.0, 20.0, 0.0])
HERE = np.array([11.0, 22.0, 3.0])


def sp(mask: int, frame: int = 1, yaw_enu: float = math.pi / 2, **kw: Any) -> Any:
    return setpoint_from_local_ned(
        mask,
        frame,
        kw.get("p", (1.0, 2.0, -3.0)),
        kw.get("v", (0.5, -0.5, 0.1)),
        kw.get("a", (0.1, 0.2, 0.3)),
        kw.get("yaw", 0.3),
        kw.get("yaw_rate", 0.2),
        ORIGIN,
        HERE,
        yaw_enu,
    )


def test_setpoint_type_masks() -> None:
    nan3 = [math.nan] * 3
    # position + yaw (MAVSDK's PositionNedYaw): ENU = origin + (east, north, up)
    s = sp(8 | 16 | 32 | 64 | 128 | 256 | 2048)
    np.testing.assert_allclose(s.position_m, [12.0, 21.0, 3.0])
    np.testing.assert_array_equal(s.velocity_m_s, nan3)
    np.testing.assert_array_equal(s.acceleration_m_s2, nan3)
    assert s.yaw_rad == pytest.approx(math.pi / 2 - 0.3) and math.isnan(s.yaw_rate_rad_s)
    # velocity only + yaw rate
    s = sp(1 | 2 | 4 | 64 | 128 | 256 | 1024)
    np.testing.assert_array_equal(s.position_m, nan3)
    np.testing.assert_allclose(s.velocity_m_s, [-0.5, 0.5, -0.1])
    assert math.isnan(s.yaw_rad) and s.yaw_rate_rad_s == pytest.approx(-0.2)
    # position + velocity + acceleration + yaw (REFERENCE_NOTES: type_mask 2048)
    s = sp(2048)
    np.testing.assert_allclose(s.position_m, [12.0, 21.0, 3.0])
    np.testing.assert_allclose(s.velocity_m_s, [-0.5, 0.5, -0.1])
    np.testing.assert_allclose(s.acceleration_m_s2, [0.2, 0.1, -0.3])
    assert s.valid()
    # FORCE bit: accelerations ignored
    s = sp(512 | 2048)
    np.testing.assert_array_equal(s.acceleration_m_s2, nan3)
    # mixed: xy velocity, z position
    s = sp(1 | 2 | 32 | 64 | 128 | 256 | 1024 | 2048)
    assert math.isnan(s.position_m[0]) and s.position_m[2] == pytest.approx(3.0)
    assert math.isnan(s.velocity_m_s[2]) and s.valid()
    # everything ignored, or NaN values where they count: not a valid setpoint
    assert not sp(0xFFF).valid()
    assert not sp(8 | 16 | 32 | 64 | 128 | 256, p=(math.nan, 0.0, 0.0)).valid()
    # unsupported frame (global): rejected
    assert sp(0, frame=mavlink.MAV_FRAME_GLOBAL_INT) is None


def test_setpoint_offset_and_body_frames() -> None:
    mask = 64 | 128 | 256 | 1024 | 2048
    s = sp(mask, frame=7, v=(0.0, 0.0, 0.0))  # LOCAL_OFFSET_NED: from the current position
    np.testing.assert_allclose(s.position_m, HERE + [2.0, 1.0, 3.0])
    # BODY_NED facing east (ENU yaw 0): forward = east, right = south
    s = sp(mask | 1 | 2 | 4, frame=8, yaw_enu=0.0, v=(1.0, 2.0, 0.5))
    np.testing.assert_allclose(s.velocity_m_s, [1.0, -2.0, -0.5], atol=1e-12)


# ---- collisions, ground truth, depth -------------------------------------------------------


def test_obstacle_and_vehicle_collisions_are_reported() -> None:
    from onboard.world import World

    # vehicle 1 at the origin, vehicle 2 3 m east; a cylinder 3 m north of vehicle 1
    world = World(np.array([[0.0, 3.0, 0.3, 0.0, 5.0]]), np.zeros((0, 7)), np.zeros((0, 6)), 0.0)
    truth = InMemoryTruth()
    f = make_fleet(2, world=world, truth=[truth], spawn=((0.0, 0.0, 0.0), (3.0, 0.0, 0.0)))
    a, b = f.autopilots
    run(f, 0.6)
    run(f, 1.2, sp={0: (0.0, 0.0, -1.5), 1: (0.0, 0.0, -1.5)})
    for ap in (a, b):
        ap.command_set_mode(f.t_s, Mode.OFFBOARD)
        ap.command_arm(f.t_s, True)
    # vehicle 1 flies north through the trunk; vehicle 2 stays
    run(f, 8.0, sp={0: (6.0, 0.0, -1.5), 1: (0.0, 0.0, -1.5)})
    ev = f.collision_events()
    assert [(e.kind, e.system_ids) for e in ev] == [("obstacle", (1,))]
    assert ev[0].distance_m < 0.0
    assert truth.latest[1].collisions == 1 and truth.latest[2].collisions == 0
    # vehicle 1 flies onto vehicle 2's position (3 m east of its own origin)
    run(f, 8.0, sp={0: (0.0, 3.0, -1.5), 1: (0.0, 0.0, -1.5)})
    kinds = [(e.kind, e.system_ids) for e in f.collision_events()]
    assert ("vehicle", (1, 2)) in kinds
    assert f.summary()["min_vehicle_distance_m"] < 0.4


def test_collision_can_disarm() -> None:
    from onboard.world import World

    world = World(np.array([[0.0, 2.0, 0.3, 0.0, 5.0]]), np.zeros((0, 7)), np.zeros((0, 6)), 0.0)
    cfg = FleetConfig(
        count=1,
        local_port_offset=None,
        collision_action="disarm",
        autopilot=AutopilotParams(boot_time_s=0.5),
    )
    f = Fleet(cfg, world)
    run(f, 0.6)
    run(f, 1.2, sp={0: (0.0, 0.0, -1.5)})
    ap = f.autopilots[0]
    ap.command_set_mode(f.t_s, Mode.OFFBOARD)
    ap.command_arm(f.t_s, True)
    run(f, 6.0, sp={0: (5.0, 0.0, -1.5)})
    assert f.collision_events()[0].kind == "obstacle" and not ap.armed


def test_truth_samples_match_the_estimate() -> None:
    truth = InMemoryTruth()
    f = make_fleet(2, truth=[truth])
    run(f, 0.6)
    run(f, 1.2, sp={0: (1.0, 0.0, -2.0), 1: (0.0, 0.0, -2.0)})
    for ap in f.autopilots:
        ap.command_set_mode(f.t_s, Mode.OFFBOARD)
        ap.command_arm(f.t_s, True)
    run(f, 6.0, sp={0: (1.0, 0.0, -2.0), 1: (0.0, 0.0, -2.0)})
    s1, s2 = truth.latest[1], truth.latest[2]
    assert s1.armed and s1.mode == "OFFBOARD" and not s1.landed
    # ENU world: vehicle 1 spawned at (0, -0.75, 0), 1 m north, 2 m up
    np.testing.assert_allclose(s1.position_m, [0.0, 0.25, 2.0], atol=0.1)
    np.testing.assert_allclose(s2.position_m, [0.0, 0.75, 2.0], atol=0.1)
    r = np.array(s1.quaternion)
    assert np.linalg.norm(r) == pytest.approx(1.0)
    assert type(s1).from_bytes(s1.to_bytes()) == s1
    assert len(truth.history) > 100


def test_depth_frames_from_the_true_pose() -> None:
    pytest.importorskip("onboard.mapping.simcam")  # the perception work's simulated D435
    from onboard.mapping.camera import check_frame
    from onboard.world import World
    from sitl_mock.truth import DepthImage, simulated_d435

    # a box 3 m north of the vehicle; the vehicle faces north (spawn yaw 90 deg ENU)
    world = World(np.zeros((0, 5)), np.zeros((0, 7)), np.array([[-5, 3.0, 0, 5, 4.0, 5]]), 0.0)
    truth = InMemoryTruth()
    cfg = FleetConfig(count=1, local_port_offset=None, autopilot=AutopilotParams(boot_time_s=0.5))
    f = Fleet(cfg, world, [truth], {1: simulated_d435(world, step=4)}, depth_rate_hz=10.0)
    run(f, 0.6)
    run(f, 1.2, sp={0: (0.0, 0.0, -1.5)})
    ap = f.autopilots[0]
    ap.command_set_mode(f.t_s, Mode.OFFBOARD)
    ap.command_arm(f.t_s, True)
    run(f, 5.0, sp={0: (0.0, 0.0, -1.5)})
    assert f._depth is not None and f._depth.render_once() == 1
    img = truth.depth[1]
    centre = img.depth_m[240, 320]
    cam_y = img.position[1]
    assert centre == pytest.approx(3.0 - cam_y, abs=0.02)  # the box face, along the optical axis
    back = DepthImage.from_bytes(img.to_bytes())
    np.testing.assert_allclose(back.depth_m, img.depth_m, atol=6e-4)
    assert check_frame(back.to_depth_frame()).shape == (480, 640)
    # the onboard side reads it as a depth source, with the camera pose alongside
    source = truth.depth_source(1)
    frame = source.read()
    assert frame is not None and source.read() is None
    assert source.intrinsics.width == 640
    pos, rot = truth.pose_provider(1)(frame.stamp_s)
    np.testing.assert_allclose(rot, frame.rotation, atol=1e-12)
