"""`krang bag`: look inside recorded MCAP bags and rescue unfinished ones.

The dispatcher (krang_cli.main) calls register(subparsers); `python -m krang_cli.bag ...` runs the
same commands standalone.
"""

from __future__ import annotations

import argparse
import json
import sys
from datetime import datetime, timezone

from krang_bag.reader import BagError, bag_info
from krang_bag.recover import default_output, recover

_INFO_HELP = """Print what a bag holds: topics, message types, message counts, the QoS the
publishers offered (reliability/durability) and the recorded time span. Only the summary is read,
so this is fast on large bags. A bag whose recorder was killed has no summary: `krang bag recover`
rescues it."""

_RECOVER_HELP = """Rescue a bag that was never finished (recorder killed with SIGKILL, power cut,
full disk). Every message in its completed chunks is copied, with its schema, QoS metadata and
timestamps, into a new finished bag that rosbag2, Foxglove, rosbags and mcap_ros2 can read. The
unfinished last chunk (at most the recorder's chunk_size of data) is lost. The source file is never
modified. Also works on a finished bag, as a validating copy."""


def register(subparsers) -> argparse.ArgumentParser:
    """Add `bag info` and `bag recover` to the krang CLI."""
    parser = subparsers.add_parser(
        'bag',
        help='inspect and recover MCAP bags',
        description='Inspect recorded MCAP bags (`info`) and rescue unfinished ones (`recover`).',
    )
    commands = parser.add_subparsers(dest='bag_command', metavar='{info,recover}', required=True)

    info = commands.add_parser(
        'info', help='topics, types, counts and duration of a bag', description=_INFO_HELP
    )
    info.add_argument('bag', metavar='BAG', help='the .mcap file')
    info.add_argument('--json', action='store_true', help='print the information as one JSON line')
    info.set_defaults(func=run_info)

    rescue = commands.add_parser(
        'recover',
        help='rescue the messages of an unfinished (killed) bag',
        description=_RECOVER_HELP,
    )
    rescue.add_argument('bag', metavar='BAG', help='the unfinished .mcap file')
    rescue.add_argument(
        '--out',
        metavar='FILE',
        default=None,
        help='where to write the rescued bag (default: BAG with .recovered.mcap); '
        'an existing file is not overwritten unless --force',
    )
    rescue.add_argument('--force', action='store_true', help='overwrite --out if it exists')
    rescue.add_argument(
        '--json', action='store_true', help='print the recovery report as one JSON line'
    )
    rescue.set_defaults(func=run_recover)
    return parser


def _qos_word(offers: list) -> str:
    if not offers:
        return '-'
    words = {f'{qos.get("reliability", "?")}/{qos.get("durability", "?")}' for qos in offers}
    return ','.join(sorted(words))


def _stamp(ns: int) -> str:
    return datetime.fromtimestamp(ns / 1e9, tz=timezone.utc).isoformat(timespec='milliseconds')


def run_info(args) -> int:
    try:
        info = bag_info(args.bag)
    except BagError as err:
        print(f'krang bag info: {err}', file=sys.stderr)
        return 1
    if getattr(args, 'json', False):
        print(
            json.dumps(
                {
                    'path': str(info.path),
                    'size_bytes': info.size_bytes,
                    'profile': info.profile,
                    'messages': info.message_count,
                    'duration_s': info.duration_s,
                    'start_ns': info.start_ns,
                    'end_ns': info.end_ns,
                    'chunks': info.chunk_count,
                    'compression': list(info.compression),
                    'topics': {
                        t.topic: {
                            'type': t.type_name,
                            'count': t.message_count,
                            'type_hash': t.type_hash,
                            'offered_qos': t.offered_qos,
                        }
                        for t in info.topics.values()
                    },
                }
            )
        )
        return 0
    print(
        f'Bag:         {info.path}  ({info.size_bytes / 1e6:.2f} MB, profile '
        f'{info.profile or "-"}, written by {info.library or "?"})'
    )
    print(
        f'Messages:    {info.message_count} in {info.chunk_count} chunk(s), '
        f'compression {", ".join(info.compression) or "none"}'
    )
    print(f'Duration:    {info.duration_s:.3f} s')
    if info.message_count:
        print(f'Start / end: {_stamp(info.start_ns)} / {_stamp(info.end_ns)}')
    print(f'Topics:      {len(info.topics)}')
    width_topic = max([len(t) for t in info.topics] + [5])
    width_type = max([len(t.type_name) for t in info.topics.values()] + [4])
    print(f'  {"topic":<{width_topic}}  {"type":<{width_type}}  {"count":>8}  offered QoS')
    for topic in info.topics.values():
        print(
            f'  {topic.topic:<{width_topic}}  {topic.type_name:<{width_type}}  '
            f'{topic.message_count:>8}  {_qos_word(topic.offered_qos)}'
        )
    return 0


def run_recover(args) -> int:
    out = args.out if args.out is not None else default_output(args.bag)
    try:
        report = recover(args.bag, out, overwrite=getattr(args, 'force', False))
    except FileExistsError:
        print(
            f'krang bag recover: {out} exists; choose another --out or pass --force',
            file=sys.stderr,
        )
        return 1
    except (BagError, ValueError) as err:
        print(f'krang bag recover: {err}', file=sys.stderr)
        return 1
    if getattr(args, 'json', False):
        print(
            json.dumps(
                {
                    'source': str(report.source),
                    'output': str(report.output),
                    'messages': report.messages,
                    'chunks': report.chunks,
                    'bad_chunks': report.bad_chunks,
                    'truncated': report.truncated,
                    'data_complete': report.data_complete,
                    'topics': report.topics,
                }
            )
        )
    else:
        print(report.summary())
        for topic, count in sorted(report.topics.items()):
            print(f'  {topic}: {count}')
    return 0


def main(argv=None) -> int:
    """Standalone entry: `python -m krang_cli.bag info BAG`."""
    parser = argparse.ArgumentParser(prog='krang')
    register(parser.add_subparsers(dest='command', required=True))
    args = parser.parse_args(['bag', *(sys.argv[1:] if argv is None else argv)])
    return args.func(args)


if __name__ == '__main__':
    sys.exit(main())
