"""``metadata.yaml``, version 9 (ROS 2 Jazzy): the bag's table of contents.

Written atomically (a temporary file, fsync, rename, fsync of the directory), so a crash at
any moment leaves either the previous or the new one, never half of one. The recorder
rewrites it when a file is opened, when a topic appears, at every split and at the close.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

from components.recording.errors import BagError

#: The file name rosbag2 looks for in a bag directory.
METADATA_FILE = "metadata.yaml"
#: The ``metadata.yaml`` version Jazzy writes.
VERSION = 9
#: The ROS distribution whose bags msctl writes.
ROS_DISTRO = "jazzy"
#: The storage plugin msctl's bags use.
STORAGE = "mcap"


def default_bag_name(now: datetime | None = None) -> str:
    """``rosbag2_YYYY_MM_DD-HH_MM_SS``, rosbag2's default directory name (local time)."""
    return (now or datetime.now()).strftime("rosbag2_%Y_%m_%d-%H_%M_%S")


def file_name(directory: Path, index: int) -> str:
    """The name of a bag's ``index``-th data file: ``<dirname>_<index>.mcap``."""
    return f"{directory.name}_{index}.mcap"


@dataclass
class TopicRecord:
    """One topic of a bag, with the number of its messages.

    Attributes:
        name: Fully qualified topic name.
        type: ``pkg/msg/Name``.
        type_hash: ``RIHS01_...`` (empty when the sender announced none).
        offered_qos_profiles: One profile per publisher (see :mod:`.definitions`).
        message_count: Messages of this topic in the bag.
        serialization_format: Always ``cdr`` for bags msctl writes.
    """

    name: str
    type: str
    type_hash: str = ""
    offered_qos_profiles: list[dict[str, Any]] = field(default_factory=list)
    message_count: int = 0
    serialization_format: str = "cdr"


@dataclass
class FileRecord:
    """One data file of a bag.

    Attributes:
        path: File name relative to the bag directory.
        starting_time: First message's log time, ns since the epoch (0 when empty).
        duration: Last minus first log time, ns.
        message_count: Messages in the file.
    """

    path: str
    starting_time: int = 0
    duration: int = 0
    message_count: int = 0


@dataclass
class BagMetadata:
    """The content of ``metadata.yaml``.

    Attributes:
        topics: Every topic, in the order they were first seen.
        files: Every data file, in order.
        starting_time: First log time of the bag, ns since the epoch (0 when empty).
        duration: Last minus first log time, ns.
        message_count: Messages in the bag.
        compression_format: rosbag2's file/message compression (msctl compresses inside
            MCAP chunks instead, so ``""``).
        compression_mode: As above.
        custom_data: Free key/value text (msctl writes who recorded the bag).
        ros_distro: The distribution named in the bag.
        storage_identifier: The storage plugin (``mcap``).
        version: The metadata version read (msctl writes 9).
    """

    topics: list[TopicRecord] = field(default_factory=list)
    files: list[FileRecord] = field(default_factory=list)
    starting_time: int = 0
    duration: int = 0
    message_count: int = 0
    compression_format: str = ""
    compression_mode: str = ""
    custom_data: dict[str, str] | None = None
    ros_distro: str = ROS_DISTRO
    storage_identifier: str = STORAGE
    version: int = VERSION

    def to_document(self) -> dict[str, Any]:
        """The YAML document, as rosbag2 writes it."""
        return {
            "rosbag2_bagfile_information": {
                "version": VERSION,
                "storage_identifier": self.storage_identifier,
                "duration": {"nanoseconds": self.duration},
                "starting_time": {"nanoseconds_since_epoch": self.starting_time},
                "message_count": self.message_count,
                "topics_with_message_count": [
                    {
                        "topic_metadata": {
                            "name": t.name,
                            "type": t.type,
                            "serialization_format": t.serialization_format,
                            "offered_qos_profiles": t.offered_qos_profiles,
                            "type_description_hash": t.type_hash,
                        },
                        "message_count": t.message_count,
                    }
                    for t in self.topics
                ],
                "compression_format": self.compression_format,
                "compression_mode": self.compression_mode,
                "relative_file_paths": [f.path for f in self.files],
                "files": [
                    {
                        "path": f.path,
                        "starting_time": {"nanoseconds_since_epoch": f.starting_time},
                        "duration": {"nanoseconds": f.duration},
                        "message_count": f.message_count,
                    }
                    for f in self.files
                ],
                "custom_data": self.custom_data,
                "ros_distro": self.ros_distro,
            }
        }

    def to_yaml(self) -> str:
        """The document as YAML text."""
        import yaml

        return yaml.safe_dump(self.to_document(), sort_keys=False, default_flow_style=False)

    @classmethod
    def from_document(cls, document: Any, source: str) -> BagMetadata:
        """Parse a ``metadata.yaml`` document (ours or another tool's, versions 4 to 9).

        Args:
            document: The loaded YAML.
            source: Named in errors (the file's path).

        Raises:
            BagError: Naming the key that is missing or wrong.
        """
        if not isinstance(document, Mapping) or "rosbag2_bagfile_information" not in document:
            raise BagError(f"{source} has no 'rosbag2_bagfile_information' key: not a rosbag2 bag")
        info = document["rosbag2_bagfile_information"]
        where = f"{source}: rosbag2_bagfile_information"
        try:
            topics = []
            for entry in _list(info.get("topics_with_message_count")):
                meta = entry["topic_metadata"]
                profiles = meta.get("offered_qos_profiles") or []
                if isinstance(profiles, str):  # versions before 9: YAML inside a string
                    import yaml

                    profiles = yaml.safe_load(profiles) or []
                topics.append(
                    TopicRecord(
                        name=str(meta["name"]),
                        type=str(meta["type"]),
                        type_hash=str(meta.get("type_description_hash") or ""),
                        offered_qos_profiles=list(profiles),
                        message_count=int(entry.get("message_count", 0)),
                        serialization_format=str(meta.get("serialization_format", "cdr")),
                    )
                )
            paths = [str(p) for p in _list(info.get("relative_file_paths"))]
            described = {
                str(f["path"]): f for f in _list(info.get("files")) if isinstance(f, Mapping)
            }
            files = []
            for path in paths:
                entry = described.get(path, {})
                files.append(
                    FileRecord(
                        path=path,
                        starting_time=int(
                            (entry.get("starting_time") or {}).get("nanoseconds_since_epoch", 0)
                        ),
                        duration=int((entry.get("duration") or {}).get("nanoseconds", 0)),
                        message_count=int(entry.get("message_count", 0)),
                    )
                )
            return cls(
                topics=topics,
                files=files,
                starting_time=int(info["starting_time"]["nanoseconds_since_epoch"]),
                duration=int(info["duration"]["nanoseconds"]),
                message_count=int(info["message_count"]),
                compression_format=str(info.get("compression_format") or ""),
                compression_mode=str(info.get("compression_mode") or ""),
                custom_data=info.get("custom_data"),
                ros_distro=str(info.get("ros_distro") or ""),
                storage_identifier=str(info["storage_identifier"]),
                version=int(info["version"]),
            )
        except KeyError as exc:
            raise BagError(f"{where} lacks the key {exc.args[0]!r}") from None
        except (TypeError, ValueError, AttributeError) as exc:
            raise BagError(f"{where} is malformed: {exc}") from None


def _list(value: Any) -> list[Any]:
    if value is None:
        return []
    if not isinstance(value, list):
        raise TypeError(f"expected a list, found {type(value).__name__}")
    return value


def write_metadata(directory: Path, metadata: BagMetadata) -> Path:
    """Write ``metadata.yaml`` atomically into ``directory``; returns its path.

    Raises:
        OSError: If the disk refuses (the previous file, if any, is left as it was).
    """
    target = directory / METADATA_FILE
    text = metadata.to_yaml().encode()
    handle, temporary = tempfile.mkstemp(prefix=".metadata.", suffix=".tmp", dir=directory)
    try:
        with os.fdopen(handle, "wb") as stream:
            stream.write(text)
            stream.flush()
            os.fsync(stream.fileno())
        os.chmod(temporary, 0o644)
        os.replace(temporary, target)
    except BaseException:
        try:
            os.unlink(temporary)
        except OSError:
            pass
        raise
    _fsync_directory(directory)
    return target


def _fsync_directory(directory: Path) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def read_metadata(directory: Path) -> BagMetadata:
    """Read a bag's ``metadata.yaml``.

    Raises:
        BagError: If the directory is not a bag or the file does not parse; names which.
    """
    import yaml

    if not directory.exists():
        raise BagError(f"no such bag directory: {directory}")
    if not directory.is_dir():
        raise BagError(f"{directory} is not a directory; a bag is a directory with {METADATA_FILE}")
    path = directory / METADATA_FILE
    if not path.is_file():
        raise BagError(
            f"{directory} is not a bag: it has no {METADATA_FILE}",
            hint="give the bag directory (the one holding metadata.yaml and the .mcap files)",
        )
    try:
        document = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise BagError(f"cannot read {path}: {str(exc).splitlines()[0]}") from exc
    return BagMetadata.from_document(document, str(path))
