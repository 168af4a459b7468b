"""Paths (pose, tangent, curvature, signed distance, chords), vehicle dynamics and the RK4 integrator."""

from __future__ import annotations

import math

import pytest

from fmus.model.angles import wrap_angle
from fmus.model.dynamics import (
    M3PI_TRACK,
    KinematicDynamics,
    M3piDynamics,
    differential_wheel_speeds,
    make_dynamics,
)
from fmus.model.integrate import integrate, rk4_step, substep_count
from fmus.model.paths import PATH_KINDS, CirclePath, LinePath, make_path

PI = math.pi

PATHS = [
    CirclePath(50.0),
    CirclePath(50.0, direction=-1),
    CirclePath(1.0, center_x=2.0, center_y=-3.0, direction=1, start_angle=0.4),
    CirclePath(1.0, center_x=-0.5, center_y=0.25, direction=-1, start_angle=-2.0),
    LinePath(),
    LinePath(3.0, -1.0, 2.2),
    LinePath(-10.0, 4.0, -0.7),
]
PATH_IDS = ["ccw50", "cw50", "ccw1", "cw1", "line0", "line1", "line2"]
ARCS = [-120.0, -3.3, 0.0, 0.01, 1.0, 7.5, 400.0]


def scale(path):
    return path.radius if isinstance(path, CirclePath) else 1.0


# --------------------------------------------------------------------------------------------------
# paths
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("path", PATHS, ids=PATH_IDS)
def test_pose_is_on_the_path(path):
    for s in ARCS:
        x, y, _ = path.pose_at(s)
        # coordinates of order 400 m at most: hypot/projection rounding is ~1e-13 absolute
        assert abs(path.signed_distance(x, y)) < 1e-12 * max(1.0, abs(x), abs(y))


@pytest.mark.parametrize("path", PATHS, ids=PATH_IDS)
def test_heading_is_the_tangent(path):
    for s in ARCS:
        h = 1e-4 * scale(path)
        x1, y1, _ = path.pose_at(s - h)
        x2, y2, _ = path.pose_at(s + h)
        _, _, heading = path.pose_at(s)
        dx, dy = (x2 - x1) / (2 * h), (y2 - y1) / (2 * h)
        # central difference: direction error ~ (h/R)^2/6 ~ 2e-9; its length is the unit speed of
        # the arc-length parametrization to the same order; rounding ~eps*400/h ~ 1e-9 at most.
        assert math.hypot(dx, dy) == pytest.approx(1.0, abs=1e-7)
        assert abs(wrap_angle(math.atan2(dy, dx) - heading)) < 1e-7


@pytest.mark.parametrize("path", PATHS, ids=PATH_IDS)
def test_curvature_is_the_heading_rate(path):
    for s in ARCS:
        h = 1e-3 * scale(path)
        rate = wrap_angle(path.pose_at(s + h)[2] - path.pose_at(s - h)[2]) / (2 * h)
        # the heading is linear in s on both paths: only rounding, ~eps * |heading| / h ~ 1e-11
        assert rate == pytest.approx(path.curvature(s), abs=1e-9 / scale(path))


def test_curvature_sign_follows_direction():
    assert CirclePath(50.0, direction=1).curvature(3.0) == pytest.approx(1 / 50.0, rel=1e-15)
    assert CirclePath(50.0, direction=-1).curvature(3.0) == pytest.approx(-1 / 50.0, rel=1e-15)
    assert LinePath(heading=1.0).curvature(3.0) == 0.0
    # counter-clockwise turns left: the centre is on the left of the heading, and vice versa
    for direction in (1, -1):
        path = CirclePath(2.0, 1.0, 1.0, direction, 0.3)
        x, y, heading = path.pose_at(1.7)
        to_centre = (1.0 - x, 1.0 - y)
        left = (-math.sin(heading), math.cos(heading))
        assert direction * (to_centre[0] * left[0] + to_centre[1] * left[1]) == pytest.approx(2.0, rel=1e-12)


def test_circle_start_and_direction():
    path = CirclePath(2.0, 1.0, -1.0, 1, 0.5)
    x, y, heading = path.pose_at(0.0)
    assert (x, y) == pytest.approx((1.0 + 2.0 * math.cos(0.5), -1.0 + 2.0 * math.sin(0.5)), abs=1e-15)
    assert heading == pytest.approx(0.5 + PI / 2, abs=1e-15)
    # a quarter turn of arc, either way
    x, y, _ = path.pose_at(PI)  # s = pi = R * pi/2
    assert (x, y) == pytest.approx((1.0 + 2.0 * math.cos(0.5 + PI / 2), -1.0 + 2.0 * math.sin(0.5 + PI / 2)), abs=1e-14)
    cw = CirclePath(2.0, 1.0, -1.0, -1, 0.5)
    x, y, heading = cw.pose_at(PI)
    assert (x, y) == pytest.approx((1.0 + 2.0 * math.cos(0.5 - PI / 2), -1.0 + 2.0 * math.sin(0.5 - PI / 2)), abs=1e-14)
    assert wrap_angle(heading - (0.5 - PI)) == pytest.approx(0.0, abs=1e-14)


@pytest.mark.parametrize("path", PATHS[:4], ids=PATH_IDS[:4])
def test_arc_for_chord_inverts_the_chord(path):
    radius = path.radius
    for fraction in (1e-6, 0.01, 0.3, 0.7, 0.99, 1.0):
        chord = fraction * 2 * radius
        arc = path.arc_for_chord(chord)
        for s in (0.0, 1.3, -5.0):
            x1, y1, _ = path.pose_at(s)
            x2, y2, _ = path.pose_at(s + arc)
            # positions of order R + centre offset (<= 54 m): rounding ~1e-14
            assert math.hypot(x2 - x1, y2 - y1) == pytest.approx(chord, rel=1e-9, abs=1e-12)
        assert arc >= chord  # an arc is never shorter than its chord
    assert path.arc_for_chord(2 * radius) == pytest.approx(PI * radius, rel=1e-15)
    assert path.arc_for_chord(0.0) == 0.0
    with pytest.raises(ValueError):
        path.arc_for_chord(2 * radius * (1 + 1e-9))


def test_line_arc_for_chord_is_the_chord():
    path = LinePath(1.0, 2.0, 0.3)
    for chord in (0.0, 0.7, 75.0, 1e6):
        assert path.arc_for_chord(chord) == chord


@pytest.mark.parametrize("direction", [1, -1])
def test_circle_signed_distance_is_positive_outside(direction):
    path = CirclePath(5.0, 1.0, 2.0, direction, 0.0)
    for angle in (0.0, 1.0, -2.5):
        for offset in (-4.0, -0.1, 0.0, 0.1, 3.0):
            r = 5.0 + offset
            x, y = 1.0 + r * math.cos(angle), 2.0 + r * math.sin(angle)
            assert path.signed_distance(x, y) == pytest.approx(offset, abs=1e-14)
    assert path.signed_distance(1.0, 2.0) == -5.0  # the centre
    nx, ny = path.outward_normal(1.0 + 3.0, 2.0 + 4.0)
    assert (nx, ny) == pytest.approx((0.6, 0.8), abs=1e-15)


def test_line_signed_distance_is_positive_to_the_right_of_travel():
    for heading in (0.0, 0.9, PI / 2, -2.4, PI):
        path = LinePath(3.0, -1.0, heading)
        right = (math.sin(heading), -math.cos(heading))  # heading rotated by -90 degrees
        for s in (-4.0, 0.0, 6.0):
            x0, y0, _ = path.pose_at(s)
            for offset in (-2.0, 0.5, 10.0):
                x, y = x0 + offset * right[0], y0 + offset * right[1]
                assert path.signed_distance(x, y) == pytest.approx(offset, abs=1e-13)
        assert path.outward_normal(0.0, 0.0) == pytest.approx(right, abs=1e-15)
    # heading east: south (y < 0) is on the right
    assert LinePath().signed_distance(5.0, -1.0) == 1.0
    assert LinePath().signed_distance(5.0, 1.0) == -1.0


def test_line_right_matches_ccw_circle_outside():
    # on a CCW circle travel, outside is on the right of travel, as for a line
    circle = CirclePath(10.0)
    x, y, heading = circle.pose_at(4.0)
    right = (math.sin(heading), -math.cos(heading))
    assert circle.signed_distance(x + 0.5 * right[0], y + 0.5 * right[1]) == pytest.approx(0.5, rel=1e-9)
    tangent_line = LinePath(x, y, heading)
    assert tangent_line.signed_distance(x + 0.5 * right[0], y + 0.5 * right[1]) == pytest.approx(0.5, rel=1e-12)


def test_make_path_builds_the_right_paths():
    circle = make_path("circle", radius=2.0, x0=1.0, y0=-1.0, heading=0.5, direction=-1)
    assert circle == CirclePath(2.0, 1.0, -1.0, -1, 0.5)
    line = make_path("line", x0=1.0, y0=-1.0, heading=0.5)
    assert line == LinePath(1.0, -1.0, 0.5)
    assert set(PATH_KINDS) == {"circle", "line"}


@pytest.mark.parametrize(
    "kwargs",
    [
        {"kind": "spiral"},
        {"kind": "Circle"},
        {"kind": ""},
        {"kind": "circle", "radius": 0.0},
        {"kind": "circle", "radius": -5.0},
        {"kind": "circle", "radius": float("nan")},
        {"kind": "circle", "direction": 0},
        {"kind": "circle", "direction": 2},
        {"kind": "circle", "direction": -2},
    ],
)
def test_make_path_rejects_bad_parameters(kwargs):
    with pytest.raises(ValueError):
        make_path(**kwargs)


# --------------------------------------------------------------------------------------------------
# dynamics
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("speed", [0.35, 1.0, 10.0, -0.5])
@pytest.mark.parametrize("accel", [0.0, 0.1225, -2.0, 30.0])
@pytest.mark.parametrize("track", [M3PI_TRACK, 1.5])
def test_differential_wheel_speeds_eqs_9_10(speed, accel, track):
    right, left = differential_wheel_speeds(speed, accel, track)
    assert 0.5 * (right + left) == pytest.approx(speed, rel=1e-14, abs=1e-15)
    assert (right - left) / track == pytest.approx(accel / speed, rel=1e-12, abs=1e-15)
    if accel != 0.0:
        turn_radius = speed**2 / accel  # R_t = V^2/a
        assert right == pytest.approx(speed * (1 + track / (2 * turn_radius)), rel=1e-12)
        assert left == pytest.approx(speed * (1 - track / (2 * turn_radius)), rel=1e-12)
    else:
        assert right == left == speed


def test_kinematic_derivative():
    dyn = KinematicDynamics(k_v=0.5)
    state = dyn.initial_state(1.0, 2.0, 0.3, 4.0)
    assert state == [1.0, 2.0, 0.3, 4.0]
    der = dyn.derivative(state, 2.0, 6.0, 0.0)
    assert der == pytest.approx([4 * math.cos(0.3), 4 * math.sin(0.3), 0.5, 1.0], rel=1e-15)
    # a speed disturbance moves the vehicle faster over ground; the speed loop does not see it
    der = dyn.derivative(state, 2.0, 6.0, 1.0)
    assert der == pytest.approx([5 * math.cos(0.3), 5 * math.sin(0.3), 0.4, 1.0], rel=1e-15)
    assert dyn.speed(state, 1.0) == 5.0
    assert dyn.heading_rate(der) == der[2] and dyn.speed_rate(der) == der[3]


@pytest.mark.parametrize("setpoint", [0.2, 0.35, 0.6])
@pytest.mark.parametrize("accel", [0.0, 0.1225, -0.3, 0.5])
def test_m3pi_steady_state_turns_like_the_kinematic_model(setpoint, accel):
    m3pi = M3piDynamics(k_v=0.5)
    right_cmd, left_cmd = m3pi.wheel_commands(setpoint, accel)
    assert max(abs(right_cmd), abs(left_cmd)) < m3pi.wheel_speed_max  # unclipped cases
    state = [0.3, -0.2, 1.2, right_cmd, left_cmd, setpoint]
    der = m3pi.derivative(state, accel, setpoint, 0.0)
    # wheels at their commands: no motor transient, setpoint at its command: no speed change
    assert der[3] == pytest.approx(0.0, abs=1e-12) and der[4] == pytest.approx(0.0, abs=1e-12)
    assert der[5] == 0.0
    assert m3pi.speed_rate(der) == pytest.approx(0.0, abs=1e-12)
    assert m3pi.speed(state, 0.0) == pytest.approx(setpoint, rel=1e-14)
    kin = KinematicDynamics(k_v=0.5)
    kder = kin.derivative([0.3, -0.2, 1.2, setpoint], accel, setpoint, 0.0)
    # heading rate a/V_s, and the same velocity over ground (rounding only)
    assert m3pi.heading_rate(der) == pytest.approx(accel / setpoint, rel=1e-12, abs=1e-15)
    assert der[:3] == pytest.approx(kder[:3], rel=1e-12, abs=1e-15)


def test_m3pi_motor_lag_and_speed_loop():
    m3pi = M3piDynamics(k_v=2.0, motor_time_constant=0.05)
    state = m3pi.initial_state(0.0, 0.0, 0.0, 0.3)
    assert state == [0.0, 0.0, 0.0, 0.3, 0.3, 0.3]
    der = m3pi.derivative(state, 0.0, 0.5, 0.0)
    assert der[3] == der[4] == 0.0  # wheels already at the setpoint's commands
    assert der[5] == pytest.approx(2.0 * 0.2)  # the controller's speed loop on the setpoint
    state = [0.0, 0.0, 0.0, 0.2, 0.1, 0.3]
    der = m3pi.derivative(state, 0.0, 0.3, 0.0)
    assert der[3] == pytest.approx((0.3 - 0.2) / 0.05) and der[4] == pytest.approx((0.3 - 0.1) / 0.05)
    assert der[2] == pytest.approx((0.2 - 0.1) / M3PI_TRACK)
    assert m3pi.wheel_speeds(state, 0.0, 0.05) == pytest.approx((0.25, 0.15))


def test_m3pi_wheel_commands_are_clipped():
    m3pi = M3piDynamics(k_v=0.5, wheel_speed_max=1.0)
    # hard left turn: right wheel would exceed the limit
    right, left = m3pi.wheel_commands(0.8, 20.0)
    unclipped = differential_wheel_speeds(0.8, 20.0, M3PI_TRACK)
    assert unclipped[0] > 1.0 and right == 1.0
    assert left == pytest.approx(unclipped[1])
    # both wheels beyond the limit: both clipped, the turn is lost
    right, left = m3pi.wheel_commands(1.5, 0.1)
    assert (right, left) == (1.0, 1.0)
    # hard right turn at low speed: the right wheel runs backwards, clipped at -limit
    right, left = m3pi.wheel_commands(0.1, -20.0)
    assert right == -1.0 and left == 1.0
    # clipped commands turn slower than a/V
    state = [0.0, 0.0, 0.0, right, left, 0.1]
    assert m3pi.derivative(state, -20.0, 0.1, 0.0)[2] == pytest.approx(-2.0 / M3PI_TRACK)
    assert abs(-2.0 / M3PI_TRACK) < abs(-20.0 / 0.1)
    # a different limit is honoured
    assert M3piDynamics(k_v=0.5, wheel_speed_max=0.4).wheel_commands(0.35, 1.0) == pytest.approx(
        (0.4, 0.35 - 0.5 * M3PI_TRACK * 1.0 / 0.35)
    )


def test_make_dynamics():
    assert make_dynamics("kinematic", 0.5, track=0.1) == KinematicDynamics(0.5, 0.1)
    assert make_dynamics("m3pi", 0.5, 0.1, 0.8, 0.02) == M3piDynamics(0.5, 0.1, 0.8, 0.02)
    with pytest.raises(ValueError, match="unknown dynamics"):
        make_dynamics("bicycle", 0.5)


# --------------------------------------------------------------------------------------------------
# integrator
# --------------------------------------------------------------------------------------------------


def test_substep_count():
    assert substep_count(0.01, 0.01) == 1
    assert substep_count(0.02, 0.01) == 2
    assert substep_count(0.025, 0.01) == 3
    assert substep_count(0.3, 0.1) == 3  # 0.3/0.1 = 2.9999999999999996 in floating point
    assert substep_count(0.7, 0.1) == 7
    # 0.07/0.01 = 7.000000000000001 in floating point: the tolerance keeps it at 7, not 8
    assert 0.07 / 0.01 > 7.0
    assert substep_count(0.07, 0.01) == 7
    assert substep_count(0.14, 0.005) == 28
    # but a step really longer than n substeps needs n + 1
    assert substep_count(0.0700001, 0.01) == 8
    assert substep_count(0.001, 0.01) == 1
    assert substep_count(1.0, 0.01) == 100


def test_integrate_uses_equal_substeps():
    calls = []

    def f(t, y):
        calls.append(t)
        return [1.0]

    assert integrate(f, 2.0, [0.0], 0.025, 0.01) == pytest.approx([0.025], rel=1e-14)
    assert len(calls) == 12  # 3 substeps of 4 stages
    h = 0.025 / 3
    expected = []
    for k in range(3):
        t0 = 2.0 + k * h
        expected += [t0, t0 + h / 2, t0 + h / 2, t0 + h]
    assert calls == pytest.approx(expected, abs=1e-15)


def test_rk4_is_exact_for_cubic_time_dependence():
    # y' = 3 t^2 + 2 t: Simpson's rule (RK4 for f(t)) is exact for cubics; rounding only
    y = integrate(lambda t, y: [3 * t * t + 2 * t], 1.5, [1.5**3 + 1.5**2], 0.7, 0.1)
    assert y[0] == pytest.approx(2.2**3 + 2.2**2, rel=1e-13)


def _order(errors):
    return [math.log2(a / b) for a, b in zip(errors, errors[1:])]


def test_rk4_converges_with_order_four_on_decay():
    errors = []
    for n in (10, 20, 40, 80):
        y = integrate(lambda t, y: [-y[0]], 0.0, [1.0], 2.0, 2.0 / n)
        errors.append(abs(y[0] - math.exp(-2.0)))
    # errors 4e-6 .. 9e-10, far above rounding (1e-16): the observed order tends to 4 as h -> 0,
    # the h^5 term adding ~0.03 per halving at these steps (measured 4.12, 4.06, 4.03)
    orders = _order(errors)
    for p in orders:
        assert p == pytest.approx(4.0, abs=0.15)
    assert abs(orders[-1] - 4.0) < abs(orders[0] - 4.0)  # approaching 4 from the asymptotics


def test_rk4_converges_with_order_four_on_rotation():
    def f(t, y):
        return [-y[1], y[0]]

    errors = []
    for n in (8, 16, 32, 64):
        y = [1.0, 0.0]
        h = 2 * PI / n
        for _ in range(n):
            y = rk4_step(f, 0.0, y, h)
        errors.append(math.hypot(y[0] - 1.0, y[1]))
    for p in _order(errors):
        assert p == pytest.approx(4.0, abs=0.15)
