"""The closed form's verdict (orchestrator/analysis/verdict.py): one object, the same in `platoon analyze`,
`platoon stability` and `platoon stability-map`; the loop's second moment held to a Monte-Carlo over delivery
patterns, and a growing loop reported as growing by all three."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from orchestrator.analysis.chain_model import chain_model
from orchestrator.analysis.loop_moments import _Layout, _one_period, loop_radii, paper_loop
from orchestrator.analysis.verdict import GROWS, NO_LOOP, NOT_COMPUTED, SETTLES, closed_form_verdict
from orchestrator.scenario.config import load_config
from orchestrator.sweep.stability_map import _point
from tests.test_cli import platoon, workdir  # noqa: F401  (the CLI as users call it, and its folder fixture)
from tests.test_loop_moments import PAIR, _pair


def _drawn_operator(config, rng: np.random.Generator, draws: int) -> np.ndarray:
    """E[Phi (x) Phi] estimated from ``draws`` periods whose deliveries are drawn beacon by beacon (each lost
    with the link's probability), each Phi stepped from its drawn pattern: no enumeration, no pi(delta).
    (A pattern drawn again reuses its Phi (x) Phi: the estimate is the drawn patterns' frequencies.)"""
    loop = paper_loop(chain_model(config), 1)
    layout = _Layout(loop)
    products: dict[tuple, np.ndarray] = {}
    counts: dict[tuple, int] = {}
    for _ in range(draws):
        lost: dict[tuple, bool] = {}
        drawn = lambda arrival: lost.setdefault(arrival, rng.random() >= config.links.loss)  # noqa: E731
        phi = _one_period(loop, layout, drawn)
        key = tuple(sorted(lost.items()))
        if key not in products:
            products[key] = np.kron(phi, phi)
        counts[key] = counts.get(key, 0) + 1
    return sum(count / draws * products[key] for key, count in counts.items())


def test_the_loops_second_moment_is_a_monte_carlo_over_delivery_patterns(tmp_path: Path) -> None:
    """Extrapolated 0.2 s links at 80 % loss (the mean decays by 0.9531 a period, the mean square by 0.9480,
    its square would be 0.9085): the mean square's radius from the enumerated patterns is the Monte-Carlo's
    (8 batches of 500 drawn periods: within 4 of their standard errors), and far (over 10 standard errors) from
    the mean's square, which a mean square "computed as the mean's square" would give."""
    config = _pair(tmp_path, "extrapolate", 0.2, 30.0, 1e-3)
    config = config.model_copy(update={"links": config.links.model_copy(update={"loss": 0.8})})
    growth = loop_radii(chain_model(config), 1)
    assert growth.mean_square is not None and growth.mean_stable
    rng = np.random.default_rng(52)
    batches = [float(np.abs(np.linalg.eigvals(_drawn_operator(config, rng, 500))).max()) for _ in range(8)]
    estimate, error = float(np.mean(batches)), float(np.std(batches, ddof=1) / math.sqrt(len(batches)))
    assert abs(growth.mean_square - estimate) < 4 * error, (growth.mean_square, batches)
    assert abs(growth.mean**2 - estimate) > 10 * error, (growth.mean**2, estimate, error)


def _growing(tmp_path: Path):
    """Two vehicles, extrapolated 1.40 s links (the loop grows at +0.037 1/s: tests/test_loop_moments.py)."""
    return _pair(tmp_path, "extrapolate", 1.40, 30.0, 1e-3)


def test_the_verdict_names_its_loop(tmp_path: Path) -> None:
    verdict = closed_form_verdict(_growing(tmp_path))
    assert verdict.loop.state == GROWS and not verdict.string_stable and "GROWS" in verdict.line()
    settled = closed_form_verdict(_pair(tmp_path, "extrapolate", 1.38, 30.0, 1e-3))
    assert settled.loop.state == SETTLES and settled.loop.mean_radius < 1.0
    config = _pair(tmp_path, "hold", 0.4, 30.0, 1e-3)
    bursty = config.model_copy(update={"links": config.links.model_copy(update={"loss": 0.3, "burst": 3.0})})
    unknown = closed_form_verdict(bursty)
    assert unknown.loop.state == NOT_COMPUTED and "burst" in unknown.loop.reason and "not computed" in unknown.line()
    acc = config.model_copy(update={"platoon": config.platoon.model_copy(update={"speed_law": "acc"})})
    assert closed_form_verdict(acc).loop.state == NO_LOOP


def test_a_growing_loop_is_reported_by_analyze_stability_and_the_map(tmp_path: Path, workdir: Path) -> None:  # noqa: F811
    """The same verdict line from the three commands: `analyze` on the config, `stability` on a run of it,
    and the map's verdict for that run."""
    path = tmp_path / "growing.toml"
    path.write_text(PAIR.format(coupling="extrapolate", delay=1.40, stop=30.0, push=1e-3))
    config, _ = load_config(path, [])
    line = closed_form_verdict(config).line()
    analyzed = platoon("analyze", path, "--no-measure", cwd=workdir)
    assert analyzed.returncode == 0, analyzed.stderr
    assert line in analyzed.stdout
    trace = tmp_path / "growing.mcap"
    assert platoon("run", path, "--out", trace, "--quiet", cwd=workdir).returncode == 0
    measured = platoon("stability", trace, cwd=workdir)
    assert measured.returncode == 0, measured.stderr
    assert line in measured.stdout
    mapped = _point(config.model_dump(mode="json", exclude_none=True), None, True)[2]  # the map's verdict of the run
    assert mapped.loop.state == GROWS and not mapped.string_stable and mapped.line() == line  # mean square aside, equal


def test_analyze_prints_the_cascades_bounds_and_labels_the_averaged_ones() -> None:
    """The study under cacc with 0.3 s links: the delay bound is the cascade's 0.38 s (where runs start to grow,
    tests/test_sampled_chain.py), not the averaged 0.42 s; the averaged bounds only under their label, after."""
    from orchestrator.analysis.string_stability import chain_report

    config, _ = load_config("configs/study/string_stability.toml", ["platoon.speed_law=cacc", "links.delay=0.3"])
    lines = chain_report(config).splitlines()
    label = next(i for i, line in enumerate(lines) if line.startswith("  for comparison only, the phase-averaged"))
    cascade = [line for line in lines[:label] if line.startswith("  (cascade)")]
    assert cascade[-1].endswith("string stable for every link delay on the step grid up to 0.38 s")
    assert "time_gap >= 0.4064 s" in cascade[0]  # the study's 0.5 s is inside it
    assert not [line for line in lines[:label] if "(phase-averaged)" in line and "bound" not in line
                and ("time_gap >=" in line or "delays up to" in line)]
    assert all(line.startswith("    (phase-averaged)") for line in lines[label + 1:])
