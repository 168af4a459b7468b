"""The [links] tables of a config (docs/config.md, "Links"): the keys a link may set, per direction and per
vehicle, and how the layers resolve into one link's ``LinkParameters`` (fmus.model.link)."""

from __future__ import annotations

from typing import Annotated

from pydantic import Field

from fmus.model.link import LinkParameters

from .config_types import Unit, StrictModel

LinkTime = Annotated[float, Field(ge=0.0, le=3600.0), Unit("s")]
LINK_DIRECTIONS = ("backward", "forward")


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


def _link_layers(links: Links, direction: str, vehicle: int) -> list[LinkKeys]:
    """The tables that may set a key of one link, narrowest first."""
    own = links.vehicles.get(str(vehicle))
    layers = [getattr(own, direction)] if own is not None else []
    return layers + [getattr(links, direction), links]


def link_stream(direction: str, vehicle: int) -> int:
    """A link's own stream of the seed: 2 (N - 1) for vehicle N's backward link, + 1 for its forward one."""
    return 2 * (vehicle - 1) + LINK_DIRECTIONS.index(direction)


def resolve_link(links: Links, direction: str, vehicle: int) -> LinkParameters:
    """The settings of vehicle ``vehicle``'s ``direction`` link: each key from the narrowest table that
    sets it, else the perfect link's."""
    layers = _link_layers(links, direction, vehicle)
    default = LinkParameters()
    values = {key: next((getattr(t, key) for t in layers if getattr(t, key) is not None), getattr(default, key))
              for key in LinkKeys.model_fields}
    return LinkParameters(**values, stream=link_stream(direction, vehicle))
