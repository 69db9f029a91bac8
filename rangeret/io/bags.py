"""Bags read and written with `rosbags` (the `bags` extra): rosbag2 folders (sqlite3 or MCAP
storage) and ROS 1 `.bag` files, no ROS install needed.

`open_bag` reads a bag of either kind (`bag_format` tells which); `SourceBag.copy_to` writes a
new bag with the same connections (topic, type, definition, rosbag2 offered QoS profiles or ROS 1
caller id and latching) and takes each message's raw bytes with its timestamp. A bag of the
source's own kind gets the bytes as they are; a conversion between ROS 1 and rosbag2 re-encodes
each message between the two wire formats (the ROS 1 header's `seq` dropped, or written as 0).
`atomic_bag` gives the new bag a temporary sibling that takes the target's name only once it is
complete.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import secrets
import shutil
import struct
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.interfaces import (
    Connection,
    ConnectionExtRosbag1,
    ConnectionExtRosbag2,
    MessageDefinitionFormat,
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.rosbag1 import WriterError as Ros1WriterError
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin
from rosbags.rosbag2 import Writer as Ros2Writer
from rosbags.rosbag2 import WriterError as Ros2WriterError
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, TypesysError, get_typestore

from rangeret.exceptions import InputError
from rangeret.io.bounded_yaml import YamlLimitError, load_yaml
from rangeret.io.pointcloud2 import CloudField, CloudMessageError

#: The bag kinds read and written: a rosbag2 folder in each storage, and a ROS 1 file.
BAG_FORMATS = ("rosbag2-sqlite3", "rosbag2-mcap", "ros1")
POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
ROS1_MAGIC = b"#ROSBAG V2.0\n"
#: The rosbag2 metadata version written (the newest `rosbags` writes).
ROSBAG2_VERSION = 9
#: The offered QoS profile a latched ROS 1 topic gets in a rosbag2 bag (what `ros2 bag` records
#: for a transient-local publisher).
_LATCHED = Qos(
    QosHistory.UNKNOWN,
    0,
    QosReliability.RELIABLE,
    QosDurability.TRANSIENT_LOCAL,
    QosTime(2147483647, 4294967295),
    QosTime(2147483647, 4294967295),
    QosLiveliness.AUTOMATIC,
    QosTime(2147483647, 4294967295),
    avoid_ros_namespace_conventions=False,
)
_HEADER = "std_msgs/msg/Header"
_STORAGES = {"rosbag2-sqlite3": StoragePlugin.SQLITE3, "rosbag2-mcap": StoragePlugin.MCAP}
_READ_ERRORS = (AnyReaderError, SerdeError, TypesysError, KeyError, ValueError, OSError)


class BagError(InputError, ValueError):
    """A bag that cannot be read or written, a missing or wrong topic, or a bad target path."""


def bag_format(path: Path) -> str:
    """The kind of bag at `path` (one of `BAG_FORMATS`): a folder with a `metadata.yaml` is a
    rosbag2 bag of its storage, a `.bag` file starting with the ROS 1 header a ROS 1 bag."""
    if path.is_dir():
        meta = path / "metadata.yaml"
        if not meta.is_file():
            raise BagError(f"{path}: a folder without metadata.yaml is not a rosbag2 bag")
        try:
            info = load_yaml(meta)
            storage = info["rosbag2_bagfile_information"]["storage_identifier"]  # type: ignore[index]
        except (YamlLimitError, KeyError, TypeError) as exc:
            raise BagError(f"{meta}: not rosbag2 metadata ({exc})") from exc
        fmt = f"rosbag2-{storage}"
        if fmt not in _STORAGES:
            raise BagError(f"{path}: rosbag2 storage {storage!r} is not sqlite3 or mcap")
        return fmt
    if not path.exists():
        raise BagError(f"{path}: no such bag")
    with open(path, "rb") as f:
        magic = f.read(len(ROS1_MAGIC))
    if magic != ROS1_MAGIC:
        raise BagError(
            f"{path}: neither a rosbag2 folder (with metadata.yaml) nor a ROS 1 bag (a file "
            "starting with #ROSBAG V2.0)"
        )
    if path.suffix != ".bag":
        raise BagError(f"{path}: a ROS 1 bag's name must end in .bag")
    return "ros1"


def check_target(target: Path, fmt: str, *, overwrite: bool, source: Path | None = None) -> None:
    """BagError unless a bag of kind `fmt` may be written at `target`: a ROS 1 bag's name ends
    in .bag and a rosbag2 folder's does not, an existing target needs `overwrite`, and whatever
    `overwrite` says, the target neither is, holds nor lies inside the source, and an existing
    folder is replaced only when this command wrote it (its run record beside it)."""
    if fmt not in BAG_FORMATS:
        raise BagError(f"unknown bag format {fmt!r}; the formats: {', '.join(BAG_FORMATS)}")
    if (fmt == "ros1") != (target.suffix == ".bag"):
        need = "end in .bag" if fmt == "ros1" else "not end in .bag (that names a ROS 1 bag)"
        raise BagError(f"{target}: the name of a {fmt} bag must {need}")
    if source is not None and target.resolve() == source.resolve():
        raise BagError(f"{target}: the labelled bag cannot replace the bag it is read from")
    if source is not None and source.resolve().is_relative_to(target.resolve()):
        raise BagError(
            f"{target}: the labelled bag cannot replace a folder that holds the bag it is read "
            f"from ({source}); choose another --out"
        )
    if source is not None and target.resolve().is_relative_to(source.resolve()):
        raise BagError(f"{target}: the labelled bag cannot be written inside the bag it reads")
    if not (target.exists() or target.is_symlink()):
        return
    if not overwrite:
        raise BagError(f"{target} exists; pass --overwrite to replace it")
    if target.is_dir() and not run_record_path(target).is_file():
        raise BagError(
            f"{target} is a folder this command did not write (no {run_record_path(target).name} "
            "beside it), so --overwrite does not replace it; choose another --out"
        )


def run_record_path(target: Path) -> Path:
    """Where the run record of the bag at `target` lies: `TARGET.run.json`, beside it."""
    return target.with_name(target.name + ".run.json")


@contextlib.contextmanager
def atomic_bag(target: Path, fmt: str, *, overwrite: bool) -> Iterator[Path]:
    """Yield a path (not yet there) to write a bag of kind `fmt` at, inside a hidden temporary
    folder beside `target`; on a clean exit the bag takes `target`'s name (an old one removed
    with `overwrite`), else it is removed and `target` is left as it was."""
    check_target(target, fmt, overwrite=overwrite)
    target.parent.mkdir(parents=True, exist_ok=True)
    staging = target.parent / f".{target.name}.{secrets.token_hex(4)}.tmp"
    staging.mkdir()
    try:
        written = staging / target.name
        yield written
        if target.exists() or target.is_symlink():
            old = staging / f".{target.name}.old"
            os.rename(target, old)
        os.rename(written, target)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


@dataclass(frozen=True)
class BagTopic:
    """One topic of a bag: its message type and how many messages it holds."""

    name: str
    msgtype: str
    count: int


class SourceBag:
    """An open bag: its topics, its messages in timestamp order, and its messages decoded."""

    def __init__(self, path: Path, fmt: str, reader: AnyReader) -> None:
        self.path = path
        self.format = fmt
        self.reader = reader

    @property
    def is_ros2(self) -> bool:
        """Whether the bag is a rosbag2 one (CDR messages) rather than a ROS 1 one."""
        return self.format != "ros1"

    def topics(self) -> dict[str, BagTopic]:
        """Every topic of the bag, by name."""
        return {
            name: BagTopic(name, info.msgtype or "(several types)", info.msgcount)
            for name, info in self.reader.topics.items()
        }

    def cloud_topic(self, topic: str) -> BagTopic:
        """The topic `topic`, checked to hold PointCloud2 messages; else a BagError naming the
        bag and the topics it has."""
        topics = self.topics()
        listing = ", ".join(f"{t.name} ({t.msgtype})" for t in topics.values()) or "none"
        if topic not in topics:
            raise BagError(f"{self.path}: has no topic {topic!r}; its topics: {listing}")
        found = topics[topic]
        if found.msgtype != POINTCLOUD2:
            raise BagError(
                f"{self.path}: topic {topic} holds {found.msgtype}, not {POINTCLOUD2}; "
                f"its topics: {listing}"
            )
        return found

    def messages(self) -> Iterator[tuple[Connection, int, bytes]]:
        """Every message as (connection, timestamp in ns, raw bytes), in the bag's order."""
        try:
            yield from self.reader.messages()
        except _READ_ERRORS as exc:
            raise BagError(f"{self.path}: cannot be read ({exc})") from exc

    def decode(self, raw: bytes, msgtype: str, source: str) -> Any:
        """A message's bytes as a message object; unreadable bytes are a CloudMessageError
        (kind `deserialize`) naming `source`."""
        store = self.reader.typestore
        try:
            if self.is_ros2:
                return store.deserialize_cdr(raw, msgtype)
            return store.deserialize_ros1(raw, msgtype)
        except (SerdeError, struct.error, ValueError, IndexError, KeyError) as exc:
            raise CloudMessageError(
                source, "deserialize", f"cannot be read as {msgtype} ({exc})"
            ) from exc

    def encode_cloud(
        self, msg: Any, fields: Sequence[CloudField], point_step: int, data: bytes
    ) -> bytes:
        """The bytes of PointCloud2 `msg` with new fields, point step and dense data (its header,
        size and every other member kept), in the bag's own wire format."""
        field_type = self.reader.typestore.types["sensor_msgs/msg/PointField"]
        cloud = dataclasses.replace(
            msg,
            fields=[
                field_type(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count)
                for f in fields
            ],
            point_step=point_step,
            row_step=point_step * int(msg.width),
            data=np.frombuffer(data, dtype=np.uint8),
        )
        store = self.reader.typestore
        if self.is_ros2:
            return bytes(store.serialize_cdr(cloud, POINTCLOUD2, little_endian=True))
        return bytes(store.serialize_ros1(cloud, POINTCLOUD2))

    @contextlib.contextmanager
    def copy_to(self, path: Path, fmt: str) -> Iterator[TargetBag]:
        """A new bag of kind `fmt` at `path` with every connection of this one; closed (made
        complete) on a clean exit, abandoned on an error."""
        writer: Ros1Writer | Ros2Writer
        try:
            if fmt == "ros1":
                writer = Ros1Writer(path)
            else:
                writer = Ros2Writer(path, version=ROSBAG2_VERSION, storage_plugin=_STORAGES[fmt])
                if self.is_ros2:
                    _copy_rosbag2_settings(self.reader, writer)
            with writer:
                yield TargetBag(self, writer, fmt)
        except (Ros1WriterError, Ros2WriterError) as exc:
            raise BagError(f"{path}: cannot be written ({exc})") from exc


def _copy_rosbag2_settings(reader: AnyReader, writer: Ros2Writer) -> None:
    """A rosbag2 source's compression and custom data, for the rosbag2 bag written from it."""
    (source,) = reader.readers
    mode = (source.compression_mode or "").lower()
    if mode in ("file", "message"):
        writer.set_compression(CompressionMode[mode.upper()], CompressionFormat.ZSTD)
    for key, value in (source.storage.metadata.custom or {}).items():
        writer.set_custom_data(str(key), str(value))


class TargetBag:
    """A bag being written from a source bag: each source connection has its counterpart, and a
    message written gets the target's wire format."""

    def __init__(self, source: SourceBag, writer: Ros1Writer | Ros2Writer, fmt: str) -> None:
        self.source = source
        self.writer = writer
        self.is_ros2 = fmt != "ros1"
        self.store = _target_typestore(source, self.is_ros2)
        self.connections: dict[int, Connection] = {}
        self.converters: dict[str, Callable[[bytes], bytes]] = {}
        made: dict[tuple[str, str, str], Connection] = {}
        for conn in source.reader.connections:
            ext = self._ext(conn)
            key = (conn.topic, conn.msgtype, repr(ext))
            if key not in made:
                made[key] = self._add(conn, ext)
            self.connections[conn.id] = made[key]
            self.converters.setdefault(conn.msgtype, self._converter(conn.msgtype))

    def _ext(self, conn: Connection) -> ConnectionExtRosbag1 | ConnectionExtRosbag2:
        """The connection's ROS-1 or rosbag2 settings, mapped to the target's kind."""
        ext = conn.ext
        if self.is_ros2:
            if isinstance(ext, ConnectionExtRosbag2):
                return ext
            return ConnectionExtRosbag2("cdr", [_LATCHED] if ext.latching else [])
        if isinstance(ext, ConnectionExtRosbag1):
            return ext
        latched = any(
            q.durability == QosDurability.TRANSIENT_LOCAL for q in ext.offered_qos_profiles
        )
        return ConnectionExtRosbag1(None, int(latched))

    def _add(
        self, conn: Connection, ext: ConnectionExtRosbag1 | ConnectionExtRosbag2
    ) -> Connection:
        """The target's connection for a source connection: its own definition and hash when the
        kinds match, else those the target's kind gives the type."""
        same = self.is_ros2 == self.source.is_ros2 and conn.msgdef.format != (
            MessageDefinitionFormat.NONE
        )
        msgdef = conn.msgdef.data if same and conn.digest else None
        digest = conn.digest if msgdef is not None else None
        if isinstance(ext, ConnectionExtRosbag2):
            assert isinstance(self.writer, Ros2Writer)
            return self.writer.add_connection(
                conn.topic,
                conn.msgtype,
                typestore=self.store,
                msgdef=msgdef,
                rihs01=digest,
                serialization_format=ext.serialization_format,
                offered_qos_profiles=ext.offered_qos_profiles,
            )
        assert isinstance(self.writer, Ros1Writer)
        return self.writer.add_connection(
            conn.topic,
            conn.msgtype,
            typestore=self.store,
            msgdef=msgdef,
            md5sum=digest,
            callerid=ext.callerid,
            latching=ext.latching,
        )

    def _converter(self, msgtype: str) -> Callable[[bytes], bytes]:
        """Source bytes of `msgtype` to target bytes: themselves within a kind, else re-encoded."""
        if self.is_ros2 == self.source.is_ros2:
            return lambda raw: raw
        if self.is_ros2:
            return lambda raw: bytes(self.store.ros1_to_cdr(raw, msgtype))
        store = self.source.reader.typestore
        return lambda raw: bytes(store.cdr_to_ros1(raw, msgtype))

    def write(self, conn: Connection, timestamp: int, raw: bytes) -> None:
        """Write a message of source connection `conn` (its bytes in the source's format)."""
        try:
            data = self.converters[conn.msgtype](raw)
        except (SerdeError, ValueError, IndexError, KeyError) as exc:
            raise BagError(
                f"{self.source.path}: a {conn.topic} message at t={timestamp} cannot be "
                f"converted ({exc})"
            ) from exc
        self.writer.write(self.connections[conn.id], timestamp, data)


def _target_typestore(source: SourceBag, to_ros2: bool) -> Any:
    """The types of the source bag as the target's kind defines them: the source's own, or the
    same with the other kind's `std_msgs/Header` (ROS 1's has a `seq`, ROS 2's none)."""
    store = source.reader.typestore
    if to_ros2 == source.is_ros2:
        return store
    header = get_typestore(Stores.ROS2_HUMBLE if to_ros2 else Stores.ROS1_NOETIC).fielddefs[_HEADER]
    target = get_typestore(Stores.EMPTY)
    target.register({**store.fielddefs, _HEADER: header})
    return target


@contextlib.contextmanager
def open_bag(path: Path) -> Iterator[SourceBag]:
    """The bag at `path` (a rosbag2 folder or a ROS 1 file), open for reading; one that cannot
    be opened is a BagError naming it."""
    fmt = bag_format(path)
    default = get_typestore(Stores.ROS1_NOETIC if fmt == "ros1" else Stores.ROS2_HUMBLE)
    reader = AnyReader([path], default_typestore=default)
    try:
        reader.open()
    except _READ_ERRORS as exc:
        raise BagError(f"{path}: cannot be opened as a {fmt} bag ({exc})") from exc
    try:
        yield SourceBag(path, fmt, reader)
    finally:
        reader.close()
