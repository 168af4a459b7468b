"""Angles, guidance laws and the paper's equilibrium (sections 2-3, eqs. 1-5).

Sign convention of the paper's state equations. The paper's text defines alpha_t = gamma_t - lambda
and alpha_v = lambda - gamma_v, but its eq. 1 (alpha_t_dot = V_t/R - (V_t sin alpha_t - V sin
alpha_v)/d, alpha_v_dot = a/V - (...)/d), its equilibrium x_eq = (d*, asin(d*/2R), -asin(d*/2R),
V_c) and its platoon law a_i = V^2/d (-4 sin alpha_v - 2 sin alpha_t) all need alpha_v = gamma_v -
lambda: lambda_dot = (V_t sin(gamma_t - lambda) - V sin(gamma_v - lambda))/d is the kinematics.
``test_paper_state_equations_are_the_kinematics`` checks this against finite differences, and the
equilibrium tests below use alpha_v = gamma_v - lambda (with lambda - gamma_v the geometric state of
a vehicle on the circle would be +asin(d*/2R), not the paper's x_eq).
"""

from __future__ import annotations

import math

import pytest

from fmus.model.angles import wrap_angle
from fmus.model.guidance import (
    LAWS,
    equilibrium_angles,
    lateral_acceleration,
    line_of_sight,
    spacing_speed,
    spacing_speed_rate,
    speed_loop,
)

PI = math.pi


# --------------------------------------------------------------------------------------------------
# wrap_angle
# --------------------------------------------------------------------------------------------------


def test_wrap_angle_pi_stays_pi_and_minus_pi_becomes_pi():
    assert wrap_angle(PI) == PI
    assert wrap_angle(-PI) == PI
    # odd multiples of pi land on the closed end of (-pi, pi]: fmod is exact and 3*pi, 7*pi round
    # to within half an ulp of the float pi's multiples, so the result is the float pi exactly.
    assert wrap_angle(3.0 * PI) == PI
    assert wrap_angle(-3.0 * PI) == PI


def test_wrap_angle_is_identity_inside_the_interval():
    for x in (0.0, 1e-300, -1e-300, 0.5, -0.5, 3.0, -3.0, PI - 1e-15, -PI + 1e-15):
        assert wrap_angle(x) == x


def test_wrap_angle_just_outside_the_interval_wraps():
    # pi + 1e-12 is just above pi: it must come out just above -pi (same direction), and vice versa.
    assert wrap_angle(PI + 1e-12) == pytest.approx(-PI + 1e-12, abs=1e-15)
    assert wrap_angle(-PI - 1e-12) == pytest.approx(PI - 1e-12, abs=1e-15)


@pytest.mark.parametrize("k", [1, -1, 2, -2, 5, -7, 1000, -1000, 10**6, -(10**6)])
def test_wrap_angle_multiples_of_two_pi_wrap_to_zero(k):
    x = k * 2.0 * PI
    # fmod is exact, so the only error is the rounding of k * 2pi itself: half an ulp of x.
    assert abs(wrap_angle(x)) <= math.ulp(x)


@pytest.mark.parametrize("theta", [0.3, -2.9, 3.1, -0.001, 1.5])
@pytest.mark.parametrize("k", [3, -3, 250, -250, 10**5, -(10**5)])
def test_wrap_angle_large_windings(theta, k):
    x = theta + k * 2.0 * PI
    wrapped = wrap_angle(x)
    assert -PI < wrapped <= PI
    # rounding of theta + k*2pi is at most an ulp of x (two roundings of half an ulp each)
    assert wrapped == pytest.approx(theta, abs=2.0 * math.ulp(x))


def test_wrap_angle_range_and_equivalence_on_a_sweep():
    for i in range(-2000, 2001):
        x = i * 0.0137 + 0.001 * i * i  # irregular spacing, up to ~4000 rad
        w = wrap_angle(x)
        assert -PI < w <= PI
        # same direction: sin and cos agree to the rounding of |x| (< 1e-12 here)
        assert math.sin(w) == pytest.approx(math.sin(x), abs=1e-11)
        assert math.cos(w) == pytest.approx(math.cos(x), abs=1e-11)


# --------------------------------------------------------------------------------------------------
# line of sight and lateral acceleration
# --------------------------------------------------------------------------------------------------


def test_line_of_sight():
    d, los = line_of_sight(1.0, 2.0, 4.0, 6.0)
    assert d == pytest.approx(5.0, rel=1e-15)
    assert los == pytest.approx(math.atan2(4.0, 3.0), abs=1e-15)
    d, los = line_of_sight(0.0, 0.0, -1.0, 0.0)
    assert (d, los) == (1.0, PI)


def test_lateral_acceleration_rejects_unknown_law():
    with pytest.raises(ValueError, match="unknown guidance law"):
        lateral_acceleration("cosine", 1.0, 1.0, 0.1, 0.0, 0.0)
    with pytest.raises(ValueError):
        lateral_acceleration("", 1.0, 1.0, 0.0, 0.0, 0.0)
    with pytest.raises(ValueError):
        lateral_acceleration("Sine", 1.0, 1.0, 0.0, 0.0, 0.0)  # case matters


def test_lateral_acceleration_formulas():
    v, d, los, gv, gt = 3.0, 12.0, 0.4, 0.1, 0.9
    gain = v * v / d
    assert lateral_acceleration("regular", v, d, los, gv, gt) == pytest.approx(
        gain * (4 * (los - gv) + 2 * (los - gt)), rel=1e-14
    )
    assert lateral_acceleration("sine", v, d, los, gv, gt) == pytest.approx(
        gain * (4 * math.sin(los - gv) + 2 * math.sin(los - gt)), rel=1e-14
    )


@pytest.mark.parametrize("law", LAWS)
def test_lateral_acceleration_is_insensitive_to_winding(law):
    # wound-up headings (many turns) must act like their wrapped values
    v, d, los, gv, gt = 2.0, 5.0, 0.3, -0.2, 0.5
    ref = lateral_acceleration(law, v, d, los, gv, gt)
    wound = lateral_acceleration(law, v, d, los + 4 * 2 * PI, gv - 7 * 2 * PI, gt + 3 * 2 * PI)
    # rounding of ~50 rad angles: ~1e-14 rad, times gain*6 ~ 5
    assert wound == pytest.approx(ref, abs=1e-12)


def test_regular_law_wraps_large_errors():
    # an error of 350 deg is a -10 deg error for the regular law, not 350 deg
    a = lateral_acceleration("regular", 1.0, 1.0, math.radians(350.0), 0.0, 0.0)
    assert a == pytest.approx(6.0 * math.radians(-10.0), abs=1e-12)


def test_regular_and_sine_agree_to_second_order_for_small_angles():
    v, d = 4.0, 10.0
    gain = v * v / d
    diffs = []
    for eps in (1e-1, 5e-2, 2.5e-2, 1.25e-2):
        los, gv, gt = 0.7 + eps, 0.7 - 0.5 * eps, 0.7 + 2.0 * eps  # errors 1.5 eps and -eps
        reg = lateral_acceleration("regular", v, d, los, gv, gt)
        sin_ = lateral_acceleration("sine", v, d, los, gv, gt)
        diff = reg - sin_
        # x - sin x = x^3/6 - ...: the difference is gain*(4 (1.5eps)^3 + 2 (-eps)^3)/6 + O(eps^5)
        expected = gain * (4 * (1.5 * eps) ** 3 + 2 * (-eps) ** 3) / 6.0
        assert diff == pytest.approx(expected, rel=eps**2)  # next term relative size ~ eps^2/20
        # both laws are first order in eps; their difference is third order
        assert abs(diff) < 1e-2 * abs(reg) * eps / 1e-1
        diffs.append(diff)
    for coarse, fine in zip(diffs, diffs[1:]):
        assert coarse / fine == pytest.approx(8.0, rel=0.02)  # halving eps divides it by 2^3


# --------------------------------------------------------------------------------------------------
# The paper's equilibrium on a circle (eqs. 1, 4, 5)
# --------------------------------------------------------------------------------------------------


def paper_f(state, a, target_speed, curvature, k_v, v_c):
    """The paper's eq. 1: f(x, u) for x = (d, alpha_t, alpha_v, V), u = (1/R, V_c)."""
    d, alpha_t, alpha_v, v = state
    los_rate = (target_speed * math.sin(alpha_t) - v * math.sin(alpha_v)) / d
    return [
        target_speed * math.cos(alpha_t) - v * math.cos(alpha_v),
        target_speed * curvature - los_rate,
        a / v - los_rate,
        k_v * (v_c - v),
    ]


def circle_pose(radius, angle, direction=1):
    """Point of a circle about the origin at polar angle ``angle``, tangent heading for ``direction``."""
    return radius * math.cos(angle), radius * math.sin(angle), angle + direction * 0.5 * PI


def chase_geometry(radius, chord, target_angle=0.7, direction=1):
    """Target on the circle, tangent; vehicle on the circle a chord ``chord`` behind it, tangent."""
    tx, ty, gt = circle_pose(radius, target_angle, direction)
    behind = 2.0 * math.asin(chord / (2.0 * radius))  # central angle of the chord
    vx, vy, gv = circle_pose(radius, target_angle - direction * behind, direction)
    return (vx, vy, gv), (tx, ty, gt)


def paper_state_and_accel(law, radius, d_star, v_c, direction=1, target_angle=0.7):
    (vx, vy, gv), (tx, ty, gt) = chase_geometry(radius, d_star, target_angle, direction)
    d, los = line_of_sight(vx, vy, tx, ty)
    v = v_c
    target_speed = spacing_speed(v, d, d_star)  # eq. 3
    a = lateral_acceleration(law, v, d, los, gv, gt)
    state = (d, wrap_angle(gt - los), wrap_angle(gv - los), v)
    return state, a, target_speed


EQUILIBRIUM_CASES = [
    # (R, d*, V_c): the paper's simulation scale and its m3pi hardware values
    (50.0, 75.0, 10.0),
    (50.0, 20.0, 10.0),
    (1.0, 0.7, 0.35),
    (1.0, 1.9, 0.35),
]


@pytest.mark.parametrize("radius,d_star,v_c", EQUILIBRIUM_CASES)
def test_geometry_is_the_papers_equilibrium_state(radius, d_star, v_c):
    state, _, target_speed = paper_state_and_accel("sine", radius, d_star, v_c)
    alpha_t, alpha_v = equilibrium_angles(d_star, radius)
    # positions of order R, atan2/hypot: errors of a few ulp of R -> 1e-12 is generous
    assert state[0] == pytest.approx(d_star, rel=1e-12)
    assert state[1] == pytest.approx(alpha_t, abs=1e-12)
    assert state[2] == pytest.approx(alpha_v, abs=1e-12)
    assert alpha_t == pytest.approx(math.asin(d_star / (2 * radius)), rel=1e-15)
    assert alpha_v == -alpha_t
    assert target_speed == pytest.approx(v_c, rel=1e-12)


@pytest.mark.parametrize("direction", [1, -1])
@pytest.mark.parametrize("radius,d_star,v_c", EQUILIBRIUM_CASES)
def test_sine_law_equilibrium_is_a_fixed_point_on_a_circle(radius, d_star, v_c, direction):
    state, a, target_speed = paper_state_and_accel("sine", radius, d_star, v_c, direction)
    f = paper_f(state, a, target_speed, direction / radius, k_v=0.5, v_c=v_c)
    # every term is O(V/R) <= 0.35 1/s computed from O(1) trig of angles exact to ~1e-16:
    # the residual is rounding only, ~1e-16; 1e-12 leaves a wide margin.
    assert max(abs(c) for c in f) < 1e-12
    # and the sine law commands exactly the circle's centripetal acceleration
    assert a == pytest.approx(direction * v_c**2 / radius, rel=1e-12)


@pytest.mark.parametrize("radius,d_star,v_c", EQUILIBRIUM_CASES)
def test_sine_law_fixed_point_from_the_papers_x_eq_directly(radius, d_star, v_c):
    # The same check with x_eq as printed, the law written in the paper's state variables:
    # lambda - gamma_v = -alpha_v and lambda - gamma_t = -alpha_t.
    alpha_t, alpha_v = equilibrium_angles(d_star, radius)
    los = 0.3
    gv, gt = los + alpha_v, los + alpha_t
    a = lateral_acceleration("sine", v_c, d_star, los, gv, gt)
    f = paper_f((d_star, alpha_t, alpha_v, v_c), a, spacing_speed(v_c, d_star, d_star), 1 / radius, 0.5, v_c)
    assert max(abs(c) for c in f) < 1e-12  # rounding only, see above


@pytest.mark.parametrize("radius,d_star,v_c", EQUILIBRIUM_CASES)
def test_regular_law_equilibrium_is_not_a_fixed_point_on_a_circle(radius, d_star, v_c):
    state, a, target_speed = paper_state_and_accel("regular", radius, d_star, v_c)
    f = paper_f(state, a, target_speed, 1.0 / radius, k_v=0.5, v_c=v_c)
    # regular law: a = V^2/d * (2 alpha) instead of V^2/d * 2 sin(alpha) = V^2/R, so
    # alpha_v_dot = V (2 alpha - 2 sin alpha)/d; smallest case (R=50, d*=20, V=10): ~2.7e-3.
    alpha = math.asin(d_star / (2 * radius))
    expected = v_c * (2 * alpha - 2 * math.sin(alpha)) / d_star
    assert f[2] == pytest.approx(expected, rel=1e-9)
    assert abs(f[2]) > 1e-3
    assert f[0] == pytest.approx(0.0, abs=1e-12) and f[1] == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("law", LAWS)
@pytest.mark.parametrize("d_star,v_c", [(75.0, 10.0), (0.7, 0.35)])
def test_both_laws_have_the_equilibrium_on_a_straight_line(law, d_star, v_c):
    heading = 0.4
    vx, vy = 3.0, -2.0
    tx, ty = vx + d_star * math.cos(heading), vy + d_star * math.sin(heading)
    d, los = line_of_sight(vx, vy, tx, ty)
    a = lateral_acceleration(law, v_c, d, los, heading, heading)
    state = (d, wrap_angle(heading - los), wrap_angle(heading - los), v_c)
    f = paper_f(state, a, spacing_speed(v_c, d, d_star), 0.0, k_v=0.5, v_c=v_c)  # 1/R = 0
    assert max(abs(c) for c in f) < 1e-12  # atan2 rounding of the LOS only
    assert abs(a) < 1e-12


@pytest.mark.parametrize("direction", [1, -1])
@pytest.mark.parametrize("radius", [50.0, 1.0])
def test_sine_law_circle_invariance(radius, direction):
    """A vehicle on the circle, tangent, chasing any target on the circle, tangent: a = V^2/R.

    The chord angle phi gives lambda - gamma_v = phi/2 and lambda - gamma_t = -phi/2, so the sine law
    gives V^2/d * 2 sin(phi/2) = V^2/d * d/R whatever the chord and whatever the target's speed.
    """
    for k in range(1, 40):
        phi = k * 2 * PI / 40.0  # target up to almost a full turn ahead, wrapped angles included
        chord = 2 * radius * math.sin(0.5 * phi)
        for speed in (0.1, 0.35, 3.0, 17.0):
            for start in (0.0, 2.0, -3.0, 40.0):  # wound-up polar angles too
                vx, vy, gv = circle_pose(radius, start, direction)
                tx, ty, gt = circle_pose(radius, start + direction * phi, direction)
                d, los = line_of_sight(vx, vy, tx, ty)
                assert d == pytest.approx(chord, rel=1e-9, abs=1e-12)
                a = lateral_acceleration("sine", speed, d, los, gv, gt)
                # relative rounding of d (shortest chord ~0.16 R) and of the angles: < 1e-12
                assert a == pytest.approx(direction * speed**2 / radius, rel=1e-11)


def test_regular_law_breaks_circle_invariance():
    radius, speed = 50.0, 10.0
    vx, vy, gv = circle_pose(radius, 0.0)
    tx, ty, gt = circle_pose(radius, 1.5)
    d, los = line_of_sight(vx, vy, tx, ty)
    a = lateral_acceleration("regular", speed, d, los, gv, gt)
    # regular: V^2/d * phi vs V^2/R: phi/(2 sin(phi/2)) = 1.5/(2 sin 0.75) = 1.098
    assert a / (speed**2 / radius) == pytest.approx(1.5 / (2 * math.sin(0.75)), rel=1e-9)


def test_paper_state_equations_are_the_kinematics():
    """eq. 1 with alpha_t = gamma_t - lambda, alpha_v = gamma_v - lambda matches finite differences.

    Target on a circle of radius R at speed V_t; vehicle moving with speed V and heading rate a/V.
    Central differences with h = 1e-5 s: truncation ~h^2 * (third derivative ~1) ~ 1e-10, rounding
    ~1e-16 / 1e-5 = 1e-11; tolerance 1e-7.
    """
    radius, vt, v, a = 20.0, 3.0, 2.5, 0.8
    x0, y0, g0 = 5.0, -4.0, 1.1  # vehicle initial pose, off the path

    def geometry(t):
        theta = 0.3 + vt * t / radius
        tx, ty, gt = circle_pose(radius, theta)
        turn = a / v
        g = g0 + turn * t
        vx = x0 + v * (math.sin(g) - math.sin(g0)) / turn
        vy = y0 - v * (math.cos(g) - math.cos(g0)) / turn
        d, los = line_of_sight(vx, vy, tx, ty)
        return d, gt - los, g - los

    h = 1e-5
    plus, minus = geometry(h), geometry(-h)
    numeric = [(p - m) / (2 * h) for p, m in zip(plus, minus)]
    d, alpha_t, alpha_v = geometry(0.0)
    f = paper_f((d, alpha_t, alpha_v, v), a, vt, 1 / radius, k_v=0.0, v_c=v)
    assert f[:3] == pytest.approx(numeric, abs=1e-7)
    # with the text's alpha_v = lambda - gamma_v the alpha_t equation would be off by 2 V sin/d
    wrong = paper_f((d, alpha_t, -alpha_v, v), a, vt, 1 / radius, 0.0, v)
    assert abs(wrong[1] - numeric[1]) > 1e-2


# --------------------------------------------------------------------------------------------------
# spacing speed and speed loop
# --------------------------------------------------------------------------------------------------


def test_spacing_speed():
    assert spacing_speed(10.0, 75.0, 75.0) == 10.0  # at the spacing, same speed (eq. 3)
    assert spacing_speed(10.0, 150.0, 75.0) == pytest.approx(5.0, rel=1e-15)  # far: slower
    assert spacing_speed(0.35, 0.35, 0.7) == pytest.approx(0.7, rel=1e-15)  # close: faster


@pytest.mark.parametrize(
    "v0,vdot,d0,ddot,d_star",
    [(10.0, 0.3, 80.0, -1.5, 75.0), (0.35, -0.05, 0.6, 0.02, 0.7), (2.0, 0.0, 5.0, 1.0, 3.0)],
)
def test_spacing_speed_rate_is_the_time_derivative(v0, vdot, d0, ddot, d_star):
    # speed and gap quadratic in time; the central difference of the spacing speed at t = 0 has
    # truncation ~h^2 * f''' ~ 1e-8 * O(1) and rounding ~eps * O(10) / h ~ 1e-11: tolerance 1e-7.
    def spacing(t):
        return spacing_speed(v0 + vdot * t + 0.1 * t * t, d0 + ddot * t - 0.2 * t * t, d_star)

    h = 1e-4
    numeric = (spacing(h) - spacing(-h)) / (2 * h)
    analytic = spacing_speed_rate(v0, vdot, d0, ddot, d_star)
    assert analytic == pytest.approx(numeric, abs=1e-7, rel=1e-7)


def test_spacing_speed_rate_zero_when_speed_and_gap_are_steady():
    assert spacing_speed_rate(10.0, 0.0, 75.0, 0.0, 75.0) == 0.0


def test_speed_loop():
    assert speed_loop(0.5, 10.0, 8.0) == pytest.approx(1.0)
    assert speed_loop(0.5, 10.0, 10.0) == 0.0
    assert speed_loop(2.0, 0.35, 0.45) == pytest.approx(-0.2)


def test_equilibrium_angles():
    alpha_t, alpha_v = equilibrium_angles(0.7, 1.0)
    assert alpha_t == pytest.approx(math.asin(0.35), rel=1e-15)
    assert alpha_v == -alpha_t
    alpha_t, alpha_v = equilibrium_angles(100.0, 50.0)  # chord = diameter
    assert alpha_t == pytest.approx(PI / 2, rel=1e-15)
