"""Coupling between communication points: arc extrapolation, and a vehicle stepper in hold/extrapolate."""

from __future__ import annotations

import math

import pytest

from fmus.model import coupling
from fmus.model.angles import wrap_angle
from fmus.model.coupling import COUPLING_MODES, arc_extrapolate, check_coupling, linear_extrapolate
from fmus.model.dynamics import KinematicDynamics
from fmus.model.guidance import spacing_speed
from fmus.model.factory import vehicle_parameter_errors
from fmus.model.vehicle import VehicleModel, VehicleStepper

PI = math.pi


def on_circle(cx, cy, radius, angle, direction):
    """Point of the circle at polar angle ``angle`` and its tangent heading for ``direction``."""
    return cx + radius * math.cos(angle), cy + radius * math.sin(angle), angle + direction * 0.5 * PI


# --------------------------------------------------------------------------------------------------
# arc_extrapolate
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("direction", [1, -1])
@pytest.mark.parametrize("radius,speed", [(50.0, 10.0), (1.0, 0.35), (3.0, 2.0)])
@pytest.mark.parametrize("speed_rate", [0.0, 0.4, -0.05])
def test_arc_extrapolate_stays_on_the_circle(radius, speed, speed_rate, direction):
    cx, cy = 2.0, -1.0
    for angle in (0.0, 1.0, -2.8):
        x, y, heading = on_circle(cx, cy, radius, angle, direction)
        for dt in (-2.0, -0.3, -1e-4, 0.0, 1e-6, 0.01, 0.5, 3.0):
            ex, ey, eh, ev = arc_extrapolate(x, y, heading, speed, speed_rate, direction * speed / radius, dt)
            # coordinates of order R + 2: the closed form rounds to a few ulp of them (~1e-14)
            assert abs(math.hypot(ex - cx, ey - cy) - radius) < 1e-12
            # still tangent, and moved by the arc length (speed*dt + speed_rate*dt^2/2)/R in angle
            polar = math.atan2(ey - cy, ex - cx)
            assert abs(wrap_angle(eh - (polar + direction * 0.5 * PI))) < 1e-12
            arc = dt * (speed + 0.5 * speed_rate * dt)
            assert abs(wrap_angle(polar - angle - direction * arc / radius)) < 1e-12
            assert ev == pytest.approx(speed + speed_rate * dt, rel=1e-15, abs=1e-15)


@pytest.mark.parametrize("speed_rate", [0.0, 1.5, -0.5])
def test_arc_extrapolate_zero_turn_rate_is_a_straight_line(speed_rate):
    x, y, heading, speed = 1.0, 2.0, 0.7, 3.0
    for dt in (-1.0, 0.0, 0.25, 2.0):
        ex, ey, eh, ev = arc_extrapolate(x, y, heading, speed, speed_rate, 0.0, dt)
        arc = speed * dt + 0.5 * speed_rate * dt * dt
        assert (ex, ey) == pytest.approx((x + arc * math.cos(heading), y + arc * math.sin(heading)), abs=1e-14)
        assert eh == heading
        assert ev == pytest.approx(speed + speed_rate * dt, abs=1e-15)


def test_arc_extrapolate_zero_dt_is_the_sample():
    assert arc_extrapolate(1.0, 2.0, 0.3, 4.0, 0.5, 0.2, 0.0) == (1.0, 2.0, 0.3, 4.0)


def exact_arc(x, y, heading, curvature, arc):
    """Reference: the point of the circle through (x, y) with the given curvature, via its centre."""
    cx, cy = x - math.sin(heading) / curvature, y + math.cos(heading) / curvature
    h2 = heading + curvature * arc
    return cx + math.sin(h2) / curvature, cy - math.cos(h2) / curvature, h2


@pytest.mark.parametrize("sign", [1, -1])
def test_arc_series_and_closed_form_agree_at_the_switch(sign, monkeypatch):
    limit = coupling._SERIES_LIMIT
    assert limit == pytest.approx(1e-3)  # the switch this test is written around
    # speed 1, turn rate 1e-3 (radius 1000 m), dt around 1 s: turn u = 1e-3 * dt crosses the switch
    x, y, heading, speed = 3.0, -2.0, 0.4, 1.0
    below = arc_extrapolate(x, y, heading, speed, 0.0, sign * 1e-3, 1.0 - 1e-9)  # series
    above = arc_extrapolate(x, y, heading, speed, 0.0, sign * 1e-3, 1.0 + 1e-9)  # closed form
    # continuity across the switch: the outputs move by ~1e-9 (the dt change) and nothing more
    assert above[:3] == pytest.approx(below[:3], abs=3e-9)
    # each branch against the centre-based reference (cancellation there ~R * eps ~ 2e-13)
    for dt, result in ((1.0 - 1e-9, below), (1.0 + 1e-9, above)):
        ref = exact_arc(x, y, heading, sign * 1e-3, dt)
        assert result[:3] == pytest.approx(ref, abs=1e-11)
    # the same input through both branches: force the other one by moving the switch.
    # Closed form (1 - cos u)/u at u ~ 1e-3 loses ~eps/u^2 ~ 2e-10 relative to cancellation, on an
    # across-track offset of ~5e-4 m: ~1e-13 m. The series, truncated after u^5, errs ~u^7/40320.
    for dt in (0.5, 0.999, 1.001, 2.0):
        natural = arc_extrapolate(x, y, heading, speed, 0.0, sign * 1e-3, dt)
        monkeypatch.setattr(coupling, "_SERIES_LIMIT", 1.0 if dt > 1.0 else 1e-6)
        forced = arc_extrapolate(x, y, heading, speed, 0.0, sign * 1e-3, dt)
        monkeypatch.setattr(coupling, "_SERIES_LIMIT", limit)
        assert forced == pytest.approx(natural, abs=1e-12)


def test_arc_factors_series_matches_closed_form():
    for u in (1e-6, -1e-5, 1e-4, 5e-4, -9.99e-4):
        along, across = coupling._arc_factors(u)
        # exact to the truncation of the series (~u^6), vs cancellation of the closed form,
        # ~eps/|u| absolute for (1 - cos u)/u: 1e-10 at u = 1e-6
        assert along == pytest.approx(math.sin(u) / u, abs=1e-15)
        assert across == pytest.approx((1 - math.cos(u)) / u, abs=2e-16 / abs(u) + 1e-18)
        assert across == pytest.approx(u / 2, rel=u * u)  # leading term


def integrate_unicycle(x, y, heading, speed, speed_rate, curvature, dt, n):
    """Independent reference: RK4 on (x, y, heading) with v(t) = speed + speed_rate t, heading' = k v."""

    def f(t, s):
        v = speed + speed_rate * t
        return (v * math.cos(s[2]), v * math.sin(s[2]), curvature * v)

    h = dt / n
    s = (x, y, heading)
    t = 0.0
    for _ in range(n):
        k1 = f(t, s)
        k2 = f(t + h / 2, tuple(a + h / 2 * b for a, b in zip(s, k1)))
        k3 = f(t + h / 2, tuple(a + h / 2 * b for a, b in zip(s, k2)))
        k4 = f(t + h, tuple(a + h * b for a, b in zip(s, k3)))
        s = tuple(a + h / 6 * (b + 2 * c + 2 * d + e) for a, b, c, d, e in zip(s, k1, k2, k3, k4))
        t += h
    return s


@pytest.mark.parametrize(
    "speed,speed_rate,turn_rate,dt",
    [
        (10.0, 0.0, 0.2, 1.5),
        (10.0, 0.8, 0.2, 1.5),
        (0.35, -0.05, 0.35, 2.0),
        (2.0, 0.3, -0.9, -1.2),
        (5.0, -1.0, 1e-4, 1.0),  # series branch
        (1.0, 0.2, 3.0, 0.7),  # more than a radian of turn
    ],
)
def test_arc_extrapolate_matches_an_integrated_unicycle(speed, speed_rate, turn_rate, dt):
    x, y, heading = 1.0, -3.0, 2.5
    curvature = turn_rate / speed
    ref = integrate_unicycle(x, y, heading, speed, speed_rate, curvature, dt, 2000)
    ex, ey, eh, ev = arc_extrapolate(x, y, heading, speed, speed_rate, turn_rate, dt)
    # RK4 with 2000 steps: global error ~ (h * rate)^4 * length ~ (1e-3 * 3)^4 * 20 ~ 2e-9 worst
    # case bound, measured ~1e-13; rounding ~2000 * 1e-16 * 20 ~ 4e-12. Tolerance 1e-9.
    assert (ex, ey, eh) == pytest.approx(ref, abs=1e-9)
    assert ev == pytest.approx(speed + speed_rate * dt, abs=1e-14)


@pytest.mark.parametrize(
    "speed,speed_rate,turn_rate,dt",
    [(10.0, 0.5, 0.2, 2.0), (0.35, -0.05, 0.35, 1.0), (3.0, 0.0, 0.0, 1.0), (4.0, 1.0, 2e-3, 0.1), (1.0, 0.1, -4.0, 0.5)],
)
def test_arc_extrapolate_forward_then_backward_returns(speed, speed_rate, turn_rate, dt):
    x, y, heading = 5.0, 6.0, -0.4
    fx, fy, fh, fv = arc_extrapolate(x, y, heading, speed, speed_rate, turn_rate, dt)
    # the curvature is what the arc keeps: the turn rate at the new sample is curvature * speed
    back_turn = turn_rate / speed * fv
    bx, by, bh, bv = arc_extrapolate(fx, fy, fh, fv, speed_rate, back_turn, -dt)
    # rounding on coordinates of order 30 m: ~1e-14
    assert (bx, by, bh, bv) == pytest.approx((x, y, heading, speed), abs=1e-12)


def test_linear_extrapolate_and_check_coupling():
    assert linear_extrapolate(2.0, 0.5, 3.0) == 3.5
    assert linear_extrapolate(2.0, 0.5, -2.0) == 1.0
    assert COUPLING_MODES == ("hold", "extrapolate")
    for mode in COUPLING_MODES:
        check_coupling(mode)
    with pytest.raises(ValueError, match="unknown coupling"):
        check_coupling("jacobi")


# --------------------------------------------------------------------------------------------------
# VehicleStepper on a circle, hold vs extrapolate
# --------------------------------------------------------------------------------------------------


CIRCLE_CASES = [
    # (R, d*, V0, V_c, V_t0, target speed rate, direction)
    (50.0, 75.0, 10.0, 10.0, 10.0, 0.0, 1),
    (50.0, 20.0, 15.0, 12.0, 14.0, 0.2, 1),
    (50.0, 40.0, 8.0, 10.0, 8.0, 0.0, -1),
    (1.0, 0.7, 0.35, 0.35, 0.35, 0.0, 1),
    (1.0, 0.3, 0.5, 0.4, 0.6, -0.02, -1),
]


class CircleTarget:
    """Exact target on a circle about the origin: arc length s(t) = V_t0 t + b t^2/2 from angle a0."""

    def __init__(self, radius, angle0, speed0, speed_rate, direction):
        self.radius, self.angle0, self.speed0, self.speed_rate, self.direction = (
            radius,
            angle0,
            speed0,
            speed_rate,
            direction,
        )

    def speed(self, t):
        return self.speed0 + self.speed_rate * t

    def pose(self, t):
        arc = self.speed0 * t + 0.5 * self.speed_rate * t * t
        return on_circle(0.0, 0.0, self.radius, self.angle0 + self.direction * arc / self.radius, self.direction)

    def sample_into(self, stepper, t):
        stepper.target_x, stepper.target_y, stepper.target_heading = self.pose(t)
        stepper.target_speed = self.speed(t)
        stepper.target_speed_rate = self.speed_rate
        stepper.target_turn_rate = self.direction * self.speed(t) / self.radius
        stepper.target_time = t


def make_circle_stepper(radius, d_star, v0, v_c, direction, mode, max_substep):
    model = VehicleModel("sine", d_star, v_c, True, KinematicDynamics(k_v=0.5))
    behind = 2.0 * math.asin(d_star / (2.0 * radius))
    x, y, heading = on_circle(0.0, 0.0, radius, 0.3 - direction * behind, direction)
    return VehicleStepper(model, mode, max_substep, [x, y, heading, v0], 0.0)


@pytest.mark.parametrize("sample_at_end", [False, True], ids=["jacobi", "gauss-seidel"])
@pytest.mark.parametrize("mode", COUPLING_MODES)
@pytest.mark.parametrize("radius,d_star,v0,v_c,vt0,vt_rate,direction", CIRCLE_CASES)
def test_vehicle_stays_on_the_circle(radius, d_star, v0, v_c, vt0, vt_rate, direction, mode, sample_at_end):
    """Circle invariance inside a co-simulation step: whatever the target sample (held or moved),
    it is on the circle and tangent, so the sine law commands V^2/R and the vehicle stays on it."""
    h = 0.02  # a communication step of four RK4 substeps of 5 ms (see the tolerance below)
    stepper = make_circle_stepper(radius, d_star, v0, v_c, direction, mode, max_substep=0.005)
    target = CircleTarget(radius, 0.3, vt0, vt_rate, direction)
    t = 0.0
    for _ in range(250):
        sample_time = t + h if sample_at_end else t
        target.sample_into(stepper, sample_time)
        if mode == "extrapolate":
            # the stepper sees the exact target at any time of the step (arc extrapolation is exact
            # on a circle with a linear speed): rounding of coordinates of order R only
            for tau in (t, t + 0.5 * h, t + h):
                seen = stepper.target_at(tau)
                assert seen[:2] == pytest.approx(target.pose(tau)[:2], abs=1e-12 * radius)
                assert seen[3] == pytest.approx(target.speed(tau), abs=1e-12)
        else:
            assert stepper.target_at(t + 0.5 * h) == (*target.pose(sample_time), target.speed(sample_time))
        stepper.step(t, h)
        t += h
        x, y, heading, speed = stepper.state
        # Only RK4 truncation moves the vehicle off the circle (its stages leave it, where the law
        # is no longer exactly V^2/R): measured max |r - R| <= 9e-11 and heading error <= 2.4e-10
        # rad over these cases at 5 ms substeps, scaling as h^4 (x16 at 10 ms, /16 at 2.5 ms); the
        # stiffest case is d* = 0.3 m at 0.5 m/s (law gain ~6V/d ~ 10 1/s). Tolerance 1e-9.
        assert abs(math.hypot(x, y) - radius) < 1e-9
        assert abs(wrap_angle(heading - (math.atan2(y, x) + direction * 0.5 * PI))) < 1e-9
    assert stepper.time == pytest.approx(250 * h, rel=1e-12)
    # the speed loop ran: V -> V_c with k_v = 0.5 over 5 s
    assert speed == pytest.approx(v_c + (v0 - v_c) * math.exp(-0.5 * t), rel=1e-8)


@pytest.mark.parametrize("mode", COUPLING_MODES)
def test_vehicle_outputs_on_the_circle(mode):
    radius, d_star, speed = 1.0, 0.7, 0.35
    stepper = make_circle_stepper(radius, d_star, speed, speed, 1, mode, 0.01)
    target = CircleTarget(radius, 0.3, speed, 0.0, 1)
    target.sample_into(stepper, 0.0)
    out = stepper.outputs()
    # equilibrium: a = V^2/R, turn rate V/R, gap d*, the gap neither opening nor closing
    assert out["lateral_acceleration"] == pytest.approx(speed**2 / radius, rel=1e-12)
    assert out["turn_rate"] == pytest.approx(speed / radius, rel=1e-12)
    assert out["gap"] == pytest.approx(d_star, rel=1e-12)
    assert out["gap_rate"] == pytest.approx(0.0, abs=1e-12)
    assert out["speed"] == speed and out["speed_rate"] == 0.0
    assert out["wheel.right"] - out["wheel.left"] == pytest.approx(
        stepper.model.dynamics.track * speed / radius, rel=1e-12
    )


def test_extrapolation_moves_the_target_and_hold_does_not():
    samples = {"target_x": 1.0, "target_y": 0.0, "target_heading": 0.5 * PI, "target_speed": 1.0,
               "target_speed_rate": 0.0, "target_turn_rate": 1.0, "target_time": 2.0}
    for mode in COUPLING_MODES:
        stepper = make_circle_stepper(1.0, 0.5, 1.0, 1.0, 1, mode, 0.01)
        for name, value in samples.items():
            setattr(stepper, name, value)
        seen = stepper.target_at(2.0 + 0.5 * PI)  # a quarter turn after the sample
        if mode == "hold":
            assert seen == (1.0, 0.0, 0.5 * PI, 1.0)
        else:
            assert seen == pytest.approx((0.0, 1.0, PI, 1.0), abs=1e-15)
        seen = stepper.target_at(2.0 - 0.5 * PI)  # and before it (backwards)
        if mode == "extrapolate":
            assert seen == pytest.approx((0.0, -1.0, 0.0, 1.0), abs=1e-15)


@pytest.mark.parametrize("mode", COUPLING_MODES)
def test_follower_inputs_set_the_speed_command(mode):
    model = VehicleModel("sine", 2.0, 99.0, False, KinematicDynamics(k_v=0.5))
    stepper = VehicleStepper(model, mode, 0.01, [0.0, 0.0, 0.0, 1.0], 5.0)
    stepper.target_x, stepper.target_speed = 2.0, 1.0
    stepper.follower_speed, stepper.follower_gap = 1.2, 2.5
    stepper.follower_speed_rate, stepper.follower_gap_rate, stepper.follower_time = 0.1, -0.2, 4.0
    der = stepper.derivative(5.0, stepper.state)
    if mode == "hold":
        commanded = spacing_speed(1.2, 2.5, 2.0)
    else:
        commanded = spacing_speed(1.3, 2.3, 2.0)  # moved on by 1 s at the sent rates
    assert der[3] == pytest.approx(0.5 * (commanded - 1.0), rel=1e-14)
    assert der[2] == pytest.approx(0.0, abs=1e-15)  # target dead ahead, same heading


def test_step_rejects_a_stopped_vehicle():
    model = VehicleModel("sine", 2.0, -5.0, True, KinematicDynamics(k_v=1.0))
    stepper = VehicleStepper(model, "hold", 0.01, [0.0, 0.0, 0.0, 1.0], 0.0)
    stepper.target_x, stepper.target_speed = 2.0, 1.0
    with pytest.raises(ValueError, match="speed fell"):
        for k in range(200):
            stepper.step(k * 0.01, 0.01)


# --------------------------------------------------------------------------------------------------
# parameter validation
# --------------------------------------------------------------------------------------------------

GOOD = {
    "law": "sine",
    "d_star": 0.7,
    "k_v": 0.5,
    "v_c": 0.35,
    "dynamics": "m3pi",
    "coupling": "extrapolate",
    "max_substep": 0.01,
    "initial.speed": 0.35,
    "m3pi.track": 0.084,
    "m3pi.wheel_speed_max": 1.0,
    "m3pi.motor_time_constant": 0.05,
    "m3pi.wheel_gain_right": 1.0,  # a robot's own truth: the nominal one
    "m3pi.wheel_gain_left": 1.0,
    "m3pi.wheel_deadband": 0.0,
    "m3pi.command_latency": 0.0,
    "m3pi.pose_latency": 0.0,
    "speed_law": "paper",
    "time_gap": 2.0,
    "standstill_gap": 0.0,
    "cacc_gain": 0.2,
    "speed_max": 0.0,
}


def test_vehicle_parameter_errors_accepts_good_parameters():
    assert vehicle_parameter_errors(GOOD) == []
    assert vehicle_parameter_errors({**GOOD, "law": "regular", "dynamics": "kinematic", "coupling": "hold"}) == []


@pytest.mark.parametrize(
    "name,value",
    [
        ("d_star", 0.0),
        ("d_star", -1.0),
        ("d_star", float("nan")),
        ("d_star", float("inf")),
        ("k_v", 0.0),
        ("k_v", -0.5),
        ("law", "cosine"),
        ("dynamics", "bicycle"),
        ("coupling", "jacobi"),
        ("v_c", 0.0),
        ("max_substep", 0.0),
        ("initial.speed", -0.1),
        ("m3pi.track", 0.0),
        ("m3pi.wheel_speed_max", 0.0),
        ("m3pi.motor_time_constant", 0.0),
        ("speed_law", "pid"),
        ("time_gap", 0.0),
        ("standstill_gap", -0.1),
        ("standstill_gap", float("inf")),
        ("cacc_gain", 0.0),
        ("speed_max", -1.0),
        ("speed_max", float("inf")),
    ],
)
def test_vehicle_parameter_errors_names_each_bad_parameter(name, value):
    errors = vehicle_parameter_errors({**GOOD, name: value})
    assert len(errors) == 1
    assert errors[0].startswith(f"{name} = ")


def test_vehicle_parameter_errors_lists_every_problem():
    errors = vehicle_parameter_errors({**GOOD, "d_star": -1.0, "k_v": 0.0, "law": "x", "dynamics": "y", "coupling": "z"})
    assert len(errors) == 5
    for name in ("law", "dynamics", "coupling", "d_star", "k_v"):
        assert any(e.startswith(f"{name} = ") for e in errors)
