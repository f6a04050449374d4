"""Translational quadrotor model with a PX4-like position / velocity / acceleration controller.

Pure numerics (no sockets, clocks or files), ENU world frame, SI units, vectorised over the
fleet in one numba kernel. Per vehicle and substep ``h``:

- controller (PX4's multicopter position control structure): per axis, a position setpoint
  gives ``v_cmd = K_p (p_sp - p_est) + v_ff``; else a velocity setpoint is ``v_cmd``; velocity
  limits (horizontal norm, climb, descent); then ``a_cmd = K_vp e_v + I - K_vd a + a_ff`` with
  ``e_v = v_cmd - v`` and the integrator ``I`` (clamped); an axis without position or velocity is
  driven by its acceleration setpoint alone;
- thrust: specific thrust ``f = a_cmd + g e_z``; vertical part clamped to the thrust range
  (``g / hover_thrust * [thrust_min, thrust_max]``), horizontal part to the tilt limit and the
  remaining thrust, horizontal acceleration to ``acc_xy_max``;
- the attitude and motors follow ``f`` with a first-order lag ``tau_thrust_s``;
- ``a = f_act - g e_z - drag v + w`` with ``w`` an Ornstein-Uhlenbeck wind gust;
- ground contact: a solid plane at each vehicle's ground height; on it the vehicle sticks
  (no sliding) until its thrust exceeds its weight; the vertical speed at touchdown is recorded
  as the impact speed;
- yaw: proportional tracking of a yaw setpoint (or a yaw-rate setpoint), rate limited, lagged;
- the state estimate the controller sees (and MAVLink reports) is the true position plus an
  Ornstein-Uhlenbeck error (an EKF's slowly wandering position error).

Randomness comes only from the ``noise`` array the caller draws from a seeded generator, so a
run is reproducible from its seed and its inputs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np
from numba import njit

# ---- state columns (N, NS) -----------------------------------------------------------------
S_P = 0  # 0..2 true position ENU [m]
S_V = 3  # 3..5 true velocity ENU [m/s]
S_F = 6  # 6..8 actual specific thrust ENU [m/s^2]
S_YAW = 9  # yaw ENU [rad], from east counter-clockwise
S_YAWRATE = 10  # [rad/s]
S_I = 11  # 11..13 velocity-loop integrator [m/s^2]
S_W = 14  # 14..16 wind gust acceleration [m/s^2]
S_E = 17  # 17..19 position estimate error [m]
S_GROUND = 20  # 1.0 while in contact with the ground
S_A = 21  # 21..23 true acceleration ENU [m/s^2] (last substep)
S_IMPACT = 24  # largest touchdown speed since the caller last reset it [m/s]
S_FCMD = 25  # 25..27 commanded specific thrust ENU [m/s^2]
S_VCMD = 28  # 28..30 velocity command of the last substep (NaN on acceleration-only axes)
NS = 31

# ---- command columns (N, NC); NaN = not set -------------------------------------------------
C_POS = 0  # 0..2 position setpoint ENU [m]
C_VEL = 3  # 3..5 velocity setpoint (feed-forward with a position) ENU [m/s]
C_ACC = 6  # 6..8 acceleration feed-forward / setpoint ENU [m/s^2]
C_YAW = 9  # yaw setpoint ENU [rad]
C_YAWRATE = 10  # yaw-rate setpoint [rad/s]
C_MOTOR = 11  # 0 motors off, 1 idle (spinning, minimum thrust), 2 controlled
NC = 12

MOTOR_OFF = 0.0
MOTOR_IDLE = 1.0
MOTOR_RUN = 2.0

# ---- attitude outputs (N, NA) ---------------------------------------------------------------
A_R = 0  # 0..8 rotation FLU body -> ENU world, row-major
A_OMEGA = 9  # 9..11 body rates FLU [rad/s]
A_SPECIFIC = 12  # 12..14 specific force in body FLU [m/s^2] (what an accelerometer reads)
A_THRUST = 15  # normalised collective thrust 0..1
NA = 16


@dataclass(frozen=True)
class DynamicsParams:
    """Vehicle model and controller gains; the defaults are PX4's multicopter defaults
    (``MPC_*``) for a small quadrotor with a thrust-to-weight ratio of 2."""

    g_m_s2: float = 9.80665
    hover_thrust: float = 0.5  # MPC_THR_HOVER
    thrust_min: float = 0.12  # MPC_THR_MIN
    thrust_max: float = 1.0  # MPC_THR_MAX
    tilt_max_deg: float = 45.0  # MPC_TILTMAX_AIR
    acc_xy_max_m_s2: float = 8.0
    v_xy_max_m_s: float = 12.0  # MPC_XY_VEL_MAX
    v_up_max_m_s: float = 3.0  # MPC_Z_VEL_MAX_UP
    v_down_max_m_s: float = 1.5  # MPC_Z_VEL_MAX_DN
    pos_gain_xy: float = 0.95  # MPC_XY_P
    pos_gain_z: float = 1.0  # MPC_Z_P
    vel_p_xy: float = 1.8  # MPC_XY_VEL_P_ACC
    vel_i_xy: float = 0.4  # MPC_XY_VEL_I_ACC
    vel_d_xy: float = 0.2  # MPC_XY_VEL_D_ACC
    vel_p_z: float = 4.0  # MPC_Z_VEL_P_ACC
    vel_i_z: float = 2.0  # MPC_Z_VEL_I_ACC
    vel_d_z: float = 0.0  # MPC_Z_VEL_D_ACC
    integrator_max_m_s2: float = 4.0
    tau_thrust_s: float = 0.08  # attitude loop + motor response
    drag_per_s: float = 0.3  # linear drag coefficient (acceleration per unit speed)
    yaw_gain: float = 2.8  # MC_YAW_P
    yawrate_max_deg_s: float = 200.0  # MC_YAWRATE_MAX
    tau_yaw_s: float = 0.1
    wind_sigma_m_s2: float = 0.05  # gust acceleration, stationary standard deviation
    wind_tau_s: float = 2.0
    pos_noise_sigma_m: float = 0.01  # estimate error, stationary standard deviation
    pos_noise_tau_s: float = 2.0
    max_substep_s: float = 0.0025

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if not math.isfinite(v):
                raise ValueError(f"{f.name} must be finite")
        positive = (
            "g_m_s2",
            "hover_thrust",
            "thrust_max",
            "tau_thrust_s",
            "tau_yaw_s",
            "wind_tau_s",
            "pos_noise_tau_s",
            "max_substep_s",
            "v_xy_max_m_s",
            "v_up_max_m_s",
            "v_down_max_m_s",
            "acc_xy_max_m_s2",
        )
        for name in positive:
            if getattr(self, name) <= 0.0:
                raise ValueError(f"{name} must be > 0")
        if not 0.0 <= self.thrust_min < self.hover_thrust < self.thrust_max:
            raise ValueError("need 0 <= thrust_min < hover_thrust < thrust_max")
        if not 0.0 < self.tilt_max_deg < 90.0:
            raise ValueError("tilt_max_deg must be in (0, 90)")
        for name in ("wind_sigma_m_s2", "pos_noise_sigma_m", "drag_per_s"):
            if getattr(self, name) < 0.0:
                raise ValueError(f"{name} must be >= 0")

    def as_array(self) -> np.ndarray:
        """The kernel's parameter vector (order: ``_PARAM_ORDER``)."""
        return np.array([float(getattr(self, n)) for n in _PARAM_ORDER])

    @property
    def f_max_m_s2(self) -> float:
        """Largest specific thrust (full throttle)."""
        return self.g_m_s2 / self.hover_thrust * self.thrust_max


_PARAM_ORDER = tuple(f.name for f in fields(DynamicsParams))
_PI = {name: i for i, name in enumerate(_PARAM_ORDER)}
P_G = _PI["g_m_s2"]
P_HOVER = _PI["hover_thrust"]
P_TMIN = _PI["thrust_min"]
P_TMAX = _PI["thrust_max"]
P_TILT = _PI["tilt_max_deg"]
P_AXY = _PI["acc_xy_max_m_s2"]
P_VXY = _PI["v_xy_max_m_s"]
P_VUP = _PI["v_up_max_m_s"]
P_VDN = _PI["v_down_max_m_s"]
P_KPXY = _PI["pos_gain_xy"]
P_KPZ = _PI["pos_gain_z"]
P_KVPXY = _PI["vel_p_xy"]
P_KVIXY = _PI["vel_i_xy"]
P_KVDXY = _PI["vel_d_xy"]
P_KVPZ = _PI["vel_p_z"]
P_KVIZ = _PI["vel_i_z"]
P_KVDZ = _PI["vel_d_z"]
P_IMAX = _PI["integrator_max_m_s2"]
P_TAUF = _PI["tau_thrust_s"]
P_DRAG = _PI["drag_per_s"]
P_KYAW = _PI["yaw_gain"]
P_RMAX = _PI["yawrate_max_deg_s"]
P_TAUY = _PI["tau_yaw_s"]
P_WSIG = _PI["wind_sigma_m_s2"]
P_WTAU = _PI["wind_tau_s"]
P_ESIG = _PI["pos_noise_sigma_m"]
P_ETAU = _PI["pos_noise_tau_s"]
P_HMAX = _PI["max_substep_s"]

NOISE_PER_SUBSTEP = 6  # 3 wind + 3 estimate-error standard normals


def initial_state(
    positions_enu_m: np.ndarray, yaws_enu_rad: np.ndarray | None = None
) -> np.ndarray:
    """State array (N, NS) of vehicles at rest on the ground at ``positions_enu_m`` (N, 3)."""
    p = np.asarray(positions_enu_m, dtype=np.float64).reshape(-1, 3)
    s = np.zeros((p.shape[0], NS))
    s[:, S_P : S_P + 3] = p
    if yaws_enu_rad is not None:
        s[:, S_YAW] = np.asarray(yaws_enu_rad, dtype=np.float64).reshape(-1)
    s[:, S_GROUND] = 1.0
    s[:, S_VCMD : S_VCMD + 3] = np.nan
    return s


def idle_commands(n: int) -> np.ndarray:
    """Command array (N, NC): nothing set, motors off."""
    c = np.full((n, NC), np.nan)
    c[:, C_MOTOR] = MOTOR_OFF
    return c


def substeps(dt_s: float, params: DynamicsParams) -> int:
    """Number of substeps the kernel takes for a step of ``dt_s``."""
    return max(1, int(math.ceil(dt_s / params.max_substep_s - 1e-9)))


@njit(cache=True, nogil=True)
def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@njit(cache=True, nogil=True)
def step_fleet(
    state: np.ndarray,
    cmd: np.ndarray,
    prm: np.ndarray,
    ground_z: np.ndarray,
    dt: float,
    noise: np.ndarray,
) -> None:
    """Advance every vehicle by ``dt`` in ``noise.shape[1]`` equal substeps, in place.

    state (N, NS), cmd (N, NC), prm (as ``DynamicsParams.as_array``), ground_z (N,),
    noise (N, K, NOISE_PER_SUBSTEP) standard normals for K substeps.
    """
    n = state.shape[0]
    nsub = noise.shape[1]
    h = dt / nsub
    g = prm[P_G]
    f_scale = g / prm[P_HOVER]
    f_min = f_scale * prm[P_TMIN]
    f_max = f_scale * prm[P_TMAX]
    tan_tilt = math.tan(math.radians(prm[P_TILT]))
    kf = 1.0 - math.exp(-h / prm[P_TAUF])
    ky = 1.0 - math.exp(-h / prm[P_TAUY])
    rmax = math.radians(prm[P_RMAX])
    w_decay = h / prm[P_WTAU]
    w_amp = prm[P_WSIG] * math.sqrt(2.0 * h / prm[P_WTAU])
    e_decay = h / prm[P_ETAU]
    e_amp = prm[P_ESIG] * math.sqrt(2.0 * h / prm[P_ETAU])
    kp = np.empty(3)
    kvp = np.empty(3)
    kvi = np.empty(3)
    kvd = np.empty(3)
    vc = np.empty(3)
    acc = np.empty(3)
    f = np.empty(3)
    for i in range(n):
        s = state[i]
        c = cmd[i]
        kp[0] = prm[P_KPXY]
        kp[1] = prm[P_KPXY]
        kp[2] = prm[P_KPZ]
        kvp[0] = prm[P_KVPXY]
        kvp[1] = prm[P_KVPXY]
        kvp[2] = prm[P_KVPZ]
        kvi[0] = prm[P_KVIXY]
        kvi[1] = prm[P_KVIXY]
        kvi[2] = prm[P_KVIZ]
        kvd[0] = prm[P_KVDXY]
        kvd[1] = prm[P_KVDXY]
        kvd[2] = prm[P_KVDZ]
        motor = c[C_MOTOR]
        for k in range(nsub):
            # ---- controller --------------------------------------------------------------
            if motor > 1.5:
                for a in range(3):
                    ps = c[C_POS + a]
                    vs = c[C_VEL + a]
                    if not math.isnan(ps):
                        p_est = s[S_P + a] + s[S_E + a]
                        vc[a] = kp[a] * (ps - p_est) + (0.0 if math.isnan(vs) else vs)
                    else:
                        vc[a] = vs  # NaN when the axis is acceleration-only
                if not math.isnan(vc[0]) and not math.isnan(vc[1]):
                    nxy = math.sqrt(vc[0] * vc[0] + vc[1] * vc[1])
                    if nxy > prm[P_VXY]:
                        vc[0] *= prm[P_VXY] / nxy
                        vc[1] *= prm[P_VXY] / nxy
                else:
                    for a in range(2):
                        if not math.isnan(vc[a]):
                            vc[a] = min(max(vc[a], -prm[P_VXY]), prm[P_VXY])
                if not math.isnan(vc[2]):
                    vc[2] = min(max(vc[2], -prm[P_VDN]), prm[P_VUP])
                for a in range(3):
                    aff = c[C_ACC + a]
                    if math.isnan(aff):
                        aff = 0.0
                    if not math.isnan(vc[a]):
                        ev = vc[a] - s[S_V + a]
                        acc[a] = kvp[a] * ev + s[S_I + a] - kvd[a] * s[S_A + a] + aff
                        s[S_I + a] = min(
                            max(s[S_I + a] + kvi[a] * ev * h, -prm[P_IMAX]), prm[P_IMAX]
                        )
                    else:
                        acc[a] = aff
                        s[S_I + a] = 0.0
                    s[S_VCMD + a] = vc[a]
                axy = math.sqrt(acc[0] * acc[0] + acc[1] * acc[1])
                if axy > prm[P_AXY]:
                    acc[0] *= prm[P_AXY] / axy
                    acc[1] *= prm[P_AXY] / axy
                f[2] = min(max(acc[2] + g, f_min), f_max)
                fxy_max = min(f[2] * tan_tilt, math.sqrt(max(f_max * f_max - f[2] * f[2], 0.0)))
                nxy = math.sqrt(acc[0] * acc[0] + acc[1] * acc[1])
                scale = 1.0 if nxy <= fxy_max else fxy_max / nxy
                f[0] = acc[0] * scale
                f[1] = acc[1] * scale
            else:
                f[0] = 0.0
                f[1] = 0.0
                f[2] = f_min if motor > 0.5 else 0.0
                for a in range(3):
                    s[S_I + a] = 0.0
                    s[S_VCMD + a] = math.nan
            for a in range(3):
                s[S_FCMD + a] = f[a]
                s[S_F + a] += (f[a] - s[S_F + a]) * kf
            # ---- disturbances and estimate error (Ornstein-Uhlenbeck) ----------------------
            for a in range(3):
                s[S_W + a] += -s[S_W + a] * w_decay + w_amp * noise[i, k, a]
                s[S_E + a] += -s[S_E + a] * e_decay + e_amp * noise[i, k, 3 + a]
            # ---- translational dynamics ----------------------------------------------------
            gz = ground_z[i]
            lift = s[S_F + 2] + s[S_W + 2] - g
            if s[S_GROUND] > 0.5 and lift <= 0.0:
                for a in range(3):
                    s[S_V + a] = 0.0
                    s[S_A + a] = 0.0
                s[S_P + 2] = gz
            else:
                for a in range(3):
                    acc_a = s[S_F + a] + s[S_W + a] - prm[P_DRAG] * s[S_V + a]
                    if a == 2:
                        acc_a -= g
                    s[S_A + a] = acc_a
                    s[S_V + a] += acc_a * h
                    s[S_P + a] += s[S_V + a] * h
                if s[S_P + 2] <= gz:
                    if s[S_V + 2] < 0.0:
                        s[S_IMPACT] = max(s[S_IMPACT], -s[S_V + 2])
                    s[S_P + 2] = gz
                    for a in range(3):
                        s[S_V + a] = 0.0
                        s[S_A + a] = 0.0
                    s[S_GROUND] = 1.0
                elif s[S_P + 2] > gz + 1e-4:
                    s[S_GROUND] = 0.0
            # ---- yaw -----------------------------------------------------------------------
            if motor > 1.5 and s[S_GROUND] < 0.5:
                ys = c[C_YAW]
                if not math.isnan(ys):
                    r = prm[P_KYAW] * _wrap(ys - s[S_YAW])
                elif not math.isnan(c[C_YAWRATE]):
                    r = c[C_YAWRATE]
                else:
                    r = 0.0
                r = min(max(r, -rmax), rmax)
                s[S_YAWRATE] += (r - s[S_YAWRATE]) * ky
            else:
                s[S_YAWRATE] = 0.0
            s[S_YAW] = _wrap(s[S_YAW] + s[S_YAWRATE] * h)


@njit(cache=True, nogil=True)
def rotation_from_thrust(fx: float, fy: float, fz: float, yaw: float) -> np.ndarray:
    """Rotation FLU body -> ENU world (3, 3) of a vehicle whose body z axis points along the
    specific thrust ``(fx, fy, fz)`` (vertical when it is ~0 or points down) and whose body x
    axis is the heading ``yaw`` (ENU) projected onto the plane normal to it."""
    fn = math.sqrt(fx * fx + fy * fy + fz * fz)
    if fn < 1e-3 or fz <= 0.0:
        zx, zy, zz = 0.0, 0.0, 1.0
    else:
        zx, zy, zz = fx / fn, fy / fn, fz / fn
    cy = math.cos(yaw)
    sy = math.sin(yaw)
    # y_b = z_b x heading, normalised; x_b = y_b x z_b
    yx = -zz * sy
    yy = zz * cy
    yz = zx * sy - zy * cy
    yn = math.sqrt(yx * yx + yy * yy + yz * yz)
    yx /= yn
    yy /= yn
    yz /= yn
    r = np.empty((3, 3))
    r[0, 0] = yy * zz - yz * zy
    r[1, 0] = yz * zx - yx * zz
    r[2, 0] = yx * zy - yy * zx
    r[0, 1], r[1, 1], r[2, 1] = yx, yy, yz
    r[0, 2], r[1, 2], r[2, 2] = zx, zy, zz
    return r


@njit(cache=True, nogil=True)
def attitude_fleet(
    state: np.ndarray, prm: np.ndarray, r_prev: np.ndarray, dt: float, out: np.ndarray
) -> None:
    """Attitude implied by the thrust direction and yaw, with body rates and specific force.

    The body z axis points along the actual specific thrust (vertical when it is ~0), the body
    x axis is the heading projected onto the plane normal to it. ``r_prev`` (N, 9) holds the
    previous rotations (row-major) and is updated; body rates are the finite difference over
    ``dt`` (zero when ``dt`` <= 0). out (N, NA).
    """
    n = state.shape[0]
    g = prm[P_G]
    f_max = g / prm[P_HOVER] * prm[P_TMAX]
    r = np.empty((3, 3))
    rp = np.empty((3, 3))
    for i in range(n):
        s = state[i]
        r[:, :] = rotation_from_thrust(s[S_F], s[S_F + 1], s[S_F + 2], s[S_YAW])
        fz = s[S_F + 2]
        fn = math.sqrt(s[S_F] ** 2 + s[S_F + 1] ** 2 + fz * fz)
        for a in range(3):
            for b in range(3):
                rp[a, b] = r_prev[i, 3 * a + b]
                out[i, A_R + 3 * a + b] = r[a, b]
        # body rates: vee of the skew part of R_prev^T R over dt
        if dt > 0.0 and rp[0, 0] + rp[1, 1] + rp[2, 2] != 0.0:
            m = rp.T @ r
            out[i, A_OMEGA] = 0.5 * (m[2, 1] - m[1, 2]) / dt
            out[i, A_OMEGA + 1] = 0.5 * (m[0, 2] - m[2, 0]) / dt
            out[i, A_OMEGA + 2] = 0.5 * (m[1, 0] - m[0, 1]) / dt
        else:
            out[i, A_OMEGA] = 0.0
            out[i, A_OMEGA + 1] = 0.0
            out[i, A_OMEGA + 2] = 0.0
        for a in range(3):
            for b in range(3):
                r_prev[i, 3 * a + b] = r[a, b]
        # specific force (acceleration minus gravity) in the body frame
        sfx = s[S_A]
        sfy = s[S_A + 1]
        sfz = s[S_A + 2] + g
        out[i, A_SPECIFIC] = r[0, 0] * sfx + r[1, 0] * sfy + r[2, 0] * sfz
        out[i, A_SPECIFIC + 1] = r[0, 1] * sfx + r[1, 1] * sfy + r[2, 1] * sfz
        out[i, A_SPECIFIC + 2] = r[0, 2] * sfx + r[1, 2] * sfy + r[2, 2] * sfz
        out[i, A_THRUST] = min(max(fn / f_max, 0.0), 1.0) * (1.0 if fz > 0.0 else 0.0)


@njit(cache=True, nogil=True)
def close_pairs(pos: np.ndarray, threshold: float, out: np.ndarray) -> tuple[int, float]:
    """Vehicle pairs (a < b) closer than ``threshold``: written to ``out`` (M, 2) as indices
    (at most M); returns their number and the smallest distance of any pair (inf if < 2)."""
    n = pos.shape[0]
    count = 0
    d_min = math.inf
    for a in range(n):
        for b in range(a + 1, n):
            dx = pos[a, 0] - pos[b, 0]
            dy = pos[a, 1] - pos[b, 1]
            dz = pos[a, 2] - pos[b, 2]
            d = math.sqrt(dx * dx + dy * dy + dz * dz)
            if d < d_min:
                d_min = d
            if d < threshold and count < out.shape[0]:
                out[count, 0] = a
                out[count, 1] = b
                count += 1
    return count, d_min


# ---------------------------------------------------------------------------------------------
# Offline helpers: the same kernel driven without any autopilot or network


def simulate_setpoint(
    params: DynamicsParams,
    start_enu_m: np.ndarray,
    command: np.ndarray,
    duration_s: float,
    dt_s: float = 0.01,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Fly one vehicle, already hovering at ``start_enu_m``, on a constant ``command`` (NC,).

    Returns times (K,) and true positions (K, 3) sampled every ``dt_s`` (first row: start).
    The vehicle starts in trimmed hover (thrust = weight, integrators zero, in the air).
    """
    st = initial_state(np.asarray(start_enu_m, dtype=np.float64).reshape(1, 3))
    st[0, S_GROUND] = 0.0
    st[0, S_F + 2] = params.g_m_s2
    cmd = np.asarray(command, dtype=np.float64).reshape(1, NC).copy()
    prm = params.as_array()
    ground = np.array([-1.0e9])
    nsub = substeps(dt_s, params)
    rng = np.random.default_rng(seed)
    k_steps = int(round(duration_s / dt_s))
    t = np.arange(k_steps + 1) * dt_s
    p = np.empty((k_steps + 1, 3))
    p[0] = st[0, S_P : S_P + 3]
    for k in range(k_steps):
        noise = rng.standard_normal((1, nsub, NOISE_PER_SUBSTEP))
        step_fleet(st, cmd, prm, ground, dt_s, noise)
        p[k + 1] = st[0, S_P : S_P + 3]
    return t, p


def step_metrics(
    t_s: np.ndarray, y: np.ndarray, y0: float, y1: float, settle_band: float = 0.05
) -> dict[str, float]:
    """Rise time (10 % -> 90 %), overshoot (fraction of the step), settling time into
    ``settle_band`` of the step, and the final error, of a response ``y(t)`` from y0 to y1.

    Times are measured from ``t_s[0]``; NaN where the response never gets there.
    """
    t = np.asarray(t_s, dtype=np.float64)
    yy = np.asarray(y, dtype=np.float64)
    step = y1 - y0
    if step == 0.0:
        raise ValueError("step of zero size")
    frac = (yy - y0) / step
    t0 = t[0]

    def first_reach(level: float) -> float:
        idx = np.flatnonzero(frac >= level)
        if idx.size == 0:
            return math.nan
        j = int(idx[0])
        if j == 0:
            return float(t[0] - t0)
        # linear interpolation between samples
        a, b = frac[j - 1], frac[j]
        w = (level - a) / (b - a) if b != a else 1.0
        return float(t[j - 1] + w * (t[j] - t[j - 1]) - t0)

    t10 = first_reach(0.1)
    t90 = first_reach(0.9)
    outside = np.flatnonzero(np.abs(frac - 1.0) > settle_band)
    if outside.size == 0:
        t_settle = 0.0
    elif outside[-1] == frac.size - 1:
        t_settle = math.nan
    else:
        t_settle = float(t[outside[-1] + 1] - t0)
    return {
        "rise_time_s": t90 - t10,
        "t10_s": t10,
        "t90_s": t90,
        "overshoot_fraction": float(max(np.max(frac) - 1.0, 0.0)),
        "settling_time_s": t_settle,
        "final_error_m": float(abs(yy[-1] - y1)),
    }
