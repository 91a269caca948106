"""A recording whose process died (power loss, SIGKILL) is rebuilt into a valid MCAP with every whole
message (``capture.mcap.recovery.recover_recording``)."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from capture.mcap.reader import McapSource
from capture.mcap.recovery import recover_recording


def _one_message_per_chunk(path: Path, messages: int) -> list[tuple[int, int]]:
    """An MCAP whose every message is its own chunk; the (start, end) byte range of each chunk."""
    with open(path, "wb") as file:
        writer = Writer(file, chunk_size=1)
        writer.start()
        schema = writer.register_schema("raw", "jsonschema", b"{}")
        channel = writer.register_channel("/numbers", "json", schema)
        for k in range(messages):
            writer.add_message(channel, log_time=k, data=b'{"k": %d}' % k, publish_time=k)
        writer.finish()
    with open(path, "rb") as file:
        summary = make_reader(file).get_summary()
    return sorted((c.chunk_start_offset, c.chunk_start_offset + c.chunk_length) for c in summary.chunk_indexes)


@pytest.mark.parametrize("cut_fraction", [0.3, 0.5, 0.9])
def test_recovery_keeps_every_message_whose_chunk_the_cut_left_whole(tmp_path, cut_fraction):
    whole = tmp_path / "whole.mcap"
    chunks = _one_message_per_chunk(whole, 40)
    data = whole.read_bytes()
    cut = int(cut_fraction * len(data))
    partial = tmp_path / "session.mcap.partial"
    partial.write_bytes(data[:cut])
    expected = sum(end <= cut for _, end in chunks)  # each chunk holds one message

    recovered = recover_recording(partial)

    assert recovered.path == tmp_path / "session.mcap" and recovered.messages == expected
    with open(recovered.path, "rb") as file:
        reader = make_reader(file)
        assert reader.get_summary().statistics.message_count == expected
        assert [int(m.log_time) for _, _, m in reader.iter_messages()] == list(range(expected))


def test_recovery_refuses_what_it_cannot_or_must_not_do(tmp_path):
    not_mcap = tmp_path / "x.mcap.partial"
    not_mcap.write_bytes(b"hello")
    with pytest.raises(ValueError, match="not an MCAP"):
        recover_recording(not_mcap)
    whole = tmp_path / "y.mcap"
    _one_message_per_chunk(whole, 3)
    header_only = tmp_path / "y2.mcap.partial"
    header_only.write_bytes(whole.read_bytes()[:30])
    with pytest.raises(ValueError, match="no whole message"):
        recover_recording(header_only)
    assert not (tmp_path / "y2.mcap").exists() and not list(tmp_path.glob("*.recovering"))
    partial = tmp_path / "y.mcap.partial"
    partial.write_bytes(whole.read_bytes())
    with pytest.raises(FileExistsError):
        recover_recording(partial)  # y.mcap exists: never replaced without asking
    assert recover_recording(partial, overwrite=True).messages == 3


def test_a_killed_recording_is_recovered_with_its_frames(tmp_path):
    """``record`` killed with SIGKILL (as by a power loss) leaves only X.mcap.partial; recovery gives an
    MCAP that McapSource replays, with as many frames as whole depth images were written."""
    out = tmp_path / "r.mcap"
    partial = tmp_path / "r.mcap.partial"
    process = subprocess.Popen([sys.executable, "-m", "pipeline.cli", "record", "--camera", "virtual", "--out", str(out),
                                "--duration", "60", "--views", "600"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                               cwd=Path(__file__).resolve().parents[1])
    try:
        deadline = time.monotonic() + 90
        while not (partial.exists() and partial.stat().st_size > 4_000_000):  # a few chunks of frames written
            assert process.poll() is None and time.monotonic() < deadline, "record ended or wrote too little"
            time.sleep(0.2)
        process.send_signal(signal.SIGKILL)
        process.wait(timeout=30)
    finally:
        if process.poll() is None:
            process.kill()
    assert not out.exists() and partial.exists()

    recovered = recover_recording(partial)

    assert recovered.messages > 0 and recovered.depth_images > 0
    with McapSource(recovered.path) as source:
        frames = sum(1 for _ in source)
    # every depth image but possibly the last (whose meta may lie in the cut chunk) is a whole frame
    assert recovered.depth_images - 1 <= frames <= recovered.depth_images
    assert os.path.getsize(recovered.path) > 0
