"""The rmw_zenoh convention: how ROS 2's Zenoh middleware names topics, attaches metadata and announces
its graph. Every rule here cites ros2/rmw_zenoh's ``docs/design.md`` (section in brackets) and the
function of ``rmw_zenoh_cpp/src/detail/`` that implements it; tests/test_ros2.py checks them field by
field against the design document's own examples.

* Topic key [Topic and Service name mapping; ``TopicInfo::TopicInfo``]:
  ``<domain_id>/<fully qualified name without leading or trailing "/">/<DDS type name>/<type hash>``.
* Attachment of every ``put`` [Publishers; ``AttachmentData::serialize_to_zbytes``]: the sequence number
  (int64 LE, from 1 per publisher), the source timestamp (int64 LE, ns since the Unix epoch), the GID
  length (one byte, 16) and the 16-byte GID: 33 bytes, written with Zenoh's own serializer
  (``zenoh.ext.z_serialize``, the format of the ``zenoh::ext::Serializer`` rmw_zenoh uses). This is the
  layout of rmw_zenoh 0.2.4 and later on Jazzy, and of Kilted and Rolling; the first Jazzy binaries
  (up to 0.2.3) wrote labelled fields instead and do not read it. Humble has no type hashes in its
  keys and is not matched.
* Liveliness tokens [Graph Cache; ``Entity::Entity``, ``mangle_name``, ``qos_to_keyexpr``]: a node
  ``@ros2_lv/<domain>/<zid>/<nid>/<nid>/NN/<enclave>/<namespace>/<node>``, a publisher or subscription
  ``@ros2_lv/<domain>/<zid>/<nid>/<eid>/MP|MS/<enclave>/<namespace>/<node>/<topic>/<type>/<hash>/<qos>``,
  every name mangled ("/" -> "%"), the QoS as ``qos_to_keyexpr`` writes it (a field equal to
  rmw_zenoh's default, RELIABLE / VOLATILE / KEEP_LAST 42 / infinite durations, is left empty).
* GID [``Entity::Entity``]: the XXH3-128 hash of the entity's liveliness key, low 64 bits then high
  64 bits, each little-endian.
"""

from __future__ import annotations

import time

import xxhash
import zenoh
import zenoh.ext

from ..protocol import Drop, MessageError
from .messages import dds_type_name, type_hash

ADMIN_SPACE = "@ros2_lv"
NODE, PUBLISHER, SUBSCRIPTION = "NN", "MP", "MS"
GID_SIZE = 16
ATTACHMENT_SIZE = 8 + 8 + 1 + GID_SIZE
# rmw's enum values (rmw/types.h) and rmw_zenoh's defaults (qos.cpp, QoS::QoS)
RELIABLE, BEST_EFFORT = 1, 2
DEFAULT_RELIABILITY, DEFAULT_DEPTH = RELIABLE, 42


def strip_slashes(name: str) -> str:
    """A name without its leading and trailing "/" (``strip_slashes`` in liveliness_utils.cpp)."""
    return name.strip("/")


def topic_key(domain: int, topic: str, typename: str) -> str:
    """The key expression of a topic: ``0/chatter/std_msgs::msg::dds_::String_/RIHS01_df66...``."""
    return f"{domain}/{strip_slashes(topic)}/{dds_type_name(typename)}/{type_hash(typename)}"


def mangle(name: str) -> str:
    """Each "/" replaced by "%" (``mangle_name``): "/" -> "%", "/a/b" -> "%a%b"."""
    return name.replace("/", "%")


def qos_text(reliability: int = RELIABLE, depth: int = 10) -> str:
    """``qos_to_keyexpr`` for a VOLATILE, KEEP_LAST profile with infinite deadline, lifespan and lease:
    ``<reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:<liveliness>,<s>,<ns>``
    with each field equal to the default left empty."""
    reliable = "" if reliability == DEFAULT_RELIABILITY else str(reliability)
    depth_text = "" if depth == DEFAULT_DEPTH else str(depth)
    return f"{reliable}::,{depth_text}:,:,:,,"


def node_token(domain: int, zid: str, node_id: int, namespace: str, node: str, enclave: str = "/") -> str:
    """A node's liveliness key (its id written twice, as ``Entity::Entity`` does for a node)."""
    return "/".join((ADMIN_SPACE, str(domain), zid, str(node_id), str(node_id), NODE, mangle(enclave),
                     mangle(namespace), mangle(node)))


def entity_token(domain: int, zid: str, node_id: int, entity_id: int, kind: str, namespace: str, node: str,
                 topic: str, typename: str, qos: str, enclave: str = "/") -> str:
    """A publisher's (``MP``) or subscription's (``MS``) liveliness key."""
    return "/".join((ADMIN_SPACE, str(domain), zid, str(node_id), str(entity_id), kind, mangle(enclave),
                     mangle(namespace), mangle(node), mangle(topic), mangle(dds_type_name(typename)),
                     mangle(type_hash(typename)), qos))


def gid(liveliness_key: str) -> bytes:
    """The entity's 16-byte GID: XXH3-128 of its liveliness key, low 64 bits first, little-endian."""
    return xxhash.xxh3_128_intdigest(liveliness_key.encode()).to_bytes(GID_SIZE, "little")


def attachment(sequence: int, gid_bytes: bytes, timestamp_ns: int | None = None) -> bytes:
    """The 33-byte attachment of a ``put``: sequence number, source time (ns), GID length, GID."""
    stamp = time.time_ns() if timestamp_ns is None else timestamp_ns
    return zenoh.ext.z_serialize((zenoh.ext.Int64(sequence), zenoh.ext.Int64(stamp), bytes(gid_bytes))).to_bytes()


def parse_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source time in ns, GID) of an attachment, or ``MessageError`` naming the problem."""
    if len(data) != ATTACHMENT_SIZE:
        raise MessageError(Drop.MALFORMED, f"rmw_zenoh attachment: {len(data)} bytes, expected {ATTACHMENT_SIZE} "
                                           "(sequence, timestamp, GID: rmw_zenoh 0.2.4 or later)")
    try:
        sequence, stamp, gid_bytes = zenoh.ext.z_deserialize(tuple[zenoh.ext.Int64, zenoh.ext.Int64, bytes],
                                                             zenoh.ZBytes(data))
    except zenoh.ext.ZDeserializeError as error:
        raise MessageError(Drop.MALFORMED, f"rmw_zenoh attachment: {error}") from None
    if len(gid_bytes) != GID_SIZE:
        raise MessageError(Drop.MALFORMED, f"rmw_zenoh attachment: a GID of {len(gid_bytes)} bytes, expected 16")
    return int(sequence), int(stamp), bytes(gid_bytes)


def parse_entity_token(key: str) -> dict[str, str] | None:
    """The fields of a publisher's or subscription's liveliness key (``entity_token``'s inverse, names
    demangled), or None for any other key (a node's, a malformed one)."""
    parts = key.split("/")
    if len(parts) != 13 or parts[0] != ADMIN_SPACE or parts[5] not in (PUBLISHER, SUBSCRIPTION):
        return None
    names = ("domain", "zid", "node_id", "entity_id", "kind", "enclave", "namespace", "node", "topic", "type", "hash", "qos")
    fields = dict(zip(names, parts[1:]))
    for name in ("enclave", "namespace", "node", "topic", "type", "hash"):
        fields[name] = fields[name].replace("%", "/")
    return fields
