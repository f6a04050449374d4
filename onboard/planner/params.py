"""Planner parameters: one frozen dataclass, every field documented with its meaning and default."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from onboard.planner.lbfgs import LbfgsParams

FORMATION_PENALTIES = ("linear", "cubic", "linear-unit", "relative")
SWARM_TARGETS = ("own-goal", "centroid", "slowest")
FRESH_STARTS = ("never", "line", "astar")


BRAKE_REFERENCE_S = 1.0
"""The default of ``PlannerParams.brake_reference_s``."""


@dataclass(frozen=True)
class PlannerParams:
    """Weights and limits of the spatial-temporal optimisation (paper Eq. 10) and its driver."""

    # --- trajectory shape -------------------------------------------------------------------
    v_max_m_s: float = 0.5
    """Speed limit of J_d (and the cruise speed of the initial guess)."""
    a_max_m_s2: float = 3.0
    """Acceleration limit of J_d."""
    j_max_m_s3: float = 20.0
    """Jerk limit of J_d (the public code has none; the paper lists it)."""
    horizon_m: float = 7.5
    """Planning horizon: the local target lies this far along the way to the goal."""
    piece_length_m: float = 1.8
    """Approximate length of one MINCO piece of the initial guess (sets the piece count M)."""
    max_pieces: int = 8
    """Upper bound on M."""
    kappa: int = 8
    """Constraint points per piece (kappa_i in the paper); kappa + 1 samples including ends."""

    # --- cost weights (lambda of Eq. 10) ------------------------------------------------------
    w_time: float = 40.0
    """J_t: weight of the total duration."""
    w_obstacle: float = 1.0e8
    """J_o: weight of max(d_thr - d, 0)^3 over constraint points. Short and steep (with
    ``obstacle_clearance_m`` 0.34), where the public code has 5e4 from 0.5 m (ours was 5e4 from
    0.6 m): the soft cubic let the formation pull win down to the safety check (every table
    flight passed a trunk at 0.220-0.245 m, the optimiser's own solutions, no refusal), and a
    longer range moves every drone off its slot around every trunk. With the check at 0.3 m:
    5e4 from 0.6 m gave medium e_sim 0.0293; 2e5 from 0.6: 0.0165; 1e6 from 0.45: 0.0119; 1e8
    from 0.36: 0.0100; 1e8 from 0.34: 0.0092 (0.0088 at the old 0.22 m margin; BENCHMARKS.md
    section 8, twelfth session)."""
    obstacle_clearance_m: float = 0.34
    """d_thr of J_o: distance to obstacle surfaces below which points are penalised; a little
    above ``check_obstacle_m`` so that the check is a last resort. Also the A* retries' first
    clearance (``astar_ladder_m``)."""
    w_swarm: float = 5.0e4
    """J_r: weight of max(D_r^2 - d^2, 0)^3 against every peer at the same global time."""
    swarm_clearance_m: float = 0.75
    """D_r of J_r, centre to centre."""
    swarm_z_scale: float = 0.5
    """Vertical separations count this much in J_r's distance (downwash: z counts half)."""
    w_feasibility: float = 1.0e8
    """J_d: weight of the velocity, acceleration and jerk limit penalties."""
    limit_margin: float = 0.97
    """J_d penalises speed, acceleration and jerk above this fraction of their limits: a soft
    penalty balances the other terms slightly past where it starts, so a margin below 1 keeps
    the flown values within the limits without a stiff weight. Table (3 x 20 forests, 0.5 m/s):
    margin 1 flies at most 0.518 / 0.519 / 0.522 m/s, 0.97 at most 0.503 / 0.513 / 0.510 m/s
    with mean e_sim 0.0107 / 0.0209 / 0.0218 -> 0.0110 / 0.0166 / 0.0282 and flights 2-3 s
    longer. 0.97 is part of the default set of 2026-11-24 (see ``lead_slowdown_m``)."""
    w_limit_hard: float = 1.0e10
    """J_d's steep part: the same penalty with this weight beyond the limits themselves (not
    their ``limit_margin`` fraction), only when ``w_feasibility`` is on. The soft part alone
    lets a strong pull (the formation, an A* retry's way) carry a plan a few per cent over the
    limit: table (3 x 20 forests, 0.5 m/s) top speed 0.513 / 0.521 / 0.516 m/s with 0, 0.503 /
    0.503 / 0.506 with 1e10 (0.503 / 0.503 / 0.504 with 1e12), mean e_sim 0.0034 / 0.0078 /
    0.0152 -> 0.0038 / 0.0081 / 0.0133, flight times unchanged (BENCHMARKS section 8)."""
    speed_cap_frac: float = 1.015
    """A plan the safety check accepts whose speed (sampled, ``kernels.peak_speed``) exceeds
    this fraction of ``v_max_m_s`` is solved again from there on ``Problem.cap_prob`` (twice
    the constraint points, J_d's steep part 100 times stiffer), and the new plan is flown if
    it is slower and the check accepts it outright (0: off; while re-forming
    ``reform_speed_cap_frac`` instead). J_d is a penalty sampled at the
    constraint points: in a chain of shape recovery's 0.1 s replans each plan kept a little of
    the last one's overshoot ahead of it, and the formation's pull carried forest-dense seed
    200 to 0.5112 m/s, 2.2 % over; every setting of the weights tried before moved other
    flights over instead. ``bench table`` (3 x 3 x 20, AMD host): top speed at most 0.5112 ->
    0.5074 m/s, means 0.0023 / 0.0036 / 0.0074 -> 0.0023 / 0.0037 / 0.0073 seeded, no trial
    over 0.02 either way. At 1.01 the cap acted in up to 197 plans of a flight (each solved
    down to ~0.501 m/s) and two unseen dense forests folded (0.0323, 0.0587); at 1.015 it acts
    in a few, and a flight within the cap flies as before to the bit (BENCHMARKS.md section 8,
    nineteenth session)."""
    pace_floor_frac: float = 0.5
    """J_t's pace floor, where the local target is the drone's own goal (the swarm within
    ``horizon_m`` of its goals): a plan that takes longer than the straight distance to it at
    this fraction of the speed limit, plus the time to brake from the start's speed and
    ``pace_slack_s``, pays ``w_pace`` per s^2 beyond. 0: off. The time term is linear and the
    formation term integrates over the plan's duration, so drones that follow each other's
    plans keep their shape at any common pace; near the goals, where the plan ends at rest,
    nothing anchors that pace, and swarms crawled: ``bench hidden --outage-s 0`` (three
    drones, two swapping sides over 11 m at 1 m/s), seed 18: two drones 5 m short of their
    goals planned 34 s for 6 m and backed away for 10 s, the flight 47.3 s. Mid-flight the
    plan's end is passed at speed (``target_speed_frac``) and the floor is off. At 0.5 (40
    seeds): flight median 28.1 -> 25.0 s, the longest 47.3 -> 38.2 s; ``bench table`` (3 x 20)
    the same means and flights (0.0028 / 0.0046 / 0.0099); the demo's twin, seeds 1-12: the
    new shape within 10 s in 10 of 12 either way; the fault trials 582 of 587 home against
    583 (seed 1000, trial 69 either way) and 589 of 594 against 577 (seed 2000); BENCHMARKS.md
    section 10, seventeenth session. On everywhere
    (with the lead's speed limit), not kept: the fault trials 578 of 587."""
    pace_slack_s: float = 2.0
    """The pace floor's slack [s]."""
    w_pace: float = 1.0e3
    """The pace floor's weight [per s^2]."""
    w_uniform: float = 1.0e3
    """J_u: weight of the variance of squared distances between consecutive constraint points."""
    w_formation: float = 1.5e5
    """J_f: weight of the formation penalty (about 1e7 suits 'cubic'). 1e5 (was 3e4) is part of
    the default set of 2026-11-24 (see ``lead_slowdown_m``); alone it breaks the speed limit
    (0.539 m/s), with ``limit_margin`` 0.97 it keeps it within 2-3 %. 1.5e5 since 2026-12-04,
    with the stiffer refinement (``refine_kappa_factor``): the reference forests' e_sim 0.00201
    -> 0.00164 (four draws), the three table sets and the mapped flights held, the fault trials
    alike (two runs of 100; BENCHMARKS.md section 8). The flight service keeps 1e5
    (``config/onboard.yaml``): on the real stack the new shape came within 10 s of a formation
    change in 16 of 20 flights at 1.5e5 against 19 of 20 at 1e5 (section 10, 2026-12-04)."""
    formation_stride: int = 2
    """J_f is evaluated on every formation_stride-th constraint point (kappa must divide)."""
    target_speed_frac: float = 0.5
    """The local target's end velocity: this fraction of J_d's speed limit (after the lead
    slow-down), along the way from the target to the goal, when the goal lies beyond the target
    by more than the braking distance; 0: every plan ends at rest at its target. The public
    EGO-family planners end a local plan at the global path's speed there. At rest, every
    plan a drone broadcasts slows down toward its end, each drone follows its peers' slowing
    plans through the formation term, and the swarm's common speed decays: the triangle-3
    flight through forest-small slowed to 0.05 m/s and never arrived (36 s without the
    formation term); with 0.5 it arrives in 64.5 s, with 1.0 in 45.6 s. The table (3 x 20,
    exact distances) at 0 / 0.5 / 1.0: mean e_sim 0.0047 / 0.0034 / 0.0067 (sparse), 0.0094 /
    0.0078 / 0.0106 (medium), 0.0184 / 0.0152 / 0.0195 (dense), flights 91-102 / 108-109 /
    88-94 s (BENCHMARKS.md section 8)."""
    tau_scale: float = 1.0
    """The solver sees tau / tau_scale: balances the time variables against the waypoints."""
    formation_penalty: str = "linear"
    """'linear': f per constraint point, as the public code (with the exact gradient here);
    'cubic': the paper's max(f, 0)^3. Linear is the default: on 10 medium-forest flights it held
    the hexagon about 2.8x closer (mean e_sim 0.0038 vs 0.0106) at equal clearance; the cube of
    a small f has almost no pull near the desired shape (BENCHMARKS.md). For comparisons only:
    'linear-unit', the public code's own gradient scaled to unit length (inconsistent with its
    cost); 'relative', Turpin et al.'s fixed relative positions to every peer (no rotation or
    scaling), w times the squared offset error."""

    # --- acceptance and fallbacks --------------------------------------------------------------
    check_obstacle_m: float = 0.3
    """A trajectory is unsafe where it comes closer than this to an obstacle surface (the
    drone's body, 0.2 m, plus 0.1 m). It was 0.22 m, and the table's closest approaches sat at
    that value (the soft obstacle term, see ``w_obstacle``): 2 cm from touching. With the
    short steep J_o every table flight keeps >= 0.300 m (BENCHMARKS.md section 8, twelfth
    session). On a mapped field the obstacles are also inflated by the map's
    ``inflation_m``."""
    check_obstacle_horizon_s: float = 0.0
    """> 0: the obstacle part of the check judges a new trajectory over this many seconds from
    its start only (0: to its end). For a drone planning on its own map: a plan reaches about
    15 s (``horizon_m`` at the speed limit) where the map, 4-5 m of camera range and the edge of
    its window, is not yet formed, so a plan clear on one frame's map grazes a trunk mapped on
    the next, far ahead; refusing it costs retries that leave the formation out, although the
    next replans (every second) see that trunk long before it is near. Mapped fast time,
    forest-medium seeds 1-12 with the change to rectangle-7, at 4 s: refused attempts about
    halved, new shape within 10 s in 3 of 12 against 1, mean e_sim 0.050 against 0.047 (no
    better), closest trunk 0.315 m against 0.288 m (BENCHMARKS.md section 8, ninth session of
    2026-11-29). A plan kept by a later replan is checked again from that replan's start, so
    the far part is judged once it is within this horizon. On exact fields (the table) it
    loosened the shape (0.0078 -> 0.0119): off by default, set for the flight service's map
    (``config/onboard.yaml``)."""
    check_drone_horizon_s: float = 0.0
    """> 0: the peer part of the check judges a new trajectory over this many seconds from its
    start only (at least ``brake_reference_s``; 0: to its end). A peer's broadcast trajectory
    far ahead is a guess that its next replans replace (every second, every 0.1 s while
    re-forming), and on the real stack those replans also come late and off it; a formation
    plan refused for a conflict 10-20 s ahead is replaced by a retry without the formation
    term. Real stack, 2026-12-03, seed 1: one drone refused its formation plans 29 times in
    14 s for a peer 0.0-0.4 m away 11-23 s ahead, flew without the formation term, and the
    hexagon spread to e_sim 0.3 (BENCHMARKS.md section 10). A plan kept by a later replan is
    checked again from that replan's start, and the service's monitor watches the peers'
    newest trajectories over its own horizon, so a conflict is judged once it is within
    this horizon. Off by default. The fast-time twin of the demo (seeds 1-12, the change to
    rectangle-7) at 4 s: the same figures within the flights' spread (11 of 12 within 10 s
    either way, mean e_sim 0.0153 against 0.0146): the twin's peers fly their plans exactly
    and replan in time, so it meets few such conflicts. The real stack, seeds 1-5 at 4 s: the
    refusals for a peer 4 s ahead or more went (51 -> 1-3 a flight on seed 1) but the shape did
    not come back (3 of 5 within 10 s, mean e_sim 0.048 against 0.041 in the run before): the
    plans flown without the formation term are refused for obstacles (BENCHMARKS.md section
    10, 2026-12-04)."""
    check_drone_m: float = 0.5
    """A trajectory is unsafe where it comes closer than this to a peer (same global time).
    Two bodies of 0.2 m touch at 0.4 m; the check leaves 0.1 m for both vehicles' tracking and
    the age of the peer's plan, as ``check_obstacle_m`` leaves 0.1 m to a trunk. It was 0.45:
    drones that cross pass at the check distance (fault trials: closest pair 0.456-0.47 m in
    several trials; unseen table worlds: 0.463 m), and in CI's bus-faults flight (a drone the
    others could not hear, crossing a peer at 1.7 m/s closing speed) that left 0.3997 m, twice.
    At 0.5: ``bench faults --seed 1000`` closest pair 0.458 -> 0.509 m with every healthy drone
    arrived and e_sim 0.0083 -> 0.0084; the table 0.0028 / 0.0056 / 0.0122 -> 0.0029 / 0.0061 /
    0.0133, unseen worlds 0.0034 / 0.0076 / 0.0153 -> 0.0038 / 0.0069 / 0.0153 (closest pair
    0.463 -> 0.528 m); BENCHMARKS.md section 9b, fourth session of 2026-11-30."""
    check_step_s: float = 0.05
    """Time step of the safety check of a new trajectory."""
    check_known_s: float = 1.0
    """A trajectory may not enter space the map has not observed during its first this many
    seconds: the part flown before the next replan replaces it (1.0 = the agent's replan period;
    a trajectory kept by that replan is checked again on the newer map); 0 disables the test.
    Exact (analytic) fields are observed everywhere, so it changes nothing on them. It was off
    while the map carved nothing along depth pixels without a return (the space at flight
    height stayed unobserved unless a trunk lay behind it: with 1.0 the hexagon's mapped
    flight through forest-medium seed 2 then had 95 emergency stops and only 4 of 7 drones
    arrived); since the map clears free space along such pixels (``OccupancyParams.no_return_m``)
    that flight arrives 7 of 7 with no attempt refused for unobserved space (BENCHMARKS.md
    section 4)."""
    check_known_margin_m: float = 0.3
    """> 0: nor may it, during those ``check_known_s``, come within this of unobserved space
    (map cells neither observed nor counted occupied behind a hit) in its layer, at least half
    of this closer to it than it starts: a trunk the camera never faced beside the way (out of
    its field of view, or hidden behind another) is unobserved space, not free space, to the
    check (``kernels._near_unseen``; a grid with a mask of observed cells only). A way that
    starts about as close to unobserved space is not judged: beside a drone that has not moved
    yet space is always unobserved (with every cell closer than the start judged, no drone of
    the twin left its start at 0.3), and one that leaves it for observed space passes. 0: only
    the trajectory's own samples are tested.
    On a real-stack flight (2026-12-03, forest-medium seed 18) a drone curved toward a trunk
    hidden behind another and then 40-65 deg off its camera's axis; every plan the check
    accepted over the last 3 s passed through that trunk beyond its first second, and the one
    inside its first second 0.10 m from it: it collided."""
    lead_slowdown_m: float = 2.0
    """Time-consistent formation: a drone ahead of its slot (relative to the centroid of itself
    and its peers, along its way to the goal) by ``lead`` metres plans with the speed limit of
    J_d scaled by ``1 - lead / lead_slowdown_m`` (at least ``lead_min_speed_frac``), so the
    swarm waits for a drone left behind instead of flying on at full speed; 0 disables. With 1.5
    (and ``astar_keeps_formation``, before the swarm target) the table's 20 forests per density
    went from mean e_sim 0.0107 / 0.0209 / 0.0218 (max 0.038 / 0.066 / 0.062) to 0.0114 /
    0.0152 / 0.0221 (max 0.045 / 0.037 / 0.049), and flights took 8-10 s longer. The default
    set since 2026-11-24 (2.0, ``lead_deadband_m`` 1.0, ``lead_from_slowest``, ``w_formation``
    1e5, ``astar_keeps_formation``, ``limit_margin`` 0.97, with the 'centroid' swarm target;
    BENCHMARKS.md section 8): mean e_sim on the table's worlds 0.0080 / 0.0127 / 0.0182 ->
    0.0063 / 0.0088 / 0.0094, on unseen seeds 101-120 0.0069 / 0.0097 / 0.0202 -> 0.0046 /
    0.0081 / 0.0158, on the reference forest 0.0028 -> 0.0018, on mapped forest-medium seeds 1-4
    0.060 / 0.010 / 0.146 / 0.054 -> 0.016 / 0.003 / 0.042 / 0.008 (closest trunk 0.314 ->
    0.226 m there). It is off for ``reform_s`` after a formation change."""
    lead_min_speed_frac: float = 0.3
    """Lower bound of that scale."""
    lead_deadband_m: float = 1.0
    """A lead up to this is not slowed: the scale of ``lead_slowdown_m`` is taken of the lead
    minus this (the ordinary spread of a formation in a forest then costs no speed)."""
    lead_from_slowest: bool = True
    """With ``lead_slowdown_m``: measure the lead from the member least advanced along the
    shared path (the 'slowest' reference of ``swarm_target``) instead of the centroid or the
    swarm target's reference: a drone left behind slows every drone ahead of it, not only by
    its share of the centroid."""
    lead_turned: bool = False
    """With ``lead_from_slowest``: measure the members' leads against the template turned to the
    yaw the swarm holds (a least-squares fit), not at the template's own yaw. The formation
    term, e_sim and e_dist do not see the yaw, and the swarm turns by up to 30 deg in a forest;
    at the template's yaw a turned formation reads as drones ahead and drones behind, and the
    front ones wait for a "laggard" in its place in the shape (``bench faults --seed 1000``:
    a swarm that had lost two members flew on at 0.5-0.6 m/s instead of 0.9 and arrived at 62 s
    instead of 44-47 s without the slow-down, 2026-11-29). Off by default: on, the table's mean
    e_sim fell in every density and 1757 of 1772 healthy drones arrived in 300 fault trials
    (1725 off), but one of those trials had a collision (a peer killed in a close pass stopped
    in the other's way), none off; BENCHMARKS section 8, 2026-11-29 (fourth session)."""
    lead_slowest_beyond_m: float = 1.5
    """While recovering the shape (``recover_e_sim``; the lead is then measured from the
    centroid), a member left further behind than this still slows the drones ahead of it: the
    lead is the larger of the one from the centroid and the one from the member least advanced
    less this. From the centroid alone, a drone that falls far behind its slot is never waited
    for: the swarm cruises near the speed limit, so it cannot catch up, and the shape stays
    broken for the rest of the flight. Seen in the mapped twin of the demo (seed 1 with the
    service's ``check_obstacle_horizon_s`` 4, and the real stack's seed 1 on 2026-11-30, fifth
    session): the centre drone stuck 3.2 m behind, in the lane of the drone ahead of it, e_sim
    0.12-0.21 for 55 s, in the open too. Recovery's lead from the member least advanced with no
    margin held that flight but lost others and the table (mean e_sim 0.0032 / 0.0070 / 0.0152
    against 0.0029 / 0.0061 / 0.0133); at 1.5 m the table is as before and the twin's mean e_sim
    0.0318 -> 0.0252 (BENCHMARKS.md section 8, 2026-11-30, seventh session). Not while
    re-forming (``reform_params`` turns it off): a new shape often forms turned from the
    template's yaw, and at the template's yaw its members read as behind, so the swarm waited for
    drones that were in their place (twin seed 8: e_sim 0.041 -> 0.059 with it; with recovery
    only, the twin's mean e_sim 0.0237 and worst 0.033 against 0.0252 and 0.059). 0: off (the
    centroid only; the slowest member throughout is ``lead_from_slowest``)."""
    fresh_alternative: str = "line"
    """A plan accepted from the warm start (the previous trajectory) is solved once more from a
    fresh start, and of the two the one of lower cost that the check accepts outright is flown.
    The warm start keeps the way round each trunk that the last plan took; when the local target
    moves (a new slot, the swarm turning), the way that was best for the old target may cost the
    drone a long slide along a trunk or a place out of its slot. 'line' (the default since the
    tenth session of 2026-11-30): the fresh start is the straight line to the local target, also
    where a trunk blocks it (the solver's obstacle term pushes it off); 'astar': an A* path where
    the line is blocked (the search costs more than the second solve); 'never' (not 'off', which
    YAML reads as false): the warm start alone. ``reform_params`` uses 'astar' while re-forming
    (``reform_fresh_start``). 'line' against 'never' (BENCHMARKS.md section 8, ninth and tenth
    sessions of 2026-11-30): seeded table mean e_sim 0.0026 / 0.0045 / 0.0102 against 0.0029 /
    0.0063 / 0.0131, no trial over 0.02 (two dense ones); unseen seeds 0.0025 / 0.0049 / 0.0104
    against 0.0038 / 0.0067 / 0.0160; fault trials e_sim 0.0060 against 0.0076 with no collision
    either way; the demo's mapped twin in plain flight 0.0281 against 0.0305 (seeds 1-12), with
    a change in flight 0.0244 against 0.0332 (seeds 1-24; the new shape within 10 s in 8 of 24
    against 10). The price: ``bench planner``'s median plan 2.6 ms against 0.9 ms. 'astar':
    0.0029 / 0.0046 / 0.0094, one unseen medium world folded (0.0526), median plan 6.9 ms."""
    fresh_coarse_kappa: int = 1
    """The fresh start's solve (``fresh_alternative``) first solves a coarse problem, with this
    many constraint points per piece (the formation term at each), to the loose stop
    ``fresh_coarse_delta``, and then the full problem from there (0: the full problem from the
    guess). The full objective's many constraint points make a rugged landscape for a start as
    far off as the straight line through trunks: on 600 recorded replans (forest-medium seed 1,
    forest-dense seed 2) the coarse pass at 1 (the pieces' ends only) finds a fresh plan cheaper
    than the warm one in 53 % / 44 % of them against 28 % / 34 %, for 17-22 % less work
    (BENCHMARKS.md section 8, 2026-12-01, eighteenth session). Its evaluations count in the
    result's."""
    fresh_coarse_delta: float = 1e-2
    """The coarse pass's stop: relative decrease of the cost over the solver's ``past``
    iterations below this (the full solve's is ``lbfgs.delta``)."""
    fresh_guess_speed_frac: float = 0.8
    """The fresh start's path is timed at this fraction of the problem's speed limit (the
    limit margin and the lead slow-down applied; 0: at ``v_max_m_s``, as before). Timed at
    the limit itself, a minimum-jerk path overshoots it between its waypoints, and the first
    iterations spend themselves on the feasibility penalty (~10 fewer evaluations at 0.8)."""
    fresh_period_s: float = 0.0
    """The fresh start (``fresh_alternative``) at most once per this many seconds of global
    time: a replan solves it only when a multiple of the period lies between the previous
    trajectory's start and its own (0: at every replan). A gate on the replan's inputs alone,
    so that a replayed replan (``bench planner``) makes the same choice as in flight. Replans
    on the regular grid (1 s) are never gated by a period up to 1 s; the shape's recovery
    replans every ``reform_replan_period_s`` (0.1 s), and its fresh starts there, a tenth of a
    second apart, solve nearly the same problem again. ``reform_params`` keeps every replan's
    fresh start while re-forming. Measured at 1 s (BENCHMARKS.md section 8, 2026-12-04, third
    session): ``bench planner`` median 0.84 ms against 1.53 ms (the fresh start in 24 % of the
    replans), the seeded table the same (0.0024 / 0.0039 / 0.0073), but on the unseen sets one
    medium trial at 0.0284 (``--seed 100``) and one dense at 0.0246 (``--seed 200``) against
    none over 0.02, and flights 1-2 s longer: the recovery's fresh starts hold the tails.
    0.3 s and 0.5 s gave 1.13 and 1.03 ms: no period meets both targets on this host."""
    soft_formation_scale: float = 0.0
    """When the plan with the formation term (and its A* retry) is refused, one more attempt
    with the formation weight times this, before the plan without it (0: off). The refusals
    come where the formation's pull takes the drone past the check's distance to a trunk; a
    drone without the term flies its own way for as long as that lasts (real stack,
    forest-medium seed 3: drone 1 planned without it for 12 s and the hexagon folded, e_sim
    up to 0.41). Measured at 0.3 with ``fresh_alternative`` 'line' (BENCHMARKS.md section 8,
    tenth session of 2026-11-30): no consistent gain. The demo's mapped twin, plain flight
    (seeds 1-12), mean e_sim 0.0262 against 0.0281 (alone, with 'never': 0.0309 against
    0.0305, flights 4 s longer); with a change in flight (seeds 1-24) the new shape within 10
    s in 11 of 24 against 8 but mean e_sim 0.0282 against 0.0244; seeded table 0.0024 / 0.0046
    / 0.0094 against 0.0026 / 0.0045 / 0.0102."""
    reform_fresh_start: bool = True
    """While re-forming (``reform_s``): ``fresh_alternative`` 'astar' (with 'line' the twin
    below gave 4 of 12 within 10 s, against 7 with 'astar'). Measured on the demo's fast-time
    twin (``bench demo --fastsim-only``, hexagon-7 -> rectangle-7 20 s after the start,
    forest-medium seeds 1-24, mapped at 3 frames/s): the new shape within 10 s in 10 of 24
    against 5, within 15 s in 17 against 11; faster in 18 of the 24 seeds; mean e_sim 0.0282 /
    0.0381 against 0.0288 / 0.0393 (seeds 1-12 / 13-24), flights as long, closest trunk as far
    (BENCHMARKS.md section 10, ninth session of 2026-11-30)."""
    reform_speed_cap_frac: float = 0.0
    """``speed_cap_frac`` while re-forming (``reform_s``; 0: no cap then; shape recovery keeps
    ``speed_cap_frac``). The drones accelerate hard into their new slots, and the cap's second
    solve, which lands a plan near 0.501 m/s, holds one back against its peers: in the demo's
    fast-time twin (seeds 1-24) the cap folded seeds 3 and 23 (0.0152 -> 0.0654, 0.0239 ->
    0.0565), 22 of seed 23's 38 capped plans in the 5 s after the change (BENCHMARKS.md
    section 10, nineteenth session)."""
    reform_s: float = 10.0
    """For this long after a formation change in flight (a new template, slot or epoch; the
    flight's first assignment is not a change) a drone plans with ``reform_params``: the lead
    slow-down measured from the centroid reference (``reform_lead_from_centroid``) and the
    formation weight scaled by ``reform_formation_scale``. While the swarm re-shapes, every
    drone is off its new slot by design: slowing the drones ahead for the one farthest from its
    slot stalls the change (measured: three drones, line -> triangle at 1 m/s with the lead
    slow-down from the slowest member, 2.0 / 1.0 m: the triangle reached after ~35 s instead of
    ~16 s, the swarm shrunk to a knot of crossing drones). ``DroneAgent`` applies it; the
    planner itself has no notion of time since."""
    reform_hold_e_sim: float = 0.01
    """Re-forming (``reform_params``) goes on past ``reform_s`` while the swarm's shape as this
    drone sees it at a replan (as ``recover_e_sim`` scores it) is further than this from the new
    template, until it first is not or ``reform_hold_max_s`` after the change (0: off; re-forming
    ends at ``reform_s`` whatever the shape). Shape recovery then takes over as usual. Without
    it a swarm that has not reached the new shape by ``reform_s`` falls back to recovery's
    weaker formation weight and can spread again (BENCHMARKS.md section 10, twenty-fifth
    session: e_sim 0.016 at 10 s, 0.043 at 13 s, the shape at 54.8 s). Measured at 0.01 (the
    shape score #10 asks for) in the demo's fast-time twin, seeds 1-48 (section 10,
    twenty-sixth session): the same 44 of 48 within 10 s, the slowest 14.7 s against 26.9 s
    (seed 46), none over 15 s against one; mean e_sim 0.0175 against 0.0177, closest trunk and
    top speed unchanged, flights 0.4 s longer on average."""
    reform_hold_max_s: float = 30.0
    """The longest re-forming lasts after a change with ``reform_hold_e_sim`` (at least
    ``reform_s``)."""
    reform_lead_from_centroid: bool = True
    """While re-forming (``reform_s``): keep the lead slow-down, measured from the centroid
    reference instead of the slowest member (``lead_from_slowest`` off): a drone ahead of its new
    slot waits, one behind is not held back by the drone farthest from its slot. False: no lead
    slow-down while re-forming (the rule until 2026-11-24). Without it, drones ahead of their new
    slot flew on at full speed and those behind could never catch up: in the fast-time
    hexagon-7 -> rectangle-7 change in forest-medium the along-path offsets from the new slots
    grew over the 10 s (BENCHMARKS.md section 10, eleventh session)."""
    reform_replan_period_s: float = 0.1
    """While re-forming (``reform_s``), the agent replans at most this long after its last
    replan (0: on its own grid only, ``replan_period_s``). Each drone's plan answers the plans
    its peers last broadcast, so a move that every drone makes at once converges in replans
    rather than in seconds. Fast time, forest-medium seeds 1-20, hexagon-7 -> rectangle-7 20 s
    after the start, exact distances: the new shape within 10 s in 11 of 20 at the 1 s grid, 13
    at 0.5 s, 15 at 0.25 s; hexagon-7 -> arrow-7 (seeds 1-10) 2 -> 6 of 10. The price: the shape
    is entered at the yaw nearest the old one, and turning it to the goals' yaw afterwards
    (the lead slow-down) made flights longer, mean 98 -> 109 s (104-106 s with
    ``target_speed_frac`` 0.5; BENCHMARKS.md section 10). 0.1 since 2026-12-01, with
    ``recover_replan_period_s``: see there.
    The agent's own parameter, kept here beside ``reform_s``; the planner has no notion of
    it."""
    recover_e_sim: float = 0.005
    """Shape recovery: when the swarm's shape as this drone sees it at a replan (its own start
    and its formation peers' broadcast plans at that time, scored with the similarity metric
    against their slots' points of the template) is further than this from the template, the
    drone plans for the next ``recover_hold_s`` as while re-forming (``recover_params``: with
    ``recover_formation_scale`` for the formation weight's factor), replanning every
    ``recover_replan_period_s``. After trunks split the formation, the shape otherwise comes back
    only 8-10 s after the last one (section 8 of BENCHMARKS.md, 2026-11-30). Not while
    re-forming (that has its own parameters) nor without the lead slow-down. 0: off.
    Measured (``bench table``, 20 worlds a density, and the reference forests, BENCHMARKS.md
    section 8, 2026-11-30 third session): mean e_sim 0.0038 / 0.0081 / 0.0137 / 0.0032 (sparse /
    medium / dense / reference) off, 0.0028 / 0.0056 / 0.0122 / 0.0023 at 0.005."""
    recover_hold_s: float = 2.0
    """Shape recovery (``recover_e_sim``) lasts this long after the last replan that found the
    shape off."""
    recover_replan_period_s: float = 0.1
    """While recovering the shape (``recover_e_sim``), the agent replans at most this long
    after its last replan (0: on its own grid only), as ``reform_replan_period_s`` does while
    re-forming. The agent's own parameter, like that one. Both 0.25 until 2026-12-01 (one
    parameter then). Both at 0.1 (BENCHMARKS.md section 10, sixteenth session), the demo's
    fast-time twin (forest-medium, mapped, hexagon-7 -> rectangle-7 20 s in, seeds 1-36): the
    new shape sooner in 26 seeds, later in 9 (within 10 s in 23 of 36 against 17, median 8.3 s
    against 10.3 s), mean e_sim 0.0227 against 0.0255, flights 1.6 s longer; the real stack 2 of
    5 within 10 s (its runs at 0.25 s: 1-3 of 5); ``bench table``'s top speed
    within 2 % of the limit on all 180 worlds; the fault trials' flights 1.4 s longer
    (median), one of them (a drone killed, one stuck) not home within its 60 s. Recovery
    alone at 0.1 (re-forming at 0.25): 8 of 12 within 10 s, one drone not home (seed 3: it
    went back and forth between two ways through a trunk cluster, each refused in turn by
    the check's 4 s horizon on its own map)."""
    unheard_margin_m: float = 0.3
    """Added to ``check_drone_m`` and ``swarm_clearance_m`` while a peer reports that it does
    not hear this drone (``DroneAgent.set_unheard``: the peer's status says this drone's link
    is down or has been quiet for a second). Such a peer plans around this drone's last
    broadcast trajectory and its ghosts, not around where it flies; this drone alone keeps the
    two apart, against a peer's plan that may change toward it at every replan. In CI's
    bus-faults flight (a drone whose uplink was held for 7.5 s) that left 0.3997 m between two
    drones that crossed at 1.7 m/s closing speed, at the 0.45 m check of the time. 0.2 until
    2026-12-01: ``bench hidden --outage-from 3`` (800 flights, the twin holding after a brake
    as the service does) had one contact (0.399 m) and the hidden drone's closest peer at
    0.399 / 0.560 m (seeds 1-400 / 401-800); at 0.3 none, 0.608 / 0.578 m, the flights as
    long (BENCHMARKS.md section 9b). 0: off."""
    brake_reference_s: float = BRAKE_REFERENCE_S
    """The safety check's rule for a way that comes inside its distance of an obstacle or a
    peer: it may come as close as a braking stop from the same start would within this long
    (``kernels._band``'s floor; a start inside the distance may back out that way, and when
    every attempt is refused such a way is flown as a last resort rather than the stop).
    Beyond it, a peer that hears this drone replans around the stop."""
    unheard_brake_reference_s: float = 3.0
    """``brake_reference_s`` while a peer reports that it does not hear this drone
    (``unheard_params``): that peer flies on through the place where a stop would leave this
    drone, so the stop is judged over the time it holds there: the stop itself (about 1 s),
    the flight service's hover before it retries (1 s) and the retry's start. In CI's
    bus-faults flight (2026-12-01) the unheard drone refused every way, the closest 0.53 m
    from a peer, for a stop that the peer flew through 1.6 s later, 0.315 m apart."""
    recover_formation_scale: float = 3.0
    """While recovering the shape (``recover_e_sim``), ``w_formation`` is multiplied by this
    (in place of ``reform_formation_scale``), and so is ``w_altitude_hold`` (without it the
    stronger pull dipped a drone of ``tests/test_altitude_hold.py``'s triangle 0.19 m, against
    0.05 m): 2, 3 and 4 measured alike on sparse and medium forests; 3 kept the dense ones
    best."""
    recover_limit_scale: float = 1.0
    """While recovering the shape (``recover_e_sim``), ``w_feasibility`` and ``w_limit_hard``
    are multiplied by this (1: as in normal flight). The formation weight is then x3
    (``recover_formation_scale``), and its pull carries plan after plan (replanned every 0.25
    s, each from the state the last one left) past the speed limit: the table's top speed,
    0.511 m/s, is set there. Measured at 3 (BENCHMARKS.md section 8, 2026-12-01): top speed
    0.5075 / 0.5049 / 0.5075 m/s on the seeded and two unseen sets of 60 worlds (the default
    0.511 / 0.508 / 0.512), mean e_sim 0.0026 / 0.0047 / 0.0099, 0.0025 / 0.0059 / 0.0110 and
    0.0024 / 0.0037 / 0.0100 (the default 0.0026 / 0.0045 / 0.0102, 0.0025 / 0.0049 / 0.0104,
    0.0020 / 0.0036 / 0.0115), trials over 0.02: 3 against 1 (the worst 0.045 against 0.086);
    fault trials e_sim 0.0075 against 0.0060. Off: the shape, not the last percent of speed,
    decided it."""
    reform_formation_scale: float = 6.0
    """While re-forming (``reform_s``), ``w_formation`` is multiplied by this: the time term and
    the obstacle terms otherwise spread the move to the new slots over the whole horizon (7.5 m
    ahead, 15 s at 0.5 m/s). Measured with ``reform_lead_from_centroid`` (fast time,
    forest-medium seeds 1-5, mapped at 5 frames/s, change 20 s after the start; BENCHMARKS.md
    section 10, eleventh session): hexagon-7 -> rectangle-7, the new shape after median 8.7 s at
    1.0 and 4.9 s at 3.0 (4 of 5 within 10 s either way); hexagon-7 -> arrow-7, 3 of 5 within
    10 s at 1.0 and 1 of 5 at 3.0. Chosen for the rectangle, which the 7-drone demo's change
    flies; not settled for other shapes. 6.0 since 2026-11-28 (fast time, change 20 s after the
    start, the new shape within 10 s at 3.0 -> 6.0): rectangle-7 on exact distances, seeds 1-30,
    20 -> 24 of 30; arrow-7, seeds 1-20, 8 -> 8 of 20; rectangle-7 mapped (3 frames/s, step 3,
    band 0.4-1.8 m), seeds 1-5, 3 -> 4 of 5 (mean e_sim 0.055 -> 0.038); at 10.0: 2 of 5 mapped
    and the arrow's top speed 0.515 m/s (BENCHMARKS.md section 10). 1.0: unchanged."""
    reform_obstacle_scale: float = 1.0
    """While re-forming (``reform_s``), ``w_obstacle`` is multiplied by this (shape recovery keeps
    the plain weight). The formation term pulls ``reform_formation_scale`` times harder then,
    times ``1 + reform_formation_front_gain`` at the plan's start, and against the plain cubic
    obstacle term it won down to 0.26-0.30 m from a trunk: the check refused those plans and the
    drone flew plans without the formation, round the trunk's other side (1.0: unchanged).
    Measured at 10 and not taken (BENCHMARKS.md section 10, twenty-fifth session): the demo's
    twin 44 of 48 seeds within 10 s either way (mean e_sim 0.0164 against 0.0177, closest trunk
    0.332 against 0.322 m); the real stack, seeds 6-15, 6 of 10 against 7 of 10, on a busier
    host; the plans without the formation while re-forming fell from 0-53 to 0-7 a flight, and
    the slow flights stayed slow (seed 7: trunks pushed two drones off their slots after the
    shape had come to e_sim 0.035)."""
    formation_front_gain: float = 0.0
    """J_f weighs the plan's first seconds more: at the plan's own time t its weight is
    ``w_formation`` times ``1 + formation_front_gain * exp(-t / formation_front_s)`` (0: a
    uniform weight, the paper's). The plan's formation error is integrated over the whole
    horizon (15 s at 0.5 m/s), where the shape the swarm holds now is what is flown next; set
    for re-forming by ``reform_formation_front_gain``."""
    formation_front_s: float = 3.0
    """The time constant of ``formation_front_gain``'s decay along the plan [s]."""
    reform_formation_front_gain: float = 4.0
    """``formation_front_gain`` while re-forming (``reform_s``; recovery keeps the plain one).
    The re-forming plans spread the move to the new slots over the horizon, and near misses
    stayed near misses: the twin's slow seeds came within e_sim 0.0105-0.014 of the new shape
    and the trunks pushed it apart again. Measured in the demo's twin (hexagon-7 -> rectangle-7
    20 s after the goal, forest-medium, mapped; BENCHMARKS.md section 10, twenty-third session):
    the new shape within 10 s in 12 of 12 (seeds 1-12) and 10 of 12 (13-24) at 4.0, against 10
    and 8 of 12 at 0."""
    swarm_target: str = "centroid"
    """Swarm-consistent local target (issue #11). 'own-goal' (the option off, the default until
    2026-11-23; not 'off', which YAML reads as false): the local target lies ``horizon_m`` along the
    straight line to the drone's own goal. 'centroid': the swarm's reference origin is estimated
    from the drone and its formation peers (at the replan's start) as the mean of ``p_j -
    F[slot_j]``; the local target is that origin advanced ``horizon_m`` along the shared path to the
    goal's origin (``goal - F[slot]``) plus the drone's slot ``F[slot]``, then moved along the line
    from the drone to the nearest point clear of obstacles as the 'own-goal' target: a drone that
    went round a trunk the other way is pulled back towards its slot, and the swarm's targets stay a
    formation. 'slowest': the reference origin is moved back along the shared path to the member
    least advanced on it (time-consistent: the targets of drones ahead come closer). With
    ``lead_slowdown_m`` > 0 and a swarm target, the lead is measured from this reference (for
    'slowest': ahead of the slowest member's pace). Within ``horizon_m`` of the goal's origin the
    target is the drone's own goal. Measured (``bench table --method ours --jobs 1``, the same 3 x
    20 worlds, all 60 flights succeed, 0 collisions, min trunk clearance 0.220 m in every run): mean
    e_sim 0.0107 / 0.0242 / 0.0292 (sparse / medium / dense; max 0.038 / 0.112 / 0.096) ->
    'centroid' 0.0080 / 0.0127 / 0.0182 (max 0.020 / 0.027 / 0.039) with flights 3-7 s longer;
    'slowest' 0.0080 / 0.0155 / 0.0271 (one dense fold, 0.111); 'centroid' with ``lead_slowdown_m``
    1.5 0.0088 / 0.0152 / 0.0206 and flights 11-21 s longer. 'centroid' with ``w_formation`` 1e5:
    0.0067 / 0.0109 / 0.0155 (max 0.026 / 0.039 / 0.043), but top speed 0.539 m/s. On unseen worlds
    (seeds 101-120) 'own-goal' -> 'centroid': 0.0118 / 0.0186 / 0.0242 (max 0.096 / 0.160 / 0.074)
    -> 0.0069 / 0.0097 / 0.0202 (max 0.015 / 0.017 / 0.097); the reference forest 0.0039 -> 0.0028.
    The default since then (BENCHMARKS.md section 8)."""
    comfort_obstacle_m: float = 0.0
    """When the first attempt's trajectory passes closer than this to an obstacle (and closer
    than it starts), the planner also optimises from an A* path at ``obstacle_clearance_m``
    with the same terms, and keeps whichever passes the safety check with the larger clearance:
    the warm start keeps the gap it chose when the gap was far, so a narrow one is otherwise
    flown at whatever the check allows. 0 disables."""
    refine_penalty_scale: float = 100.0
    """An attempt's solution that the safety check refuses is solved again from where it is,
    with tight tolerances; when it passes closer than ``check_obstacle_m`` to an obstacle, on
    ``refine_kappa_factor`` times the constraint points and with the obstacle and limit
    penalties (``w_obstacle``, ``w_feasibility``, ``w_limit_hard``) this many times stiffer
    (1: the same weights). Most refusals are a trunk 1-4 cm inside the check's distance seconds
    ahead: the formation pull wins over the short steep obstacle term there, or the trajectory
    passes the trunk between two constraint points. Without the stiffer solve, a drone in a
    pocket of trunks can have every attempt refused by such a margin, replan after replan: in
    the unseen dense forest of seed 202 one drone kept its previous plan for 11 s, backed out
    and went round, and the hexagon folded (e_sim 0.0676, BENCHMARKS.md section 8, 2026-12-04
    sixth session). When the stiffer refinement is not accepted outright, the plain tight
    solve runs too and the one standing higher is flown (accepted outright, a last resort,
    refused): alone, the stiffer obstacle term held an unheard drone overtaken in a corridor of
    trunks in the corridor's middle, 0.46 m from the peer passing it instead of 0.55 m
    (``tests/test_hearing.py``). Default 100 with ``refine_kappa_factor`` 2 since 2026-12-04
    (seventh session): the three table sets (180 flights) have no trial over 0.02 (0.0676
    before) and lower or equal means, the reference forests 0.00201 (0.00218), the fault
    trials no collision, the mapped fast-time flights (seeds 1-10) 10 of 10 with no collision,
    closest trunk 0.328 m. Off (1 and 1) for the flight service (``config/onboard.yaml``: on the
    real stack on 2026-12-04 it cut the obstacle refusals tenfold, but re-formed within 10 s in
    15 of 20 flights against 19 of 20 without); on its map, measured on 2026-11-29
    (BENCHMARKS.md sections 8 and 10; seeds 1-12 of the mapped twin, 3 frames/s, step 3) it
    halved the refusals but lowered the closest passes to trunks (the least of 12 flights 0.293
    -> 0.243-0.278 m): a refined plan stays in the tight spot at the check's distance, and the
    map is wrong by up to 0.15 m (p99)."""
    refine_kappa_factor: int = 2
    """That second solve evaluates the costs on this many times ``kappa`` constraint points per
    piece (1: the same). A piece is 1-8 s long; at ``kappa`` 8 its points lie up
    to 0.4 m apart, and a plan that keeps 0.34 m at every point can pass a trunk at 0.29 m
    between two: the check, sampling every ``check_step_s``, refuses it."""
    astar_keeps_formation: bool = True
    """When the first attempt fails the check, retry from an A* path with the formation term
    before the retry without it (the latter flies its own way around and can split the shape).
    On by default since 2026-11-24 (the set of ``lead_slowdown_m``). Alone (before the swarm
    target and the lead slow-down) it took one medium forest from e_sim 0.048 to 0.139 (a drone
    left behind). With the check at 0.3 m and the comfort test it helps (4 forests per density:
    mean e_sim 0.0168 / 0.0242 / 0.0332 without, 0.0162 / 0.0176 / 0.0274 with)."""
    astar_resolution_m: float = 0.2
    """Cell size of the A* fallback search."""
    astar_clearances_m: tuple[float, ...] = (0.5, 0.4)
    """Rescue levels of the A* fallback, largest first. The A* attempts of a replan look for a
    path at ``obstacle_clearance_m``, else at ``check_obstacle_m`` (``astar_ladder_m``). Only
    when every attempt of the replan was refused by the safety check and the A* retry's path
    keeps less than the smallest of them, one more attempt (without the formation term) starts
    from an A* path at the largest of these levels above ``check_obstacle_m`` that finds a path
    (``astar_rescue_ladder_m``; with the default 0.34 / 0.3 ladder, 0.5 and 0.4); it is flown if
    the check accepts it. A safe previous trajectory that still moves the drone is kept before
    trying it (as before the rescue existed), one that holds the drone where it is (a hover)
    only after it failed too. A path
    at the check's own distance threads gaps that the optimised trajectory cannot pass with
    the check's margin (its obstacle term trades centimetres against the others; a mapped gap
    is narrower than the true one): in the mapped flight of forest-medium seed 3, a drone in
    front of a 0.59 m gap (ESDF at most 0.19 m inside it) was offered only the way through the
    gap for 150 s, refused every time (158 kept hovers), while A* at 0.5 m found the way around
    (issue #11). Tried in every A* attempt instead, these levels folded three dense table
    forests (mean e_sim 0.0292 -> 0.0464): a roomier way around, away from the slot, where the
    check-distance path was flown fine. () disables the rescue."""
    z_limits_m: tuple[float, float] = (0.3, 3.1)
    """Altitude band (z_min, z_max) [m] of every accepted trajectory: the safety check rejects a
    trajectory that leaves it (one that starts outside may fly back in, never farther out), the
    optimiser's J_z keeps the constraint points ``altitude_margin_m`` inside it, the A* fallback
    searches that inner band and local targets and goals are moved into it. Below the ground
    and above the map window an ESDF knows nothing (it reports free space), so an unbounded
    optimiser let the tail of a 7 s plan sink to z -1.7 m or climb to 5.3 m (issue #10's
    demo). Default 0.3-3.1 m, for flight at about 1 m: 0.3 m above the ground, 0.4 m under
    the top of ``OccupancyParams``' default window (11 x 11 x 4 m from 0.5 m below the ground;
    the flight service fits its window to this band instead, ``mapping.window_band_margin_m``
    each side); with the margin, the A* fallback searches 0.4-3.0 m as before the band
    existed. The service should pass the intersection with its geofence."""
    w_altitude: float = 1.0e7
    """J_z: weight of max(z_lo - z, 0)^3 + max(z - z_hi, 0)^3 over constraint points, with
    (z_lo, z_hi) the band shrunk by ``altitude_margin_m``."""
    w_altitude_hold: float = 1.0e5
    """J_z's altitude hold: weight of (z - z_goal)^2 over the constraint points, z_goal the
    altitude of the drone's goal (moved into the band). The formation metric is invariant to
    rotation, so a level formation tilted costs nothing more. Flown exactly, its drones stay
    level (the vertical gradient is zero by symmetry), but any altitude error breaks the
    symmetry and the shape tilts to ease its spacing between the trunks: with drones started
    up to 5 cm off 1 m, every one of 6 medium forests tilted the hexagon to 0.4-3.0 m (over the
    2.5-3 m trunks, and over the map's top) within seconds; on the real stack half the swarm
    climbed to 3 m (issue #10). With 1e5 the spread stayed under 0.1 m (BENCHMARKS §10). 0: off
    (a 3-D shape is held too: each drone holds its own goal's altitude)."""
    altitude_hold_knee_m: float = 0.1
    """The altitude hold is quadratic up to this deviation from the goal's altitude and linear
    beyond (its pull stops growing at 2 ``w_altitude_hold`` times this): a fixed pull is
    enough to keep a level shape level, and a bounded one yields to an obstacle that asks for
    a climb or a descent instead of squeezing the plan against it."""
    altitude_margin_m: float = 0.1
    """J_z starts this far inside ``z_limits_m``, so the optimiser's solution stays inside the
    band the safety check enforces (a soft penalty balances the other terms slightly past where
    it starts)."""
    lbfgs: LbfgsParams = field(
        default_factory=lambda: LbfgsParams(
            mem_size=16,
            g_epsilon=1e-5,
            past=3,
            delta=1e-3,
            max_iterations=200,
            max_evaluations=400,
        )
    )
    """Solver settings."""

    def __post_init__(self) -> None:
        positive = (
            "v_max_m_s",
            "a_max_m_s2",
            "j_max_m_s3",
            "horizon_m",
            "piece_length_m",
            "obstacle_clearance_m",
            "altitude_hold_knee_m",
            "swarm_clearance_m",
            "swarm_z_scale",
            "check_step_s",
            "astar_resolution_m",
            "tau_scale",
            "limit_margin",
        )
        for name in positive:
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value!r}")
        # no multirotor this planner serves flies faster or pulls harder (bounds, not tuning)
        for name, top in (("v_max_m_s", 30.0), ("a_max_m_s2", 50.0)):
            value = getattr(self, name)
            if value > top:
                raise ValueError(f"{name} must be at most {top:g}, got {value!r}")
        nonneg = (
            "w_time",
            "w_obstacle",
            "w_swarm",
            "w_feasibility",
            "w_limit_hard",
            "w_uniform",
            "w_formation",
            "pace_floor_frac",
            "pace_slack_s",
            "w_pace",
            "check_obstacle_m",
            "check_drone_m",
            "check_obstacle_horizon_s",
            "check_drone_horizon_s",
            "check_known_s",
            "check_known_margin_m",
            "lead_slowdown_m",
            "lead_deadband_m",
            "lead_slowest_beyond_m",
            "reform_s",
            "reform_hold_e_sim",
            "reform_hold_max_s",
            "reform_replan_period_s",
            "formation_front_gain",
            "reform_formation_front_gain",
            "recover_e_sim",
            "recover_hold_s",
            "recover_replan_period_s",
            "unheard_margin_m",
            "brake_reference_s",
            "unheard_brake_reference_s",
            "w_altitude",
            "w_altitude_hold",
            "altitude_margin_m",
            "comfort_obstacle_m",
        )
        for name in nonneg:
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a non-negative number, got {value!r}")
        if self.check_known_margin_m > 2.0:  # the cells it reads grow with its cube
            raise ValueError(
                f"check_known_margin_m must be at most 2 m, got {self.check_known_margin_m!r}"
            )
        k = self.refine_kappa_factor
        if not (isinstance(k, int) and not isinstance(k, bool) and 1 <= k <= 8):
            raise ValueError(f"refine_kappa_factor must be an integer 1-8, got {k!r}")
        if not (np.isfinite(self.refine_penalty_scale) and self.refine_penalty_scale >= 1.0):
            raise ValueError(
                f"refine_penalty_scale must be a number >= 1, got {self.refine_penalty_scale!r}"
            )
        k = self.fresh_coarse_kappa
        if not (isinstance(k, int) and not isinstance(k, bool) and 0 <= k <= 64):
            raise ValueError(f"fresh_coarse_kappa must be an integer 0-64, got {k!r}")
        if not (np.isfinite(self.fresh_coarse_delta) and 0.0 < self.fresh_coarse_delta < 1.0):
            raise ValueError(
                f"fresh_coarse_delta must be in (0, 1), got {self.fresh_coarse_delta!r}"
            )
        if not (
            np.isfinite(self.fresh_guess_speed_frac) and 0.0 <= self.fresh_guess_speed_frac <= 1.0
        ):
            raise ValueError(
                f"fresh_guess_speed_frac must be in [0, 1], got {self.fresh_guess_speed_frac!r}"
            )
        if not (np.isfinite(self.fresh_period_s) and 0.0 <= self.fresh_period_s <= 60.0):
            raise ValueError(f"fresh_period_s must be in [0, 60] s, got {self.fresh_period_s!r}")
        if not (np.isfinite(self.formation_front_s) and self.formation_front_s > 0):
            raise ValueError(
                f"formation_front_s must be a positive number, got {self.formation_front_s!r}"
            )
        for name in ("speed_cap_frac", "reform_speed_cap_frac"):
            cap = getattr(self, name)
            if not (np.isfinite(cap) and (cap == 0.0 or 1.0 <= cap <= 1.5)):
                raise ValueError(f"{name} must be 0 (off) or in [1, 1.5], got {cap!r}")
        if self.pace_floor_frac > 1.0:
            raise ValueError(
                "pace_floor_frac must be at most 1 (a pace above the speed limit), "
                f"got {self.pace_floor_frac!r}"
            )
        if not (np.isfinite(self.recover_limit_scale) and self.recover_limit_scale >= 1.0):
            raise ValueError(
                f"recover_limit_scale must be a number >= 1, got {self.recover_limit_scale!r}"
            )
        if not (np.isfinite(self.recover_formation_scale) and self.recover_formation_scale > 0):
            raise ValueError(
                "recover_formation_scale must be a positive number, "
                f"got {self.recover_formation_scale!r}"
            )
        if not (np.isfinite(self.reform_formation_scale) and self.reform_formation_scale > 0):
            raise ValueError(
                "reform_formation_scale must be a positive number, "
                f"got {self.reform_formation_scale!r}"
            )
        if not (np.isfinite(self.reform_obstacle_scale) and self.reform_obstacle_scale >= 1.0):
            raise ValueError(
                f"reform_obstacle_scale must be a number >= 1, got {self.reform_obstacle_scale!r}"
            )
        if not (np.isfinite(self.target_speed_frac) and 0.0 <= self.target_speed_frac <= 1.0):
            raise ValueError(f"target_speed_frac must be in [0, 1], got {self.target_speed_frac!r}")
        if not 0.0 < self.lead_min_speed_frac <= 1.0:
            raise ValueError(
                f"lead_min_speed_frac must be in (0, 1], got {self.lead_min_speed_frac!r}"
            )
        levels = self.astar_clearances_m
        if not all(np.isfinite(c) and c > 0 for c in levels):
            raise ValueError(f"astar_clearances_m must hold positive numbers, got {levels!r}")
        if any(b >= a for a, b in zip(levels, levels[1:], strict=False)):
            raise ValueError(
                f"astar_clearances_m must be strictly decreasing (largest first), got {levels!r}"
            )
        if self.kappa < 1 or self.max_pieces < 1:
            raise ValueError("kappa and max_pieces must be at least 1")
        if self.formation_stride < 1 or self.kappa % self.formation_stride != 0:
            raise ValueError(
                f"formation_stride ({self.formation_stride}) must be >= 1 and divide kappa "
                f"({self.kappa})"
            )
        if self.swarm_target not in SWARM_TARGETS:
            raise ValueError(
                f"swarm_target must be one of {SWARM_TARGETS}, got {self.swarm_target!r}"
            )
        if not (0.0 <= self.soft_formation_scale < 1.0):
            raise ValueError(
                f"soft_formation_scale must be in [0, 1), got {self.soft_formation_scale!r}"
            )
        if self.fresh_alternative not in FRESH_STARTS:
            raise ValueError(
                f"fresh_alternative must be one of {FRESH_STARTS}, got {self.fresh_alternative!r}"
            )
        if self.formation_penalty not in FORMATION_PENALTIES:
            raise ValueError(
                f"formation_penalty must be one of {FORMATION_PENALTIES}, "
                f"got {self.formation_penalty!r}"
            )
        lo, hi = self.z_limits_m
        if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
            raise ValueError(
                f"z_limits_m must be finite (low, high) with low < high, got {lo!r}, {hi!r}"
            )
        if not (-1.0e4 <= lo and hi <= 1.0e4):
            raise ValueError(f"z_limits_m must lie within +-10 km, got ({lo!r}, {hi!r})")
        if not hi - lo > 2.0 * self.altitude_margin_m:
            raise ValueError(
                f"z_limits_m ({lo:g}, {hi:g}) must be wider than twice altitude_margin_m "
                f"({self.altitude_margin_m:g})"
            )

    @property
    def astar_ladder_m(self) -> tuple[float, ...]:
        """The clearances the A* attempts of a replan try, in order: ``obstacle_clearance_m``,
        then ``check_obstacle_m`` (just the former when it is not the larger)."""
        top, check = float(self.obstacle_clearance_m), float(self.check_obstacle_m)
        return (top, check) if top > check else (top,)

    @property
    def astar_rescue_ladder_m(self) -> tuple[float, ...]:
        """The clearances of the rescue attempt's A* search, largest first: the levels of
        ``astar_clearances_m`` above ``check_obstacle_m`` (others are left out; they may lie
        above ``obstacle_clearance_m``: the optimiser's clearance is kept a little above the
        check's); () when there is no rescue."""
        check = self.check_obstacle_m
        return tuple(float(c) for c in self.astar_clearances_m if c > check)

    @property
    def altitude_band_inner_m(self) -> tuple[float, float]:
        """The band J_z and the A* fallback keep to: ``z_limits_m`` shrunk by the margin."""
        lo, hi = self.z_limits_m
        return lo + self.altitude_margin_m, hi - self.altitude_margin_m


def reform_params(params: PlannerParams) -> PlannerParams:
    """The parameters a drone plans with for ``reform_s`` after a formation change in flight:
    the formation weight scaled by ``reform_formation_scale``; the lead slow-down measured from
    the centroid reference alone (``reform_lead_from_centroid``; ``lead_slowest_beyond_m`` off),
    else off; a fresh start beside the warm one (``reform_fresh_start``); the speed cap
    ``reform_speed_cap_frac``; the fresh start at every replan (``fresh_period_s`` 0)."""
    p = dataclasses.replace(
        params,
        w_formation=params.w_formation * params.reform_formation_scale,
        formation_front_gain=params.reform_formation_front_gain,
        w_obstacle=params.w_obstacle * params.reform_obstacle_scale,
        fresh_alternative="astar" if params.reform_fresh_start else params.fresh_alternative,
        fresh_period_s=0.0,
        speed_cap_frac=params.reform_speed_cap_frac,
    )
    if params.reform_lead_from_centroid:
        return dataclasses.replace(p, lead_from_slowest=False, lead_slowest_beyond_m=0.0)
    return dataclasses.replace(p, lead_slowdown_m=0.0)


def recover_params(params: PlannerParams) -> PlannerParams:
    """The parameters a drone plans with while recovering the shape (``recover_e_sim``): those
    of re-forming (``reform_params``), with the formation weight and the altitude hold scaled by
    ``recover_formation_scale``, the limit penalties by ``recover_limit_scale``, a member far
    behind waited for (``lead_slowest_beyond_m``), and the fresh start of ``fresh_alternative``
    and ``fresh_period_s`` and the speed cap ``speed_cap_frac`` (not re-forming's)."""
    k = params.recover_formation_scale
    return dataclasses.replace(
        reform_params(params),
        w_formation=params.w_formation * k,
        formation_front_gain=params.formation_front_gain,
        w_obstacle=params.w_obstacle,
        w_altitude_hold=params.w_altitude_hold * k,
        w_feasibility=params.w_feasibility * params.recover_limit_scale,
        w_limit_hard=params.w_limit_hard * params.recover_limit_scale,
        lead_slowest_beyond_m=params.lead_slowest_beyond_m,
        fresh_alternative=params.fresh_alternative,
        fresh_period_s=params.fresh_period_s,
        speed_cap_frac=params.speed_cap_frac,
    )


def unheard_params(params: PlannerParams) -> PlannerParams:
    """``params`` for a drone that a peer does not hear: the check distance to peers and the
    optimiser's clearance to them widened by ``unheard_margin_m``, and a braking stop judged
    over ``unheard_brake_reference_s`` (when longer than ``brake_reference_s``)."""
    m = params.unheard_margin_m
    ref = max(params.brake_reference_s, params.unheard_brake_reference_s)
    if m == 0.0 and ref == params.brake_reference_s:
        return params
    return dataclasses.replace(
        params,
        check_drone_m=params.check_drone_m + m,
        swarm_clearance_m=params.swarm_clearance_m + m,
        brake_reference_s=ref,
    )
