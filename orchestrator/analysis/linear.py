"""Linear stability about the circular equilibrium, and string stability from a disturbance run.

The paper linearizes its relative coordinates x_i = (d_i, alpha_t_i, alpha_v_i, V_i) about
x_eq = (d*, asin(d*/2R), -asin(d*/2R), V_c) and lists the 4n eigenvalues in closed form (eq. 9). We
linearize numerically the very right-hand side our FMUs integrate (``fmus.model.platoon``), mapped
to the paper's coordinates: alpha_t = gamma_t - lambda, alpha_v = gamma_v - lambda (the sign the
paper's equations and equilibrium need; its text prints lambda - gamma_v). Only the kinematic vehicle
has the paper's 4 states per vehicle, so the analysis uses kinematic dynamics.
"""

from __future__ import annotations

import math
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass
from typing import Callable

import numpy as np

from fmus.model.angles import wrap_angle
from fmus.model.dynamics import KinematicDynamics
from fmus.model.platoon import PlatoonSystem
from fmus.model.target import VirtualTargetStepper
from fmus.model.vehicle import VehicleModel, VehicleStepper

from orchestrator.scenario.config import Config
from orchestrator.scenario.scenario import path_of

# progress(label, steps) -> a context manager giving a tick(steps done) or None (orchestrator/observers/progress.py)
Progress = Callable[[str, int], AbstractContextManager[Callable[[int], None] | None]]

# Central differences with this relative perturbation: truncation ~1e-12, rounding ~1e-10.
_PERTURBATION = 1e-6


def require_paper_law(config: Config) -> None:
    """Refuse, with the reason, a platoon in which some vehicle follows another speed law than the paper's:
    the linearization about the circle and the speed-chain G(s) below are the paper's law's."""
    laws = sorted({config.speed_law_of(i) for i in range(1, config.platoon.count + 1)} - {"paper"})
    if laws:
        raise ValueError(f"platoon.speed_law = {laws[0]!r}: the linearization (eigenvalues, eq. 9, the speed chain's "
                         "peak gain) knows only the paper's speed law; docs/model.md, section 11, gives acc's and "
                         "cacc's G(s) and string-stability conditions")


def platoon_system(config: Config, count: int | None = None, speed_chain_gap: str = "follower") -> PlatoonSystem:
    """The config's platoon with kinematic vehicles, as one system (state: s, then x, y, heading, V)."""
    require_paper_law(config)
    n = count or config.platoon.count
    p = config.platoon
    path = path_of(config)
    target = VirtualTargetStepper(path, p.d_star, "hold", config.simulation.max_substep, 0.0, 0.0)
    vehicles = [
        VehicleStepper(
            VehicleModel(p.law, p.d_star, p.speed, i == n, KinematicDynamics(p.k_v)),
            "hold", config.simulation.max_substep, [0.0, 0.0, 0.0, p.speed], 0.0,
        )
        for i in range(1, n + 1)
    ]
    return PlatoonSystem(target, vehicles, speed_chain_gap)


def _absolute(system: PlatoonSystem, relative: np.ndarray) -> list[float]:
    """Absolute state from relative coordinates, chaining each vehicle behind its target."""
    x, y, heading = system.target.path.pose_at(0.0)
    state = [0.0]
    for i in range(len(system.vehicles)):
        d, alpha_t, alpha_v, speed = relative[4 * i : 4 * i + 4]
        los = heading - alpha_t
        x, y = x - d * math.cos(los), y - d * math.sin(los)
        heading = los + alpha_v
        state += [x, y, heading, speed]
    return state


def _relative_rate(system: PlatoonSystem, state: list[float]) -> np.ndarray:
    """d/dt of the relative coordinates, from the absolute right-hand side by exact kinematics."""
    rate = system.derivative(0.0, state)
    path = system.target.path
    tx, ty, th = path.pose_at(state[0])
    t_vx, t_vy = rate[0] * math.cos(th), rate[0] * math.sin(th)
    t_turn = rate[0] * path.curvature(state[0])
    result = []
    for i in range(len(system.vehicles)):
        x, y, heading, _ = state[1 + 4 * i : 5 + 4 * i]
        vx, vy, turn, accel = rate[1 + 4 * i : 5 + 4 * i]
        dx, dy, dvx, dvy = tx - x, ty - y, t_vx - vx, t_vy - vy
        d2 = dx * dx + dy * dy
        los_rate = (dx * dvy - dy * dvx) / d2
        result += [(dx * dvx + dy * dvy) / math.sqrt(d2), t_turn - los_rate, turn - los_rate, accel]
        tx, ty, th, t_vx, t_vy, t_turn = x, y, heading, vx, vy, turn
    return np.array(result)


def equilibrium(config: Config, count: int) -> np.ndarray:
    alpha = 0.0
    if config.path.kind == "circle":
        turn = 1.0 if config.path.direction == "ccw" else -1.0
        alpha = turn * math.asin(config.platoon.d_star / (2.0 * config.path.radius))
    return np.tile([config.platoon.d_star, alpha, -alpha, config.platoon.speed], count)


def jacobian(config: Config, count: int | None = None, speed_chain_gap: str = "follower") -> tuple[np.ndarray, float]:
    """A = df/dx at the equilibrium (paper coordinates), and the residual |f(x_eq)|."""
    n = count or config.platoon.count
    system = platoon_system(config, n, speed_chain_gap)
    x0 = equilibrium(config, n)
    f0 = _relative_rate(system, _absolute(system, x0))
    columns = []
    for k in range(4 * n):
        h = _PERTURBATION * max(1.0, abs(x0[k]))
        up, down = x0.copy(), x0.copy()
        up[k] += h
        down[k] -= h
        columns.append((_relative_rate(system, _absolute(system, up)) - _relative_rate(system, _absolute(system, down))) / (2 * h))
    return np.array(columns).T, float(np.max(np.abs(f0)))


@dataclass(frozen=True)
class Family:
    label: str
    value: complex
    count: int


def paper_eigenvalues(config: Config, count: int) -> list[Family]:
    """The paper's eq. 9, with beta left unknown (only beta = 0.95 at k_v = 0.5 is given)."""
    p = config.platoon
    k_v, v, d = p.k_v, p.speed, p.d_star
    radius = config.path.radius if config.path.kind == "circle" else math.inf
    alpha = math.sqrt(1.0 - (d / (2.0 * radius)) ** 2)
    imag = v * math.sqrt(2.0 * (alpha**2 / d**2 + 1.0 / (4.0 * radius**2)))
    families = [
        Family("lambda_1 = -k_v", complex(-k_v), 1),
        Family("lambda_2 = -V_c alpha/d*", complex(-v * alpha / d), 1),
        Family("lambda_3..n+2 = -2 V_c alpha/d* + j ...", complex(-2 * v * alpha / d, imag), count),
        Family("lambda_n+3..2n+2 = -2 V_c alpha/d* - j ...", complex(-2 * v * alpha / d, -imag), count),
    ]
    if count > 1 and abs(k_v - 0.5) < 1e-12:
        families += [
            Family("lambda_2n+3..3n+1 = -(1-beta) k_v, beta = 0.95", complex(-0.05 * k_v), count - 1),
            Family("lambda_3n+2..4n = -beta k_v, beta = 0.95", complex(-0.95 * k_v), count - 1),
        ]
    return families


# A family of k repeated eigenvalues is usually a Jordan block, whose computed eigenvalues scatter
# over a radius ~(1e-10)^(1/k) from rounding alone. So a predicted value lambda with multiplicity k is
# tested by rank instead: (A - lambda I)^k must have exactly k singular values at rounding level.
_NULL = 1e-9  # singular values below this count as zero (A has entries ~1, errors ~1e-10)
_GAP = 1e3  # the next singular value must be this much larger for the test to be decisive


def multiplicity_test(a: np.ndarray, value: complex, count: int) -> str:
    """'confirmed', 'not an eigenvalue', or 'inconclusive' for value with algebraic multiplicity count."""
    identity = np.eye(len(a))
    singular = np.linalg.svd(np.linalg.matrix_power(a - value * identity, count), compute_uv=False)
    smallest = singular[-count]
    following = singular[-count - 1] if count < len(singular) else math.inf
    if smallest <= _NULL and following >= _GAP * max(smallest, 1e-300):
        return "confirmed"
    if np.linalg.svd(a - value * identity, compute_uv=False)[-1] > _NULL * _GAP:
        return "not an eigenvalue"
    return "inconclusive in double precision (try platoon.count <= 10; the families do not depend on n)"


def our_families(config: Config, count: int) -> list[Family]:
    """Our closed form: the paper's first four families, and the speed chain's roots of
    s^2 + k_v s + k_v V_c alpha/d* (n-1 each), where the paper lists -(1-beta) k_v and -beta k_v."""
    families = paper_eigenvalues(config, count)[:4]
    if count > 1:
        p = config.platoon
        alpha = math.sqrt(1.0 - (p.d_star / (2.0 * config.path.radius)) ** 2)
        for root in np.roots([1.0, p.k_v, p.k_v * p.speed * alpha / p.d_star]):
            families.append(Family("speed chain: root of s^2 + k_v s + k_v V_c alpha/d*", complex(root), count - 1))
    return families


# Real parts within this of zero are zero to the accuracy of the finite-difference Jacobian.
_ZERO_REAL = 1e-7


def stability_word(largest_real_part: float) -> str:
    if largest_real_part < -_ZERO_REAL:
        return "exponentially stable"
    if largest_real_part <= _ZERO_REAL:
        return "MARGINAL (an eigenvalue at zero: some state is not regulated)"
    return "UNSTABLE"


def stability_verdict(eigenvalues: np.ndarray, families: list[Family], tests: list[str]) -> str:
    """The verdict line: from the computed eigenvalues when every closed-form family is confirmed (or
    one is refuted: then the closed form does not hold for this configuration), else from the families.

    Computed eigenvalues of a Jordan block of size k scatter over a radius ~(1e-10)^(1/k) from
    rounding alone: 0.46 for k = 30, 0.79 for k = 100. Past about 25 vehicles their largest real part
    means nothing (at 100 vehicles it comes out positive, though the platoon is stable). The
    families account for every eigenvalue (their counts add up to the state's size), are confirmed
    by rank where double precision can tell, and do not depend on the platoon's size.
    """
    computed = float(eigenvalues.real.max())
    trusted = all(test != "not an eigenvalue" for test in tests) and sum(f.count for f in families) == len(eigenvalues)
    if all(test == "confirmed" for test in tests) or not trusted:
        return f"verdict: {stability_word(computed)} (largest real part {computed:+.6f})"
    closed_form = max(family.value.real for family in families)
    block = max(family.count for family, test in zip(families, tests) if test != "confirmed")
    return (f"verdict: {stability_word(closed_form)} (largest real part {closed_form:+.6f}, from the closed-form "
            f"families; the computed eigenvalues give {computed:+.6f}, but around a family of {block} repeated "
            f"eigenvalues they scatter by up to ~{1e-10 ** (1.0 / block):.2f} from rounding alone)")


def _c(value: complex) -> str:
    return f"{value.real:+.6f}{value.imag:+.6f}j"


def eigen_report(config: Config) -> str:
    if config.path.kind != "circle":
        raise ValueError("path.kind = 'line': the analysis linearizes about the circular equilibrium; use a circle")
    n = config.platoon.count
    a, residual = jacobian(config)
    eigenvalues = np.linalg.eigvals(a)
    order = np.argsort(eigenvalues.real)
    lines = [
        f"Linearization of {config.name}: {n} kinematic vehicle(s), {config.platoon.law} law, "
        f"R = {config.path.radius:g} m, d* = {config.platoon.d_star:g} m, V_c = {config.platoon.speed:g} m/s, k_v = {config.platoon.k_v:g} 1/s",
        f"residual |f(x_eq)| = {residual:.3e}  ({'an equilibrium' if residual < 1e-9 else 'NOT an equilibrium of this law'})",
        "eigenvalues [1/s] (ours, from the model code):",
    ]
    for value in eigenvalues[order]:
        lines.append(f"  {value.real:+.6f} {value.imag:+.6f}j")
    ours = our_families(config, n)
    if any(family.count > 1 for family in ours):  # a k-fold root comes out of the solver as k values around it
        spread = max(min(abs(value - family.value) for family in ours) for value in eigenvalues)
        lines.append(f"  (a repeated root is computed as k values around it: an error e in A (A is differentiated "
                     f"numerically) moves a k-fold root by about e^(1/k); these lie up to {spread:.1e} 1/s from the "
                     "families below, which are tested by rank, not by them)")
    lines.append("eigenvalue families [1/s], ours in closed form (a family of k is tested by the rank of (A - lambda I)^k):")
    tests = [multiplicity_test(a, family.value, family.count) for family in ours]
    for family, test in zip(ours, tests):
        lines.append(f"  {family.label:52s} {_c(family.value)} x{family.count}: {test}")
    lines.append("the paper's eq. 9, family by family [1/s]:")
    chain = ", ".join(_c(f.value) for f in ours[4:])
    for family in paper_eigenvalues(config, n):
        verdict = multiplicity_test(a, family.value, family.count)
        if verdict == "confirmed":
            verdict = "agrees"
        elif verdict == "not an eigenvalue" and chain:
            verdict = f"DIFFERS: not an eigenvalue; our speed-chain family is {chain}"
        lines.append(f"  {family.label:52s} {_c(family.value)} x{family.count}: {verdict}")
    if n > 1 and abs(config.platoon.k_v - 0.5) > 1e-12:
        lines.append("  (the paper gives beta only for k_v = 0.5, so its last two families are not evaluated here)")
    lines.append(stability_verdict(eigenvalues, ours, tests))
    if n > 1:
        own, _ = jacobian(config, speed_chain_gap="own")
        worst = np.linalg.eigvals(own).real.max()
        lines.append(
            f"with the paper's printed V_cmd,i = V_(i+1) d*/d_i instead of d_(i+1): largest real part {worst:+.6f} "
            f"({stability_word(worst)})"
        )
    return "\n".join(lines)
