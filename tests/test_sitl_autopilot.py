"""PX4-like flight logic of the mock, stepped in simulated time without sockets.

A ``Fleet`` that is never opened runs its ticks headless; messages go through the same MAVLink
handlers as on the network (``VehicleLink.handle``), only nothing is sent. The behaviours are
PX4 v1.16's (``sitl_mock/README.md``, conformance table), each checked so that today's PX4 rule
passes and the rule the mock used to have would fail.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from pymavlink.dialects.v20 import development as mavlink

from sitl_mock import dynamics as dyn
from sitl_mock.autopilot import (
    ARMING_DENIED_TEXT,
    AutopilotParams,
    LandedState,
    Mode,
    Result,
    Severity,
    offboard_loss_action_from_code,
)
from sitl_mock.fleet import Fleet, FleetConfig
from sitl_mock.mavlink_io import parse_position_target_local_ned, setpoint_from_local_ned
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


def send_sp(f: Fleet, i: int, p: tuple[float, float, float], mask: int = POS_ONLY) -> None:
    """One SET_POSITION_TARGET_LOCAL_NED (frame 1) to vehicle ``i`` through its MAVLink handler."""
    f.links[i].handle(
        MAV.set_position_target_local_ned_encode(0, i + 1, 1, 1, mask, *p, 0, 0, 0, 0, 0, 0, 0, 0)
    )


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
                send_sp(f, i, p)
        f.tick()


def run_until(f: Fleet, pred: Any, max_s: float, sp: Any = None) -> float:
    """Tick (streaming ``sp`` as ``run`` does) until ``pred()``; returns the simulated time it
    took; fails after ``max_s``."""
    t0 = f.t_s
    every = max(1, int(round(1.0 / (20.0 * f.dt_s))))
    k = 0
    while not pred():
        assert f.t_s - t0 < max_s, f"condition not reached within {max_s} s (simulated)"
        if sp and k % every == 0:
            for i, p in sp.items():
                send_sp(f, i, p)
        f.tick()
        k += 1
    return f.t_s - t0


def local_ned(f: Fleet, i: int = 0) -> np.ndarray:
    s = f.state[i]
    est = s[dyn.S_P : dyn.S_P + 3] + s[dyn.S_E : dyn.S_E + 3] - f.spawns[i]
    return np.array([est[1], est[0], -est[2]])


def texts(f: Fleet, i: int = 0) -> list[tuple[Severity, str]]:
    """Status events of vehicle ``i`` since the previous call (on this fleet)."""
    log = list(f.autopilots[i].event_log)
    seen: dict[int, int] = f.__dict__.setdefault("_test_texts_seen", {})
    start = seen.get(i, 0)
    seen[i] = len(log)
    return [(e.severity, e.text) for _, e in log[start:]]


def airborne_in_offboard(f: Fleet, target: tuple[float, float, float] = (0.0, 0.0, -2.5)) -> None:
    """Boot, one setpoint, Offboard, arm, fly to ``target`` (local NED)."""
    ap = f.autopilots[0]
    run(f, 0.6)
    send_sp(f, 0, target)
    assert ap.command_set_mode(f.t_s, Mode.OFFBOARD) == Result.ACCEPTED
    assert ap.command_arm(f.t_s, True) == Result.ACCEPTED
    tgt = np.array(target)
    run_until(f, lambda: np.linalg.norm(local_ned(f) - tgt) < 0.05, 15.0, sp={0: target})
    run(f, 1.0, sp={0: target})


def test_px4_custom_mode_encoding() -> None:
    assert Mode.HOLD.custom_mode == 0x03040000
    assert Mode.OFFBOARD.custom_mode == 0x00060000
    assert Mode.LAND.custom_mode == 0x06040000
    assert Mode.TAKEOFF.custom_mode == 0x02040000
    assert Mode.POSCTL.custom_mode == 0x00030000 == 196608
    for m in Mode:
        assert Mode.from_custom_mode(m.custom_mode) is m
    assert Mode.from_main_sub(4, 0) is Mode.MISSION
    assert Mode.from_main_sub(6, 3) is Mode.OFFBOARD  # sub mode ignored outside AUTO
    assert Mode.from_main_sub(9, 0) is None


def test_px4_defaults() -> None:
    """PX4 v1.16's defaults for the parameters the mock models (commander, land detector, RTL)."""
    p = AutopilotParams()
    assert p.offboard_loss_timeout_s == 1.0  # COM_OF_LOSS_T
    assert p.offboard_loss_action == "position" and p.offboard_loss_action_code == 0
    assert p.disarm_land_s == 2.0 and p.disarm_preflight_s == 10.0  # COM_DISARM_LAND / _PRFLT
    assert p.land_detect_s == 1.0  # LNDMC_TRIG_TIME
    assert p.rtl_return_alt_m == 60.0  # RTL_RETURN_ALT
    assert p.offboard_stream_min_s == 0.0  # no warm-up
    # COM_OBL_RC_ACT value codes, and the ones the mock refuses
    assert [offboard_loss_action_from_code(c) for c in (0, 1, 3, 4, 5, 7)] == [
        "position",
        "altitude",
        "rtl",
        "land",
        "hold",
        "disarm",
    ]
    for bad in (2, 6, 8, -1):
        with pytest.raises(ValueError, match="COM_OBL_RC_ACT"):
            offboard_loss_action_from_code(bad)
    with pytest.raises(ValueError, match="offboard_loss_action"):
        AutopilotParams(offboard_loss_action="stabilized")  # type: ignore[arg-type]


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
    assert (Severity.INFO, "Disarmed by auto preflight disarming") in texts(f)
    assert ap.command_arm(f.t_s, False) == Result.ACCEPTED  # disarming when disarmed


def test_offboard_is_accepted_after_one_setpoint() -> None:
    """PX4 v1.16: one setpoint younger than COM_OF_LOSS_T is enough to enter Offboard and to
    arm in it (no 2 Hz / 1 s warm-up)."""
    f = make_fleet()
    ap = f.autopilots[0]
    run(f, 0.6)
    assert ap.command_set_mode(f.t_s, Mode.OFFBOARD) == Result.TEMPORARILY_REJECTED  # none yet
    assert (Severity.CRITICAL, "Switching to Offboard is currently not possible") in texts(f)
    send_sp(f, 0, (0.0, 0.0, -2.0))
    assert ap.command_set_mode(f.t_s, Mode.OFFBOARD) == Result.ACCEPTED  # at once
    assert ap.mode is Mode.OFFBOARD and ap.user_mode is Mode.OFFBOARD
    assert ap.command_arm(f.t_s, True) == Result.ACCEPTED
    assert (Severity.INFO, "Armed by external command") in texts(f)
    # a setpoint older than COM_OF_LOSS_T is not enough
    g = make_fleet()
    run(g, 0.6)
    send_sp(g, 0, (0.0, 0.0, -2.0))
    run(g, 0.95)
    assert g.autopilots[0].command_set_mode(g.t_s, Mode.OFFBOARD) == Result.ACCEPTED
    h = make_fleet()
    run(h, 0.6)
    send_sp(h, 0, (0.0, 0.0, -2.0))
    run(h, 1.05)
    assert h.autopilots[0].command_set_mode(h.t_s, Mode.OFFBOARD) == Result.TEMPORARILY_REJECTED
    # a setpoint that sets nothing is PX4's "invalid": it does not count
    k = make_fleet()
    run(k, 0.6)
    send_sp(k, 0, (0.0, 0.0, 0.0), mask=0xFFF & ~512)
    assert k.links[0].stats.setpoints_malformed == 1 and k.links[0].stats.setpoints == 0
    assert k.autopilots[0].command_set_mode(k.t_s, Mode.OFFBOARD) == Result.TEMPORARILY_REJECTED
    # the optional (non-PX4) warm-up rule, for clients that want it tested
    w = make_fleet(offboard_stream_min_s=1.0, offboard_min_rate_hz=2.0)
    run(w, 0.6)
    send_sp(w, 0, (0.0, 0.0, -2.0))
    assert w.autopilots[0].command_set_mode(w.t_s, Mode.OFFBOARD) == Result.TEMPORARILY_REJECTED
    run(w, 1.1, sp={0: (0.0, 0.0, -2.0)})
    assert w.autopilots[0].command_set_mode(w.t_s, Mode.OFFBOARD) == Result.ACCEPTED


def test_offboard_loss_falls_back_to_position_mode_and_returns() -> None:
    """COM_OBL_RC_ACT 0 (default): after COM_OF_LOSS_T without setpoints, Position mode (which
    descends at ~MPC_LAND_SPEED without RC, as observed), "Failsafe activated", the user's mode
    still Offboard; setpoints again while airborne: back to Offboard by itself."""
    f = make_fleet()
    ap = f.autopilots[0]
    airborne_in_offboard(f, (2.0, 1.0, -4.0))
    send_sp(f, 0, (2.0, 1.0, -4.0))  # the last setpoint
    texts(f)
    run(f, 0.95)
    assert ap.mode is Mode.OFFBOARD and ap.failsafe is None
    lost_after = run_until(f, lambda: ap.failsafe is not None, 0.2) + 0.95
    assert 1.0 < lost_after <= 1.0 + 1.5 * f.dt_s  # COM_OF_LOSS_T
    assert (ap.mode, ap.user_mode, ap.failsafe) == (Mode.POSCTL, Mode.OFFBOARD, "offboard_loss")
    assert (Severity.CRITICAL, "Failsafe activated") in texts(f)
    assert ap.armed
    run(f, 1.0)  # the vertical speed settles
    z0, xy0 = local_ned(f)[2], local_ned(f)[:2]
    run(f, 2.0)
    vz_down = (local_ned(f)[2] - z0) / 2.0
    assert vz_down == pytest.approx(0.7, abs=0.07)  # MPC_LAND_SPEED
    assert np.linalg.norm(local_ned(f)[:2] - xy0) < 0.2
    # setpoints again while airborne: Offboard within a tick
    send_sp(f, 0, (2.0, 1.0, -4.0))
    f.tick()
    assert (ap.mode, ap.failsafe) == (Mode.OFFBOARD, None)
    run(f, 6.0, sp={0: (2.0, 1.0, -4.0)})
    np.testing.assert_allclose(local_ned(f), [2.0, 1.0, -4.0], atol=0.1)
    # lost again, for good: it descends to the ground, lands, disarms 2 s later
    texts(f)
    run_until(f, lambda: ap.landed, 12.0)
    t_land = f.t_s
    run_until(f, lambda: not ap.armed, 3.0)
    assert f.t_s - t_land == pytest.approx(2.0, abs=0.02)  # COM_DISARM_LAND
    events = [t for _, t in texts(f)]
    assert events == ["Failsafe activated", "Landing detected", "Disarmed by landing"]
    # after the auto-disarm: back in Offboard, where arming is refused without a stream
    assert (ap.mode, ap.user_mode, ap.failsafe) == (Mode.OFFBOARD, Mode.OFFBOARD, None)
    assert not ap.prearm_ok(f.t_s)
    assert ap.command_arm(f.t_s, True) == Result.TEMPORARILY_REJECTED
    assert ap.command_set_mode(f.t_s, Mode.HOLD) == Result.ACCEPTED
    assert ap.prearm_ok(f.t_s) and ap.command_arm(f.t_s, True) == Result.ACCEPTED


@pytest.mark.parametrize(
    ("action", "mode"),
    [
        ("hold", Mode.HOLD),
        ("land", Mode.LAND),
        ("rtl", Mode.RTL),
        ("altitude", Mode.ALTCTL),
        ("disarm", None),
    ],
)
def test_offboard_loss_actions(action: str, mode: Mode | None) -> None:
    f = make_fleet(offboard_loss_action=action, rtl_return_alt_m=5.0)
    ap = f.autopilots[0]
    airborne_in_offboard(f)
    run(f, 1.1)
    assert ap.failsafe == ("offboard_loss" if mode is not None else None)
    if mode is None:
        assert not ap.armed  # disarmed in the air: it falls
        run(f, 2.0)
        assert f.state[0, dyn.S_P + 2] == 0.0
        return
    assert ap.mode is mode and ap.user_mode is Mode.OFFBOARD
    send_sp(f, 0, (0.0, 0.0, -2.5))
    f.tick()
    assert ap.mode is Mode.OFFBOARD and ap.failsafe is None  # the stream came back


def test_choosing_a_mode_ends_the_offboard_loss_failsafe() -> None:
    f = make_fleet()
    ap = f.autopilots[0]
    airborne_in_offboard(f)
    run(f, 1.1)
    assert ap.mode is Mode.POSCTL
    assert ap.command_set_mode(f.t_s, Mode.HOLD) == Result.ACCEPTED
    assert (ap.mode, ap.user_mode, ap.failsafe) == (Mode.HOLD, Mode.HOLD, None)
    z = local_ned(f)[2]
    send_sp(f, 0, (0.0, 0.0, -2.5))
    run(f, 3.0)
    assert ap.mode is Mode.HOLD  # setpoints no longer pull it back into Offboard
    assert local_ned(f)[2] == pytest.approx(z, abs=0.15)


def test_forced_arm_is_denied_like_a_normal_arm() -> None:
    """PX4 v1.16 ignores the force value (21196) for arming over MAVLink (observed)."""
    f = make_fleet()
    ap = f.autopilots[0]
    run(f, 0.6)
    send_sp(f, 0, (0.0, 0.0, -2.0))
    assert ap.command_set_mode(f.t_s, Mode.OFFBOARD) == Result.ACCEPTED
    run(f, 1.5)  # the stream is gone
    texts(f)
    link = f.links[0]
    results = []
    for force in (0.0, 21196.0):
        link.handle(MAV.command_long_encode(1, 1, 400, 0, 1.0, force, 0, 0, 0, 0, 0))
        results.append(ap.armed)
    assert results == [False, False]
    assert texts(f) == [(Severity.CRITICAL, ARMING_DENIED_TEXT)] * 2
    assert ap.command_arm(f.t_s, True, force=True) == Result.TEMPORARILY_REJECTED


def test_takeoff_hold_land_cycle_and_home() -> None:
    f = make_fleet()
    ap = f.autopilots[0]
    run(f, 0.6)
    home0 = ap.home_m.copy()
    assert ap.command_arm(f.t_s, True) == Result.ACCEPTED
    assert ap.home_updates == 1  # PX4 sets home at arming
    assert ap.command_takeoff(f.t_s, None) == Result.ACCEPTED
    assert ap.mode is Mode.TAKEOFF
    run(f, 1.5)
    assert ap.landed_state() is LandedState.TAKEOFF
    assert ap.home_updates == 2  # and again just after takeoff
    assert np.linalg.norm(ap.home_m - home0) < 0.1
    run(f, 3.5)
    assert ap.mode is Mode.HOLD and ap.user_mode is Mode.HOLD  # Hold by itself after the climb
    assert local_ned(f)[2] == pytest.approx(-2.5, abs=0.15)
    assert ap.landed_state() is LandedState.IN_AIR
    assert ap.command_arm(f.t_s, False) == Result.TEMPORARILY_REJECTED  # in the air
    events = [t for _, t in texts(f)]
    assert events == [
        "Armed by external command",
        "Using default takeoff altitude: 2.5 m",
        "Takeoff detected",
        "Disarming denied: not landed",
    ]
    assert ap.command_land(f.t_s) == Result.ACCEPTED
    run(f, 2.0)
    assert ap.landed_state() is LandedState.LANDING
    run_until(f, lambda: not ap.armed, 10.0)
    events = [t for _, t in texts(f)]
    assert events == ["Landing at current position", "Landing detected", "Disarmed by landing"]
    assert ap.mode is Mode.HOLD  # the last mode the user chose that is not Land


def test_failsafe_land_and_forced_disarm() -> None:
    f = make_fleet(offboard_loss_action="land", offboard_loss_timeout_s=0.5)
    ap = f.autopilots[0]
    airborne_in_offboard(f, (0.0, 0.0, -2.0))
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


def test_position_fallback_with_rc_holds() -> None:
    f = make_fleet(rc_present=True)
    ap = f.autopilots[0]
    airborne_in_offboard(f, (1.0, 0.0, -3.0))
    run(f, 1.1)
    assert ap.mode is Mode.POSCTL
    run(f, 3.0)
    np.testing.assert_allclose(local_ned(f), [1.0, 0.0, -3.0], atol=0.15)


def test_return_to_launch() -> None:
    f = make_fleet(rtl_return_alt_m=4.0)
    ap = f.autopilots[0]
    airborne_in_offboard(f, (0.0, 0.0, -2.0))
    run(f, 7.0, sp={0: (6.0, 3.0, -2.0)})
    assert ap.command_rtl(f.t_s) == Result.ACCEPTED
    run(f, 25.0)
    assert not ap.armed and ap.landed
    np.testing.assert_allclose(local_ned(f)[:2], [0.0, 0.0], atol=0.2)


def test_a_setpoint_leaving_an_axis_uncontrolled_stops_the_vehicle() -> None:
    """PX4's position controller refuses it (every axis needs a setpoint, x and y in pairs)
    and stops; the stream still counts, so no offboard-loss failsafe follows."""
    f = make_fleet()
    ap = f.autopilots[0]
    airborne_in_offboard(f, (0.0, 0.0, -3.0))
    # fly north at 2 m/s (velocity only, altitude by position)
    vel_n = 1 | 2 | 32 | 64 | 128 | 256 | 1024 | 2048
    link = f.links[0]

    def velocity_sp() -> None:
        link.handle(
            MAV.set_position_target_local_ned_encode(
                0, 1, 1, 1, vel_n, 0, 0, -3.0, 2.0, 0, 0, 0, 0, 0, 0, 0
            )
        )

    for _ in range(60):
        velocity_sp()
        run(f, 0.05)
    assert f.state[0, dyn.S_V + 1] == pytest.approx(2.0, abs=0.1)
    # x / y position only: z uncontrolled
    xy_only = 4 | 8 | 16 | 32 | 64 | 128 | 256 | 1024 | 2048
    for _ in range(80):
        link.handle(
            MAV.set_position_target_local_ned_encode(
                0, 1, 1, 1, xy_only, 20.0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0
            )
        )
        run(f, 0.05)
    assert ap.mode is Mode.OFFBOARD and ap.failsafe is None
    assert np.linalg.norm(f.state[0, dyn.S_V : dyn.S_V + 3]) < 0.1  # stopped, not flying to 20 m
    assert local_ned(f)[0] < 6.0
    assert link.stats.setpoints_malformed == 0  # accepted as a stream, refused by the controller


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
        kw.get("r"),
    )


def test_setpoint_type_masks_local_ned() -> None:
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
    # in frame 1 each velocity component counts on its own
    s = sp(1 | 2 | 4 | 8 | 64 | 128 | 256 | 1024 | 2048)
    np.testing.assert_allclose(s.velocity_m_s, [-0.5, math.nan, -0.1])
    assert s.controls_any() and not s.valid()  # x without y: PX4 stops
    # FORCE with an acceleration: PX4 ignores the whole message
    assert sp(512 | 2048) is None
    assert sp(512 | 64 | 128 | 256 | 2048) is not None  # FORCE without acceleration: fine
    # mixed: xy velocity, z position
    s = sp(1 | 2 | 32 | 64 | 128 | 256 | 1024 | 2048)
    assert math.isnan(s.position_m[0]) and s.position_m[2] == pytest.approx(3.0)
    assert math.isnan(s.velocity_m_s[2]) and s.valid()
    # an axis without anything: a stream message, but not flyable
    s = sp(4 | 8 | 16 | 32 | 64 | 128 | 256 | 1024 | 2048)
    assert s.controls_any() and not s.valid()
    # everything ignored, or NaN where it counts: PX4's "invalid"
    r = parse_position_target_local_ned(
        0xFFF & ~512, 1, (0, 0, 0), (0, 0, 0), (0, 0, 0), 0, 0, ORIGIN, np.eye(3)
    )
    assert r.setpoint is None and r.error == "SET_POSITION_TARGET_LOCAL_NED invalid"
    assert sp(8 | 16 | 32 | 64 | 128 | 256, p=(math.nan,) * 3) is None


def test_setpoint_frames_as_px4_parses_them() -> None:
    def parse(frame: int, mask: int, r: np.ndarray | None = None, **kw: Any) -> Any:
        return parse_position_target_local_ned(
            mask,
            frame,
            kw.get("p", (1.0, 2.0, -3.0)),
            kw.get("v", (1.0, 2.0, 0.5)),
            kw.get("a", (0.5, 0.0, 0.0)),
            0.3,
            0.0,
            ORIGIN,
            np.eye(3) if r is None else r,
        )

    pos_only = 8 | 16 | 32 | 64 | 128 | 256 | 1024 | 2048
    for frame in (7, 9, 12, 0, 99):
        got = parse(frame, pos_only)
        assert got.setpoint is None
        assert got.error == f"SET_POSITION_TARGET_LOCAL_NED coordinate frame {frame} unsupported"
    # frame 8 (BODY_NED): positions never used -> a position-only message is "invalid"
    assert parse(8, pos_only).error == "SET_POSITION_TARGET_LOCAL_NED invalid"
    # velocity turned by the heading; facing east (NED yaw 90 deg): forward = east, right = south
    r_east = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    vel = 1 | 2 | 4 | 64 | 128 | 256 | 1024 | 2048
    s = parse(8, vel, r_east).setpoint
    np.testing.assert_allclose(s.velocity_m_s, [1.0, -2.0, -0.5], atol=1e-12)  # ENU
    np.testing.assert_array_equal(s.position_m, [math.nan] * 3)
    # one velocity ignore bit drops the whole velocity vector in frame 8
    got = parse(8, vel | 16)
    assert got.setpoint is None and got.error.endswith("invalid")
    # the acceleration is turned by the whole attitude (here: pitched 90 deg nose up)
    acc = 1 | 2 | 4 | 8 | 16 | 32 | 1024 | 2048
    r_pitch = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # FRD -> NED
    s = parse(8, acc, r_pitch).setpoint
    np.testing.assert_allclose(s.acceleration_m_s2, [0.0, 0.0, 0.5], atol=1e-12)  # up (ENU)


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
    import onboard.mapping.simcam  # noqa: F401 - the perception work's simulated D435
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
    assert img.decimation == 4 and img.depth_m.shape == (120, 160)  # every 4th pixel
    centre = img.depth_m[60, 80]  # pixel (320, 240) of the camera
    cam_y = img.position[1]
    assert centre == pytest.approx(3.0 - cam_y, abs=0.02)  # the box face, along the optical axis
    back = DepthImage.from_bytes(img.to_bytes())
    np.testing.assert_allclose(back.depth_m, img.depth_m, atol=6e-4)
    assert check_frame(back.to_depth_frame()).shape == (120, 160)
    # the onboard side reads it as a depth source, with the camera pose alongside
    source = truth.depth_source(1)
    assert source.newest_stamp_s() == img.stamp_s  # arrived, not yet read
    frame = source.read()
    assert frame is not None and source.read() is None
    assert source.intrinsics.width == 160 and frame.decimation == 4
    pos, rot = truth.pose_provider(1)(frame.stamp_s)
    np.testing.assert_allclose(rot, frame.rotation, atol=1e-12)
