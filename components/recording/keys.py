"""What a recorded sample says about itself: its data key's topic, type and hash, and its
attachment's sequence number and source time."""

from __future__ import annotations

from dataclasses import dataclass

from components.data_archiver.core import SequenceTracker


@dataclass(frozen=True)
class TopicKey:
    """What a data key says: topic, type and hash."""

    topic: str
    type: str
    type_hash: str


def parse_key(key: str, domain: int) -> TopicKey | None:
    """Topic, type and hash of an rmw_zenoh data key (``None`` if it is not one)."""
    from components.comm.types import UnknownTypeError, normalize_type_name

    parts = key.split("/")
    if len(parts) < 4 or parts[0] != str(domain) or "::" not in parts[-2]:
        return None
    try:
        type_name = normalize_type_name(parts[-2])
    except UnknownTypeError:
        return None
    return TopicKey("/" + "/".join(parts[1:-2]), type_name, parts[-1])


def read_attachment(
    attachment: bytes, topic_id: int, tracker: SequenceTracker
) -> tuple[int, int, int | None]:
    """Sequence number, source time and samples missed before it, from a sample's attachment
    in either form (the 33-byte one or the older keyed 77-byte one); ``(0, 0, None)`` when
    it is neither."""
    from components.comm.attachment import Attachment, AttachmentError

    try:
        parsed = Attachment.decode(attachment)
    except AttachmentError:
        return 0, 0, None
    missing = tracker.count(topic_id, parsed.gid, parsed.sequence_number)
    return parsed.sequence_number, parsed.source_timestamp, missing
