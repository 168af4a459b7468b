"""The [links] tables of a config (docs/config.md, "Links"): the keys a link may set, per direction and per
vehicle, and how the layers resolve into one link's ``LinkParameters`` (fmus.model.link)."""

from __future__ import annotations

from typing import Annotated

from pydantic import Field

from .config_logic import LINK_DIRECTIONS, link_stream, resolve_link  # noqa: F401  (re-exported)
from .config_types import Unit, StrictModel

LinkTime = Annotated[float, Field(ge=0.0, le=3600.0), Unit("s")]


class LinkKeys(StrictModel):
    """One link's settings (docs/links.md); a key left out comes from the wider table."""

    delay: LinkTime | None = Field(None, description="s from a message's output_time to its arrival")
    jitter: LinkTime | None = Field(None, description="s: each message's extra delay is uniform in [0, jitter]")
    period: LinkTime | None = Field(None, description="s between beacons; 0: every communication step")
    loss: Annotated[float, Field(ge=0.0, le=1.0)] | None = Field(None, description="probability a message is lost")
    burst: Annotated[float, Field(ge=1.0, le=1e6)] | None = Field(
        None, description="mean burst length in messages; > 1: Gilbert-Elliott losses with the same mean loss")
    seed: int | None = Field(None, ge=0, le=2**31 - 1, description="seed of every link's random stream")


class VehicleLinks(StrictModel):
    """The two links between vehicle N and the component ahead of it (the target for vehicle 1)."""

    backward: LinkKeys = LinkKeys()
    forward: LinkKeys = LinkKeys()


class Links(LinkKeys):
    """``[links]``: every link; ``[links.backward]``, ``[links.forward]``: one direction;
    ``[links.vehicles.N.backward]`` / ``.forward``: the links of vehicle N. The narrowest wins."""

    backward: LinkKeys = LinkKeys()
    forward: LinkKeys = LinkKeys()
    vehicles: dict[str, VehicleLinks] = Field(default_factory=dict)
