"""Start values of both FMUs: the paper's highway case (R = 50 m, d* = 75 m, V_c = 25 m/s).

Each FMU run alone, inputs unconnected, must do something sane. The VirtualTarget then circles at
25 m/s (its lead's speed and gap inputs say "on spacing"); the Vehicle chases a target that starts
where the VirtualTarget starts and moves on steadily (its target inputs describe t = 0 and are
dead-reckoned), starting on the circle one chord d* behind it at 80 % of V_c.
"""

from __future__ import annotations

from fmus.model.paths import CirclePath

RADIUS = 50.0
D_STAR = 75.0
SPEED = 25.0
K_V = 0.5
STOP_TIME = 60.0
STEP = 0.01
MAX_SUBSTEP = 0.01
# The speed laws beyond the paper's (docs/model.md, section 11; docs/config.md says why these values):
# a 2 s time gap, and the standstill gap that makes the equilibrium gap d* at V_c (d* - h V_c = 25 m).
TIME_GAP = 2.0
STANDSTILL_GAP = D_STAR - TIME_GAP * SPEED
CACC_GAIN = 0.2  # Ploeg et al. (ITSC 2011): k_p = 0.2 1/s

_circle = CirclePath(RADIUS)
TARGET_X, TARGET_Y, TARGET_HEADING = _circle.pose_at(0.0)
TARGET_TURN_RATE = SPEED / RADIUS
VEHICLE_X, VEHICLE_Y, VEHICLE_HEADING = _circle.pose_at(-_circle.arc_for_chord(D_STAR))
VEHICLE_SPEED = 0.8 * SPEED
