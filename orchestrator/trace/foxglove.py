"""Channels for Foxglove (and Lichtblick): a 3D scene, frame transforms, plottable errors, a run log.

Written next to the per-component ``/platoon/<component>`` channels by ``TraceWriter`` (see
docs/foxglove.md and docs/trace-format.md):

* ``/platoon/errors`` (JSON, schema ``platoon.errors``): at every recorded communication point, per
  vehicle ``path_error`` (signed distance to the configured path, m), ``gap_error`` (d - d*, m) and
  ``speed_error`` (V - V_c, m/s); plottable as ``/platoon/errors.vehicle1.path_error``.
* ``/platoon/scene`` (``foxglove.SceneUpdate``, protobuf): the whole scene in every message (the path
  as a line, each vehicle as a box with a heading arrow, a label and a short history line, the target
  as a sphere), so that a seek shows everything; published at ``scene_rate`` Hz of simulated time.
* ``/platoon/tf`` (``foxglove.FrameTransforms``): ``world`` -> ``target``, ``world`` -> ``vehicleN`` at
  the scene's rate, so every entity's frame ``world`` is defined and a 3D panel can follow a vehicle.
* ``/platoon/log`` (``foxglove.Log``): run started, completed, failed (with the error) or interrupted.

The Foxglove message classes and their schemas come from foxglove-sdk (``foxglove.messages``), which
encodes them as protobuf with schema names ``foxglove.SceneUpdate`` etc.; this module never writes a
schema by hand. ``layout(n)`` builds the Foxglove layout shipped as ``layouts/platoon.json``.
"""

from __future__ import annotations

import json
import math
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Sequence

from .encoding import ChannelSpec, register_mcap, template_of
from .format import CHANNEL_PREFIX, LINK_PREFIX, SCENE_TOPIC, TF_TOPIC, is_link
from .number_text import number_texts


class _FoxgloveMessages:
    """``foxglove.messages``, imported when the first scene is encoded: a run's stepping process (which
    builds only ``SceneSettings``; its trace worker encodes) never pays for the SDK's import."""

    def __getattr__(self, name: str) -> Any:
        from foxglove import messages

        globals()["fg"] = messages  # later lookups go straight to the module
        return getattr(messages, name)


fg: Any = _FoxgloveMessages()

if TYPE_CHECKING:
    from orchestrator.scenario.config import Config

ERRORS_TOPIC = "/platoon/errors"
LOG_TOPIC = "/platoon/log"
ROOT_FRAME = "world"
ERROR_FIELDS = ("path_error", "gap_error", "speed_error")

SCENE_RATE = 10.0  # Hz of simulated time
HISTORY = 5.0  # s of simulated time behind each vehicle, at most (scene_scale shortens it)
PATH_POINTS = 180  # points of a circle path's line loop

# Matplotlib's tab10 (also the colours of `platoon report --plots`), as 0..1 RGB.
PALETTE = [
    (0.122, 0.467, 0.706), (1.000, 0.498, 0.055), (0.173, 0.627, 0.173), (0.839, 0.153, 0.157),
    (0.580, 0.404, 0.741), (0.549, 0.337, 0.294), (0.890, 0.467, 0.761), (0.498, 0.498, 0.498),
    (0.737, 0.741, 0.133), (0.090, 0.745, 0.812),
]

Write = Callable[[int, int, bytes], None]  # (channel id, log time ns, data)

MARKER_PIXELS = 9.0  # the screen-size dash drawn on every vehicle, so that it shows at any zoom
PATH_PIXELS = 2.0  # the path's line width on screen
TRAIL_PIXELS = 3.0  # a vehicle's trail width on screen
TRAIL_SHARE = 0.08  # a trail covers at most this share of a circle's circumference ...
TRAIL_GAP_SHARE = 0.4  # ... and of d*, so trails show recent motion, never the whole circle
LABEL_OFFSET = 0.06  # labels sit this share of the view's extent off the path (outside a circle, left of a line)
LABEL_ALL_UP_TO = 10  # platoons up to this size get a "vehicleN" label per vehicle, larger ones "N"


def vehicle_colors(count: int) -> list[tuple[float, float, float]]:
    """One colour per vehicle: tab10 up to 10 vehicles, else viridis from vehicle 1 to vehicle ``count``.

    The same colours in the 3D scene, the layout's plot series and ``platoon figure``, so that a
    vehicle is the same colour everywhere; viridis (a scale, not a cycle) keeps 100 vehicles apart by
    their place in the platoon, where a 10-colour cycle would repeat.
    """
    if count <= len(PALETTE):
        return PALETTE[:count]
    from .viridis import viridis  # matplotlib's table: importing matplotlib would cost ~0.1 s per run

    return [viridis(i / (count - 1)) for i in range(count)]


def hex_color(rgb: tuple[float, float, float]) -> str:
    return "#" + "".join(f"{round(255 * c):02x}" for c in rgb)


def vehicle_label(name: str, vehicles: int) -> str:
    """A vehicle's label in the scene: its name, or only its number in a large platoon (less clutter)."""
    if vehicles <= LABEL_ALL_UP_TO or not name.startswith("vehicle"):
        return name
    return name[len("vehicle"):]


@dataclass(frozen=True)
class SceneScale:
    """Sizes that follow a run's scale, so that a 50 m and a 1 m circle look alike on screen.

    ``extent``: the length the view must show (a circle's diameter, a line platoon's length); ``size``:
    a vehicle's box length, a fraction of the extent but never longer than the space between vehicles;
    ``history``: seconds of trail behind each vehicle.
    """

    extent: float
    size: float
    history: float


def scene_scale(settings: "SceneSettings", vehicles: int, history: float = HISTORY) -> SceneScale:
    count = max(vehicles, 1)
    d_star = settings.d_star
    if settings.path_kind == "circle":
        circumference = 2.0 * math.pi * settings.radius
        extent = 2.0 * settings.radius
        spacing = min(d_star, circumference / count)
        trail = min(TRAIL_SHARE * circumference, TRAIL_GAP_SHARE * d_star)
    else:
        extent = (count + 1) * d_star  # the target and every vehicle, d* apart
        spacing = d_star
        trail = TRAIL_GAP_SHARE * d_star
    size = min(0.08 * extent, 0.6 * spacing)
    speed = abs(settings.v_c)
    return SceneScale(extent, size, min(history, trail / speed) if speed > 0 else history)



def errors_schema(vehicles: Sequence[str]) -> bytes:
    """JSON Schema of ``/platoon/errors``: plain numbers only (a nullable type would not plot)."""
    fields = {
        "path_error": {"type": "number", "description": "signed distance to the path, m (circle: r - R)"},
        "gap_error": {"type": "number", "description": "d - d*, m"},
        "speed_error": {"type": "number", "description": "V - V_c, m/s"},
    }
    properties: dict[str, Any] = {"t": {"type": "number", "description": "simulation time [s]"}}
    for name in vehicles:
        properties[name] = {
            "type": "object",
            "properties": fields,
            "required": list(ERROR_FIELDS),
            "additionalProperties": False,
        }
    return json.dumps(
        {
            "$schema": "https://json-schema.org/draft/2020-12/schema",
            "title": "platoon.errors",
            "type": "object",
            "properties": properties,
            "required": ["t", *vehicles],
            "additionalProperties": False,
        }
    ).encode()


def _quaternion(yaw: float) -> fg.Quaternion:
    return fg.Quaternion(x=0.0, y=0.0, z=math.sin(0.5 * yaw), w=math.cos(0.5 * yaw))


def _color(rgb: tuple[float, float, float], alpha: float = 1.0) -> fg.Color:
    return fg.Color(r=rgb[0], g=rgb[1], b=rgb[2], a=alpha)


def _timestamp(stamp: int) -> fg.Timestamp:
    return fg.Timestamp(sec=stamp // 1_000_000_000, nsec=stamp % 1_000_000_000)


@dataclass(frozen=True)
class SceneSettings:
    """What the Foxglove channels take from a run's config: the path and the platoon's set-points.

    Plain and picklable, so that the trace worker process (orchestrator/trace/serve.py) gets it without
    importing the config's validation library.
    """

    path: Any  # the fmus.model path (signed distance, geometry)
    path_kind: str
    center: tuple[float, float]
    radius: float
    heading: float
    d_star: float
    v_c: float

    @classmethod
    def of(cls, config: "Config") -> "SceneSettings":
        from orchestrator.scenario.scenario import path_of

        p = config.path
        return cls(path_of(config), p.kind, (float(p.center[0]), float(p.center[1])), float(p.radius),
                   float(p.heading), float(config.platoon.d_star), float(config.platoon.speed))


class FoxgloveChannels:
    """Derived channels of one run. ``TraceWriter`` calls ``register`` once, ``row`` per recorded row."""

    def __init__(
        self,
        settings: "SceneSettings | Config",
        components: Sequence[tuple[str, Sequence[str]]],
        scene_rate: float = SCENE_RATE,
        history: float = HISTORY,
    ) -> None:
        settings = settings if isinstance(settings, SceneSettings) else SceneSettings.of(settings)
        self.settings = settings
        self.path = settings.path
        self.names = [name for name, _ in components]
        self.vehicles = [name for name in self.names if name.startswith("vehicle")]
        # what the scene draws: the target and the vehicles (a link only repeats a sender's, stale, pose)
        self.bodies = [name for name in self.names if not is_link(name)]
        self._index = {name: i for i, name in enumerate(self.names)}
        outputs = {name: list(keys) for name, keys in components}
        # positions of x, y, heading (every component) and of gap, speed (vehicles) among the outputs
        self._pose = {name: tuple(outputs[name].index(k) for k in ("x", "y", "heading")) for name in self.bodies}
        self._gap_speed = {name: (outputs[name].index("gap"), outputs[name].index("speed")) for name in self.vehicles}
        self.d_star = settings.d_star
        self.v_c = settings.v_c
        self.period = 1.0 / scene_rate if scene_rate > 0 else math.inf
        self._next_scene = 0.0
        scale = scene_scale(settings, len(self.vehicles), history)
        self._trail_end: dict[str, tuple[float, float]] = {}  # the last point of each trail
        self._history = {name: deque(maxlen=max(2, int(round(scale.history * scene_rate)))) for name in self.vehicles}
        size = scale.size
        self._size = size
        self._label_offset = LABEL_OFFSET * scale.extent
        self._box = fg.Vector3(x=size, y=0.45 * size, z=0.35 * size)
        self._labels = {name: vehicle_label(name, len(self.vehicles)) for name in self.bodies}
        self._colors = dict(zip(self.vehicles, vehicle_colors(len(self.vehicles))))
        self._path_points = self._circle_points() if settings.path_kind == "circle" else None
        # the errors JSON cut where the numbers go (orchestrator/trace/native_encoder.c fills the pieces)
        self.errors_pieces = [b'{"t":']
        for i, name in enumerate(self.vehicles):
            self.errors_pieces += [(b"}," if i else b",") + json.dumps(name).encode() + b':{"path_error":',
                                   b',"gap_error":', b',"speed_error":']
        self.errors_pieces.append(b"}}" if self.vehicles else b"}")
        self._errors_template = template_of(self.errors_pieces)
        self._white = _color((1.0, 1.0, 1.0))
        self._grey = _color((0.6, 0.6, 0.6))
        self._solid = {name: _color(rgb) for name, rgb in self._colors.items()}
        self._faded = {name: _color(rgb, 0.6) for name, rgb in self._colors.items()}
        self._level = _quaternion(0.0)
        self.channels: dict[str, int] = {}
        self.scenes = 0

    # --- registration -------------------------------------------------------------------------

    def specs(self) -> dict[str, ChannelSpec]:
        """The channels by key ("errors", "scene", "tf", "log"), in the order they are registered."""
        specs = {"errors": ChannelSpec(ERRORS_TOPIC, "platoon.errors", "jsonschema", errors_schema(self.vehicles), "json",
                                       {"platoon.kind": "errors"})}
        for key, topic, kind in (("scene", SCENE_TOPIC, fg.SceneUpdate), ("tf", TF_TOPIC, fg.FrameTransforms),
                                 ("log", LOG_TOPIC, fg.Log)):
            schema = kind.get_schema()
            specs[key] = ChannelSpec(topic, schema.name, schema.encoding, bytes(schema.data), "protobuf",
                                     {"platoon.kind": "foxglove"})
        return specs

    def register(self, writer: Any) -> None:
        """Register schemas and channels on an ``mcap.writer.Writer`` (before any message)."""
        self.bind(lambda spec: register_mcap(writer, spec))

    def bind(self, register: Callable[[ChannelSpec], int]) -> None:
        """Declare the channels on a sink: ``register(spec)`` returns the id the sink's messages carry."""
        for key, spec in self.specs().items():
            self.channels[key] = register(spec)

    def native_arguments(self, starts: Sequence[int]) -> tuple[Any, ...] | None:
        """What the C encoder (orchestrator/trace/native_encoder.c) needs to write these channels, from the
        row positions of each component's first output; None for a path it cannot measure."""
        from fmus.model.paths import CirclePath, LinePath

        if isinstance(self.path, CirclePath):
            distance = (True, self.path.center_x, self.path.center_y, self.path.radius)
        elif isinstance(self.path, LinePath):
            distance = (False, self.path.origin_x, self.path.origin_y, self.path.heading)
        else:
            return None
        bodies = []
        for name in self.bodies:
            start = starts[self._index[name]]
            ix, iy, ih = (start + i for i in self._pose[name])
            ig, iv = (start + i for i in self._gap_speed[name]) if name in self._history else (0, 0)
            rgb = self._colors.get(name, (1.0, 1.0, 1.0))
            bodies.append((ix, iy, ih, ig, iv, name in self._history, name.encode(), self._labels[name].encode(),
                           (*rgb, 1.0), (*rgb, 0.6)))
        history = next(iter(self._history.values())).maxlen if self._history else 2
        points = [v for xy in self._circle_xy() for v in xy] if self._path_points is not None else []
        s = self.settings
        return ((self.channels["errors"], self.channels["tf"], self.channels["scene"]), self.errors_pieces, bodies,
                distance, (self.period, self._next_scene, self._size, self._label_offset, self.d_star, self.v_c),
                history, (self._path_points is not None, s.center[0], s.center[1], s.heading), points)

    # --- per block ----------------------------------------------------------------------------

    def row(self, time: float, stamp: int, outputs: Sequence[Sequence[float]]) -> list[tuple[int, bytes]]:
        """(channel, data) at one recorded row: the errors; the scene and transforms when one is due."""
        messages = [(self.channels["errors"], self.errors_message(time, outputs))]
        if self.advance(time, outputs):
            messages.extend(self._scene(stamp, self._poses(outputs), {name: list(h) for name, h in self._history.items()}))
        return messages

    def advance(self, time: float, outputs: Sequence[Sequence[float]]) -> bool:
        """Follow one recorded row: at a scene tick, add the vehicles' positions to their trails; True then."""
        if time < self._next_scene - 1e-9:
            return False
        for name, (x, y, _) in zip(self.bodies, self._poses(outputs)):
            if name in self._history:
                self._history[name].append(fg.Point3(x=x, y=y, z=0.0))
                self._trail_end[name] = (x, y)
        while self._next_scene <= time + 1e-9:
            self._next_scene += self.period
        return True

    def snapshot(self, time: float, stamp: int, outputs: Sequence[Sequence[float]]) -> list[tuple[int, bytes]]:
        """(channel, data) of the errors, transforms and whole scene at any row, the trails so far ending at
        the vehicles (the live view's frame between two scene ticks); changes no state."""
        poses = self._poses(outputs)
        trails = {}
        for name, (x, y, _) in zip(self.bodies, poses):
            if name in self._history:
                trail = trails[name] = list(self._history[name])
                if self._trail_end.get(name) != (x, y):  # at a scene tick the trail ends here already
                    trail.append(fg.Point3(x=x, y=y, z=0.0))
        return [(self.channels["errors"], self.errors_message(time, outputs)), *self._scene(stamp, poses, trails)]

    @property
    def next_scene(self) -> float:
        """Simulated time of the next scene tick."""
        return self._next_scene

    def errors_message(self, time: float, outputs: Sequence[Sequence[float]]) -> bytes:
        """The ``/platoon/errors`` JSON at one row; raises ValueError rather than write nan or inf."""
        distance = self.path.signed_distance
        values = [float(time)]
        for name in self.vehicles:
            row = outputs[self._index[name]]
            ix, iy, _ = self._pose[name]
            ig, iv = self._gap_speed[name]
            values.append(float(distance(row[ix], row[iy])))
            values.append(float(row[ig]) - self.d_star)
            values.append(float(row[iv]) - self.v_c)
        if not math.isfinite(sum(values)):
            raise ValueError(f"an error at t = {time:g} s is not finite")
        return self._errors_template % tuple(number_texts(values))

    def _circle_xy(self) -> list[tuple[float, float]]:
        p = self.settings
        return [(p.center[0] + p.radius * math.cos(a), p.center[1] + p.radius * math.sin(a))
                for a in (2.0 * math.pi * k / PATH_POINTS for k in range(PATH_POINTS))]

    def _circle_points(self) -> list[fg.Point3]:
        return [fg.Point3(x=x, y=y, z=0.0) for x, y in self._circle_xy()]

    def _line_points(self, poses: list[tuple[float, float, float]]) -> list[fg.Point3]:
        p = self.settings
        ux, uy = math.cos(p.heading), math.sin(p.heading)
        along = [(x - p.center[0]) * ux + (y - p.center[1]) * uy for x, y, _ in poses]
        margin = 2.0 * self.d_star
        low, high = min(along) - margin, max(along) + margin
        return [fg.Point3(x=p.center[0] + s * ux, y=p.center[1] + s * uy, z=0.0) for s in (low, high)]

    def _outward(self, x: float, y: float, heading: float) -> tuple[float, float]:
        """Unit vector off the path where a label does not cover the vehicles: outward of a circle, left of a line."""
        if self._path_points is not None:
            dx, dy = x - self.settings.center[0], y - self.settings.center[1]
            r = math.hypot(dx, dy)
            if r > 0.0:
                return dx / r, dy / r
        return -math.sin(heading), math.cos(heading)

    def _poses(self, outputs: Sequence[Sequence[float]]) -> list[tuple[float, float, float]]:
        """(x, y, heading) of every body (the target, the vehicles), in component order."""
        poses = []
        for name in self.bodies:
            values = outputs[self._index[name]]
            ix, iy, ih = self._pose[name]
            poses.append((values[ix], values[iy], values[ih]))
        return poses

    def _scene(self, stamp: int, poses: list[tuple[float, float, float]],
               trails: dict[str, list[fg.Point3]]) -> list[tuple[int, bytes]]:
        when = _timestamp(stamp)
        size = self._size
        points = self._path_points if self._path_points is not None else self._line_points(poses)
        entities = [
            fg.SceneEntity(
                timestamp=when, frame_id=ROOT_FRAME, id="path",
                lines=[fg.LinePrimitive(
                    type=fg.LinePrimitiveLineType.LineLoop if self._path_points is not None else fg.LinePrimitiveLineType.LineStrip,
                    thickness=PATH_PIXELS, scale_invariant=True, points=points, color=self._grey)],
            )
        ]
        transforms = []
        for name, (x, y, heading) in zip(self.bodies, poses):
            pose = fg.Pose(position=fg.Vector3(x=x, y=y, z=0.0), orientation=_quaternion(heading))
            transforms.append(fg.FrameTransform(
                timestamp=when, parent_frame_id=ROOT_FRAME, child_frame_id=name,
                translation=fg.Vector3(x=x, y=y, z=0.0), rotation=_quaternion(heading)))
            nx, ny = self._outward(x, y, heading)
            label = fg.TextPrimitive(
                pose=fg.Pose(position=fg.Vector3(x=x + self._label_offset * nx, y=y + self._label_offset * ny,
                                                 z=0.8 * size), orientation=self._level),
                billboard=True, font_size=12.0, scale_invariant=True, color=self._white, text=self._labels[name])
            # a dash along the heading, drawn in screen pixels: the vehicle shows however far one zooms out
            back = fg.Point3(x=x - 0.5 * size * math.cos(heading), y=y - 0.5 * size * math.sin(heading), z=0.01 * size)
            front = fg.Point3(x=x + 0.5 * size * math.cos(heading), y=y + 0.5 * size * math.sin(heading), z=0.01 * size)
            if name in self._history:
                color = self._solid[name]
                entities.append(fg.SceneEntity(
                    timestamp=when, frame_id=ROOT_FRAME, id=name,
                    cubes=[fg.CubePrimitive(pose=pose, size=self._box, color=color)],
                    arrows=[fg.ArrowPrimitive(pose=pose, shaft_length=0.9 * size, shaft_diameter=0.1 * size,
                                              head_length=0.4 * size, head_diameter=0.25 * size, color=color)],
                    lines=[fg.LinePrimitive(type=fg.LinePrimitiveLineType.LineStrip, thickness=TRAIL_PIXELS,
                                            scale_invariant=True, points=trails[name], color=self._faded[name]),
                           fg.LinePrimitive(type=fg.LinePrimitiveLineType.LineList, thickness=MARKER_PIXELS,
                                            scale_invariant=True, points=[back, front], color=color)],
                    texts=[label],
                ))
            else:  # the virtual target
                entities.append(fg.SceneEntity(
                    timestamp=when, frame_id=ROOT_FRAME, id=name,
                    spheres=[fg.SpherePrimitive(pose=pose, size=fg.Vector3(x=0.5 * size, y=0.5 * size, z=0.5 * size),
                                                color=self._white)],
                    arrows=[fg.ArrowPrimitive(pose=pose, shaft_length=0.6 * size, shaft_diameter=0.08 * size,
                                              head_length=0.3 * size, head_diameter=0.2 * size, color=self._white)],
                    lines=[fg.LinePrimitive(type=fg.LinePrimitiveLineType.LineList, thickness=0.7 * MARKER_PIXELS,
                                            scale_invariant=True, points=[back, front], color=self._white)],
                    texts=[label],
                ))
        self.scenes += 1
        return [(self.channels["tf"], fg.FrameTransforms(transforms=transforms).encode()),
                (self.channels["scene"], fg.SceneUpdate(entities=entities).encode())]

    # --- log ----------------------------------------------------------------------------------

    def log(self, write: Write, time: float, level: str, message: str) -> None:
        """One ``foxglove.Log`` line at simulation ``time``; level Info, Warning or Error."""
        stamp = int(round(max(time, 0.0) * 1e9))
        write(self.channels["log"], stamp, fg.Log(
            timestamp=_timestamp(stamp), level=getattr(fg.LogLevel, level), message=message,
            name="platoon", file="", line=0).encode())


# --- the layout ---------------------------------------------------------------------------------

VIEW_MARGIN = 1.3  # the 3D panel shows this many times the run's extent (a margin for labels, offsets)
LEGEND_UP_TO = 12  # plots of larger platoons show no legend: their series take the scene's colour scale


def message_path(topic: str, *fields: str) -> str:
    """A Foxglove message path; a field whose name holds anything but letters, digits or ``_`` is quoted.

    ``message_path("/platoon/vehicle1", "wheel.right")`` is ``/platoon/vehicle1."wheel.right"``: unquoted,
    the viewer reads field ``wheel``, then ``right``, and plots nothing.
    """
    def part(name: str) -> str:
        if name.replace("_", "a").isalnum() and not name[0].isdigit():
            return name
        return '"' + name.replace("\\", "\\\\").replace('"', '\\"') + '"'

    return topic + "".join("." + part(name) for name in fields)


def _plot(title: str, field: str, vehicles: Sequence[str], colors: Sequence[tuple[float, float, float]]) -> dict[str, Any]:
    legend = "left" if len(vehicles) <= LEGEND_UP_TO else "none"
    return {
        "foxglovePanelTitle": title,  # the key Lichtblick and Foxglove read for a panel's title
        "paths": [
            {
                "value": message_path(ERRORS_TOPIC, name, field),
                "enabled": True,
                "timestampMethod": "receiveTime",
                "label": name.replace("vehicle", "vehicle "),
                "color": hex_color(rgb),
            }
            for name, rgb in zip(vehicles, colors)
        ],
        "showXAxisLabels": True,
        "showYAxisLabels": True,
        "showLegend": legend != "none",
        "legendDisplay": legend,  # beside the plot, never over the transient and the disturbance
        "showPlotValuesInLegend": False,  # the values at the cursor carry 17 digits: the axis says enough
        "isSynced": True,
        "xAxisVal": "timestamp",
        "sidebarDimension": 150,
    }


def _link_plot(links: Sequence[str]) -> dict[str, Any]:
    """The age of the message each link delivers (docs/links.md), one series per link."""
    plot = _plot("age of information [s] (links)", "age", [], [])
    plot["paths"] = [{"value": message_path(CHANNEL_PREFIX + name, "age"), "enabled": True,
                      "timestampMethod": "receiveTime", "label": name[len(LINK_PREFIX):]} for name in links]
    plot["showLegend"], plot["legendDisplay"] = True, "left"
    return plot


def _live_plots(live: Sequence[str]) -> dict[str, dict[str, Any]]:
    """Each live robot's link (docs/hil.md, "The live view"), from its ``<vehicle>/link`` statistics, in two
    plots: the age of the poses the run used (median and largest so far: tens of ms) and the robot-side
    safety stops (a count), each on its own axis (on one, a count of 3 flattens the ages onto zero). Labels
    of at most 9 characters ("v3 median", "vehicle 3"): the legend's 150 px column shows "vehicle 4" whole and
    cut "vehicle3 med" (Lichtblick 1.10.8 at 1600x900)."""
    def plot(title: str, fields: tuple[tuple[str, str], ...]) -> dict[str, Any]:
        shown = _plot(title, "link", [], [])
        shown["paths"] = [{"value": message_path(f"{CHANNEL_PREFIX}{name}/link", field), "enabled": True,
                           "timestampMethod": "receiveTime", "label": label.format(name[len("vehicle"):])}
                          for name in live for field, label in fields]
        shown["showLegend"], shown["legendDisplay"] = True, "left"
        return shown

    return {"Plot!live": plot("live link: pose age [s] (median, max)", (("pose_age.median", "v{} median"),
                                                                         ("pose_age.max", "v{} max"))),
            "Plot!stops": plot("live link: robot-side safety stops", (("command.safety_stops", "vehicle {}"),))}


def _column(panels: Sequence[Any]) -> Any:
    """``panels`` stacked top to bottom, each the same height (a legend of 8 lines needs its share)."""
    if len(panels) == 1:
        return panels[0]
    return {"first": panels[0], "second": _column(panels[1:]), "direction": "column",
            "splitPercentage": 100.0 / len(panels)}


def _nice_step(length: float) -> float:
    """1, 2 or 5 times a power of ten, about a fifth of ``length``: the grid's cell."""
    raw = length / 5.0
    power = 10.0 ** math.floor(math.log10(raw))
    return next(step * power for step in (1.0, 2.0, 5.0, 10.0) if step * power >= raw)


def _camera(settings: SceneSettings, vehicles: int) -> tuple[dict[str, Any], dict[str, Any], str, str]:
    """(camera, grid layer, follow mode, follow frame): a top view fitted to the run's extent.

    A circle is seen whole, centred; a line platoon moves away from any fixed view, so the camera
    follows the position of its middle vehicle, the platoon's length across the panel.
    """
    scale = scene_scale(settings, vehicles)
    distance = VIEW_MARGIN * scale.extent  # an orthographic top view shows about `distance` across its height
    circle = settings.path_kind == "circle"
    target = [settings.center[0], settings.center[1], 0.0] if circle else [0.0, 0.0, 0.0]
    camera = {
        "distance": distance, "perspective": False, "phi": 0.0, "thetaOffset": 0.0,
        "targetOffset": [0.0, 0.0, 0.0], "target": target, "targetOrientation": [0.0, 0.0, 0.0, 1.0],
        "fovy": 45.0, "near": 0.001 * distance, "far": 1000.0 * distance,
    }
    step = _nice_step(scale.extent)
    cells = 2 * math.ceil(0.5 * distance * 1.8 / step)
    grid = {"visible": circle, "frameLocked": True, "label": "Grid", "instanceId": "grid",
            "layerId": "foxglove.Grid", "size": cells * step, "divisions": cells, "lineWidth": 1,
            "color": "#248eff40", "position": target, "rotation": [0, 0, 0], "order": 1}
    if circle:
        return camera, grid, "follow-none", ROOT_FRAME
    return camera, grid, "follow-position", f"vehicle{(vehicles + 1) // 2}"


def default_settings() -> SceneSettings:
    """The paper's circle (R = 50 m, d* = 75 m, V_c = 25 m/s): the static layout's view."""
    return SceneSettings(None, "circle", (0.0, 0.0), 50.0, 0.0, 75.0, 25.0)


def layout(vehicles: int = 6, settings: SceneSettings | None = None, links: Sequence[str] = (),
           live: Sequence[str] = ()) -> dict[str, Any]:
    """A Foxglove layout: a 3D panel (fitted to ``settings``' path) beside plots of path, gap and speed errors,
    and, for a run with ``links`` (their component names), of the age of each link's message, and for a run
    with ``live`` robots (their vehicles' names), of each live link.

    ``platoon layout TRACE`` and ``platoon run`` pass the run's settings and vehicle count (one series
    per vehicle, the camera fitted to its path); without them, the paper's circle.
    """
    settings = settings or default_settings()
    names = [f"vehicle{i}" for i in range(1, vehicles + 1)]
    colors = vehicle_colors(vehicles)
    camera, grid, follow_mode, follow_frame = _camera(settings, vehicles)
    hidden = {f"frame:{frame}": {"visible": False} for frame in (ROOT_FRAME, "target", *names)}
    topics = {SCENE_TOPIC: {"visible": True}, TF_TOPIC: {"visible": True}}
    three_d = {
        "foxglovePanelTitle": "platoon (top view)",
        "cameraState": camera,
        "followMode": follow_mode,
        "followTf": follow_frame,
        # the frames exist so that entities resolve; their axes and links to `world` would only clutter
        "scene": {"enableStats": False, "transforms": {"showLabel": False, "axisScale": 1.0}},
        "transforms": hidden,
        "topics": topics,
        "layers": {"grid": grid},
        "publish": {"type": "point", "poseTopic": "/move_base_simple/goal", "pointTopic": "/clicked_point",
                    "poseEstimateTopic": "/initialpose", "poseEstimateXDeviation": 0.5,
                    "poseEstimateYDeviation": 0.5, "poseEstimateThetaDeviation": 0.26179939},
        "imageMode": {},
    }
    scale_note = "" if vehicles <= LEGEND_UP_TO else f" (colour: vehicle 1 purple to {vehicles} yellow)"
    extra = {}
    if links:
        extra["Plot!links"] = _link_plot(links)
    if live:
        extra.update(_live_plots(live))
    return {
        "configById": {
            "3D!platoon": three_d,
            "Plot!path": _plot(f"path error [m]{scale_note}", "path_error", names, colors),
            "Plot!gap": _plot(f"gap error d - d* [m]{scale_note}", "gap_error", names, colors),
            "Plot!speed": _plot(f"speed error V - V_c [m/s]{scale_note}", "speed_error", names, colors),
            "RosOut!log": {"foxglovePanelTitle": "run log", "searchTerms": [], "minLogLevel": 1,
                           "topicToRender": LOG_TOPIC},
            **extra,
        },
        "globalVariables": {},
        "userNodes": {},
        "playbackConfig": {"speed": 1.0},
        "layout": {
            "first": {"first": "3D!platoon", "second": "RosOut!log", "direction": "column", "splitPercentage": 82},
            "second": _column(["Plot!path", "Plot!gap", "Plot!speed", *extra]),  # extra plots below the speed's
            "direction": "row",
            "splitPercentage": 55,
        },
    }


def layout_json(vehicles: int = 6, settings: SceneSettings | None = None) -> str:
    return json.dumps(layout(vehicles, settings), indent=2) + "\n"


if __name__ == "__main__":  # python -m orchestrator.trace.foxglove [VEHICLES] > layouts/platoon.json
    import sys

    from orchestrator.support.internal_entry import check_arguments

    usage = "python -m orchestrator.trace.foxglove [VEHICLES] > layouts/platoon.json"
    check_arguments(sys.argv[1:], usage, "Prints the static Foxglove layout for VEHICLES vehicles (default 6); "
                    "`platoon layout TRACE.mcap` fits one to a run.", fits=lambda args: len(args) <= 1 and all(
                        arg.isdigit() for arg in args))
    print(layout_json(int(sys.argv[1]) if len(sys.argv) > 1 else 6), end="")
