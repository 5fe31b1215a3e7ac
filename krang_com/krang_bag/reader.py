"""Read MCAP bags back into typed messages, plus the array helpers the analysis tools use.

Messages are decoded from the schema embedded in the bag by mcap_ros2, so no ROS package is
needed and old or foreign bags read the same as ours. They have the fields of the ROS message
types (arrays as lists, a `byte` as its number).

Times are MCAP log times: when the recorder received the message, in ns of the recorder's clock
(sim time if it ran with use_sim_time). The helpers return them in seconds.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Iterator, NamedTuple

import numpy as np
import yaml
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from krang_core.names import JOINT_STATES

RECOVER_HINT = 'it was probably never finished (recorder killed?); try `krang bag recover {path}`'


class BagError(ValueError):
    """A bag cannot be read as asked (broken file, missing topic, wrong type): bad input, so the
    command line reports it in one line like any other bad input file."""


class BagNotFoundError(BagError, FileNotFoundError):
    """The bag file does not exist."""


class BagCorruptError(BagError):
    """The file is not a finished, valid MCAP bag."""


@dataclass(frozen=True)
class TopicInfo:
    topic: str
    type_name: str
    message_count: int
    offered_qos: list = field(default_factory=list)  # dicts as in offered_qos_profiles
    type_hash: str = ''


@dataclass(frozen=True)
class BagInfo:
    path: Path
    size_bytes: int
    profile: str
    library: str
    message_count: int
    start_ns: int
    end_ns: int
    chunk_count: int
    compression: tuple[str, ...]
    topics: dict[str, TopicInfo]

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) / 1e9 if self.message_count else 0.0


class JointStateSeries(NamedTuple):
    """JointState samples: t (N,) [s]; names (J,); positions, velocities (N, J), NaN where
    absent."""

    t: np.ndarray
    names: list[str]
    positions: np.ndarray
    velocities: np.ndarray


class FloatArraySeries(NamedTuple):
    """Float64MultiArray samples: t (N,) [s]; rows (N, K), NaN-padded if lengths differ."""

    t: np.ndarray
    rows: np.ndarray


@contextlib.contextmanager
def _open_bag(path):
    """A seeking mcap reader on a bag whose footer and summary are valid, or a clear BagError."""
    path = Path(path)
    if not path.exists():
        raise BagNotFoundError(f'bag not found: {path}')
    if path.is_dir():
        raise BagError(f'{path} is a directory; give the .mcap file inside it')
    with open(path, 'rb') as stream:
        try:
            reader = make_reader(stream)
            header = reader.get_header()
        except (McapError, ValueError, EOFError) as err:
            raise BagCorruptError(
                f'{path} is not an MCAP file ({type(err).__name__}: {err})'
            ) from None
        try:
            summary = reader.get_summary()
        except Exception as err:  # mcap raises struct/EOF/magic errors on a torn tail
            raise BagCorruptError(
                f'{path} has no valid footer/summary: '
                + RECOVER_HINT.format(path=path)
                + f' ({type(err).__name__}: '
                f'{err})'
            ) from None
        yield reader, header, summary


def _channel_type_hash(channel) -> str:
    return channel.metadata.get('topic_type_hash', '')


class _Decoders:
    """One decode function per channel, from its schema (mcap_ros2)."""

    def __init__(self):
        self._by_channel: dict[int, Callable[[bytes], object]] = {}
        self._factory = DecoderFactory()

    def decode(self, schema, channel, data: bytes):
        decode = self._by_channel.get(channel.id)
        if decode is None:
            decode = self._by_channel[channel.id] = self._make(schema, channel)
        return decode(data)

    def _make(self, schema, channel) -> Callable[[bytes], object]:
        if schema is None or channel.message_encoding != 'cdr':
            raise BagError(
                f'{channel.topic}: cannot decode {channel.message_encoding!r} messages '
                'without a schema'
            )
        decode = self._factory.decoder_for('cdr', schema)
        if decode is None:
            raise BagError(f'{channel.topic}: no decoder for schema encoding {schema.encoding!r}')
        return decode


def _iter_records(path, topics: Iterable[str] | str | None):
    if isinstance(topics, str):
        topics = [topics]
    topics = None if topics is None else list(topics)
    with _open_bag(path) as (reader, _, _summary):
        try:
            yield from reader.iter_messages(topics=topics, log_time_order=True)
        except BagError:
            raise
        except Exception as err:
            raise BagCorruptError(f'{path}: damaged data ({type(err).__name__}: {err})') from None


def iter_messages(
    path, topics: Iterable[str] | str | None = None
) -> Iterator[tuple[str, int, object]]:
    """(topic, log_time_ns, message) for every message, in log-time order; `topics` filters."""
    decoders = _Decoders()
    for schema, channel, message in _iter_records(path, topics):
        try:
            msg = decoders.decode(schema, channel, message.data)
        except BagError:
            raise
        except Exception as err:
            raise BagCorruptError(
                f'{path}: cannot decode a {schema.name if schema else "?"} '
                f'message on {channel.topic} at {message.log_time} ns '
                f'({type(err).__name__}: {err})'
            ) from None
        yield channel.topic, message.log_time, msg


def bag_info(path) -> BagInfo:
    """Topics, types, counts, QoS and time range, from the summary (scans the file if it has
    none)."""
    path = Path(path)
    with _open_bag(path) as (reader, header, summary):
        if summary is not None and summary.statistics is not None:
            stats = summary.statistics
            channels, schemas_by_id = summary.channels, summary.schemas
            counts_by_channel = dict(stats.channel_message_counts)
            total, start, end = (
                stats.message_count,
                stats.message_start_time,
                stats.message_end_time,
            )
            chunk_count = stats.chunk_count
            compression = {index.compression or 'none' for index in summary.chunk_indexes}
        else:  # valid but summary-less file (other writers): count by reading it through
            channels, schemas_by_id, counts_by_channel, times = {}, {}, {}, []
            for schema, channel, message in _iter_records(path, None):
                channels[channel.id] = channel
                if schema is not None:
                    schemas_by_id[schema.id] = schema
                counts_by_channel[channel.id] = counts_by_channel.get(channel.id, 0) + 1
                times.append(message.log_time)
            total, start, end = len(times), min(times, default=0), max(times, default=0)
            chunk_count, compression = 0, set()
        topics: dict[str, TopicInfo] = {}
        for channel_id, channel in sorted(channels.items()):
            schema = schemas_by_id.get(channel.schema_id)
            count = counts_by_channel.get(channel_id, 0)
            previous = topics.get(channel.topic)
            if previous is not None:  # several channels on one topic (e.g. merged bags): sum them
                count += previous.message_count
            try:
                qos = (
                    yaml.safe_load(channel.metadata.get('offered_qos_profiles', '') or '[]') or []
                )
            except yaml.YAMLError:
                qos = []
            topics[channel.topic] = TopicInfo(
                channel.topic,
                schema.name if schema else '',
                count,
                qos,
                _channel_type_hash(channel),
            )
        return BagInfo(
            path=path,
            size_bytes=path.stat().st_size,
            profile=header.profile,
            library=header.library,
            message_count=total,
            start_ns=start,
            end_ns=end,
            chunk_count=chunk_count,
            compression=tuple(sorted(compression)),
            topics=dict(sorted(topics.items())),
        )


def message_counts(path) -> dict[str, int]:
    """topic -> number of messages, from the summary statistics."""
    return {topic: info.message_count for topic, info in bag_info(path).topics.items()}


def _require_topic(path, topic: str, type_names: tuple[str, ...]) -> None:
    topics = bag_info(path).topics
    if topic not in topics:
        raise BagError(
            f'topic {topic} is not in {path}; it has: {", ".join(topics) or "no topics"}'
        )
    if topics[topic].type_name not in type_names:
        raise BagError(
            f'{topic} in {path} is {topics[topic].type_name}, expected {" or ".join(type_names)}'
        )


def read_joint_states(path, topic: str = JOINT_STATES) -> JointStateSeries:
    """All JointState messages of a topic as arrays, joints in first-seen order."""
    _require_topic(path, topic, ('sensor_msgs/msg/JointState',))
    times, samples, column = [], [], {}
    for _, log_time, msg in iter_messages(path, [topic]):
        names = list(msg.name)
        for name in names:
            column.setdefault(name, len(column))
        times.append(log_time)
        samples.append((names, np.asarray(msg.position, float), np.asarray(msg.velocity, float)))
    positions = np.full((len(samples), len(column)), np.nan)
    velocities = np.full((len(samples), len(column)), np.nan)
    for row, (names, position, velocity) in enumerate(samples):
        index = [column[name] for name in names]
        positions[row, index[: len(position)]] = position[: len(index)]
        velocities[row, index[: len(velocity)]] = velocity[: len(index)]
    return JointStateSeries(np.asarray(times, float) / 1e9, list(column), positions, velocities)


def read_float_arrays(path, topic: str) -> FloatArraySeries:
    """All Float64MultiArray messages of a topic, one row each (e.g. /sim_krang/ground_truth); of
    a JointState topic the efforts in message order (/wheel_effort_cmd: [JLWheel, JRWheel] N m)."""
    _require_topic(path, topic, ('std_msgs/msg/Float64MultiArray', 'sensor_msgs/msg/JointState'))
    times, data = [], []
    for _, log_time, msg in iter_messages(path, [topic]):
        times.append(log_time)
        data.append(np.asarray(msg.effort if hasattr(msg, 'effort') else msg.data, float))
    rows = np.full((len(data), max((len(d) for d in data), default=0)), np.nan)
    for row, values in enumerate(data):
        rows[row, : len(values)] = values
    return FloatArraySeries(np.asarray(times, float) / 1e9, rows)
