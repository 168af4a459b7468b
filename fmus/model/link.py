"""A communication link between two platoon components: delay, jitter, beacons, loss; seeded.

A link sits on one direction of the paper's Fig. 2 wiring (the predecessor's state flowing backward,
or the follower's speed and gap flowing forward) and carries that direction's whole message: its
signals and the sender's ``output_time`` (the time they describe). docs/links.md states the semantics;
in short, at each communication step the link

1. looks at the sender's current message; if it is newer than the last one sent and a beacon is due
   (``period`` = 0: every new message; else the first new message at or after each multiple of
   ``period``), it sends it: two draws of the link's generator decide whether the message is lost
   (independently with probability ``loss``, or by a Gilbert-Elliott channel when ``burst`` > 1) and
   its extra delay (uniform in [0, ``jitter``]);
2. a message that is not lost arrives at ``output_time + delay + jitter draw``, never before one sent
   earlier (a FIFO channel: messages do not overtake);
3. delivers every message that has arrived by the step's end; the newest delivered is the message in
   use, held (sample and hold) until a newer one arrives. Its age (link time - its output_time) is the
   age of information the receiver works with.

The message at the start (initialization) is in use from the start, as without a link: the receiver
starts knowing its sender's initial state; it is not counted as sent.

The generator is splitmix64 (Steele, Lea, Flood: "Fast splittable pseudorandom number generators",
OOPSLA 2014), written here and in fmus/native/link.c, so the pythonfmu and native Link FMUs draw the
same numbers and deliver the same messages (never Python's ``random``, whose stream C cannot follow).
Pure computation, no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

# The signals a link can carry: the union of the backward (lateral) and forward (velocity) messages.
# A link's unconnected inputs keep their start value 0 and are delivered as such.
SIGNALS = ("x", "y", "heading", "speed", "speed_rate", "turn_rate", "gap", "gap_rate")

# Two times closer than this are equal (the communication grid's rounding: 0.05 + 0.1 vs 15 * 0.01).
TIME_TOLERANCE = 1e-9

# Messages a link holds at once: the one in use and those in flight. The native twin keeps them in a
# fixed ring of this size; config validation (``messages_held``) refuses links that could need more.
CAPACITY = 256

_MASK = (1 << 64) - 1
_GAMMA = 0x9E3779B97F4A7C15
_UNIT = 2.0**-53


def seed_state(seed: int, stream: int) -> int:
    """The generator's initial state for ``seed`` and a link's ``stream`` (its number in the wiring):
    every link of a run draws its own numbers, and the same ones for the same seed."""
    return ((seed & 0xFFFFFFFF) << 32 | (stream & 0xFFFFFFFF)) & _MASK


def splitmix64(state: int) -> tuple[int, int]:
    """(next state, 64-bit output) of splitmix64."""
    state = (state + _GAMMA) & _MASK
    z = state
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & _MASK
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & _MASK
    return state, z ^ (z >> 31)


def unit_draw(output: int) -> float:
    """A uniform double in [0, 1) from a 64-bit output: its top 53 bits."""
    return (output >> 11) * _UNIT


def gilbert_elliott(loss: float, burst: float) -> tuple[float, float]:
    """(p_GB, p_BG): the Good -> Bad and Bad -> Good transition probabilities per message of the
    two-state channel that loses every message in Bad and none in Good, with mean loss ``loss`` (the
    stationary probability of Bad) and mean burst length ``burst`` (messages; a Bad sojourn is geometric
    with mean 1 / p_BG)."""
    recover = 1.0 / burst
    return loss * recover / (1.0 - loss), recover


@dataclass(frozen=True)
class LinkParameters:
    delay: float = 0.0  # s, from the message's output_time to its arrival
    jitter: float = 0.0  # s, the upper end of a uniform extra delay per message
    period: float = 0.0  # s between beacons; 0: every new message is sent
    loss: float = 0.0  # probability a sent message is lost (the mean, with bursts)
    burst: float = 1.0  # mean burst length in messages; > 1 selects Gilbert-Elliott
    seed: int = 0
    stream: int = 0

    @property
    def perfect(self) -> bool:
        """A link that changes nothing: every message, at once, none lost."""
        return self.delay == 0.0 and self.jitter == 0.0 and self.period == 0.0 and self.loss == 0.0


def parameter_errors(p: LinkParameters) -> list[str]:
    """Every reason these link parameters cannot run, as sentences naming the parameter."""
    errors = []
    for name in ("delay", "jitter", "period"):
        value = getattr(p, name)
        if not (math.isfinite(value) and value >= 0.0):
            errors.append(f"{name} = {value}: must be a finite number >= 0")
    if not (0.0 <= p.loss <= 1.0):
        errors.append(f"loss = {p.loss}: must be a probability from 0 to 1")
    if not (math.isfinite(p.burst) and p.burst >= 1.0):
        errors.append(f"burst = {p.burst}: must be a finite number >= 1 (messages)")
    elif p.burst > 1.0 and 0.0 <= p.loss <= 1.0 and p.loss > p.burst / (p.burst + 1.0):
        errors.append(f"loss = {p.loss}: with burst = {p.burst} at most burst / (burst + 1) = "
                      f"{p.burst / (p.burst + 1.0):.6g} (bursts of that mean length need good spells between them)")
    for name in ("seed", "stream"):
        value = getattr(p, name)
        if not 0 <= value <= 2**31 - 1:
            errors.append(f"{name} = {value}: must be an integer from 0 to 2147483647")
    return errors


def messages_held(p: LinkParameters, step: float) -> int:
    """An upper bound on the messages a link holds at once (in use + in flight) when stepped every
    ``step`` s: a new message at most every step, a beacon at most every period - step, each in flight
    for at most delay + jitter (plus one step for the one being delivered)."""
    spacing = max(step, p.period - step)
    return math.ceil((p.delay + p.jitter) / spacing) + 3


class LinkStepper:
    """One link between communication points: the sender's current message (its inputs), the message
    in use, those in flight, the generator and the counters."""

    def __init__(self, p: LinkParameters, time: float) -> None:
        self.delay, self.jitter, self.period = p.delay, p.jitter, p.period
        self.loss, self.burst = p.loss, p.burst
        self.time = time
        self.max_substep = math.inf  # no integration: any step is one step
        self.rng = seed_state(p.seed, p.stream)
        self.in_time = 0.0
        self.in_x = self.in_y = self.in_heading = self.in_speed = self.in_speed_rate = 0.0
        self.in_turn_rate = self.in_gap = self.in_gap_rate = 0.0
        # [arrival, output_time, *SIGNALS]; None until the initial message is taken
        self.in_use: list[float] | None = None
        self.queue: list[list[float]] = []  # in flight, oldest first; lists are replaced, never changed
        self.last_sent = 0.0  # output_time of the newest message sent (or of the initial message)
        self.next_beacon = time + p.period
        self.delivered = 0
        self.lost = 0
        self.bad = False  # Gilbert-Elliott: the channel's state

    def message(self) -> list[float]:
        """The sender's current message: [output_time, *SIGNALS]."""
        return [self.in_time, self.in_x, self.in_y, self.in_heading, self.in_speed, self.in_speed_rate,
                self.in_turn_rate, self.in_gap, self.in_gap_rate]

    def take_initial(self) -> None:
        """The message at the end of initialization is in use from the start (not counted as sent)."""
        message = self.message()
        self.in_use = [message[0], *message]
        self.last_sent = message[0]

    @property
    def sent(self) -> int:
        return self.delivered + self.lost + len(self.queue)

    def _draw(self) -> float:
        self.rng, output = splitmix64(self.rng)
        return unit_draw(output)

    def _is_lost(self, draw: float) -> bool:
        if self.burst <= 1.0:
            return draw < self.loss
        to_bad, to_good = gilbert_elliott(self.loss, self.burst)
        if self.sent == 0:  # the first message finds the channel in its stationary state
            self.bad = draw < self.loss
        elif self.bad:
            self.bad = not draw < to_good
        else:
            self.bad = draw < to_bad
        return self.bad

    def _beacon_due(self, output_time: float) -> bool:
        if not output_time > self.last_sent + TIME_TOLERANCE:
            return False  # nothing new from the sender
        return self.period == 0.0 or output_time >= self.next_beacon - TIME_TOLERANCE

    def _send(self, message: list[float]) -> None:
        output_time = message[0]
        self.last_sent = output_time
        if self.period > 0.0:
            self.next_beacon = (math.floor((output_time + TIME_TOLERANCE) / self.period) + 1.0) * self.period
        lost = self._is_lost(self._draw())
        extra = self.jitter * self._draw()
        if lost:
            self.lost += 1
            return
        if len(self.queue) + 2 > CAPACITY:
            raise ValueError(f"more than {CAPACITY} messages in flight (delay + jitter spans too many beacons)")
        arrival = output_time + self.delay + extra
        latest = self.queue[-1][0] if self.queue else self.in_use[0]
        if arrival < latest:
            arrival = latest  # FIFO: no overtaking
        self.queue = self.queue + [[arrival, *message]]

    def step(self, t: float, h: float) -> None:
        if self.in_use is None:
            self.take_initial()
        message = self.message()
        if self._beacon_due(message[0]):
            self._send(message)
        now = t + h
        arrived = 0
        while arrived < len(self.queue) and self.queue[arrived][0] <= now + TIME_TOLERANCE:
            arrived += 1
        if arrived:
            self.in_use = self.queue[arrived - 1]
            self.queue = self.queue[arrived:]
            self.delivered += arrived
        self.time = now

    def outputs(self) -> dict[str, float]:
        held = self.in_use[1:] if self.in_use is not None else self.message()
        values = dict(zip(SIGNALS, held[1:]))
        values["output_time"] = held[0]
        values["sent"] = float(self.sent)
        values["delivered"] = float(self.delivered)
        values["lost"] = float(self.lost)
        values["age"] = self.time - held[0]
        return values
