"""documentation/index.html for each FMU: equations, the paper, and the variable table."""

from __future__ import annotations

import html

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # annotations only: checking that the FMUs are current must not import pythonfmu
    from fmus.slaves.base import PlatoonSlave

PAPER = (
    "I. T. Erekson, R. Sharma, A. Ratnoo, R. Gerdes, "
    "<em>Multi-vehicle Path Following using Modified Trajectory Shaping Guidance</em>."
)

EQUATIONS = {
    "Vehicle": """
<h2>Equations</h2>
<p>The vehicle at (x, y) with heading &gamma;<sub>v</sub> and speed V chases its target (x<sub>t</sub>, y<sub>t</sub>, &gamma;<sub>t</sub>).
d = |p<sub>t</sub> &minus; p| and &lambda; = atan2(y<sub>t</sub> &minus; y, x<sub>t</sub> &minus; x); angle differences are wrapped to (&minus;&pi;, &pi;].</p>
<ul>
<li>regular law (paper eq. 2): a = V&sup2;/d &middot; (4(&lambda; &minus; &gamma;<sub>v</sub>) + 2(&lambda; &minus; &gamma;<sub>t</sub>))</li>
<li>sine law (paper eq. 5): a = V&sup2;/d &middot; (4 sin(&lambda; &minus; &gamma;<sub>v</sub>) + 2 sin(&lambda; &minus; &gamma;<sub>t</sub>))</li>
<li>speed loop: dV/dt = k<sub>v</sub>(V<sub>cmd</sub> &minus; V), with V<sub>cmd</sub> = V<sub>i+1</sub> d*/d<sub>i+1</sub> (the follower's speed and gap) and V<sub>cmd</sub> = V<sub>c</sub> for the last vehicle</li>
<li>kinematic dynamics: dx/dt = V cos &gamma;, dy/dt = V sin &gamma;, d&gamma;/dt = a/V</li>
<li>m3pi dynamics: wheel commands V<sub>r,l</sub> = V<sub>s</sub>(1 &plusmn; W/(2R<sub>t</sub>)), R<sub>t</sub> = V<sub>s</sub>&sup2;/a (paper eqs. 10-11), clipped to &plusmn;wheel_speed_max,
first-order motor lag, unicycle kinematics: V = (v<sub>r</sub> + v<sub>l</sub>)/2, d&gamma;/dt = (v<sub>r</sub> &minus; v<sub>l</sub>)/W</li>
<li>a robot that is not its nominal model: each wheel heads for its gain times its command (m3pi.wheel_gain_right, _left), 0 for
a command inside m3pi.wheel_deadband; with m3pi.command_latency or m3pi.pose_latency &gt; 0, the live run's sampled loop: one
command per step from the pose the motion capture shows, acting command_latency + pose_latency later (docs/model.md)</li>
</ul>
""",
    "VirtualTarget": """
<h2>Equations</h2>
<p>The target moves along the path (circle or line) with arc length s: ds/dt = V<sub>0</sub> = V<sub>1</sub> d*/d<sub>1</sub> (paper eq. 3),
where V<sub>1</sub> and d<sub>1</sub> are the lead vehicle's speed and distance to the target.</p>
""",
}
EQUATIONS["Link"] = """
<h2>What a link does</h2>
<p>At each step the link looks at its sender's message (the <code>in.*</code> inputs and <code>in.time</code>, the time they
describe). A message newer than the last one sent is sent when a beacon is due (<code>period</code> = 0: always; else at
the first new message at or after each multiple of <code>period</code>). Two draws of a splitmix64 stream (seeded by
<code>seed</code> and <code>stream</code>) decide whether it is lost (probability <code>loss</code>; with <code>burst</code> &gt; 1
a Gilbert-Elliott channel with that mean burst length and the same mean loss) and its extra delay, uniform in
[0, <code>jitter</code>]. It arrives at in.time + delay + that extra, never before a message sent earlier. The newest
message arrived by the end of a step is the one in use (the outputs), held until a newer one arrives; <code>age</code>
is the time minus its <code>output_time</code>. The message at the end of initialization is in use from the start.
See docs/links.md of platoon-cosim.</p>
"""
EQUATIONS["LiveVehicle"] = EQUATIONS["Vehicle"] + """
<h2>A live robot</h2>
<p>The pose (x, y, &gamma;<sub>v</sub>) is the robot's, measured by its motion capture and received over Zenoh
(keys <code>&lt;hil.prefix&gt;/m3pi/&lt;hil.robot&gt;/pose</code>, <code>.../cmd/wheels</code>); the guidance above runs on it
each step and the wheel commands go to the robot with a deadline of <code>hil.command_validity</code>. Each doStep
returns when the wall clock has reached its end. No valid pose for <code>hil.pose_timeout</code>, or the robot's
liveliness token gone: a stop command is sent and doStep returns fmi2Error with the reason in the log.
Needs the <code>eclipse-zenoh</code> Python package. Protocol: docs/hil.md of platoon-cosim.</p>
"""
EQUATIONS["RemoteVehicle"] = EQUATIONS["Vehicle"] + """
<h2>A served vehicle</h2>
<p>The equations above run in a <code>platoon serve</code> on another host or process (key
<code>&lt;remote.prefix&gt;/fmu/&lt;remote.server&gt;</code>), whose FMU this one forwards to over Zenoh: the parameters
set here open its instance, each doStep sends the inputs, t and h and returns the outputs at t + h, exactly as the
served FMU computes them. No reply within <code>remote.step_timeout</code>: doStep fails (fmi2Discard) with the reason in the log, naming the
vehicle and the server. Needs the <code>eclipse-zenoh</code> Python package. Protocol: docs/remote.md of
platoon-cosim.</p>
"""

COUPLING = """
<h2>Coupling between communication points</h2>
<p>With <code>coupling = "hold"</code> inputs are held constant over a step (zero-order hold). With the default
<code>coupling = "extrapolate"</code> each input is moved to the instant it is needed: the target is dead-reckoned
along an arc (its speed, speed rate and turn rate), speeds and gaps follow their rates, all from the
<code>time</code> the sender says its values describe. Wire the <code>*_rate</code> and <code>time</code> outputs
with the values (they are ordinary signals) and the coupling error becomes second order in the step in any master.
The state is integrated with RK4 substeps no longer than <code>max_substep</code>.</p>
"""


PYTHONFMU_HOST = """<p>A pythonfmu FMU: its binary embeds CPython through libpython 3.11 and imports the model from
<code>resources/</code> (standard library only). A Python host (FMPy, libcosimpy) needs nothing more; a C or C++ host
must preload the matching libpython (the FMU binary leaves the Python symbols to the process, so <code>LD_LIBRARY_PATH</code> alone is not enough) and set <code>PYTHONHOME</code> to that Python's
prefix. See docs/fmus.md in the platoon-cosim repository.</p>"""


def documentation_html(slave: PlatoonSlave, version: str, host_requirements: str = PYTHONFMU_HOST) -> str:
    cls = type(slave)
    rows = []
    for info in cls.variables:
        start = "" if info.causality == "output" else html.escape(str(info.start))
        rows.append(
            "<tr>"
            + "".join(
                f"<td>{cell}</td>"
                for cell in (
                    f"<code>{html.escape(info.name)}</code>",
                    info.causality,
                    info.type,
                    html.escape(info.unit or ""),
                    start,
                    html.escape(info.description),
                )
            )
            + "</tr>"
        )
    table = (
        "<table><tr><th>name</th><th>causality</th><th>type</th><th>unit</th><th>start</th><th>description</th></tr>"
        + "\n".join(rows)
        + "</table>"
    )
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{cls.__name__} FMU</title>
<style>body{{font-family:sans-serif;max-width:60em;margin:2em auto}}td,th{{border:1px solid #ccc;padding:2px 6px}}table{{border-collapse:collapse}}</style>
</head><body>
<h1>{cls.__name__} (platoon-cosim {html.escape(version)})</h1>
<p>{html.escape(cls.description)}</p>
<p>Paper: {PAPER}</p>
{EQUATIONS[cls.__name__]}
{COUPLING}
<h2>Host requirements</h2>
{host_requirements}
<h2>Variables</h2>
{table}
</body></html>
"""
