"""The trace format's names and shared rules: channel topics, channel kinds, MCAP framing.

docs/trace-format.md describes the format; the writer (``trace``), the reader (``reader``) and
the recovery (``recovery``) all take their constants from here.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Iterable

if TYPE_CHECKING:  # annotations only: a run's stepping process needs no mcap (its trace worker writes)
    from mcap.records import Channel, Schema

CHANNEL_PREFIX = "/platoon/"
SCHEMA_ENCODING = "jsonschema"
MESSAGE_ENCODING = "json"
KIND_KEY = "platoon.kind"  # channel metadata: "component", "errors", "foxglove" or "live" (a robot link)
ERRORS_TOPIC = CHANNEL_PREFIX + "errors"
LOG_TOPIC = CHANNEL_PREFIX + "log"

CHUNK_SIZE = 1 << 20  # bytes of uncompressed records per chunk, at most
FLUSH_INTERVAL = 1.0  # s of wall time: a chunk is closed and the file flushed at least this often
BLOCK = 500  # rows buffered before they are encoded
MAGIC = b"\x89MCAP0\r\n"
FOOTER_LENGTH = 1 + 8 + 8 + 8 + 4  # opcode, record length, summary start, summary offset start, crc


class TraceError(ValueError):
    """A file that is not a usable trace; the message says why and what to do."""


def vehicle_names(names: "Iterable[str]") -> list[str]:
    """The vehicles among component names (``vehicle<k>``), in platoon order."""
    vehicles = [n for n in names if n.startswith("vehicle") and n[len("vehicle"):].isdigit()]
    return sorted(vehicles, key=lambda n: int(n[len("vehicle"):]))


# A communication link's component (orchestrator.scenario.wiring.link_name: link_backward2, link_forward3):
# it repeats a sender's message, so it is recorded like any component but is no body in the 3D scene.
LINK_PREFIX = "link_"


def is_link(name: str) -> bool:
    return name.startswith(LINK_PREFIX)


def link_name(direction: str, vehicle: int) -> str:
    """Component name of vehicle ``vehicle``'s link in ``direction`` ("backward": from the component
    ahead to the vehicle; "forward": from the vehicle to the component ahead), e.g. link_backward2."""
    return f"{LINK_PREFIX}{direction}{vehicle}"


def channel_name(component: str) -> str:
    return CHANNEL_PREFIX + component


# Chunk groups: which channels share chunks. A reader decompresses whole chunks, so channels read
# together share them and channels read apart do not (docs/trace-format.md, "Chunks"): the bodies (the
# vehicles', the target's and every other component's rows, the live streams, the log), what the links
# and the errors say, and the Foxglove view (the scene, 4.7 KB a row, and the transforms).
BODIES, LINKS, VIEW = 0, 1, 2
CHUNK_GROUPS = 3
SCENE_TOPIC = CHANNEL_PREFIX + "scene"
TF_TOPIC = CHANNEL_PREFIX + "tf"


def chunk_group(topic: str) -> int:
    """The chunk group of the channel ``topic``: BODIES, LINKS or VIEW."""
    if topic in (SCENE_TOPIC, TF_TOPIC):
        return VIEW
    if topic == ERRORS_TOPIC or (topic.startswith(CHANNEL_PREFIX) and is_link(topic[len(CHANNEL_PREFIX):])):
        return LINKS
    return BODIES


def channel_kind(channel: Channel, schema: Schema | None) -> str:
    """"component", "errors", "foxglove" or "other": what a channel of a trace holds."""
    if KIND_KEY in channel.metadata:
        return channel.metadata[KIND_KEY]
    # traces written before channel kinds existed: every JSON /platoon/ channel was a component
    if channel.topic.startswith(CHANNEL_PREFIX) and channel.message_encoding == MESSAGE_ENCODING:
        return "errors" if channel.topic == ERRORS_TOPIC else "component"
    return "foxglove" if schema is not None and schema.name.startswith("foxglove.") else "other"
