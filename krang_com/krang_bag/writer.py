"""MCAP bag writer in the form rosbag2 (Jazzy), Foxglove, rosbags and mcap_ros2 all accept.

It writes raw CDR bytes, exactly as they came off the wire (`create_subscription(..., raw=True)`),
so no message is ever decoded and re-encoded on the recording path (numpy-array fields included).
Each topic gets a channel with the metadata rosbag2 writes: `offered_qos_profiles` (YAML, v9 string
form, so replay restores latching and best-effort) and `topic_type_hash` (RIHS01).

Crash behaviour: messages live in an in-memory chunk until it reaches `chunk_size`, then the chunk
is written out. A process killed with SIGKILL loses the open chunk and never writes the summary;
`krang_bag.recover` restores every completed chunk. A clean `close()` loses nothing.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import yaml
from mcap.writer import CompressionType, Writer

from krang_bag import schemas

PROFILE = 'ros2'
MESSAGE_ENCODING = 'cdr'
LIBRARY = 'krang_bag'
DEFAULT_CHUNK_SIZE = 1024 * 1024
# RMW_DURATION_INFINITE: what rclpy reports for an unset deadline/lifespan/lease, as rosbag2 stores
# it.
DURATION_INFINITE_NS = 9223372036854775807
_COMPRESSION = {
    'zstd': CompressionType.ZSTD,
    'lz4': CompressionType.LZ4,
    'none': CompressionType.NONE,
}


@dataclass(frozen=True)
class OfferedQos:
    """One publisher's offered QoS, in rosbag2's words (lower-case policy names, durations in
    ns)."""

    history: str = 'keep_last'
    depth: int = 10
    reliability: str = 'reliable'
    durability: str = 'volatile'
    deadline_ns: int = DURATION_INFINITE_NS
    lifespan_ns: int = DURATION_INFINITE_NS
    liveliness: str = 'automatic'
    liveliness_lease_duration_ns: int = DURATION_INFINITE_NS
    avoid_ros_namespace_conventions: bool = False

    @classmethod
    def sensor_data(cls) -> 'OfferedQos':
        """rclpy's qos_profile_sensor_data: best effort, keep last 5."""
        return cls(depth=5, reliability='best_effort')

    @classmethod
    def latched(cls, depth: int = 1) -> 'OfferedQos':
        """Reliable transient_local: the late-joiner topics (beta, pose target)."""
        return cls(depth=depth, durability='transient_local')


def _duration_yaml(nanoseconds: int) -> dict:
    seconds, nanos = divmod(int(nanoseconds), 1_000_000_000)
    return {'sec': seconds, 'nsec': nanos}


def offered_qos_yaml(offers: list[OfferedQos] | tuple[OfferedQos, ...]) -> str:
    """The `offered_qos_profiles` channel metadata: a YAML list in rosbag2's v9 string form."""
    return yaml.safe_dump(
        [
            {
                'history': qos.history,
                'depth': int(qos.depth),
                'reliability': qos.reliability,
                'durability': qos.durability,
                'deadline': _duration_yaml(qos.deadline_ns),
                'lifespan': _duration_yaml(qos.lifespan_ns),
                'liveliness': qos.liveliness,
                'liveliness_lease_duration': _duration_yaml(qos.liveliness_lease_duration_ns),
                'avoid_ros_namespace_conventions': bool(qos.avoid_ros_namespace_conventions),
            }
            for qos in offers
        ],
        sort_keys=False,
        default_flow_style=False,
    )


def start_mcap_writer(
    stream,
    *,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    compression: str = 'zstd',
    library: str = LIBRARY,
) -> Writer:
    """An mcap Writer already started with the ros2 profile; shared by the recorder and
    recovery."""
    if compression not in _COMPRESSION:
        raise ValueError(f'compression must be one of {sorted(_COMPRESSION)}, not {compression!r}')
    writer = Writer(stream, chunk_size=chunk_size, compression=_COMPRESSION[compression])
    writer.start(profile=PROFILE, library=library)
    return writer


@dataclass
class _Channel:
    channel_id: int
    type_name: str
    message_count: int = 0


class BagWriter:
    """Writes one MCAP bag; topics are added as they are discovered. Not thread-safe.

    Use as a context manager, or call close() from a finally block: close() writes the summary
    (statistics, indexes) without which rosbag2, rosbags and mcap's seeking reader refuse the file.
    """

    def __init__(
        self,
        path,
        *,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        compression: str = 'zstd',
        overwrite: bool = False,
        library: str = LIBRARY,
    ):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # 'xb' by default: an existing recording is never clobbered by a new one.
        self._file = open(self.path, 'wb' if overwrite else 'xb')
        try:
            self._writer = start_mcap_writer(
                self._file, chunk_size=chunk_size, compression=compression, library=library
            )
        except BaseException:
            self._file.close()
            raise
        self._schema_ids: dict[str, int] = {}
        self._definitions: dict[str, str] = {}  # type -> the message definition in its schema
        self._encoders: dict = {}  # type -> CDR encoder (write_message)
        self._channels: dict[str, _Channel] = {}
        self.closed = False

    def __enter__(self) -> 'BagWriter':
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def topics(self) -> dict[str, str]:
        """topic -> 'pkg/msg/Type' of every channel added so far."""
        return {topic: channel.type_name for topic, channel in self._channels.items()}

    @property
    def message_counts(self) -> dict[str, int]:
        """Messages written per topic (for logging; readers must count the file, not this)."""
        return {topic: channel.message_count for topic, channel in self._channels.items()}

    def add_topic(
        self,
        topic: str,
        type_name: str,
        *,
        offered_qos=None,
        type_hash: str | None = None,
        definition: str | None = None,
    ) -> int:
        """Register a topic's channel (and its type's schema once); returns the channel id.

        offered_qos: the publishers' OfferedQos list; None records one default reliable profile.
        type_hash and definition default to the installed interface files of `type_name`.
        """
        self._check_open()
        type_name = schemas.normalize_type_name(type_name)
        if topic in self._channels:
            known = self._channels[topic]
            if known.type_name != type_name:
                raise ValueError(
                    f'{topic} is already recorded as {known.type_name}, not {type_name}'
                )
            return known.channel_id
        if type_name not in self._schema_ids:
            text = definition if definition is not None else schemas.message_definition(type_name)
            self._definitions[type_name] = text
            self._schema_ids[type_name] = self._writer.register_schema(
                name=type_name, encoding=schemas.SCHEMA_ENCODING, data=text.encode('utf-8')
            )
        offers = list(offered_qos) if offered_qos is not None else [OfferedQos()]
        metadata = {
            'offered_qos_profiles': offered_qos_yaml(offers),
            'topic_type_hash': type_hash or schemas.type_hash(type_name),
        }
        channel_id = self._writer.register_channel(
            topic=topic,
            message_encoding=MESSAGE_ENCODING,
            schema_id=self._schema_ids[type_name],
            metadata=metadata,
        )
        self._channels[topic] = _Channel(channel_id, type_name)
        return channel_id

    def write(
        self,
        topic: str,
        data: bytes,
        log_time_ns: int,
        publish_time_ns: int | None = None,
        sequence: int | None = None,
    ) -> None:
        """Append one serialized (CDR) message to an added topic."""
        self._check_open()
        channel = self._channels.get(topic)
        if channel is None:
            raise KeyError(f'topic {topic!r} was not added to the bag (call add_topic first)')
        channel.message_count += 1
        self._writer.add_message(
            channel_id=channel.channel_id,
            log_time=int(log_time_ns),
            data=bytes(data),
            publish_time=int(log_time_ns if publish_time_ns is None else publish_time_ns),
            sequence=(channel.message_count if sequence is None else int(sequence)) & 0xFFFFFFFF,
        )

    def write_message(
        self,
        topic: str,
        msg,
        log_time_ns: int,
        publish_time_ns: int | None = None,
        offered_qos=None,
        type_name: str | None = None,
    ) -> None:
        """Encode a message and write it, adding its topic on first use (offline tools). `msg` is a
        generated message object or a dict of its fields (nested dicts; missing fields take their
        defaults, as in a fresh message); a dict's topic needs `type_name` on first use. Encoded
        from the type's definition by mcap_ros2, so no ROS package is imported."""
        if topic not in self._channels:
            self.add_topic(topic, type_name or schemas.type_name_of(msg), offered_qos=offered_qos)
        encode = self._encoder(self._channels[topic].type_name)
        self.write(topic, encode(_plain(msg)), log_time_ns, publish_time_ns)

    def _encoder(self, type_name: str):
        encode = self._encoders.get(type_name)
        if encode is None:
            # mcap_ros2's schema-driven CDR encoder (the one its own writer uses)
            from mcap_ros2._dynamic import serialize_dynamic

            text = self._definitions[type_name]
            encode = self._encoders[type_name] = serialize_dynamic(type_name, text)[type_name]
        return encode

    def flush(self) -> None:
        """Hand completed chunks to the OS, so a later SIGKILL cannot take them with it."""
        if not self.closed:
            self._file.flush()

    def close(self) -> None:
        """Finish the file: last chunk, summary with statistics, footer. Idempotent."""
        if self.closed:
            return
        self.closed = True
        try:
            self._writer.finish()
            self._file.flush()
            os.fsync(self._file.fileno())
        finally:
            self._file.close()

    def _check_open(self) -> None:
        if self.closed:
            raise ValueError(f'bag {self.path} is already closed')


def _plain(value):
    """A message as the plain values mcap_ros2's encoder takes: nested dicts of its fields, lists
    for its arrays (numpy and array.array included), a `byte` field's bytes as its number."""
    fields = getattr(value, 'get_fields_and_field_types', None)
    if fields is not None:
        return {name: _plain(getattr(value, name)) for name in fields()}
    if isinstance(value, dict):
        return {name: _plain(v) for name, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, bytes) and len(value) == 1:
        return value[0]
    if not isinstance(value, (bytes, str)) and hasattr(value, 'tolist'):
        return value.tolist()
    return value
