"""A valid recording rebuilt from one whose process died before closing it."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from mcap.records import Channel, Message, Schema

from capture.mcap.reader import whole_records
from capture.mcap.schema import MCAP_MAGIC
from common.files import atomic_path


@dataclass(frozen=True)
class Recovery:
    """What ``recover_recording`` kept of a cut recording."""

    path: Path
    messages: int
    depth_images: int
    """Depth images among the messages (one per frame and sensor; the last may lack its other parts)."""


def recover_recording(partial: str | os.PathLike, out: str | os.PathLike | None = None,
                      overwrite: bool = False) -> Recovery:
    """A valid MCAP (footer, summary, index) from a recording whose process died before closing it
    (``<name>.mcap.partial``): every schema, channel and message of every whole record, in file order,
    written to ``out`` (default: the name without ``.partial``). A chunk the crash cut is lost whole
    (its messages cannot be read). Raises ValueError on a file that is not an MCAP or holds no
    message, FileExistsError when ``out`` exists and ``overwrite`` is not set."""
    from mcap.writer import CompressionType, Writer

    partial = Path(partial)
    out = Path(out) if out is not None else partial.with_name(partial.name.removesuffix(".partial"))
    if out == partial:
        raise ValueError(f"{partial} does not end in .partial: give the recovered file's name")
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out} exists")
    with open(partial, "rb") as file:
        if file.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
            raise ValueError(f"{partial} is not an MCAP recording")
        file.seek(0)
        size = os.fstat(file.fileno()).st_size
        messages = frames = 0
        channels: dict[int, tuple[int, Channel]] = {}
        schemas: dict[int, int] = {0: 0}
        # keep_suffix: the default temporary name, X.mcap.partial, is the input's own
        with atomic_path(out, keep_suffix=True) as scratch, open(scratch, "wb") as target:
            writer = Writer(target, compression=CompressionType.ZSTD)
            writer.start(profile="", library="mushroom-pose recover")
            for record in whole_records(file, size):
                if isinstance(record, Schema) and record.id not in schemas:
                    schemas[record.id] = writer.register_schema(record.name, record.encoding, record.data)
                elif isinstance(record, Channel) and record.id not in channels and record.schema_id in schemas:
                    channels[record.id] = (writer.register_channel(record.topic, record.message_encoding,
                                                                   schemas[record.schema_id], record.metadata),
                                           record)
                elif isinstance(record, Message) and record.channel_id in channels:
                    channel_id, channel = channels[record.channel_id]
                    writer.add_message(channel_id, record.log_time, record.data, record.publish_time,
                                       record.sequence)
                    messages += 1
                    frames += channel.topic.endswith("/depth")
            writer.finish()
            if messages == 0:
                raise ValueError(f"{partial} holds no whole message to recover")
    return Recovery(out, messages, frames)


