"""Rescue an MCAP bag that was never finished (recorder killed with SIGKILL, power cut, full disk).

Such a file has no summary or footer, so seeking readers and rosbags refuse it. Its data section is
still a valid stream of records up to the point where writing stopped: every completed chunk holds
schemas, channels and messages that can be read sequentially. We stream through it with
`mcap.stream_reader.StreamReader`, keep every chunk that is complete and passes its CRC, stop at
the torn tail, and write the contents to a new, finished bag (summary, statistics, indexes).
Schemas, channel metadata (QoS, type hash) and message timestamps are copied unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from mcap.records import Channel, Chunk, DataEnd, Footer, Header, Message, Schema
from mcap.stream_reader import StreamReader, breakup_chunk

from krang_bag.reader import BagCorruptError, BagNotFoundError
from krang_bag.writer import LIBRARY, start_mcap_writer


@dataclass
class RecoveryReport:
    source: Path
    output: Path
    messages: int = 0  # messages written to `output`
    chunks: int = 0  # chunks recovered
    bad_chunks: int = 0  # complete chunks skipped (CRC or decompression failure)
    truncated: bool = False  # the file ended before its footer
    data_complete: bool = False  # the data section ended cleanly: nothing was lost
    stop_reason: str = ''  # what ended the scan early, if anything
    topics: dict = field(default_factory=dict)  # topic -> messages recovered

    def summary(self) -> str:
        if not self.truncated:
            tail = 'the file was complete'
        elif self.data_complete:
            tail = f'only the summary was torn ({self.stop_reason}); no message lost'
        else:
            tail = f'tail truncated ({self.stop_reason}); the unfinished last chunk is lost'
        skipped = f', {self.bad_chunks} damaged chunk(s) skipped' if self.bad_chunks else ''
        return (
            f'recovered {self.messages} messages on {len(self.topics)} topics from '
            f'{self.chunks} chunk(s) of {self.source} into {self.output}; {tail}{skipped}'
        )


def default_output(source) -> Path:
    source = Path(source)
    return source.with_name(f'{source.stem}.recovered.mcap')


class _Copier:
    """Re-registers schemas and channels in the new file on first use, then copies messages."""

    def __init__(self, writer, report: RecoveryReport):
        self.writer, self.report = writer, report
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.new_schema_ids: dict[int, int] = {}
        self.new_channel_ids: dict[int, int] = {}

    def add(self, record) -> None:
        if isinstance(record, Schema):
            self.schemas.setdefault(record.id, record)
        elif isinstance(record, Channel):
            self.channels.setdefault(record.id, record)
        elif isinstance(record, Message):
            self._message(record)

    def _message(self, message: Message) -> None:
        channel = self.channels.get(message.channel_id)
        if channel is None:  # a message before its channel: cannot be interpreted, skip it
            return
        if channel.id not in self.new_channel_ids:
            schema_id = 0
            if channel.schema_id != 0:
                schema = self.schemas.get(channel.schema_id)
                if schema is None:
                    return
                if schema.id not in self.new_schema_ids:
                    self.new_schema_ids[schema.id] = self.writer.register_schema(
                        name=schema.name, encoding=schema.encoding, data=schema.data
                    )
                schema_id = self.new_schema_ids[schema.id]
            self.new_channel_ids[channel.id] = self.writer.register_channel(
                topic=channel.topic,
                message_encoding=channel.message_encoding,
                schema_id=schema_id,
                metadata=dict(channel.metadata),
            )
        self.writer.add_message(
            channel_id=self.new_channel_ids[channel.id],
            log_time=message.log_time,
            data=message.data,
            publish_time=message.publish_time,
            sequence=message.sequence,
        )
        self.report.messages += 1
        self.report.topics[channel.topic] = self.report.topics.get(channel.topic, 0) + 1


def recover(source, output=None, *, overwrite: bool = False) -> RecoveryReport:
    """Write every message of the completed chunks of `source` into a finished bag at `output`.

    output defaults to '<stem>.recovered.mcap' beside the source. Raises BagNotFoundError, or
    BagCorruptError when the file does not even start like an MCAP file.
    """
    source = Path(source)
    output = Path(output) if output is not None else default_output(source)
    if not source.is_file():
        raise BagNotFoundError(f'bag not found: {source}')
    if output.resolve() == source.resolve():
        raise ValueError('the recovered bag must not overwrite its source')
    report = RecoveryReport(source=source, output=output)
    with open(source, 'rb') as stream:
        records = StreamReader(
            stream, emit_chunks=True, record_size_limit=source.stat().st_size
        ).records
        header = _first_header(records, source)
        output.parent.mkdir(parents=True, exist_ok=True)
        with open(output, 'wb' if overwrite else 'xb') as out:
            writer = start_mcap_writer(
                out, library=f'{LIBRARY} recover (from {header.library or "?"})'
            )
            copier = _Copier(writer, report)
            try:
                _copy_records(records, copier, report, stream)
            finally:
                writer.finish()
    return report


def _first_header(records, source: Path) -> Header:
    try:
        header = next(records)
    except Exception as err:
        raise BagCorruptError(
            f'{source} is not an MCAP file ({type(err).__name__}: {err})'
        ) from None
    if not isinstance(header, Header):
        raise BagCorruptError(f'{source} does not start with an MCAP header')
    return header


def _copy_records(records, copier: _Copier, report: RecoveryReport, stream) -> None:
    """Copy records until the footer or the torn tail; `records` stops being usable after an
    error."""
    report.truncated, report.stop_reason = True, 'no footer record'
    intact_until = stream.tell()
    try:
        for record in records:
            intact_until = stream.tell()
            if isinstance(record, Chunk):
                try:
                    inner = breakup_chunk(record, validate_crc=True)
                except Exception:
                    report.bad_chunks += 1
                    continue
                report.chunks += 1
                for item in inner:
                    copier.add(item)
            elif isinstance(record, DataEnd):
                report.data_complete = True
            elif isinstance(record, Footer):
                report.truncated, report.stop_reason = False, ''
                return
            else:
                copier.add(record)  # schemas/channels/messages written outside chunks
    except Exception as err:  # EndOfFile, short or garbled record: the torn tail
        report.truncated = True
        report.stop_reason = (
            f'{type(err).__name__} after byte {intact_until} of {report.source.stat().st_size}'
        )
