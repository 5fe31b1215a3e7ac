"""mcap_recorder: record every topic discovered at run time into one MCAP bag
(our `ros2 bag record -a`).

Parameters: see `mcap_recorder --help` (krang_bag/recording.py RecorderConfig).

A topic is subscribed once it has a publisher, so the offers are known; the QoS request and the
topic selection are the plain functions of krang_bag/recording.py.

SIGINT and SIGTERM only set a flag: the writer is never interrupted half-way through a message. The
loop then drains the messages already received and finishes the bag (summary and statistics).
"""

from __future__ import annotations

import importlib
import signal
import sys
import threading
import time
from datetime import datetime

import rclpy
from rclpy.node import Node
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    LivelinessPolicy,
    QoSProfile,
    ReliabilityPolicy,
)
from rclpy.signals import SignalHandlerOptions

from krang_bag import schemas
from krang_bag.recording import (
    RecorderConfig,
    RequestQos,
    choose_request_qos,
    plan_new_topics,
    resolve_output_path,
)
from krang_bag.writer import BagWriter, OfferedQos
from krang_core import params
from krang_ros.executor import StaticSingleThreadedExecutor
from krang_ros.params import declare

NODE_NAME = 'mcap_recorder'


def describe_parameters():
    return params.describe(RecorderConfig)


# ---------------------------------------------------------------- rclpy conversions


def offered_qos_from_profile(profile) -> OfferedQos:
    """OfferedQos from an rclpy QoSProfile as returned in publisher endpoint info."""

    def name(policy_enum, value) -> str:
        try:
            return policy_enum(int(value)).name.lower()
        except ValueError:
            return 'unknown'

    return OfferedQos(
        history=name(HistoryPolicy, profile.history),
        depth=int(profile.depth),
        reliability=name(ReliabilityPolicy, profile.reliability),
        durability=name(DurabilityPolicy, profile.durability),
        deadline_ns=profile.deadline.nanoseconds,
        lifespan_ns=profile.lifespan.nanoseconds,
        liveliness=name(LivelinessPolicy, profile.liveliness),
        liveliness_lease_duration_ns=profile.liveliness_lease_duration.nanoseconds,
        avoid_ros_namespace_conventions=bool(profile.avoid_ros_namespace_conventions),
    )


def to_rclpy_qos(request: RequestQos) -> QoSProfile:
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=request.depth,
        reliability=ReliabilityPolicy.RELIABLE
        if request.reliable
        else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL
        if request.transient_local
        else DurabilityPolicy.VOLATILE,
    )


def message_class(type_name: str):
    package, interface, name = schemas.split_type_name(type_name)
    return getattr(importlib.import_module(f'{package}.{interface}'), name)


# ---------------------------------------------------------------- thin ROS shell


class McapRecorder(Node):
    """Subscribes (raw CDR) to each selected topic as it appears and appends it to the bag."""

    def __init__(self, **kwargs):
        super().__init__(NODE_NAME, **kwargs)

        cfg = declare(self, RecorderConfig)
        self.include, self.exclude = list(cfg.topics), list(cfg.exclude)
        self.include_hidden, self.queue_depth = cfg.include_hidden, cfg.queue_depth
        chunk_size, compression, poll_period_s = cfg.chunk_size, cfg.compression, cfg.poll_period_s
        self.bag = BagWriter(
            resolve_output_path(cfg.output, datetime.now()),
            chunk_size=chunk_size,
            compression=compression,
        )
        self._subscriptions_by_topic = {}
        self._reported_skips: dict[str, str] = {}
        self.get_logger().info(
            f'recording to {self.bag.path.resolve()} (topics: {self.include or "all"}, exclude: '
            f'{self.exclude or "none"}, chunk {chunk_size} B, {compression})'
        )
        try:
            self.poll_topics()
            self.create_timer(poll_period_s, self._on_poll_timer)
        except BaseException:
            self.bag.close()  # main() never sees this node: leave a finished (empty) bag behind
            raise

    @property
    def messages_written(self) -> int:
        return sum(self.bag.message_counts.values())

    def _on_poll_timer(self):
        self.poll_topics()
        self.bag.flush()

    def poll_topics(self):
        to_add, skipped = plan_new_topics(
            self.get_topic_names_and_types(),
            self._subscriptions_by_topic,
            self.include,
            self.exclude,
            self.include_hidden,
        )
        for topic, reason in skipped.items():
            self._skip_once(topic, reason)
        for topic, type_name in to_add:
            publishers = self.get_publishers_info_by_topic(topic)
            if publishers:  # else wait for one, so that its QoS offer is known
                self._subscribe(topic, type_name, publishers)

    def _skip_once(self, topic, reason):
        if self._reported_skips.get(topic) != reason:
            self._reported_skips[topic] = reason
            self.get_logger().warning(f'not recording {topic}: {reason}')

    def _subscribe(self, topic, type_name, publishers):
        try:
            cls = message_class(type_name)
            definition = schemas.message_definition(type_name)
            installed_hash = schemas.type_hash(type_name)
        except (ImportError, AttributeError, LookupError, ValueError, OSError) as err:
            self._skip_once(topic, f'type {type_name} is not installed here ({err})')
            return
        offers = [offered_qos_from_profile(info.qos_profile) for info in publishers]
        offered_hashes = {
            str(info.topic_type_hash) for info in publishers if info.topic_type_hash.version == 1
        }
        if offered_hashes - {installed_hash}:
            self.get_logger().warning(
                f'{topic}: publishers use {type_name} with hash(es) {sorted(offered_hashes)}, but '
                f'the installed definition has {installed_hash}; recording it with the installed '
                'schema'
            )
        type_hash = offered_hashes.pop() if len(offered_hashes) == 1 else installed_hash
        request = choose_request_qos(offers, self.queue_depth)
        self.bag.add_topic(
            topic, type_name, offered_qos=offers, type_hash=type_hash, definition=definition
        )
        self._subscriptions_by_topic[topic] = self.create_subscription(
            cls, topic, self._writer_for(topic), to_rclpy_qos(request), raw=True
        )
        self.get_logger().info(
            f'recording {topic} [{type_name}] from {len(publishers)} publisher(s), '
            f'{"reliable" if request.reliable else "best_effort"}, '
            f'{"transient_local" if request.transient_local else "volatile"}, depth '
            f'{request.depth}'
        )

    def _writer_for(self, topic):
        write, clock = self.bag.write, self.get_clock()

        def on_message(data: bytes, info: dict):
            write(
                topic,
                data,
                clock.now().nanoseconds,
                info.get('source_timestamp') or None,
                info.get('publication_sequence_number'),
            )

        return on_message

    def close(self):
        """Finish the bag and report what it holds. Safe to call twice."""
        if self.bag.closed:
            return
        counts = self.bag.message_counts
        self.bag.close()
        lines = ''.join(f'\n  {topic}: {count}' for topic, count in sorted(counts.items()))
        self.get_logger().info(
            f'finished {self.bag.path} with {sum(counts.values())} messages on '
            f'{len(counts)} topics:{lines}'
        )


def _install_stop_handlers() -> threading.Event:
    """SIGINT/SIGTERM set an event instead of raising inside a write; a third one exits at once."""
    stop = threading.Event()
    received = []

    def on_signal(signum, _frame):
        received.append(signum)
        if len(received) >= 3:
            raise SystemExit(128 + signum)
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    return stop


def _drain(executor, node, max_seconds: float = 1.0) -> None:
    """Take the messages that already arrived before the stop, until the queues stay idle."""
    deadline, idle = time.monotonic() + max_seconds, 0
    while idle < 3 and time.monotonic() < deadline:
        before = node.messages_written
        executor.spin_once(timeout_sec=0.02)
        idle = idle + 1 if node.messages_written == before else 0


def main(args=None) -> int:
    stop = _install_stop_handlers()
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    node = None
    executor = StaticSingleThreadedExecutor()
    try:
        try:
            node = McapRecorder()
        except FileExistsError as err:
            print(
                f'mcap_recorder: refusing to overwrite an existing bag: {err.filename}',
                file=sys.stderr,
            )
            return 1
        except params.ParameterError as err:
            print(f'error: {err}', file=sys.stderr)
            return 2
        executor.add_node(node)
        while not stop.is_set() and rclpy.ok():
            executor.spin_once(timeout_sec=0.1)
        _drain(executor, node)
        return 0
    finally:
        executor.shutdown()  # releases the handles it kept, before their node is destroyed
        if node is not None:
            node.close()
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    sys.exit(main())
