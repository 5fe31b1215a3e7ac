"""The recorder's decisions, plain functions without ROS (krang_bag/node.py is the shell):
which topics to record, with which QoS request, into which file.

The subscription QoS follows rosbag2's rule: reliable only if every publisher offers reliable,
transient_local only if every publisher does; otherwise the subscription would not match some of
them.
"""

from __future__ import annotations

import fnmatch
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from collections.abc import Iterable, Sequence

from krang_bag import schemas
from krang_bag.writer import DEFAULT_CHUNK_SIZE, OfferedQos

COMPRESSIONS = ('zstd', 'lz4', 'none')


def _doc(text):
    return field(metadata={'doc': text})


@dataclass(frozen=True)
class RecorderConfig:
    """The recorder's parameters (ROS parameters of the same names)."""

    output: str = field(
        default='',
        metadata={
            'doc': (
                "bag file, or a directory (trailing '/' or existing) for krang_<timestamp>.mcap; "
                'default '
                './krang_<timestamp>.mcap. An existing file is never overwritten'
            )
        },
    )
    topics: tuple[str, ...] = field(
        default=(), metadata={'doc': 'topic names or shell globs to record (empty = every topic)'}
    )
    exclude: tuple[str, ...] = field(
        default=(), metadata={'doc': 'topic names or globs never recorded'}
    )
    include_hidden: bool = field(
        default=False,
        metadata={'doc': "record hidden topics (a name token starting with '_') too"},
    )
    poll_period_s: float = field(
        default=0.5,
        metadata={
            'doc': 'how often the graph is polled for new topics and the file flushed [s], > 0'
        },
    )
    queue_depth: int = field(
        default=100,
        metadata={
            'doc': "minimum subscription depth (keep_last), raised to the publishers' depth, >= 1"
        },
    )
    chunk_size: int = field(
        default=DEFAULT_CHUNK_SIZE,
        metadata={
            'doc': 'bytes per MCAP chunk: the most a SIGKILL can lose (krang bag recover keeps '
            'the '
            'rest), > 0'
        },
    )
    compression: str = field(default='zstd', metadata={'doc': ' | '.join(COMPRESSIONS)})

    def __post_init__(self):
        if not self.poll_period_s > 0:
            raise ValueError(f'poll_period_s must be > 0, got {self.poll_period_s}')
        if self.queue_depth < 1 or self.chunk_size < 1:
            raise ValueError('queue_depth and chunk_size must be >= 1')
        if self.compression not in COMPRESSIONS:
            raise ValueError(
                f'compression must be one of {COMPRESSIONS}, got {self.compression!r}'
            )


@dataclass(frozen=True)
class RequestQos:
    """What the recorder requests: compatible with every current publisher of a topic."""

    reliable: bool
    transient_local: bool
    depth: int


def choose_request_qos(offers: Sequence[OfferedQos], min_depth: int = 100) -> RequestQos:
    """rosbag2's adapt_request_to_offers: the strongest request that still matches all offers.

    A reliable request does not match a best-effort publisher, and a transient_local request does
    not match a volatile one, so each is requested only when every publisher offers it.
    """
    if not offers:  # rosbag2's default request: reliable, volatile
        return RequestQos(True, False, min_depth)
    reliable = all(qos.reliability == 'reliable' for qos in offers)
    transient_local = all(qos.durability == 'transient_local' for qos in offers)
    depth = max([min_depth, *(qos.depth for qos in offers if qos.history == 'keep_last')])
    return RequestQos(reliable, transient_local, depth)


def is_hidden(topic: str) -> bool:
    return any(token.startswith('_') for token in topic.split('/'))


def topic_selected(
    topic: str,
    include: Iterable[str] = (),
    exclude: Iterable[str] = (),
    include_hidden: bool = False,
) -> bool:
    """Include list empty = everything; entries are exact names or fnmatch globs ('/imu/*')."""
    include, exclude = list(include), list(exclude)
    if not include_hidden and is_hidden(topic) and topic not in include:
        return False
    if include and not any(fnmatch.fnmatchcase(topic, pattern) for pattern in include):
        return False
    return not any(fnmatch.fnmatchcase(topic, pattern) for pattern in exclude)


def plan_new_topics(
    discovered: Iterable[tuple[str, Sequence[str]]],
    recorded: Iterable[str],
    include=(),
    exclude=(),
    include_hidden: bool = False,
):
    """Split the discovered graph into ([(topic, type)] to subscribe now, {topic: why skipped})."""
    recorded = set(recorded)
    to_add, skipped = [], {}
    for topic, types in sorted(discovered):
        if topic in recorded or not topic_selected(topic, include, exclude, include_hidden):
            continue
        if len(types) != 1:
            skipped[topic] = f'{len(types)} types on one topic ({", ".join(types)})'
            continue
        to_add.append((topic, schemas.normalize_type_name(types[0])))
    return to_add, skipped


def default_bag_name(now: datetime) -> str:
    return now.strftime('krang_%Y_%m_%d-%H_%M_%S.mcap')


def resolve_output_path(output: str, now: datetime) -> Path:
    """The bag file for the `output` parameter: empty -> cwd, a directory -> inside it, else as
    given."""
    if not output:
        return Path(default_bag_name(now))
    path = Path(output).expanduser()
    if output.endswith(('/', '\\')) or path.is_dir():
        return path / default_bag_name(now)
    return path
