"""The ego driver: route planning over the road grid, speed and steering control, traffic.

`simulate_ego` drives a random lane-following route (`_plan_route`), follows slower cars, gives
way at junctions and returns an `EgoTrack`; `_rear_ghosts` lists the traffic cars to hide because
they would drive through the ego from behind (used by `orbis2.sim.render.render_episode`).

Odometry convention
-------------------
Native step k is at t_k = k / fps with pose (x_k, y_k, yaw_k): world position and heading, yaw
counter-clockwise from +x and unwrapped (continuous). The ego frame has x forward, y left.
``speed[k]`` (m/s, >= 0) and ``yaw_rate[k]`` (rad/s, CCW positive) are constant over
[t_k, t_{k+1}); pose k+1 is the exact arc integration of pose k under them
(`orbis2.kinematics.integrate_odometry`). Frame k is rendered from pose k at time t_k.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from orbis2.kinematics import integrate_odometry
from orbis2.sim.town import Town, _rng


@dataclass
class EgoTrack:
    """Ego trajectory at the native rate `fps`; see the module docstring for the convention.

    Arrays of length T: t (s), x, y (m, world), yaw (rad, unwrapped), speed (m/s), yaw_rate (rad/s).
    """

    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    speed: np.ndarray
    yaw_rate: np.ndarray
    fps: int = 10

    def total_abs_yaw(self) -> float:
        """Total absolute heading change (rad): sum |yaw_rate| / fps."""
        return float(np.sum(np.abs(self.yaw_rate)) / self.fps)


_A_ACCEL, _A_BRAKE, _A_PLAN = 3.5, 4.5, 3.5  # m/s^2: accelerate, strongest braking, planned braking
_EGO_HALF_LEN = 2.3
_ROUTE_DS = 0.2  # m between route polyline points
# Turn arcs: radii in lane widths (the widest that keep a right turn off the kerb corner; a left
# turn starts bending a few metres before the junction) and nominal speeds (m/s), both about
# 0.9 rad/s of yaw rate.
_R_TURN_LEFT, _R_TURN_RIGHT = 2.5, 1.5
_V_TURN_LEFT, _V_TURN_RIGHT = 7.5, 4.8


@dataclass
class _Route:
    """Dense lane-centre polyline of a planned route with its junction events."""

    xy: np.ndarray  # [n, 2] points every ~ds metres
    s: np.ndarray  # arc length at each point
    heading: np.ndarray  # unwrapped tangent heading
    curvature: np.ndarray  # signed (left positive)
    lane: np.ndarray  # [n, 3] (axis, road, direction) on straight lane pieces, -1 on turn arcs
    turns: list  # (s_arc_start, s_arc_end, v_turn)
    nodes: list  # per junction: s_stop, ij, lane, stop, wait, cruise (for the leg after it)


def _plan_route(town: Town, rng: np.random.Generator, length: float, ds: float = _ROUTE_DS) -> _Route:
    """Random lane-following route over the road grid: straight, left or right at each junction.

    Lanes are the right-hand lane centres (lane width = road half width ``hw``). Turns are quarter
    circles tangent to both lane centres: radius 1.5 hw for right turns, 2.5 hw for left turns.
    A corner of the grid is a bend: the route follows it (radius: the bend's plus or minus half a
    lane, concentric with it) at sqrt(lateral acceleration x radius), with no junction to stop at.
    """
    hw, st = town.half_width, town.style
    roads = (town.road_y, town.road_x)  # axis-0 roads run along x and sit at y = road_y[j]
    along = (town.road_x, town.road_y)  # junction coordinates along each axis

    def lane_point(axis, road, d, s):
        lat = roads[axis][road] + (-d if axis == 0 else d) * hw / 2
        return np.array([s, lat]) if axis == 0 else np.array([lat, s])

    axis = int(rng.integers(2))
    road = int(rng.integers(len(roads[axis])))
    d = int(rng.choice([-1, 1]))
    seg = int(rng.integers(len(along[axis]) - 1))
    # Start on the straight part of the leg: clear of junctions, and of bends at grid corners.
    c_lo, c_hi = (town.corner(*((k, road) if axis == 0 else (road, k))) for k in (seg, seg + 1))
    lo = along[axis][seg] + (hw + 8 if c_lo is None else town.bend_radius[c_lo] + 3.0)
    hi = along[axis][seg + 1] - (hw + 8 if c_hi is None else town.bend_radius[c_hi] + 3.0)
    s0 = rng.uniform(min(lo, hi), max(lo, hi))  # a block under 23 m has no clear part: near its middle
    nxt = seg + 1 if d > 0 else seg
    cur = lane_point(axis, road, d, s0)
    pts, heads, kaps, lanes, turns, nodes = [], [], [], [], [], []
    count = 0
    total = 0.0

    def add_line(p0, p1, ln):
        nonlocal count, total
        L = float(np.linalg.norm(p1 - p0))
        n = max(int(math.ceil(L / ds)), 1)
        pts.append(p0 + (p1 - p0) * (np.arange(n)[:, None] / n))
        heads.append(np.full(n, math.atan2(p1[1] - p0[1], p1[0] - p0[0])))
        kaps.append(np.zeros(n))
        lanes.append(np.tile(np.asarray(ln, np.float64), (n, 1)))
        count += n
        total += L

    while total < length:
        h = np.array([d, 0.0]) if axis == 0 else np.array([0.0, d])
        node_s = along[axis][nxt]
        ij = (nxt, road) if axis == 0 else (road, nxt)
        options, weights = [], []
        if 0 <= nxt + d < len(along[axis]):
            options.append(0)
            weights.append(st.straight_weight)
        for sign, share in ((1, 1.0 - st.right_share), (-1, st.right_share)):  # left, right
            new_d = int(round((np.array([-h[1], h[0]]) * sign)[1 - axis]))
            if 0 <= road + new_d < len(along[1 - axis]):
                options.append(sign)
                weights.append((1.0 - st.straight_weight) * share)
        choice = options[rng.choice(len(options), p=np.asarray(weights) / np.sum(weights))]
        bend = town.corner(*ij)
        if bend is None:
            nodes.append({"stop_xy": lane_point(axis, road, d, node_s - d * (hw + 6.3)), "ij": ij,
                          "lane": (axis, road, d), "stop": rng.random() < st.stop_prob,
                          "wait": rng.uniform(*st.stop_wait_s),
                          "cruise": rng.uniform(*st.cruise_ms), "first": count})
        if choice == 0:
            end = lane_point(axis, road, d, node_s + d * (hw + 1.0))
            add_line(cur, end, (axis, road, d))
            cur = end
            nxt += d
            continue
        sign = float(choice)
        left = np.array([-h[1], h[0]])
        new_h = left * sign
        if bend is None:
            radius = hw * (_R_TURN_LEFT if sign > 0 else _R_TURN_RIGHT)
            v_turn = (_V_TURN_LEFT if sign > 0 else _V_TURN_RIGHT) * rng.uniform(*st.turn_speed_scale)
        else:
            radius = town.bend_radius[bend] + sign * hw / 2
            v_turn = math.sqrt(rng.uniform(*st.bend_lateral_accel_ms2) * radius)
        # Where the incoming and outgoing lane centres cross; the arc is tangent to both.
        corner = lane_point(axis, road, d, node_s) + np.array([new_h[1], -new_h[0]]) * hw / 2
        start = corner - h * radius
        end = corner + new_h * radius
        centre = start + left * sign * radius
        add_line(cur, start, (axis, road, d))
        n = max(int(math.ceil(radius * np.pi / 2 / ds)), 1)
        a0 = math.atan2(start[1] - centre[1], start[0] - centre[0])
        ang = a0 + sign * (np.pi / 2) * np.arange(n) / n
        pts.append(centre + radius * np.stack([np.cos(ang), np.sin(ang)], 1))
        heads.append(ang + sign * np.pi / 2)
        kaps.append(np.full(n, sign / radius))
        lanes.append(np.full((n, 3), -1.0))
        turns.append((count, count + n, v_turn))
        count += n
        total += radius * np.pi / 2
        new_axis = 1 - axis
        new_d = int(round(new_h[new_axis]))
        axis, road, d, nxt = new_axis, nxt, new_d, road + new_d
        cur = end
    add_line(cur, cur + (np.array([d, 0.0]) if axis == 0 else np.array([0.0, d])) * 50.0, (axis, road, d))
    xy = np.concatenate(pts)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    for nd in nodes:  # stop point: nearest route point after the previous junction
        i = nd.pop("first")
        win = xy[i:i + int(200 / ds)]
        nd["s_stop"] = float(s[i + int(np.argmin(np.linalg.norm(win - nd.pop("stop_xy"), axis=1)))])
    turns = [(float(s[a]), float(s[min(b, len(s) - 1)]), v) for a, b, v in turns]
    return _Route(xy, s, np.unwrap(np.concatenate(heads)), np.concatenate(kaps), np.concatenate(lanes),
                  turns, nodes)


def _junction_busy(town: Town, ij, own_lane, t0: float, t1: float) -> bool:
    """Whether any car other than those on the ego's own lane is inside junction ij during [t0, t1]."""
    i, j = ij
    hw = town.half_width
    sel = ((town.car_axis == 0) & (town.car_road == j)) | ((town.car_axis == 1) & (town.car_road == i))
    axis, road, d = own_lane
    sel &= ~((town.car_axis == axis) & (town.car_road == road) & (town.car_dir == d))
    idx = np.nonzero(sel)[0]
    if len(idx) == 0:
        return False
    times = np.arange(t0, t1, 0.25)
    al = town.car_along(times)[:, idx]
    centre = np.where(town.car_axis[idx] == 0, town.road_x[i], town.road_y[j])
    return bool(np.any(np.abs(al - centre) < hw + 1.5 + 0.5 * town.car_length[idx]))


def simulate_ego(town: Town, seed: int, duration_s: float, fps: int) -> EgoTrack:
    """Drive the ego through the town for duration_s seconds; deterministic per (town, seed).

    The ego follows the right lane of a random route, cruises at the style's `cruise_ms` per leg,
    slows for turn arcs (to the arc's nominal speed times a factor drawn per turn), follows slower
    cars in its lane, and stops at the stop line of some junctions (always when crossing traffic
    would be in the junction on arrival), waiting 1-3 s and then until the junction is clear (at
    most 6 s). Planned stops are skipped when a car behind would run into the waiting ego.
    Steering is a curvature feed-forward plus heading/lateral-error feedback; poses are the exact
    integration of the per-step controls (`integrate_odometry`).
    """
    dt = 1.0 / fps
    steps = int(round(duration_s * fps))
    rng = _rng(seed, town.seed, town._salt, 7)
    route = _plan_route(town, rng, town.style.cruise_ms[1] * duration_s + 120.0)
    lane_cache: dict = {}
    x0, y0 = route.xy[0]
    yaw0 = float(route.heading[0])
    x, y, yaw = float(x0), float(y0), yaw0
    cruise = rng.uniform(*town.style.cruise_ms)
    v = cruise * rng.uniform(0.5, 1.0)
    speed = np.zeros(steps)
    yaw_rate = np.zeros(steps)
    idx, node_i, waited = 0, 0, 0.0
    n_pts = len(route.s)
    for k in range(steps):
        t = k * dt
        # Project onto the route (local forward search).
        hi = min(idx + int((v * dt + 3.0) / _ROUTE_DS) + 10, n_pts)
        idx += int(np.argmin(np.hypot(route.xy[idx:hi, 0] - x, route.xy[idx:hi, 1] - y)))
        hp = route.heading[idx]
        ex, ey = x - route.xy[idx, 0], y - route.xy[idx, 1]
        s = route.s[idx] + math.cos(hp) * ex + math.sin(hp) * ey  # continuous arc length
        e_y = -math.sin(hp) * ex + math.cos(hp) * ey  # lateral offset, left positive
        v_t = cruise
        for s_a, s_b, v_turn in route.turns:
            if s_b > s and s_a < s + 80.0:
                v_t = min(v_t, v_turn if s >= s_a else math.sqrt(v_turn ** 2 + 2 * _A_PLAN * (s_a - s)))
        stopping = False
        if node_i < len(route.nodes):
            nd = route.nodes[node_i]
            d_stop = nd["s_stop"] - s
            if d_stop < -2.0 and not nd.get("active"):
                node_i += 1
                cruise = nd["cruise"]
            else:
                if "decided" not in nd and d_stop < v * v / (2 * _A_PLAN) + 12.0:
                    nd["decided"] = True
                    t_arr = t + max(d_stop, 0.0) / max(v, 2.0)
                    rear = _rear_traffic(town, lane_cache, nd["lane"], x, y, t, t_arr - t + nd["wait"] + 4.0)
                    nd["active"] = nd["stop"] and not rear
                if "decided" in nd and not nd.get("active") and not nd.get("released") and (
                        d_stop > v * v / (2 * _A_BRAKE) + 0.3):
                    # Give way: stop if crossing traffic will be in the junction when we get there.
                    t_arr = t + d_stop / max(v, 2.0)
                    nd["active"] = _junction_busy(town, nd["ij"], nd["lane"], t_arr - 0.3, t_arr + 2.0)
                if nd.get("active"):
                    gap = max(d_stop, 0.0)
                    v_t = min(v_t, math.sqrt(2 * _A_PLAN * gap), gap + 0.1)
                    stopping = True
                    if gap < 0.3 and v <= _A_BRAKE * dt:
                        v_t = 0.0
                        waited += dt
                        clear = not _junction_busy(town, nd["ij"], nd["lane"], t, t + 2.5)
                        if waited >= nd["wait"] and (clear or waited > 6.0):
                            nd["active"] = False
                            nd["released"] = True
                            waited = 0.0
        lane = route.lane[idx]
        if lane[0] >= 0:
            v_t = min(v_t, _follow_speed(town, lane_cache, lane, x, y, t))
        v_new = min(max(v + min(max(v_t - v, -_A_BRAKE * dt), _A_ACCEL * dt), 0.0), town.style.cruise_ms[1])
        if stopping and v_t == 0.0:
            v_new = 0.0
        # Steering: curvature feed-forward + critically damped heading / lateral feedback.
        e_psi = (yaw - hp + math.pi) % (2 * math.pi) - math.pi
        ahead = min(idx + int(0.5 * v_new * dt / _ROUTE_DS), n_pts - 1)  # curvature mid-step
        lc = max(4.0, 2.5 * v_new * dt)
        w = v_new * (route.curvature[ahead] - 2.0 * e_psi / lc - e_y / (lc * lc))
        w = min(max(w, -1.8), 1.8)
        speed[k], yaw_rate[k] = v_new, w
        xs, ys, yaws = integrate_odometry([v_new, 0.0], [w, 0.0], fps, x, y, yaw)
        x, y, yaw, v = float(xs[1]), float(ys[1]), float(yaws[1]), v_new
    xs, ys, yaws = integrate_odometry(speed, yaw_rate, fps, x0, y0, yaw0)
    return EgoTrack(np.arange(steps) / fps, xs, ys, yaws, speed, yaw_rate, fps)


def _lane_along(town: Town, cache: dict, lane, x: float, y: float, t: float):
    """Cars on a lane: signed distance ahead of the ego (m, bumper to bumper) and their speeds."""
    axis, road, d = (int(c) for c in lane)
    key = (axis, road, d)
    if key not in cache:
        cache[key] = town.lane_cars(axis, road, d)
    idx = cache[key]
    ego = x if axis == 0 else y
    gap = d * (town.car_along(t)[idx] - ego) - 0.5 * town.car_length[idx] - _EGO_HALF_LEN
    return gap, town.car_speed[idx]


def _follow_speed(town: Town, cache: dict, lane, x: float, y: float, t: float) -> float:
    """Speed limit that keeps a safe gap to the nearest car ahead in the ego's lane."""
    gap, vc = _lane_along(town, cache, lane, x, y, t)
    ahead = (gap > -1.0) & (gap < 60.0)
    if not np.any(ahead):
        return town.style.cruise_ms[1]
    g, v = gap[ahead], vc[ahead]
    lim = np.minimum(v + 0.5 * (g - 7.0), np.sqrt(v * v + 2 * 3.0 * np.maximum(g - 4.0, 0.0)))
    return float(max(np.min(lim), 0.0))


def _rear_traffic(town: Town, cache: dict, lane, x: float, y: float, t: float, horizon: float) -> bool:
    """Whether a car behind on the ego's lane would reach the ego within `horizon` seconds."""
    gap, vc = _lane_along(town, cache, lane, x, y, t)
    behind = -gap - 2 * _EGO_HALF_LEN  # positive: distance from their front to our rear
    return bool(np.any((behind > -1.0) & (behind < vc * horizon + 8.0)))


def _rear_ghosts(town: Town, track: EgoTrack) -> np.ndarray:
    """[T, n_cars] mask of traffic cars to hide because they drive through the ego from behind.

    Traffic ignores the ego, so a car catching up with a waiting ego would pass through it and
    pop up right in front of the camera. Such a car is hidden from the first frame of its
    approach from behind (already out of view) to the end of the episode.
    """
    along = town.car_along(track.t)
    dx = np.where(town.car_axis == 0, along, town.car_lat) - track.x[:, None]
    dy = np.where(town.car_axis == 0, town.car_lat, along) - track.y[:, None]
    c, s = np.cos(track.yaw)[:, None], np.sin(track.yaw)[:, None]
    fwd, side = dx * c + dy * s, dy * c - dx * s
    overlap = (np.abs(fwd) < 0.5 * town.car_length + _EGO_HALF_LEN + 0.3) & (np.abs(side) < 2.1)
    hidden = np.zeros_like(overlap)
    for car in np.nonzero(overlap.any(axis=0))[0]:
        k = int(np.argmax(overlap[:, car]))
        while k > 0 and fwd[k - 1, car] < 0 and np.abs(side[k - 1, car]) < 2.1:
            k -= 1
        hidden[k:, car] = True
    return hidden
