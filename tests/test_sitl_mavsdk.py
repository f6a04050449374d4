"""The mock flown by the unmodified ``mavsdk`` package (4.x, native binding), as a companion
computer would fly PX4: connect, wait until healthy and armable, arm, take off, offboard
position setpoints to a few NED points, stop offboard, land, disarm.

Offboard starts as in MAVSDK's own example, and as a real PX4 v1.16 accepted it: one
``set_position_ned`` and ``offboard.start()`` straight away, once, without retrying."""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import mavsdk  # noqa: F401 - a hard dependency: a broken install must fail, not skip
import pytest

from sitl_mock.autopilot import AutopilotParams
from sitl_mock.client import bind_consecutive_udp
from sitl_mock.fleet import Fleet, FleetConfig

SPEEDUP = 2.0  # COM_OF_LOSS_T (1 s) is 500 ms of wall: MAVSDK streams every 50 ms


def poll(pred: Callable[[], bool], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out waiting for {what}")
        time.sleep(0.02)


@pytest.mark.slow
@pytest.mark.vehicle
@pytest.mark.timeout(120)
def test_mavsdk_flies_the_mock() -> None:
    from mavsdk import ComponentType, Configuration, Mavsdk
    from mavsdk.plugins.action import Action
    from mavsdk.plugins.offboard import Offboard, PositionNedYaw
    from mavsdk.plugins.telemetry import FlightMode, LandedState, Telemetry

    sock = bind_consecutive_udp(1)[0]
    port = sock.getsockname()[1]
    cfg = FleetConfig(
        count=1,
        base_port=port,
        local_port_offset=None,
        speedup=SPEEDUP,
        autopilot=AutopilotParams(boot_time_s=1.0),
    )
    fleet = Fleet(cfg)
    sock.close()  # MAVSDK binds it next ("udpin://", as with PX4 SITL on 14540)
    drone = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    try:
        fleet.start()
        drone.add_any_connection(f"udpin://127.0.0.1:{port}")
        system = drone.first_autopilot(10.0)
        assert system is not None and system.has_autopilot()
        tel, action, offboard = Telemetry(system), Action(system), Offboard(system)

        def healthy() -> bool:
            h = tel.health()
            return bool(
                h.is_armable
                and h.is_local_position_ok
                and h.is_global_position_ok
                and h.is_home_position_ok
                and h.is_gyrometer_calibration_ok
            )

        poll(healthy, 15.0, "healthy and armable")
        assert tel.landed_state() == LandedState.ON_GROUND
        action.arm()
        poll(tel.armed, 5.0, "armed")
        action.takeoff()
        poll(lambda: tel.position_velocity_ned().position.down_m < -2.2, 20.0, "takeoff")
        poll(lambda: tel.flight_mode() == FlightMode.HOLD, 10.0, "hold after takeoff")
        assert tel.in_air()

        here = tel.position_velocity_ned().position
        offboard.set_position_ned(PositionNedYaw(here.north_m, here.east_m, -2.5, 0.0))
        offboard.start()  # once: it must be accepted (an OffboardError fails the test)
        poll(lambda: tel.flight_mode() == FlightMode.OFFBOARD, 5.0, "offboard")
        for target in ((3.0, 0.0, -3.0), (3.0, 3.0, -3.0), (0.0, 3.0, -2.5)):
            offboard.set_position_ned(PositionNedYaw(*target, 0.0))

            def there(t: tuple[float, float, float] = target) -> bool:
                p = tel.position_velocity_ned().position
                return math.dist((p.north_m, p.east_m, p.down_m), t) < 0.2

            poll(there, 20.0, f"reaching {target}")
        offboard.stop()
        poll(lambda: tel.flight_mode() == FlightMode.HOLD, 5.0, "hold after offboard")
        action.land()
        poll(lambda: tel.landed_state() == LandedState.LANDING, 5.0, "landing")
        poll(lambda: not tel.armed(), 30.0, "landed and disarmed")
        action.disarm()  # already disarmed by the land detector: accepted all the same
        p = tel.position_velocity_ned().position
        assert math.dist((p.north_m, p.east_m), (0.0, 3.0)) < 0.3 and abs(p.down_m) < 0.1
        assert tel.landed_state() == LandedState.ON_GROUND
    finally:
        drone.destroy()
        fleet.stop()
    st = fleet.links[0].stats
    assert st.setpoints > 20 and st.setpoints_malformed == 0 and st.rx_bad == 0
    assert st.handler_errors == 0 and fleet.loop_error is None
    assert fleet.links[0].gcs_seen  # MAVSDK as a ground station: it got the status texts
    texts = [e.text for _, e in fleet.autopilots[0].event_log]
    assert "Failsafe activated" not in texts
    assert "Armed by external command" in texts and "Disarmed by landing" in texts
    assert not fleet.collision_events()
