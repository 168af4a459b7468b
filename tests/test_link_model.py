"""The link model (fmus/model/link.py): when a message is delivered, what is held between beacons,
how many are lost, and that a seed fixes everything."""

from __future__ import annotations

import math

import pytest

from fmus.model.link import (CAPACITY, LinkParameters, LinkStepper, gilbert_elliott, messages_held, parameter_errors,
                             seed_state, splitmix64, unit_draw)

STEP = 0.01


def run(p: LinkParameters, steps: int, jacobi: bool = True) -> list[dict[str, float]]:
    """Feed the link the message of a sender whose x is its own output_time, stepped on the grid
    t_k = k STEP; return the link's outputs after each step. Jacobi: the link sees the sender's
    message at t (its step's start); Gauss-Seidel: at t + h (the sender stepped first)."""
    link = LinkStepper(p, 0.0)
    link.in_time, link.in_x = 0.0, 0.0
    link.take_initial()
    rows = []
    for k in range(steps):
        t, following = k * STEP, (k + 1) * STEP
        sent_at = t if jacobi else following
        link.in_time, link.in_x, link.in_gap = sent_at, sent_at, 2.0 * sent_at
        link.step(t, following - t)
        rows.append(link.outputs())
    return rows


def test_splitmix64_matches_the_published_reference_outputs():
    # splitmix64 seeded with 1234567 (the reference values of Vigna's splitmix64.c, as quoted by
    # many ports): the C twin draws the same, tests/test_links.py holds their traces bit for bit
    state, outputs = 1234567, []
    for _ in range(3):
        state, out = splitmix64(state)
        outputs.append(out)
    assert outputs == [6457827717110365317, 3203168211198807973, 9817491932198370423]
    assert 0.0 <= unit_draw(outputs[0]) < 1.0 and unit_draw((1 << 64) - 1) < 1.0


def test_a_perfect_link_delivers_every_message_at_the_next_point():
    rows = run(LinkParameters(), 50, jacobi=False)
    for k, row in enumerate(rows):
        assert row["output_time"] == pytest.approx((k + 1) * STEP, abs=1e-15) and row["age"] == pytest.approx(0.0, abs=1e-15)
    assert rows[-1]["sent"] == rows[-1]["delivered"] == 50 and rows[-1]["lost"] == 0


@pytest.mark.parametrize("jacobi", [True, False])
def test_a_delayed_message_is_delivered_at_its_output_time_plus_the_delay(jacobi):
    delay = 0.1  # 10 steps: 0.05 + 0.1 is 0.15000000000000002 > 15 * 0.01, the tolerance keeps it on time
    rows = run(LinkParameters(delay=delay), 100, jacobi)
    for k, row in enumerate(rows):
        now = (k + 1) * STEP
        # the newest message with output_time + delay <= now; a delay of at least one step is exact
        # under both masters (under Jacobi the link sees the message of t at its step's start)
        expected = round((now - delay) / STEP) * STEP if now >= delay - 1e-9 else 0.0
        assert row["output_time"] == pytest.approx(expected, abs=1e-12), (k, row)
        assert row["x"] == row["output_time"] and row["gap"] == 2.0 * row["output_time"]
        assert row["age"] == pytest.approx(now - expected, abs=1e-12)


def test_between_beacons_the_last_message_is_held():
    period = 0.1
    rows = run(LinkParameters(period=period), 100, jacobi=False)
    for k, row in enumerate(rows):
        now = (k + 1) * STEP
        # beacons leave at 0.1, 0.2, ... (the initial message covers 0); each is held until the next
        assert row["output_time"] == pytest.approx(math.floor(now / period + 1e-9) * period, abs=1e-12)
    assert rows[-1]["sent"] == 10 and rows[-1]["delivered"] == 10
    ages = [row["age"] for row in rows]
    assert max(ages) == pytest.approx(period - STEP, abs=1e-12)


def test_jitter_spreads_arrivals_but_never_reorders_them():
    rows = run(LinkParameters(delay=0.05, jitter=0.2, seed=7), 2000)
    times = [row["output_time"] for row in rows]
    assert all(b >= a for a, b in zip(times, times[1:]))
    ages = [row["age"] for row in rows[100:]]
    assert min(ages) >= 0.05 + STEP - 1e-9 and max(ages) <= 0.05 + 0.2 + 2 * STEP + 1e-9
    assert len(set(round(a, 9) for a in ages)) > 10  # the delay varies


def loss_fraction(p: LinkParameters, count: int) -> tuple[float, list[int]]:
    """The fraction of ``count`` messages lost, and the lengths of the runs of losses."""
    link = LinkStepper(p, 0.0)
    link.take_initial()
    bursts, run_length = [], 0
    for k in range(count):
        before = link.lost
        link.in_time = (k + 1) * STEP
        link.step(k * STEP, STEP)
        if link.lost > before:
            run_length += 1
        elif run_length:
            bursts.append(run_length)
            run_length = 0
    return link.lost / count, bursts


def test_independent_loss_rate_is_within_binomial_bounds():
    n, p = 20000, 0.2
    fraction, bursts = loss_fraction(LinkParameters(loss=p, seed=3), n)
    sigma = math.sqrt(p * (1 - p) / n)  # binomial standard deviation of the fraction
    assert abs(fraction - p) < 5 * sigma  # 5 sigma: a false failure about once in 1.7 million seeds
    # independent losses: runs are geometric with mean 1 / (1 - p)
    assert sum(bursts) / len(bursts) == pytest.approx(1 / (1 - p), rel=0.05)


def test_gilbert_elliott_keeps_the_mean_loss_and_makes_bursts_of_the_mean_length():
    n, p, burst = 40000, 0.2, 5.0
    fraction, bursts = loss_fraction(LinkParameters(loss=p, burst=burst, seed=11), n)
    to_bad, to_good = gilbert_elliott(p, burst)
    # a two-state Markov chain's mean of n steps has variance p (1 - p) / n (1 + lam) / (1 - lam),
    # lam = 1 - to_bad - to_good its second eigenvalue (the correlation of successive losses)
    lam = 1 - to_bad - to_good
    sigma = math.sqrt(p * (1 - p) / n * (1 + lam) / (1 - lam))
    assert abs(fraction - p) < 5 * sigma
    # the bursts' lengths are geometric with mean `burst` (variance burst (burst - 1)): the mean of
    # len(bursts) of them is within 5 of its standard deviations
    assert abs(sum(bursts) / len(bursts) - burst) < 5 * math.sqrt(burst * (burst - 1) / len(bursts))


def test_the_same_seed_gives_the_same_run_and_another_seed_another():
    p = LinkParameters(delay=0.03, jitter=0.05, loss=0.3, burst=3.0, seed=42, stream=2)
    first, again = run(p, 500), run(p, 500)
    assert first == again
    other = run(LinkParameters(**{**p.__dict__, "seed": 43}), 500)
    assert [r["output_time"] for r in other] != [r["output_time"] for r in first]
    assert seed_state(42, 2) != seed_state(42, 3)


def test_counters_add_up():
    rows = run(LinkParameters(delay=0.2, loss=0.25, seed=1), 300)
    last = rows[-1]
    in_flight = last["sent"] - last["delivered"] - last["lost"]
    assert 0 < in_flight <= 0.2 / STEP + 1 and last["lost"] > 0


def test_parameter_errors_name_the_parameter():
    assert parameter_errors(LinkParameters()) == []
    errors = parameter_errors(LinkParameters(delay=-1.0, loss=1.5, burst=0.5, seed=-1))
    assert [e.split(" ")[0] for e in errors] == ["delay", "loss", "burst", "seed"]
    assert "burst / (burst + 1)" in parameter_errors(LinkParameters(loss=0.9, burst=2.0))[0]


def test_the_capacity_bound_covers_what_a_link_holds():
    p = LinkParameters(delay=0.5, jitter=0.3, seed=5)
    bound = messages_held(p, STEP)
    assert bound <= CAPACITY
    link = LinkStepper(p, 0.0)
    link.take_initial()
    most = 0
    for k in range(1000):
        link.in_time = k * STEP
        link.step(k * STEP, STEP)
        most = max(most, len(link.queue) + 1)
    assert most <= bound
