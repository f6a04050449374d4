"""``swarm-gcs demo``: the whole stack on one machine, flown through the same commands an operator
sends in the field.

1. ``swarm-sitl --count N --world W --seed S --truth zenoh --depth`` (the PX4-like fleet, its
   true poses and simulated depth frames on a Zenoh endpoint of its own);
2. N x ``swarm-onboard run --id i`` (one flight service per drone: MAVLink to its vehicle, depth
   frames from the mock, the swarm bus on a loopback peer mesh, a flight record each);
3. the ground station (this process) on the same mesh: take off, assign the formation (Hungarian
   slots from where the drones hover), form up at the start, fly the formation's centre to the
   world's goal across the forest, optionally change formation in flight
   (``--formation-change NAME@SECONDS``, seconds after the goal was sent), land;
4. the result (arrived, collisions reported by the mock, e_dist, e_sim, clearances, flight time,
   setpoint jitter) and the flight report (``gcs.report``) in the flight directory.

With ``--secure`` the links are authenticated as in the field: MAVLink 2 signing between every
flight service and its vehicle (a fresh random key per drone, a 0600 file in the flight
directory's ``secrets/``; the mock imitates PX4 v1.17+ here, v1.16 cannot sign) and the swarm bus
over Zenoh TLS with mutual authentication and access control (a demo CA made by ``swarm-gcs
certs``'s code in ``pki/``). The mock's own Zenoh session (true poses and simulated depth
frames, the simulator standing in for each drone's camera) is not the swarm bus and stays
plain TCP. The run checks that the security is real (signed traffic only, TLS links only,
intruders refused) and reports it with the bus latency.

Every port is picked free on 127.0.0.1 and outside the kernel's ephemeral range
(``onboard.comm.loopback``), so two demos on one machine do not collide and no socket bound to
port 0 takes one between its pick and its bind. All child
processes run in one process group of their own; it is stopped (SIGTERM, then SIGKILL) on
success, on failure, on Ctrl-C and on SIGTERM. The exit status is 0 only on success.
"""

from __future__ import annotations

import json
import logging
import math
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np

from gcs.formations import FormationError, load_template
from gcs.pools import sigterm_interrupts
from gcs.procstat import stat_cpu_s, thread_cpu_s
from gcs.station import CommandOutcome, GroundStation, StationConfig
from onboard.comm.zenoh_session import free_loopback_endpoint, open_session, peer_mesh
from onboard.config import ConfigError, Formation, merge_mappings
from onboard.service.config import config_data

log = logging.getLogger(__name__)


class DemoError(RuntimeError):
    """The demo cannot go on (a process died, a step timed out, a command was refused)."""


DEMO_LEAD_S: float = StationConfig.resend_every_s
"""The demo's ``DemoConfig.lead_s``: the station's resend period (0.5 s), so that a drone that
missed a command hears it again by the switch."""

DEMO_LEAD_MAX_S = 10.0
"""The longest ``DemoConfig.lead_s`` the demo (and ``bench demo``) accepts."""


@dataclass(frozen=True)
class DemoConfig:
    """What to fly and how.

    formation_change: (formation name, seconds after the goal was sent) or None;
    altitude_m: cruise altitude (None: the world's start height); depth_rate_hz: frames per
    second the mock renders per drone (the machine must sustain N times that; None: 10 up to
    4 drones, 3 above, what a 2-core machine sustains), the services' depth-lost
    timeout is 4 frame periods (at least 0.5 s); sitl_nice: the mock's scheduling priority
    (it stands for the autopilots' own hardware: its clock and heartbeats must not starve
    behind the services; a negative value needs the privilege, else it is left at 0); v_max_m_s:
    the planner's speed limit (None: config/onboard.yaml's); altitude_band_m: the planner's
    altitude band as (metres below, metres above) the cruise altitude (None: ``default_band``;
    (0, 0): config/onboard.yaml's band); onboard_sets / sitl_sets: extra
    ``--set KEY=VALUE`` for every service / the mock; startup_timeout_s: until every service
    is up (the first run compiles the planner's kernels); flight_timeout_s: for the crossing
    (None: from the route length and the speed limit); out_dir: the flight directory;
    secure: MAVLink signing and Zenoh mutual TLS + access control (see the module docstring);
    mapping_nice: the services' ``mapping.thread_nice`` (None: ``default_mapping_nice``);
    lead_s: how long after its command a swarm-wide change (formation, goal) takes effect, at
    once on every drone (the station's ``StationConfig.lead_s``): on loopback a command reaches
    every service within milliseconds, and at ``DEMO_LEAD_S`` the station's first resend to a
    drone that has not answered still comes by the switch; radio links want the station's
    longer default (``StationConfig.lead_s``, 1.5 s: two resends before the switch).
    """

    drones: int = 7
    formation: str = "hexagon-7"
    world: str = "forest-medium"
    seed: int = 1
    formation_change: tuple[str, float] | None = None
    altitude_m: float | None = None
    depth_rate_hz: float | None = None
    altitude_band_m: tuple[float, float] | None = None
    sitl_nice: int = -15
    mapping_nice: int | None = None
    depth_step: int = 3
    v_max_m_s: float | None = None
    spacing_m: float = 1.5
    onboard_sets: tuple[str, ...] = ()
    sitl_sets: tuple[str, ...] = ()
    startup_timeout_s: float = 180.0
    step_timeout_s: float = 60.0
    flight_timeout_s: float | None = None
    out_dir: Path = field(
        default_factory=lambda: Path("flights") / time.strftime("demo-%Y%m%d-%H%M%S")
    )
    swarm: str = ""
    view_port: int | None = None
    report: bool = True
    secure: bool = False
    lead_s: float = DEMO_LEAD_S


# --- processes -------------------------------------------------------------------------------


def _exe(name: str, module: str) -> list[str]:
    """The console script next to this interpreter, else the module's click group."""
    script = Path(sys.executable).parent / name
    if script.is_file() and os.access(script, os.X_OK):
        return [str(script)]
    return [sys.executable, "-c", f"import sys; from {module} import main; sys.exit(main())"]


def _term_with_parent() -> None:
    """Linux: the child gets SIGTERM when this process dies, even by SIGKILL (so that not even
    a killed demo leaves its fleet running)."""
    if sys.platform.startswith("linux"):
        import ctypes

        pr_set_pdeathsig = 1
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(pr_set_pdeathsig, int(signal.SIGTERM), 0, 0, 0)


class ProcessGroup:
    """Child processes in one new process group (the first child leads it), each with its
    output in a log file. Stopping signals the children by pid (SIGTERM, so that the services
    close their flight records and the mock writes its statistics), then the whole group."""

    def __init__(self, log_dir: Path) -> None:
        self.log_dir = log_dir
        self.pgid: int | None = None
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self._logs: dict[str, IO[bytes]] = {}

    def start(
        self, name: str, argv: Sequence[str], env: dict[str, str] | None = None, nice: int = 0
    ) -> None:
        self.log_dir.mkdir(parents=True, exist_ok=True)
        out = open(self.log_dir / f"{name}.log", "wb")  # noqa: SIM115 - closed in close()
        self._logs[name] = out
        pgid = self.pgid

        def join_group() -> None:  # runs in the child between fork and exec
            os.setpgid(0, 0 if pgid is None else pgid)
            _term_with_parent()
            if nice:
                try:
                    os.setpriority(os.PRIO_PROCESS, 0, os.getpriority(os.PRIO_PROCESS, 0) + nice)
                except OSError:  # no privilege to raise the priority: run at the parent's
                    pass

        proc = subprocess.Popen(
            list(argv),
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=subprocess.STDOUT,
            env={**os.environ, **(env or {})},
            preexec_fn=join_group,  # sets the group between fork and exec
        )
        if self.pgid is None:
            self.pgid = proc.pid
        self.procs[name] = proc
        log.info("started %s (pid %d): %s", name, proc.pid, " ".join(argv))
        # who runs, for an operator (or a test) checking that nothing is left behind
        (self.log_dir / "processes.json").write_text(
            json.dumps({"pgid": self.pgid, "pids": {n: p.pid for n, p in self.procs.items()}})
        )

    def pids(self) -> list[int]:
        return [p.pid for p in self.procs.values()]

    def cpu_s(self) -> dict[str, float]:
        """CPU seconds (user + system) each running child has used so far (Linux /proc)."""
        out = {}
        for name, p in self.procs.items():
            try:
                out[name] = stat_cpu_s(f"/proc/{p.pid}/stat")
            except OSError:
                continue
        return out

    def cpu_threads_s(self) -> dict[str, dict[str, float]]:
        """CPU seconds (user + system) by OS thread name (threads of one name summed) of each
        running child so far (Linux /proc; threads that ended are not counted)."""
        out = {}
        for name, p in self.procs.items():
            try:
                out[name] = thread_cpu_s(p.pid)
            except OSError:
                continue
        return out

    def check(self, expected_running: Sequence[str] | None = None) -> None:
        """Raise :class:`DemoError` if a child that should run has exited."""
        for name in expected_running if expected_running is not None else list(self.procs):
            p = self.procs[name]
            if p.poll() is not None:
                raise DemoError(f"{name} exited with status {p.returncode}:\n{self.tail(name)}")

    def tail(self, name: str, lines: int = 15) -> str:
        try:
            text = (self.log_dir / f"{name}.log").read_text(errors="replace")
        except OSError:
            return ""
        return "\n".join("    " + ln for ln in text.splitlines()[-lines:])

    def stop(self, names: Sequence[str], timeout_s: float = 15.0) -> dict[str, int | None]:
        """SIGTERM to ``names`` (by pid), wait; SIGKILL whoever is left. Exit codes by name."""
        for n in names:
            p = self.procs[n]
            if p.poll() is None:
                try:
                    p.send_signal(signal.SIGTERM)
                except ProcessLookupError:
                    pass
        deadline = time.monotonic() + timeout_s
        for n in names:
            p = self.procs[n]
            try:
                p.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("%s did not stop after SIGTERM: killed", n)
                p.kill()
                p.wait()
        return {n: self.procs[n].returncode for n in names}

    def finish(self, name: str, timeout_s: float) -> float:
        """Wait for the one-shot child ``name`` to end; raise :class:`DemoError` unless it
        exited with 0 in time. Forgotten afterwards (``check`` would count it as exited).
        Seconds waited."""
        p = self.procs[name]
        t0 = time.monotonic()
        try:
            rc = p.wait(timeout_s)
        except subprocess.TimeoutExpired:
            raise DemoError(f"{name} did not end within {timeout_s:.0f} s") from None
        if rc != 0:
            raise DemoError(f"{name} exited with status {rc}:\n{self.tail(name)}")
        del self.procs[name]
        return time.monotonic() - t0

    def close(self, timeout_s: float = 15.0) -> None:
        """Stop every child, then make sure nothing of the group is left."""
        try:
            self.stop(list(self.procs), timeout_s)
        finally:
            if self.pgid is not None:
                try:
                    os.killpg(self.pgid, signal.SIGKILL)  # grandchildren, if any
                except ProcessLookupError:
                    pass
            for f in self._logs.values():
                f.close()


# --- security (--secure) ---------------------------------------------------------------------


@dataclass(frozen=True)
class SecurityFiles:
    """The secure demo's secrets in the flight directory (never logged, never in the records or
    the result): ``secrets/`` (mode 0700) holds each drone's MAVLink signing key
    (``mavlink-<id>.key``, 64 hex digits, mode 0600) and the mock's signing configuration (the
    same keys by system id, ``sitl-signing.json``, 0600, given with ``--config`` so that no key
    is on a command line); ``pki/`` the demo CA and the certificates of ``drone-<id>`` and
    ``gcs`` (``gcs.certs.make_demo_pki``; keys 0600)."""

    secrets_dir: Path
    signing_keys: tuple[Path, ...]
    sitl_config: Path
    pki_dir: Path

    @property
    def signing_key_pattern(self) -> str:
        """``autopilot.signing_key_file`` for every service (``{id}``: the drone id)."""
        return str(self.secrets_dir.resolve() / "mavlink-{id}.key")

    def tls_section(self) -> dict[str, str]:
        """``zenoh.tls`` for every service (``{id}``: the drone id)."""
        d = self.pki_dir.resolve()
        return {
            "root_ca_certificate": str(d / "ca.pem"),
            "certificate": str(d / "drone-{id}.pem"),
            "private_key": str(d / "drone-{id}.key"),
        }

    def gcs_tls(self) -> Any:
        from onboard.comm.security import GCS_COMMON_NAME, TlsConfig

        d = self.pki_dir.resolve()
        return TlsConfig(
            str(d / "ca.pem"), str(d / f"{GCS_COMMON_NAME}.pem"), str(d / f"{GCS_COMMON_NAME}.key")
        )


def _write_secret(path: Path, text: str) -> None:
    """Create ``path`` with mode 0600 from the start (refuses an existing file or a link)."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0)
    fd = os.open(path, flags, 0o600)
    with os.fdopen(fd, "w", encoding="ascii") as f:
        f.write(text)


def prepare_security(out: Path, drones: int, swarm: str) -> SecurityFiles:
    """Fresh random signing keys (one per drone: 32 bytes from ``os.urandom``) and a demo PKI
    in the flight directory ``out``. Mock system id = drone id + 1 (the services' default)."""
    from gcs.certs import CertError, make_demo_pki

    secrets, pki = out / "secrets", out / "pki"
    for d in (secrets, pki):
        if d.exists():
            raise DemoError(f"{d} exists (secrets of another run): use a new flight directory")
    secrets.mkdir(mode=0o700, parents=True)
    os.chmod(secrets, 0o700)
    keys = []
    signing = []
    for i in range(drones):
        key_hex = os.urandom(32).hex()
        path = secrets / f"mavlink-{i}.key"
        _write_secret(path, key_hex + "\n")
        keys.append(path)
        signing.append({"key_hex": key_hex, "require": True, "system_id": i + 1})
    sitl_config = secrets / "sitl-signing.json"
    _write_secret(sitl_config, json.dumps({"signing": signing}) + "\n")  # JSON is YAML
    try:
        make_demo_pki(pki, drones, days=2, swarm=swarm)
    except (CertError, ValueError) as e:
        raise DemoError(f"cannot make the demo certificates: {e}") from e
    return SecurityFiles(secrets, tuple(keys), sitl_config, pki)


def _session_links(session: Any, timeout_s: float = 2.0) -> list[dict[str, Any]]:
    """The links of a Zenoh session's unicast transports from its admin space (``src``,
    ``dst`` locators, ``auth_identifier``: the peer's certificate name under mutual TLS)."""
    zid = str(session.info.zid())
    out = []
    for reply in session.get(f"@/{zid}/session/transport/unicast/*/link/*", timeout=timeout_s):
        if reply.ok is None:
            continue
        link = json.loads(reply.ok.payload.to_bytes())
        link["peer"] = str(reply.ok.key_expr).split("/")[-3]
        out.append(link)
    return out


def _refused(endpoints: Any) -> bool:
    """True if a session with these endpoints cannot open (every connect endpoint must be
    reached within 1.5 s; a good handshake on loopback takes milliseconds)."""
    import dataclasses

    eps = dataclasses.replace(
        endpoints,
        extra={**endpoints.extra, "connect/timeout_ms": "1500", "connect/exit_on_failure": "true"},
    )
    try:
        s = open_session(eps)
    except RuntimeError:
        return True
    s.close()
    return False


PEER_PREFIX = "bus.peer_latency."
"""Where a service's flight record keeps its peer latency histogram (``/counters``)."""
PEER_LATENCY_TARGET_MS = {"median": 5.0, "p99": 20.0}
"""Issue #9: peer trajectory latency, publish to the planner's inbox, on loopback."""
PEER_LATENCY_DEFINITION = "peer trajectory, publish -> the planner's inbox (the target's)"
GCS_LATENCY_DEFINITION = "drone trajectory, publish -> the ground station's inbox"


def _percentiles(ms: Sequence[float]) -> dict[str, float | int | None]:
    a = np.asarray(ms, dtype=np.float64)
    if a.size == 0:
        return {"median": None, "p90": None, "p99": None, "max": None, "count": 0}
    return {
        "median": float(np.median(a)),
        "p90": float(np.percentile(a, 90)),
        "p99": float(np.percentile(a, 99)),
        "max": float(a.max()),
        "count": int(a.size),
    }


# --- the mock's truth ------------------------------------------------------------------------


class TruthWatch:
    """The mock's true poses over Zenoh (``<prefix>/<system id>/pose``): that the mock runs, and
    its per-vehicle collision counters."""

    def __init__(self, prefix: str, endpoint: str) -> None:
        from sitl_mock.truth import TruthSample

        self._decode = TruthSample.from_bytes
        self._lock = threading.Lock()
        self.latest: dict[int, Any] = {}
        self._session = open_session(connect=(endpoint,))
        self._sub = self._session.declare_subscriber(f"{prefix}/*/pose", self._on)

    def _on(self, sample: Any) -> None:
        try:
            s = self._decode(sample.payload.to_bytes())
        except (ValueError, KeyError, TypeError):
            log.warning("undecodable truth sample on %s", sample.key_expr)
            return
        with self._lock:
            self.latest[s.system_id] = s

    def snapshot(self) -> dict[int, Any]:
        with self._lock:
            return dict(self.latest)

    def collisions(self) -> int:
        return sum(int(s.collisions) for s in self.snapshot().values())

    def close(self) -> None:
        try:
            self._sub.undeclare()
        finally:
            self._session.close()


# --- the mission -----------------------------------------------------------------------------


@dataclass
class FlightLog:
    """Samples the ground station takes while the swarm flies (5 Hz, from the drones' states)."""

    t: list[float] = field(default_factory=list)
    centroid_x: list[float] = field(default_factory=list)
    e_dist: list[float] = field(default_factory=list)
    e_sim: list[float] = field(default_factory=list)
    min_pair_m: list[float] = field(default_factory=list)

    def add(self, gs: GroundStation, now: float) -> None:
        pos = gs.positions()
        err = gs.formation_error()
        p = np.array(list(pos.values())) if pos else np.zeros((0, 3))
        self.t.append(now)
        self.centroid_x.append(float(p[:, 0].mean()) if len(p) else math.nan)
        self.e_dist.append(err[0] if err is not None else math.nan)
        self.e_sim.append(err[1] if err is not None else math.nan)
        if len(p) >= 2:
            d = np.linalg.norm(p[:, None] - p[None], axis=-1)
            self.min_pair_m.append(float(d[np.triu_indices(len(p), 1)].min()))
        else:
            self.min_pair_m.append(math.nan)

    def cluttered(self, span: tuple[float, float]) -> dict[str, float | None]:
        x = np.array(self.centroid_x)
        inside = (x >= span[0]) & (x <= span[1])

        def mean(v: list[float]) -> float | None:
            a = np.array(v)[inside]
            a = a[np.isfinite(a)]
            return float(a.mean()) if a.size else None

        return {"e_dist_m": mean(self.e_dist), "e_sim": mean(self.e_sim)}


def demo_templates(
    drones: int, formation: str, change: tuple[str, float] | None
) -> list[Formation]:
    """The flight's formation template and the change's (when there is one), each with one
    point per drone: checked before anything starts, not once the change is assigned in
    flight. DemoError names the template that cannot be read or has another size."""
    try:
        templates = [load_template(formation)]
        if change is not None:
            templates.append(load_template(change[0]))
    except FormationError as e:
        raise DemoError(str(e)) from e
    for t in templates:
        if t.n != drones:
            raise DemoError(f"formation {t.name} has {t.n} points, not {drones}")
    return templates


def default_depth_rate(cfg: DemoConfig) -> float:
    """Depth frames per second and drone: ``cfg.depth_rate_hz``, else what this 2-core machine
    renders and maps in real time for the swarm's size (10 up to 4 drones, 3 above)."""
    if cfg.depth_rate_hz is not None:
        return float(cfg.depth_rate_hz)
    return 10.0 if cfg.drones <= 4 else 3.0


MAPPING_NICE = 10
"""The services' ``mapping.thread_nice`` above 4 drones. Seven services share this machine's
2 cores (a drone has a companion computer of its own): nearly saturated, every thread waits
in the run queue, and a plan of 1.8 ms of CPU took 50-72 ms (median, seed 1, nice 0) while the
mapping threads, the largest consumers, ran their 10-20 ms refreshes. At nice 10 the planner,
the bus and the monitor go first: plans 24 ms median, peer latency 8.6 ms median (against
18-25), frames missed as before (398 of 2 706 against 95-421 of 2 243-2 522); one flight at
nice 10 against four at nice 0 (BENCHMARKS.md section 10, 2026-12-02)."""


def default_mapping_nice(cfg: DemoConfig) -> int:
    """``cfg.mapping_nice``, else ``MAPPING_NICE`` above 4 drones (where the depth rate is 3
    frames/s and the band narrow: the regime measured), else 0 (the services' default)."""
    if cfg.mapping_nice is not None:
        return int(cfg.mapping_nice)
    return MAPPING_NICE if cfg.drones > 4 else 0


NARROW_BAND_M = (0.6, 0.8)
"""The planner's altitude band above 4 drones, below and above the cruise altitude (0.4-1.8 m
at the forests' 1 m): the drones hold their altitude within 0.1 m (``w_altitude_hold``), and
an ESDF refresh of that band costs about 40 % less than of the 0.3-3.1 m one (``swarm-gcs bench
mapping --window band --band LO HI --rate 5 --esdf-every 1 --max-frames 150``, forest-medium:
23-27 against 41-43 ms median on the slowest host seen), which 7 services mapping on 2 cores
need."""


def default_band(cfg: DemoConfig) -> tuple[float, float] | None:
    """(below, above) the cruise altitude of the planner's altitude band, or None for the
    onboard config's band: ``cfg.altitude_band_m`` ((0, 0) is None), else ``NARROW_BAND_M``
    above 4 drones."""
    band = cfg.altitude_band_m
    if band is None:
        return NARROW_BAND_M if cfg.drones > 4 else None
    below, above = (float(x) for x in band)
    if below == 0.0 and above == 0.0:
        return None
    if not (below > 0.0 and above > 0.0 and math.isfinite(below + above)):
        raise DemoError(f"altitude band: expected two distances > 0 (below, above), got {band}")
    return below, above


def cruise_altitude_m(cfg: DemoConfig, spec: Any) -> float:
    """``cfg.altitude_m``, else the start height of the world ``spec``."""
    if cfg.altitude_m is not None:
        return float(cfg.altitude_m)
    assert spec.start_center is not None
    return float(spec.start_center[2])


def planner_z_limits(cfg: DemoConfig, spec: Any) -> tuple[float, float] | None:
    """The planner's altitude band in metres (``default_band`` around ``cruise_altitude_m``),
    or None for the onboard config's: what the services fly, and the fast-time twin too."""
    band = default_band(cfg)
    if band is None:
        return None
    alt = cruise_altitude_m(cfg, spec)
    return round(alt - band[0], 6), round(alt + band[1], 6)


GAVE_UP = ("emergency", "landing", "landed", "pilot", "link-lost")
"""Flight states in which a drone no longer flies the mission."""

Progress = Callable[[str, dict[str, Any]], None]
"""``progress(phase, info)``: called about twice a second while waiting."""


class Demo:
    """One demo run; :meth:`run` returns the result and writes ``mission.json`` and the report.
    Use as a context manager: leaving it stops every process."""

    def __init__(self, cfg: DemoConfig, progress: Progress | None = None) -> None:
        from onboard.config import load_world_spec

        self.cfg = cfg
        self.progress = progress or (lambda phase, info: None)
        self.depth_rate_hz = default_depth_rate(cfg)
        if not 1.0 <= self.depth_rate_hz <= 30.0:
            raise DemoError(f"depth_rate_hz must lie in [1, 30], got {self.depth_rate_hz}")
        if cfg.drones < 2:
            raise DemoError("a formation needs at least 2 drones")
        if not (math.isfinite(cfg.lead_s) and 0.0 <= cfg.lead_s <= DEMO_LEAD_MAX_S):
            raise DemoError(f"lead_s must lie in [0, {DEMO_LEAD_MAX_S:g}] s, got {cfg.lead_s}")
        self.mapping_nice = default_mapping_nice(cfg)
        if not 0 <= self.mapping_nice <= 19:
            raise DemoError(f"mapping_nice must lie in [0, 19], got {self.mapping_nice}")
        self.template = demo_templates(cfg.drones, cfg.formation, cfg.formation_change)[0]
        self.spec = load_world_spec(cfg.world)
        self.z_limits = planner_z_limits(cfg, self.spec)
        self.out = Path(cfg.out_dir)
        self.out.mkdir(parents=True, exist_ok=True)
        self.swarm = cfg.swarm or f"demo{os.getpid()}"
        self.procs = ProcessGroup(self.out / "logs")
        self.truth: TruthWatch | None = None
        self.gs: GroundStation | None = None
        self.view: Any = None
        self.outcomes: list[CommandOutcome] = []
        self.assignments: list[dict[str, Any]] = []
        self.events: list[tuple[float, str]] = []
        self.flight = FlightLog()
        self.sitl_stats: dict[str, Any] = {}
        self.exit_codes: dict[str, int | None] = {}
        self.security: SecurityFiles | None = None
        self.security_checks: dict[str, Any] = {}
        self.gs_session: Any = None
        # drone trajectories as they reach this station's inbox: (sender, receive time,
        # receive time minus the sender's stamp taken just before publishing)
        self._traj_lock = threading.Lock()
        self.traj_latency: list[tuple[int, float, float]] = []
        self._records: list[Any] | None = None

    # -- lifecycle --

    def __enter__(self) -> Demo:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop everything (idempotent)."""
        if self.view is not None:
            self.view.close()
            self.view = None
        if self.gs is not None:
            self.gs.close()
            self.gs = None
        if self.gs_session is not None:
            self.gs_session.close()
            self.gs_session = None
        if self.truth is not None:
            self.truth.close()
            self.truth = None
        self.procs.close()

    def _event(self, text: str) -> None:
        self.events.append((time.time(), text))
        log.info("%s", text)

    # -- start-up --

    def start(self) -> None:
        self.t_start = time.monotonic()
        cfg = self.cfg
        n = cfg.drones
        sitl_ep = free_loopback_endpoint()
        self.sitl_endpoint = sitl_ep
        prefix = f"{self.swarm}/sim"
        from sitl_mock.client import bind_consecutive_udp

        socks = bind_consecutive_udp(n)
        base_port = socks[0].getsockname()[1]
        for sock in socks:
            sock.close()
        self.base_port = base_port
        self.world_file = self._world_file()
        if cfg.secure:
            self.security = prepare_security(self.out, n, self.swarm)
            self._event("signing keys and demo certificates made (secrets/, pki/)")
        sitl = [
            *_exe("swarm-sitl", "sitl_mock.cli"),
            "--count", str(n), "--world", str(self.world_file), "--seed", str(cfg.seed),
            "--spacing", str(cfg.spacing_m), "--base-port", str(base_port),
            "--local-port-offset", "-1", "--truth", "zenoh", "--zenoh-listen", sitl_ep,
            "--zenoh-prefix", prefix, "--depth", "--depth-rate", str(self.depth_rate_hz),
            "--depth-step", str(cfg.depth_step), "--depth-idle-rate", "1",
            "--stats-json", str(self.out / "sitl-stats.json"),
        ]  # fmt: skip
        if self.security is not None:  # the keys by system id, in a 0600 file: not on argv
            sitl += ["--config", str(self.security.sitl_config)]
        for s in cfg.sitl_sets:
            sitl += ["--set", s]
        conf = self.out / "onboard.yaml"
        conf.write_text(self._onboard_yaml(base_port, sitl_ep, prefix), encoding="utf-8")
        # what the warm-up unit does on a drone at boot: numba's kernels compiled into the
        # cache once, while the mock starts, instead of by every service at once (cold, on 2
        # cores, that took longer than the services' 60 s to READY); seconds when cached
        warm = [*_exe("swarm-onboard", "onboard.cli"), "warmup", "--config", str(conf)]
        self.procs.start("warmup", warm)
        self.procs.start("sitl", sitl, nice=cfg.sitl_nice)
        self.truth = TruthWatch(prefix, sitl_ep)
        self._wait("mock", lambda: len(self.truth.snapshot()) == n if self.truth else False,
                   cfg.step_timeout_s, ["sitl"])  # fmt: skip
        self._event(f"mock fleet up: {n} vehicles, {cfg.world} seed {cfg.seed}")
        waited = self.procs.finish("warmup", 300.0)
        self._event(f"kernels warm (waited {waited:.1f} s for the warm-up)")
        mesh = peer_mesh(n + 1)  # the drones and this ground station
        for i in range(n):
            ep = mesh[i + 1]
            argv = [
                *_exe("swarm-onboard", "onboard.cli"), "run", "--id", str(i),
                "--config", str(conf),
                "--set", f"zenoh.listen={json.dumps(list(ep.listen))}",
                "--set", f"zenoh.connect={json.dumps(list(ep.connect))}",
            ]  # fmt: skip
            for s in cfg.onboard_sets:
                argv += ["--set", s]
            self.procs.start(f"drone{i}", argv, env={"OPENBLAS_NUM_THREADS": "1"})
        gs_eps = mesh[0]
        if self.security is not None:
            from onboard.comm.security import SwarmAccessControl

            gs_eps = gs_eps.secured(
                self.security.gcs_tls(), SwarmAccessControl.for_count(self.swarm, n)
            )
        self.gs_endpoints = gs_eps
        self.drone_endpoints = mesh[1:]
        self.gs_session = open_session(gs_eps)
        self.gs = GroundStation(
            self.swarm,
            session=self.gs_session,
            config=StationConfig(ack_timeout_s=5.0, lead_s=cfg.lead_s),
        )
        gs = self.gs
        gs.node.on_trajectory(self._on_trajectory)
        ids = list(range(n))

        def all_idle() -> bool:
            v = gs.views()
            return all(i in v and v[i].alive and v[i].flight_state == "idle" for i in ids)

        self._wait("services", all_idle, cfg.startup_timeout_s)
        self._event(f"{n} flight services up and idle")
        if self.security is not None:
            self._check_bus_security()
        if cfg.view_port is not None:
            from gcs.commands import mock_world
            from gcs.view import SwarmView, station_input

            w = mock_world(str(self.world_file), n, cfg.seed, cfg.spacing_m)
            self.view = SwarmView(station_input(gs), w, port=cfg.view_port).start()
            self._event(f"Foxglove view on {self.view.url}")

    def _on_trajectory(self, env: Any, _receive_s: float) -> None:
        """A drone's trajectory accepted by this station's node (Zenoh's thread): its latency
        from the publisher's stamp to the inbox, built as a drone's inbox builds it. Both clocks
        are this machine's system clock (as in ``swarm-gcs bench bus``)."""
        from onboard.comm.messages import TrajectoryMsg

        TrajectoryMsg.from_envelope(env)
        now = time.time()
        with self._traj_lock:
            self.traj_latency.append((int(env.sender), now, now - float(env.stamp_s)))

    def bus_latency(self) -> dict[str, Any]:
        """Trajectory latency (ms), publish -> this station's inbox, while the swarm flew (from
        the take-off command to the landing command). Not the target's definition (peer to
        peer, into the planner's inbox: ``peer_latency``), and few samples (one per drone and
        replan)."""
        t0 = getattr(self, "t_takeoff", math.inf)
        t1 = getattr(self, "t_land_cmd", math.inf)
        with self._traj_lock:
            kept = [(d, lat) for d, t, lat in self.traj_latency if t0 <= t <= t1]
        out: dict[str, Any] = {"definition": GCS_LATENCY_DEFINITION}
        out.update(_percentiles([lat * 1e3 for _, lat in kept]))
        out["per_drone"] = {
            str(d): sum(1 for s, _ in kept if s == d) for d in range(self.cfg.drones)
        }
        return out

    def records(self) -> list[Any]:
        """The services' flight records in the flight directory (read once, after the flight)."""
        if self._records is None:
            from onboard.record import read_record

            self._records = [read_record(p) for p in sorted(self.out.glob("*.mcap"))]
        return self._records

    def peer_latency(self) -> dict[str, Any]:
        """Peer trajectory latency (ms), the target's definition (issue #9): publish -> the
        planner's inbox of every other service, over all services, from the take-off command
        to the landing command. Each service keeps a cumulative histogram of its samples
        (``onboard.comm.latency``; all processes share this machine's clock) in the 1 Hz
        ``/counters`` of its flight record; the window is the first snapshot at or after the
        landing command (the last one if there is none) minus the last one at or before the
        take-off command (none: a record opens at take-off, and no trajectory is published on
        the ground). Percentiles come from the merged histogram, within half a bin (1.6 %);
        count exact; max exact when ``max_exact``. The target: median < 5 ms, p99 < 20 ms."""
        from onboard.comm.latency import LatencyFigures

        out: dict[str, Any] = {"definition": PEER_LATENCY_DEFINITION}
        t0 = getattr(self, "t_takeoff", None)
        t1 = getattr(self, "t_land_cmd", math.inf)
        per_drone: dict[int, LatencyFigures] = {}
        if t0 is not None:
            for rec in self.records():
                snaps = [
                    (t, f)
                    for t, m in rec.topics.get("/counters", [])
                    if (f := LatencyFigures.from_counters(m.get("counters", {}), PEER_PREFIX))
                    is not None
                ]
                if not snaps:
                    continue
                before = [f for t, f in snaps if t <= t0]
                after = [f for t, f in snaps if t >= t1]
                end = after[0] if after else snaps[-1][1]
                window = end.minus(before[-1] if before else LatencyFigures())
                d = rec.drone_id
                per_drone[d] = LatencyFigures.merge([per_drone.get(d, LatencyFigures()), window])
        fig = LatencyFigures.merge(per_drone.values())
        out.update(fig.summary_ms())
        out["per_drone"] = {str(d): f.count for d, f in sorted(per_drone.items())}
        out["target_ms"] = dict(PEER_LATENCY_TARGET_MS)
        med, p99 = out["median"], out["p99"]
        tgt = PEER_LATENCY_TARGET_MS
        out["meets_target"] = (
            None if med is None or p99 is None else bool(med < tgt["median"] and p99 < tgt["p99"])
        )
        return out

    def _check_bus_security(self) -> None:
        """The swarm bus is secured in fact: every link of this station's session is TLS and
        authenticated as a drone of the swarm, and intruders are refused: a plain TCP session
        and a TLS session without a certificate, both to drone 0's listener."""
        from onboard.comm.security import drone_common_name
        from onboard.comm.zenoh_session import ZenohEndpoints

        assert self.gs_session is not None and self.security is not None
        links = _session_links(self.gs_session)
        locators = sorted({ep for ln in links for ep in (ln.get("src"), ln.get("dst")) if ep})
        idents = sorted({str(ln.get("auth_identifier")) for ln in links})
        want = sorted(drone_common_name(i) for i in range(self.cfg.drones))
        target = self.drone_endpoints[0].listen[0]  # tcp/127.0.0.1:PORT (its TLS listener)
        ca = str(self.security.pki_dir.resolve() / "ca.pem")
        plain = _refused(ZenohEndpoints(connect=(target,)))
        no_cert = _refused(
            ZenohEndpoints(
                connect=(target.replace("tcp/", "tls/", 1),),
                extra={"transport/link/tls/root_ca_certificate": json.dumps(ca)},
            )
        )
        self.security_checks = {
            "links": len(links),
            "link_locators_tls_only": bool(locators)
            and all(x.startswith("tls/") for x in locators),
            "link_identities": idents,
            "every_drone_authenticated": set(want) <= set(idents),
            "plain_tcp_session_refused": plain,
            "session_without_certificate_refused": no_cert,
        }
        self._event(
            f"bus security: {len(links)} links, TLS only "
            f"{self.security_checks['link_locators_tls_only']}, identities {idents}, "
            f"plain session refused {plain}, no-certificate session refused {no_cert}"
        )
        bad = [k for k, v in self.security_checks.items() if v is False]
        if bad:
            raise DemoError(f"the swarm bus is not secured as configured: {', '.join(bad)}")

    def _world_file(self) -> Path:
        """The world as flown: the named world with per-drone ``starts`` and ``goals`` in the
        formation around its start and goal centres (unless it has its own for this many
        drones), so that the mock spawns the drones in formation. The mock's forest then keeps
        clear of the same points as the fast-time simulator's, which makes the two fly the very
        same obstacles for a seed."""
        import dataclasses

        spec = self.spec
        data = dataclasses.asdict(spec)  # the fields are the file's keys (round trip exact)
        if not (spec.starts is not None and len(spec.starts) == self.cfg.drones):
            assert spec.start_center is not None and spec.goal_center is not None
            off = self.template.centered
            data["starts"] = (np.asarray(spec.start_center) + off).tolist()
            data["goals"] = (np.asarray(spec.goal_center) + off).tolist()
        # where the mock stands each vehicle: its start on the ground
        ground = 0.0 if spec.ground_z is None else float(spec.ground_z)
        self.spawns: list[list[float]] = [
            [float(p[0]), float(p[1]), ground] for p in data["starts"]
        ]
        out = self.out / "world.json"
        out.write_text(json.dumps(data, indent=1) + "\n", encoding="utf-8")
        return out

    def _onboard_yaml(self, base_port: int, sitl_ep: str, prefix: str) -> str:
        cfg = self.cfg
        planner: dict[str, Any] = {} if cfg.v_max_m_s is None else {"v_max_m_s": cfg.v_max_m_s}
        if self.z_limits is not None:
            planner["z_limits_m"] = list(self.z_limits)
        # like PX4, each mock vehicle starts its local frame where it stands (its EKF origin):
        # every service is told where that is in the swarm frame
        origins = {str(i): p for i, p in enumerate(self.spawns)}
        autopilot: dict[str, Any] = {
            "url": f"udp://127.0.0.1:{base_port}",
            "port_plus_id": True,
            "local_origins_enu_m": origins,
        }
        if self.security is not None:
            autopilot["signing_key_file"] = self.security.signing_key_pattern
            autopilot["signing_required"] = True
        data: dict[str, Any] = {
            "drone": {"swarm": self.swarm},
            "autopilot": autopilot,
            "depth": {
                "source": "zenoh-sim",
                "rate_hz": self.depth_rate_hz,
                "sim_prefix": prefix,
                "sim_connect": [sitl_ep],
                "step": cfg.depth_step,
            },
            "planner": planner,
            "mapping": {"thread_nice": self.mapping_nice},
            "reactions": {"depth_lost": {"timeout_s": max(0.5, 4.0 / self.depth_rate_hz)}},
            "record": {"enabled": True, "directory": str(self.out.resolve())},
            "logging": {"format": "json"},
        }
        if self.security is not None:
            data["zenoh"] = {
                "tls": self.security.tls_section(),
                "access_control_drones": cfg.drones,
            }
        # on top of the drone's own configuration: a file given to the service replaces
        # config/onboard.yaml, and without it the services flew another planner than the
        # drone's (check_obstacle_horizon_s 0 instead of 4 until 2026-12-02) and than the
        # fast-time twin the demo is compared with
        try:
            base = config_data()
        except ConfigError as e:
            raise DemoError(f"config/onboard.yaml: {e}") from e
        return json.dumps(merge_mappings(base, data), indent=2) + "\n"  # JSON is YAML

    # -- waiting --

    def _wait(
        self,
        what: str,
        cond: Callable[[], bool],
        timeout_s: float,
        running: Sequence[str] | None = None,
        info: Callable[[], dict[str, Any]] | None = None,
    ) -> None:
        """Poll ``cond`` until true; every child must keep running (or ``running``)."""
        deadline = time.monotonic() + timeout_s
        last = 0.0
        while not cond():
            self.procs.check(running)
            if time.monotonic() > deadline:
                raise DemoError(f"timed out after {timeout_s:.0f} s waiting for {what}")
            now = time.monotonic()
            if now - last >= 0.5:
                last = now
                self.progress(what, info() if info is not None else {})
            time.sleep(0.1)

    def _need(self, outcome: CommandOutcome) -> CommandOutcome:
        self.outcomes.append(outcome)
        self._event(outcome.describe())
        if not outcome.ok:
            raise DemoError(outcome.describe())
        return outcome

    def _own_goals(self, center: np.ndarray) -> dict[int, np.ndarray]:
        assert self.gs is not None
        known = self.gs.known_formation()
        assert known is not None
        wire = known[1]
        pts = np.asarray(wire.points_m, dtype=np.float64)
        off = pts - pts.mean(axis=0)
        return {d: center + off[s] for d, s in wire.slots.items()}

    def _at(self, goals: dict[int, np.ndarray], tol_m: float = 0.5) -> bool:
        """Every drone hovers within ``tol_m`` of its goal."""
        assert self.gs is not None
        v = self.gs.views()
        for d, g in goals.items():
            x = v.get(d)
            if x is None or x.position_m is None or x.flight_state != "hover":
                return False
            if np.linalg.norm(np.asarray(x.position_m) - g) > tol_m:
                return False
            if (x.speed_m_s or 0.0) > 0.25:
                return False
        return True

    def _assign(self, name: str) -> None:
        assert self.gs is not None
        try:
            a, out = self.gs.formation(name)
        except FormationError as e:
            raise DemoError(str(e)) from e
        self._need(out)
        self.assignments.append(
            {
                "name": a.name,
                "epoch": a.epoch,
                "effective_s": a.effective_s,
                "points_m": a.offsets_m.tolist(),
                "slots": {str(d): s for d, s in sorted(a.slots.items())},
                "yaw_deg": math.degrees(a.yaw_rad),
                "cost_m": a.cost_m,
            }
        )

    # -- the mission --

    def fly(self) -> None:
        """Take off, form up, cross, (re-shape), land."""
        cfg, gs = self.cfg, self.gs
        assert gs is not None
        spec = self.spec
        assert spec.start_center is not None and spec.goal_center is not None
        alt = cruise_altitude_m(cfg, spec)
        ids = list(range(cfg.drones))
        self.t_takeoff = time.time()
        self._need(gs.takeoff(alt))

        def all_hover() -> bool:
            v = gs.views()
            return all(i in v and v[i].flight_state == "hover" for i in ids)

        self._wait("take-off", all_hover, cfg.step_timeout_s)
        # the drones stand in formation (see _world_file): slots from where they hover
        self._assign(cfg.formation)
        start = np.array([spec.start_center[0], spec.start_center[1], alt])
        goal = np.array([spec.goal_center[0], spec.goal_center[1], alt])
        route = float(np.linalg.norm(goal - start))
        v_max = cfg.v_max_m_s or 0.5
        limit = cfg.flight_timeout_s or (route / v_max * 2.5 + 60.0)
        self.goal = goal
        self.t_goal = time.time()
        self._need(gs.goal(tuple(goal)))
        change = cfg.formation_change
        changed = change is None
        self.change_reached_s: float | None = None
        # the same from the change's common switch time (its ``effective_s``, the station's
        # lead_s after the command): the fast-time twin's clock, where the two coincide
        self.change_reached_after_switch_s: float | None = None
        self.t_change: float | None = None
        deadline = time.monotonic() + limit
        last_sample = 0.0
        while not (changed and self._at(self._own_goals(goal))):
            self.procs.check()
            self._check_flying(ids)
            now = time.time()
            if time.monotonic() > deadline:
                raise DemoError(f"the swarm did not reach the goal within {limit:.0f} s")
            if now - last_sample >= 0.2:
                last_sample = now
                self.flight.add(gs, now)
                self.progress("crossing", self._info(start, goal))
                if self.t_change is not None and self.change_reached_s is None:
                    e = self.flight.e_sim[-1]
                    switch = self.assignments[-1]["effective_s"]
                    if math.isfinite(e) and e < 0.01 and now > switch:
                        self.change_reached_s = now - self.t_change
                        self.change_reached_after_switch_s = now - switch
                        self._event(f"new formation reached (e_sim < 0.01) after "
                                    f"{self.change_reached_s:.1f} s, "
                                    f"{self.change_reached_after_switch_s:.1f} s after "
                                    f"the switch")  # fmt: skip
            if change is not None and not changed and now - self.t_goal >= change[1]:
                self.t_change = time.time()
                self._assign(change[0])
                changed = True
                self._event(f"formation changed to {change[0]} in flight")
            time.sleep(0.1)
        self.t_arrived = time.time()
        self._event(f"arrived after {self.t_arrived - self.t_goal:.1f} s")
        self.t_land_cmd = time.time()
        self._need(gs.land())

        def all_landed() -> bool:
            v = gs.views()
            return all(i in v and v[i].flight_state == "landed" for i in ids)

        self._wait("landing", all_landed, cfg.step_timeout_s)
        self.t_landed = time.time()
        self._event("landed")

    def _check_flying(self, ids: Sequence[int]) -> None:
        """Fail at once when a drone gave up the mission (emergency, landing, pilot, link)."""
        assert self.gs is not None
        views = self.gs.views()
        out = {d: views[d] for d in ids if d in views and views[d].flight_state in GAVE_UP}
        if out:
            why = "; ".join(
                f"drone {d} {v.flight_state}" + (f" ({v.message})" if v.message else "")
                for d, v in sorted(out.items())
            )
            raise DemoError(f"a drone left the mission: {why}")

    def _info(self, start: np.ndarray, goal: np.ndarray) -> dict[str, Any]:
        assert self.gs is not None
        pos = self.gs.positions()
        if not pos:
            return {}
        c = np.mean(list(pos.values()), axis=0)
        total = float(np.linalg.norm(goal - start))
        done = float(np.clip(np.dot(c - start, goal - start) / max(total, 1e-9), 0.0, total))
        states: dict[str, int] = {}
        for v in self.gs.views().values():
            states[v.flight_state or "?"] = states.get(v.flight_state or "?", 0) + 1
        return {
            "done_m": done,
            "total_m": total,
            "e_sim": self.flight.e_sim[-1] if self.flight.e_sim else math.nan,
            "min_pair_m": self.flight.min_pair_m[-1] if self.flight.min_pair_m else math.nan,
            "states": states,
            "collisions": self.truth.collisions() if self.truth else 0,
        }

    # -- the end --

    def finish(self) -> dict[str, Any]:
        """Stop the processes in order (services, then the mock), write mission.json and the
        report; returns the result."""
        names = [f"drone{i}" for i in range(self.cfg.drones)]
        live_collisions = self.truth.collisions() if self.truth else None
        self.cpu = self.procs.cpu_s()
        self.cpu_threads = self.procs.cpu_threads_s()
        self.wall_s = time.monotonic() - self.t_start
        if self.view is not None:
            self.view.close()
            self.view = None
        if self.gs is not None:
            self.gs.close()
            self.gs = None
        self.exit_codes.update(self.procs.stop(names))
        self.exit_codes.update(self.procs.stop(["sitl"]))
        stats_file = self.out / "sitl-stats.json"
        if stats_file.is_file():
            self.sitl_stats = json.loads(stats_file.read_text())
        return self._result(live_collisions)

    def signing_checks(self) -> dict[str, Any]:
        """MAVLink signing as flown: each service's autopilot counters (the last ``/counters``
        of its flight record: frames received, unsigned refused, bad signatures, unsigned let
        through) and each mock vehicle's (messages accepted, unsigned refused). With signing
        required on both ends, every frame accepted was signed with the drone's key."""
        services: dict[str, dict[str, int]] = {}
        for rec in self.records():
            last = rec.messages("/counters")
            if not last:
                continue
            c = last[-1]["counters"]
            d = str(rec.drone_id)
            prev = services.get(d, {})
            services[d] = {
                k: int(c.get(f"autopilot.{k}", 0)) + prev.get(k, 0)
                for k in (
                    "messages_received", "unsigned_rejected", "bad_signatures",
                    "unsigned_accepted", "setpoints_sent",
                )
            }  # fmt: skip
        vehicles = {
            str(int(ln["system_id"])): {
                "rx_messages": int(ln.get("rx_messages", 0)),
                "rx_rejected_unsigned": int(ln.get("rx_rejected_unsigned", 0)),
                "setpoints": int(ln.get("setpoints", 0)),
            }
            for ln in self.sitl_stats.get("links", [])
        }
        ok = (
            len(services) == self.cfg.drones
            and len(vehicles) == self.cfg.drones
            and all(
                v["messages_received"] > 0
                and v["unsigned_rejected"] == 0
                and v["bad_signatures"] == 0
                and v["unsigned_accepted"] == 0
                for v in services.values()
            )
            and all(
                v["rx_messages"] > 0 and v["rx_rejected_unsigned"] == 0 for v in vehicles.values()
            )
        )
        return {"signed_only": ok, "services": services, "vehicles": vehicles}

    def mission(self) -> dict[str, Any]:
        s = self.sitl_stats
        collisions = s.get("collisions")
        return {
            "swarm": self.swarm,
            "world": str(getattr(self, "world_file", self.cfg.world)),
            "world_name": self.cfg.world,
            "seed": self.cfg.seed,
            "count": self.cfg.drones,
            "spacing_m": self.cfg.spacing_m,
            "lead_s": self.cfg.lead_s,
            "cluttered_x": list(self.spec.cluttered_x),
            "formation": self.cfg.formation,
            "formation_change": None
            if self.cfg.formation_change is None
            else list(self.cfg.formation_change),  # fmt: skip
            "goal_m": self.goal.tolist() if hasattr(self, "goal") else None,
            "assignments": self.assignments,
            "commands": [o.to_json() for o in self.outcomes],
            "events": self.events,
            "sitl": {
                "collisions": None if collisions is None else len(collisions),
                "collision_events": collisions,
                "min_obstacle_distance_m": s.get("min_obstacle_distance_m"),
                "min_vehicle_distance_m": s.get("min_vehicle_distance_m"),
                "depth": s.get("depth"),
            },
        }

    def _result(self, live_collisions: int | None) -> dict[str, Any]:
        mission = self.mission()
        (self.out / "mission.json").write_text(json.dumps(mission, indent=2) + "\n")
        summary: dict[str, Any] = {}
        if self.cfg.report and list(self.out.glob("*.mcap")):
            from gcs.report import write_report

            summary, _ = write_report([self.out], mission=mission)
        sp = summary.get("setpoint_period_ms", {})
        flown = self.flight.cluttered(self.spec.cluttered_x)
        sitl = mission["sitl"]
        collisions = sitl["collisions"] if sitl["collisions"] is not None else live_collisions
        arrived = hasattr(self, "t_arrived")
        services_ok = all(rc == 0 for n, rc in self.exit_codes.items() if n.startswith("drone"))
        security: dict[str, Any] = {"signing": False, "zenoh_tls": False}
        secure_ok = True
        if self.security is not None:
            signing = self.signing_checks()
            bus = dict(self.security_checks)
            security = {
                "signing": True,
                "zenoh_tls": True,
                "access_control": True,
                "signing_checks": signing,
                "bus_checks": bus,
            }
            secure_ok = (
                bool(signing["signed_only"])
                and bool(bus)
                and all(v is not False for v in bus.values())
            )
        latency = self.bus_latency()
        peer_latency = self.peer_latency()
        result = {
            "success": bool(arrived and collisions == 0 and services_ok and secure_ok),
            "arrived": arrived,
            "collisions": collisions,
            "e_dist_m": flown["e_dist_m"],
            "e_sim": flown["e_sim"],
            # the mock's truth: from the body (radius body_radius_m, 0.2 m) to the nearest
            # obstacle surface, and between vehicle centres (a collision below 2 radii)
            "min_obstacle_clearance_m": sitl["min_obstacle_distance_m"],
            "min_drone_distance_m": sitl["min_vehicle_distance_m"],
            "flight_time_s": (self.t_landed - self.t_takeoff)
            if hasattr(self, "t_landed")
            else None,
            "crossing_time_s": (self.t_arrived - self.t_goal) if arrived else None,
            # from the command (issue #10's figure) and from the common switch time
            "formation_change_reached_s": getattr(self, "change_reached_s", None),
            "formation_change_reached_after_switch_s": getattr(
                self, "change_reached_after_switch_s", None
            ),
            "setpoint_period_ms": {k: sp.get(k) for k in ("median", "p99", "max", "count")},
            "peer_latency_ms": peer_latency,
            "bus_latency_ms": latency,
            "security": security,
            "plan_ms": {k: summary.get("plan_ms", {}).get(k) for k in ("median", "p90", "max")},
            "plan_cpu_ms": {
                k: summary.get("plan_cpu_ms", {}).get(k) for k in ("median", "p90", "max")
            },
            # the services' safety monitors: braking stops in flight, replans they asked for
            "monitor": summary.get("monitor"),
            # the services' holds for lost depth (a silent camera, a map lagging a live one)
            "depth_holds": summary.get("depth_holds"),
            # numba kernels the services compiled or loaded after READY: each held a thread
            # in flight (a warm-up that missed one; 0 is the rule)
            "kernels_after_ready": summary.get("kernels_after_ready"),
            # stops by the services' setpoint threads, their safety monitors silent
            "stream_guard_stops": summary.get("stream_guard_stops"),
            # the planners' refused attempts, by why (gcs.report.plan_refusals)
            "plan_refusals": summary.get("plan_refusals"),
            "depth": sitl.get("depth"),
            "exit_codes": self.exit_codes,
            "wall_s": getattr(self, "wall_s", None),
            "cpu_s": getattr(self, "cpu", {}),
            "cpu_threads_s": cpu_by_thread(getattr(self, "cpu_threads", {})),
            "flight_dir": str(self.out),
        }
        (self.out / "result.json").write_text(json.dumps(_json_safe(result), indent=2) + "\n")
        return result


def cpu_by_thread(per_process: dict[str, dict[str, float]]) -> dict[str, dict[str, float]]:
    """``ProcessGroup.cpu_threads_s``'s figures as the result keeps them: the flight
    services' threads summed over the services (``services``), the mock's (``sitl``)."""
    services: dict[str, float] = {}
    for name, threads in per_process.items():
        if name.startswith("drone"):
            for comm, cpu in threads.items():
                services[comm] = services.get(comm, 0.0) + cpu
    out = {"services": dict(sorted(services.items(), key=lambda kv: -kv[1]))}
    if "sitl" in per_process:
        out["sitl"] = dict(sorted(per_process["sitl"].items(), key=lambda kv: -kv[1]))
    return out


def _json_safe(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def run_demo(cfg: DemoConfig, progress: Progress | None = None) -> dict[str, Any]:
    """Run the whole demo; returns the result (``success`` False on any failure, with
    ``error``). Raises KeyboardInterrupt after the cleanup when interrupted."""
    with sigterm_interrupts():  # SIGTERM ends the demo like Ctrl-C: the cleanup runs
        demo = Demo(cfg, progress)
        error: str | None = None
        try:
            demo.start()
            demo.fly()
            result = demo.finish()
        except DemoError as e:
            error = str(e)
            result = demo.finish()
        finally:  # also on KeyboardInterrupt (Ctrl-C, SIGTERM), which then goes on up
            demo.close()
    if error is not None:
        result["success"] = False
        result["error"] = error
        # result.json (written by finish) says why too
        (demo.out / "result.json").write_text(json.dumps(_json_safe(result), indent=2) + "\n")
    return result


def parse_change(text: str | None) -> tuple[str, float] | None:
    """``NAME@SECONDS`` -> (NAME, SECONDS)."""
    if not text:
        return None
    name, sep, when = text.rpartition("@")
    try:
        t = float(when)
    except ValueError:
        t = math.nan
    if not sep or not name or not math.isfinite(t) or t < 0:
        raise ValueError(f"--formation-change {text!r}: expected NAME@SECONDS, e.g. arrow-7@20")
    return name, t


def demo_command() -> Any:
    import click
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    @click.command("demo")
    @click.option("--drones", type=click.IntRange(2, 64), default=7, show_default=True)
    @click.option("--formation", default="hexagon-7", show_default=True)
    @click.option("--world", default="forest-medium", show_default=True)
    @click.option("--seed", type=int, default=1, show_default=True)
    @click.option("--formation-change", "change", default=None, metavar="NAME@SECONDS",
                  help="Change formation this many seconds after the goal was sent.")  # fmt: skip
    @click.option("--depth-rate", type=click.FloatRange(1.0, 30.0), default=None,
                  help="Depth frames per second and drone [default: 10 up to 4 drones, "
                  "3 above].")  # fmt: skip
    @click.option("--v-max", type=click.FloatRange(0.1, 3.0), default=None,
                  help="Planner speed limit [m/s] (default: config/onboard.yaml's).")  # fmt: skip
    @click.option("--altitude-band", type=float, nargs=2, default=None,
                  metavar="BELOW ABOVE",
                  help="The planner's altitude band, metres below and above the cruise "
                  "altitude [default: 0.6 0.8 above 4 drones, config/onboard.yaml's up to 4]; "
                  "0 0: config/onboard.yaml's.")  # fmt: skip
    @click.option("--out", "out_dir", type=click.Path(file_okay=False, path_type=Path),
                  default=None, help="Flight directory [default: flights/demo-TIME].")  # fmt: skip
    @click.option("--view", "view_port", type=int, default=None, metavar="PORT",
                  help="Serve the live 3-D view to Foxglove on this port (0: any).")  # fmt: skip
    @click.option("--set-onboard", "onboard_sets", multiple=True, metavar="KEY=VALUE",
                  help="Override a setting of every flight service.")  # fmt: skip
    @click.option("--set-sitl", "sitl_sets", multiple=True, metavar="KEY=VALUE",
                  help="Override a setting of the mock fleet.")  # fmt: skip
    @click.option("--secure", is_flag=True,
                  help="MAVLink 2 signing between every service and its vehicle (fresh random "
                  "keys, 0600, in the flight directory; the mock imitates PX4 v1.17+) and the "
                  "swarm bus over Zenoh mutual TLS with access control (a demo CA). The mock's "
                  "truth/depth session is the simulator, not the swarm bus: it stays plain "
                  "TCP.")  # fmt: skip
    @click.option("--lead", "lead_s", type=click.FloatRange(0.0, DEMO_LEAD_MAX_S),
                  default=DEMO_LEAD_S, show_default=True,
                  help="Seconds from a formation or goal command to the common time every "
                  "drone switches at (loopback: the station's resend period).")  # fmt: skip
    @click.option("--startup-timeout", type=float, default=180.0, show_default=True)
    @click.option("--json", "as_json", is_flag=True, help="Print the result as JSON.")
    @click.option("--quiet", "-q", is_flag=True, help="No progress display.")
    def demo(
        drones: int, formation: str, world: str, seed: int, change: str | None,
        depth_rate: float | None, v_max: float | None, altitude_band: tuple[float, float] | None,
        out_dir: Path | None, view_port: int | None,
        onboard_sets: tuple[str, ...], sitl_sets: tuple[str, ...], secure: bool,
        lead_s: float, startup_timeout: float, as_json: bool, quiet: bool,
    ) -> None:  # fmt: skip
        """Fly the real stack on this machine: the mock fleet, one flight service per drone
        and this ground station, through a forest; print the result and write the report.
        Exits 0 only on success."""
        try:
            fc = parse_change(change)
        except ValueError as e:
            raise click.BadParameter(str(e), param_hint="--formation-change") from e
        cfg = DemoConfig(
            out_dir=out_dir if out_dir is not None else DemoConfig().out_dir,
            drones=drones, formation=formation, world=world, seed=seed, formation_change=fc,
            depth_rate_hz=depth_rate, v_max_m_s=v_max, view_port=view_port,
            altitude_band_m=altitude_band,
            onboard_sets=onboard_sets, sitl_sets=sitl_sets, startup_timeout_s=startup_timeout,
            secure=secure, lead_s=lead_s,
        )  # fmt: skip
        console = Console(quiet=quiet or as_json, highlight=False, stderr=True)
        logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(message)s")
        console.print(f"flight directory: {cfg.out_dir} (pid {os.getpid()})")
        columns = (
            TextColumn("{task.description}"),
            BarColumn(),
            TextColumn("{task.fields[info]}"),
            TimeElapsedColumn(),
        )
        with Progress(*columns, console=console, transient=True) as bar:
            task = bar.add_task("starting", total=1.0, info="")

            def progress(phase: str, info: dict[str, Any]) -> None:
                if "total_m" not in info:
                    bar.update(task, description=phase, info="")
                    return
                st = ", ".join(f"{k} {v}" for k, v in sorted(info["states"].items()))
                text = (
                    f"{info['done_m']:.1f}/{info['total_m']:.0f} m, e_sim {info['e_sim']:.4f}, "
                    f"min pair {info['min_pair_m']:.2f} m, collisions {info['collisions']} | {st}"
                )
                bar.update(
                    task,
                    description=phase,
                    total=info["total_m"],
                    completed=info["done_m"],
                    info=text,
                )

            try:
                result = run_demo(cfg, progress)
            except (DemoError, FormationError) as e:
                raise click.ClickException(str(e)) from e
            except KeyboardInterrupt:
                click.echo("interrupted: every process stopped", err=True)
                sys.exit(130)
        if as_json:
            click.echo(json.dumps(_json_safe(result)))
        else:
            click.echo(result_text(result))
        sys.exit(0 if result["success"] else 1)

    return demo


def _cpu_text(r: dict[str, Any]) -> str:
    """Where the run's CPU went (cores: CPU seconds over the wall time, start-up included): the
    flight services in all and their busiest threads, the mock; '' without the figures."""
    wall = r.get("wall_s")
    cpu = r.get("cpu_s") or {}
    if not cpu or not isinstance(wall, (int, float)) or not wall > 0.0:
        return ""
    services = sum(v for k, v in cpu.items() if k.startswith("drone"))
    n = sum(1 for k in cpu if k.startswith("drone"))
    threads = (r.get("cpu_threads_s") or {}).get("services") or {}
    top = ", ".join(f"{k} {v / wall:.2f}" for k, v in list(threads.items())[:6])
    text = f"CPU over the run ({wall:.0f} s, start-up included): {n} flight services "
    text += f"{services / wall:.2f} cores in all" + (f" (threads: {top})" if top else "")
    if "sitl" in cpu:
        text += f", mock {cpu['sitl'] / wall:.2f} core"
    return text + f"; this machine has {os.cpu_count()}"


def result_text(r: dict[str, Any]) -> str:
    def f(x: Any, spec: str = ".3f") -> str:
        return (
            "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, spec)
        )

    sp = r.get("setpoint_period_ms", {})
    lines = [
        f"{'SUCCESS' if r['success'] else 'FAILED'}"
        + (f": {r['error']}" if r.get("error") else ""),
        f"arrived: {'yes' if r['arrived'] else 'no'}; collisions reported by the mock: "
        f"{f(r['collisions'], 'd') if isinstance(r['collisions'], int) else '-'}",
        f"e_dist {f(r['e_dist_m'])} m, e_sim {f(r['e_sim'], '.4f')} (mean over the cluttered span)",
        f"min clearance (the mock's truth): body to obstacle "
        f"{f(r['min_obstacle_clearance_m'], '.2f')} m, between drone centres "
        f"{f(r['min_drone_distance_m'], '.2f')} m",
        f"flight time {f(r['flight_time_s'], '.1f')} s "
        f"(crossing {f(r['crossing_time_s'], '.1f')} s)",
        f"setpoint period: median {f(sp.get('median'), '.1f')} ms, "
        f"p99 {f(sp.get('p99'), '.1f')} ms, max {f(sp.get('max'), '.1f')} ms",
    ]
    mon = r.get("monitor")
    if mon:
        lines.append(
            f"safety monitors: {mon.get('brakes', 0)} braking stops in flight, "
            f"{mon.get('replans', 0)} looks (100 a second) that asked for a replan for a "
            f"conflict, {mon.get('shallow_replans', 0)} replans asked for an obstacle within the "
            "check's distance by less than the brake's slack"
        )
    dh = r.get("depth_holds")
    if dh:
        lines.append(
            f"depth: {dh.get('holds', 0)} holds for lost depth ({dh.get('map_lag_holds', 0)} "
            f"for a map over map_lag_s behind a live camera), {dh.get('map_lag_rides', 0)} "
            f"times the map lagged the camera past its timeout without a hold, "
            f"{dh.get('frames_missed', 0)} frames the mapping never saw"
        )
    ref = r.get("plan_refusals")
    if ref and ref.get("attempts"):
        from gcs.report import refusals_text

        lines.append(refusals_text(ref))
    guard = r.get("stream_guard_stops") or {}
    if any(guard.values()):
        lines.append(
            f"setpoint guards: {guard.get('stream_guard_stops', 0)} stops along the plan while "
            f"a safety monitor was silent, {guard.get('stream_gap_stops', 0)} stops from the "
            "last setpoint after a pause of the stream (a starved or hung flight service)"
        )
    kernels = r.get("kernels_after_ready")
    if kernels:
        lines.append(
            f"warm-up: {kernels} numba kernels compiled or loaded in flight, after READY (the "
            "services' logs name them; each held a thread meanwhile)"
        )
    cpu_line = _cpu_text(r)
    if cpu_line:
        lines.append(cpu_line)
    peer = r.get("peer_latency_ms") or {}
    if peer:
        tgt = peer.get("target_ms", PEER_LATENCY_TARGET_MS)
        met = peer.get("meets_target")
        lines.append(
            f"peer trajectory latency (the target's definition: publish -> each planner's "
            f"inbox, {peer.get('count', 0)} samples on {len(peer.get('per_drone', {}))} "
            f"services): median {f(peer.get('median'), '.2f')} ms, p99 "
            f"{f(peer.get('p99'), '.2f')} ms, max {f(peer.get('max'), '.2f')} ms; target median "
            f"< {tgt['median']:g} ms, p99 < {tgt['p99']:g} ms: "
            + ("-" if met is None else "met" if met else "NOT met")
        )
    lat = r.get("bus_latency_ms") or {}
    if lat:
        lines.append(
            f"ground station latency (drone trajectory -> ground station inbox, not the "
            f"target's definition, {lat.get('count', 0)} messages): median "
            f"{f(lat.get('median'), '.2f')} ms, p99 {f(lat.get('p99'), '.2f')} ms, max "
            f"{f(lat.get('max'), '.2f')} ms"
        )
    sec = r.get("security") or {}
    if sec.get("signing"):
        sg = sec.get("signing_checks", {})
        bus = sec.get("bus_checks", {})
        rx = sum(v.get("messages_received", 0) for v in sg.get("services", {}).values())
        vrx = sum(v.get("rx_messages", 0) for v in sg.get("vehicles", {}).values())

        def yes(x: Any) -> str:
            return "yes" if x else "NO"

        refused = bus.get("plain_tcp_session_refused") and bus.get(
            "session_without_certificate_refused"
        )
        idents = ", ".join(bus.get("link_identities", [])) or "-"
        lines.append(
            f"security: MAVLink 2 signing on (signed only: {yes(sg.get('signed_only'))}; {rx} "
            f"frames to the services, {vrx} to the vehicles), Zenoh mutual TLS + access control "
            f"on (TLS links only: {yes(bus.get('link_locators_tls_only'))}, identities {idents}; "
            f"plain and certificate-less sessions refused: {yes(refused)})"
        )
    else:
        lines.append("security: off (MAVLink unsigned, swarm bus plain TCP; --secure turns it on)")
    if r.get("formation_change_reached_s") is not None:
        lines.append(
            f"new formation reached after {f(r['formation_change_reached_s'], '.1f')} s "
            f"({f(r.get('formation_change_reached_after_switch_s'), '.1f')} s after the "
            "common switch time)"
        )
    lines.append(f"flight directory: {r['flight_dir']} (report in report/)")
    return "\n".join(lines)


demo = demo_command()
