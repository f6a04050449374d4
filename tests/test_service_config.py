"""The flight service's config: the shipped file loads, bad keys and values name their path."""

from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner

from onboard.cli import main
from onboard.config import ConfigError
from onboard.service.config import OnboardConfig, default_config_path, load_onboard_config


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "onboard.yaml"
    p.write_text(text)
    return p


def test_shipped_config_loads_with_the_documented_values() -> None:
    cfg = load_onboard_config(default_config_path(), drone_id=3)
    assert cfg.drone.id == 3
    assert cfg.autopilot.setpoint_rate_hz == 50.0
    assert cfg.autopilot.heartbeat_timeout_s == 1.0
    assert cfg.autopilot.endpoint(3) == "udp://127.0.0.1:14543"
    assert cfg.autopilot.target_system(3) == 4
    assert cfg.planning.replan_period_s == 1.0
    assert cfg.planning.monitor_rate_hz == 100.0
    assert cfg.reactions.depth_lost.timeout_s == 0.5
    assert cfg.mapping.esdf_rate_hz >= 10.0


def test_config_is_frozen() -> None:
    cfg = load_onboard_config(default_config_path())
    with pytest.raises(AttributeError):
        cfg.drone.id = 5  # type: ignore[misc]


def test_planner_section_overrides_planner_yaml_key_by_key(tmp_path: Path) -> None:
    from onboard.config import load_planner_params

    base = load_planner_params()
    cfg = load_onboard_config(_write(tmp_path, "planner:\n  v_max_m_s: 1.5\n"))
    assert cfg.planner.v_max_m_s == 1.5
    assert cfg.planner.w_uniform == base.w_uniform  # the rest comes from planner.yaml


@pytest.mark.parametrize(
    ("text", "path", "expected"),
    [
        ("autopilot:\n  setpoint_rate_hz: 5\n", "setpoint_rate_hz", "[10, 200]"),
        ("autopilot:\n  setpont_rate_hz: 50\n", "autopilot.setpont_rate_hz", "unknown key"),
        ("autopilot:\n  implementation: dronekit\n", "autopilot.implementation", "pymavlink"),
        ("autopilot:\n  url: tcp://x:1\n", "url", "udp://HOST:PORT"),
        ("depth:\n  source: kinect\n", "depth.source", "zenoh-sim"),
        ("planning:\n  replan_period_s: 0\n", "replan_period_s", "[0.1, 10]"),
        ("planning:\n  resend_s: [0.05, 5]\n", "resend_s[1]", "[0.01, 2]"),
        ("planning:\n  resend_s: 0.05\n", "planning.resend_s", "list"),
        ("reactions:\n  gcs_lost: {action: rtl}\n", "reactions.gcs_lost.action", "land"),
        ("reactions:\n  depth_lost: {timeout_s: -1}\n", "timeout_s", "[0.05, 10]"),
        # a map cannot be allowed to lag less than the camera's frames may
        ("reactions:\n  depth_lost: {timeout_s: 2.0, map_lag_s: 1.0}\n",
         "reactions.depth_lost: map_lag_s", "at least timeout_s (2 s)"),
        ("reactions:\n  depth_lost: {map_lag_s: 40}\n", "map_lag_s", "[0.05, 30]"),
        ("geofence:\n  min_enu_m: [0, 0, 0]\n  max_enu_m: [1, -1, 3]\n", "geofence", "min"),
        ("planner:\n  v_max_m_s: fast\n", "planner.v_max_m_s", "expected a number"),
        ("mapping:\n  occupancy: {resolution_m: -1}\n", "mapping.occupancy", "resolution_m"),
        ("drone:\n  swarm: 'a b'\n", "swarm", "letters"),
        ("flight:\n  takeoff_altitude_m: 9\n", "takeoff_altitude_m", "geofence"),
        ("geofence:\n  max_enu_m: [50, 50, 0.5]\n", "planner.z_limits_m", "too narrow"),
        ("autopilot:\n  local_origin_enu_m: [0, 2e4, 0]\n", "local_origin_enu_m", "10 km"),
        ("autopilot:\n  local_origins_enu_m: {x: [0, 0, 0]}\n", "local_origins_enu_m", "ids"),
        ("autopilot:\n  local_origins_enu_m: {7: [0, 0]}\n", "local_origins_enu_m.7", ""),
        # the silent / stuck peer reaction (onboard.agent.DroneAgent's)
        ("reactions:\n  peer_lost: {peer_silence_s: 0}\n", "reactions.peer_lost: peer_silence_s",
         "[0.05, 60]"),
        ("reactions:\n  peer_lost: {peer_silence_s: .inf}\n",
         "reactions.peer_lost.peer_silence_s", "finite"),
        ("reactions:\n  peer_lost: {peer_deviation_m: -0.3}\n",
         "reactions.peer_lost: peer_deviation_m", "[0.05, 10]"),
        ("reactions:\n  peer_lost: {peer_deviation_m: far}\n",
         "reactions.peer_lost.peer_deviation_m", "expected a number"),
        ("reactions:\n  peer_lost: {ghost_window_s: 11}\n", "reactions.peer_lost: ghost_window_s",
         "[0, 10]"),
        ("reactions:\n  peer_lost: {ghost_forget_s: -1}\n", "reactions.peer_lost: ghost_forget_s",
         "[0, 3600]"),
        ("reactions:\n  peer_lost: {ghost_forgt_s: 5}\n", "reactions.peer_lost.ghost_forgt_s",
         "unknown key"),
        ("reactions:\n  peer_lost: {peer_silence_s: 0.15}\n",
         "reactions.peer_lost.peer_silence_s", "bus.state_rate_hz 10"),
        ("reactions:\n  peer_lost: {peer_silence_in_way_s: 0.15}\n",
         "reactions.peer_lost.peer_silence_in_way_s", "bus.state_rate_hz 10"),
        ("reactions:\n  peer_lost: {peer_silence_in_way_s: 0}\n",
         "reactions.peer_lost: peer_silence_in_way_s", "[0.05, 60]"),
        ("reactions:\n  peer_lost: {peer_silence_s: 0.8, peer_silence_max_s: 0.6}\n",
         "reactions.peer_lost: peer_silence_max_s", "at least peer_silence_s"),
        # the monitor's slack below the check's distance: a brake must remain possible
        ("planning:\n  monitor_obstacle_slack_m: -0.01\n", "monitor_obstacle_slack_m",
         "[0, 1]"),
        ("planning:\n  monitor_obstacle_slack_m: 0.3\n", "planning.monitor_obstacle_slack_m",
         "never brake"),
    ],
)  # fmt: skip
def test_bad_values_name_the_key_and_the_expected_range(
    tmp_path: Path, text: str, path: str, expected: str
) -> None:
    with pytest.raises(ConfigError) as e:
        load_onboard_config(_write(tmp_path, text))
    msg = str(e.value)
    assert path in msg
    assert expected in msg


def test_the_peer_reaction_defaults_are_the_agents() -> None:
    """One owner: the service flies the agent's silence reaction with the agent's values."""
    import onboard.agent as ag

    pl = load_onboard_config(default_config_path()).reactions.peer_lost
    assert pl.peer_silence_s == ag.PEER_SILENCE_S
    assert pl.peer_silence_in_way_s == ag.PEER_SILENCE_IN_WAY_S
    assert pl.peer_silence_max_s == ag.PEER_SILENCE_MAX_S
    assert pl.peer_deviation_m == ag.PEER_DEVIATION_M
    assert pl.ghost_window_s == ag.GHOST_WINDOW_S
    assert pl.ghost_forget_s == ag.GHOST_FORGET_S


def test_the_peer_reaction_keys_reach_the_agent(tmp_path: Path) -> None:
    from onboard.service.fakes import FakeAutopilot, FakeBus
    from onboard.service.sdnotify import Notifier
    from onboard.service.service import FlightService

    text = (
        "reactions:\n  peer_lost: {peer_silence_s: 0.8, peer_deviation_m: 0.5, "
        "ghost_window_s: 0.7, ghost_forget_s: 30, avoid_for_s: 4, validity_s: 2, "
        "peer_silence_max_s: 2.5, peer_silence_in_way_s: 0.4}\n"
    )
    cfg = load_onboard_config(_write(tmp_path, text))
    svc = FlightService(cfg, FakeAutopilot(lambda: 0.0), FakeBus(), notifier=Notifier({}))
    a = svc.agent
    got = (
        a.peer_silence_s,
        a.peer_deviation_m,
        a.ghost_window_s,
        a.ghost_forget_s,
        a.peer_forget_s,
        a.validity_s,
        a.peer_silence_max_s,
        a.peer_silence_in_way_s,
    )
    assert got == (0.8, 0.5, 0.7, 30.0, 4.0, 2.0, 2.5, 0.4)


def test_each_drone_gets_its_own_autopilot_origin(tmp_path: Path) -> None:
    """One file for the swarm: drones listed in local_origins_enu_m get theirs, the others the
    common one; the link converts with it (ENU swarm frame <-> PX4's local NED frame)."""
    from onboard.autopilot.frames import position_ned_to_enu
    from onboard.service.adapters import link_config

    text = "autopilot:\n  local_origin_enu_m: [1, 2, 0]\n  local_origins_enu_m: {3: [-4, 6, 0.5]}\n"
    path = _write(tmp_path, text)
    assert link_config(load_onboard_config(path, drone_id=3)).local_origin_enu_m == (-4, 6, 0.5)
    link = link_config(load_onboard_config(path, drone_id=0))
    assert link.local_origin_enu_m == (1.0, 2.0, 0.0)
    # 1 m north and 2 m up of the origin in PX4's NED frame
    assert position_ned_to_enu((1.0, 0.0, -2.0), link.local_origin_enu_m) == (1.0, 3.0, 2.0)


def test_the_planner_band_is_cut_to_the_geofence(tmp_path: Path) -> None:
    cfg = load_onboard_config(_write(tmp_path, "geofence:\n  max_enu_m: [50, 50, 2.5]\n"))
    assert cfg.planner.z_limits_m == (0.3, 2.5)
    assert load_onboard_config(_write(tmp_path, "")).planner.z_limits_m == (0.3, 3.1)


def test_drone_id_out_of_range_is_an_error() -> None:
    with pytest.raises(ConfigError, match="id"):
        load_onboard_config(default_config_path(), drone_id=300)


def test_empty_file_gives_the_defaults(tmp_path: Path) -> None:
    cfg = load_onboard_config(_write(tmp_path, ""))
    assert cfg == OnboardConfig(planner=cfg.planner)


def test_check_config_cli(tmp_path: Path) -> None:
    runner = CliRunner()
    ok = runner.invoke(main, ["check-config", str(default_config_path())])
    assert ok.exit_code == 0, ok.output
    assert ok.output.startswith("OK")
    bad = runner.invoke(main, ["check-config", str(_write(tmp_path, "bus: {state_rate_hz: 0}\n"))])
    assert bad.exit_code == 1
    assert "bus: state_rate_hz" in bad.output
    missing = runner.invoke(main, ["check-config", str(tmp_path / "nope.yaml")])
    assert missing.exit_code == 2
