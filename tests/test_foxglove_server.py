"""live --serve-foxglove: a real WebSocket client (Foxglove's protocol) sees every channel the session
MCAP holds and decodes the pick plan as the run wrote it; clients that leave or never read do not slow
the run; a port in use is refused before anything is captured."""

import asyncio
import json
import socket
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import websockets

from capture.mcap.reader import McapSource, read_documents
from capture.mcap.schema import PLAN_JSON_TOPIC, PLAN_TOPIC

ROOT = Path(__file__).resolve().parent.parent
SUBPROTOCOL = "foxglove.sdk.v1"
"""The Foxglove WebSocket protocol's subprotocol as foxglove-sdk's server speaks it."""


def _message_data(payload: bytes) -> tuple[int, int, bytes]:
    """A binary Message Data frame (opcode 1): subscription id, log time, the message."""
    opcode, subscription, log_time = struct.unpack_from("<BIQ", payload)
    assert opcode == 1
    return subscription, log_time, payload[13:]


async def _read_everything(url: str) -> tuple[dict, dict]:
    """Subscribe to every channel the server advertises and keep each message until the server goes:
    the channels by topic and the messages by topic."""
    channels, messages = {}, {}
    async with websockets.connect(url, subprotocols=[SUBPROTOCOL], max_size=None) as connection:
        assert connection.subprotocol == SUBPROTOCOL
        try:
            async for payload in connection:
                if isinstance(payload, str):
                    message = json.loads(payload)
                    if message["op"] == "advertise":
                        new = [c for c in message["channels"] if c["topic"] not in channels]
                        channels.update({c["topic"]: c for c in new})
                        await connection.send(json.dumps({"op": "subscribe", "subscriptions": [
                            {"id": c["id"], "channelId": c["id"]} for c in new]}))
                else:
                    subscription, _, data = _message_data(payload)
                    topic = next(t for t, c in channels.items() if c["id"] == subscription)
                    messages.setdefault(topic, []).append(data)
        except websockets.ConnectionClosed:
            pass
    return channels, messages


async def _stall(url: str, done: asyncio.Event) -> None:
    """Subscribe to each channel as it is advertised until the depth images are among them, then read
    nothing until ``done`` (the client's queue holds one message, so the socket's buffers fill and stay
    full)."""
    async with websockets.connect(url, subprotocols=[SUBPROTOCOL], max_queue=1, max_size=None) as connection:
        depth = False
        while not depth:
            message = await connection.recv()
            if isinstance(message, str) and json.loads(message)["op"] == "advertise":
                advertised = json.loads(message)["channels"]
                depth = any(c["topic"].endswith("/depth") for c in advertised)
                await connection.send(json.dumps({"op": "subscribe", "subscriptions": [
                    {"id": c["id"], "channelId": c["id"]} for c in advertised]}))
        await done.wait()


async def _clients(url: str) -> tuple[dict, dict]:
    async with websockets.connect(url, subprotocols=[SUBPROTOCOL]):
        pass  # connects and leaves at once
    done = asyncio.Event()
    stalled = asyncio.create_task(_stall(url, done))
    try:
        return await _read_everything(url)
    finally:
        done.set()
        await asyncio.gather(stalled, return_exceptions=True)


def _decoded_scene_update(channel: dict, data: bytes):
    import base64

    from mcap.records import Schema
    from mcap_protobuf.decoder import DecoderFactory

    assert channel["encoding"] == "protobuf" and channel["schemaName"] == "foxglove.SceneUpdate"
    schema = Schema(id=1, name=channel["schemaName"], encoding="protobuf", data=base64.b64decode(channel["schema"]))
    return DecoderFactory().decoder_for("protobuf", schema)(data)


def test_a_live_run_serves_every_session_channel_and_its_plan_to_a_websocket_client(tmp_path):
    command = [sys.executable, "-m", "pipeline.cli", "live", "--camera", "virtual", "--views", 6, "--turns", 2,
               "--serve-foxglove", "127.0.0.1:0", "--record", tmp_path / "s.mcap",
               "--detections", tmp_path / "caps.json", "--quiet"]
    process = subprocess.Popen([str(c) for c in command], cwd=ROOT, stdout=subprocess.PIPE,
                               stderr=open(tmp_path / "stderr", "w"), text=True)
    first = process.stdout.readline()
    assert first.startswith("Foxglove server: ws://127.0.0.1:"), first + (tmp_path / "stderr").read_text()
    channels, messages = asyncio.run(_clients(first.split()[-1]))
    stdout = process.stdout.read()
    assert process.wait(timeout=120) == 0, (tmp_path / "stderr").read_text()

    from mcap.reader import make_reader

    with open(tmp_path / "s.mcap", "rb") as file:
        recorded_topics = {channel.topic for channel in make_reader(file).get_summary().channels.values()}
    assert recorded_topics <= set(channels) and {PLAN_TOPIC, PLAN_JSON_TOPIC} <= recorded_topics
    # the last unit's plan as the client decoded it is the plan of the run's own detections JSON
    document = json.loads((tmp_path / "caps.json").read_text())
    plans = [json.loads(data) for data in messages[PLAN_JSON_TOPIC]]
    assert plans[-1]["unit"] == read_documents(tmp_path / "s.mcap")[-1][1]["unit"] == 1
    assert {k: v for k, v in plans[-1].items() if k != "unit"} == document["plan"]
    scene = _decoded_scene_update(channels[PLAN_TOPIC], messages[PLAN_TOPIC][-1])
    arrows = {entity.id: entity.arrows[0].pose.position for entity in scene.entities}
    assert len(arrows) == len(document["plan"]["caps"]) > 0
    for cap in document["plan"]["caps"]:
        position = arrows[f"pick-{cap['id']}"]
        assert np.allclose([position.x, position.y, position.z], cap["grasp"])
    # the stalled and the departed clients cost the run no frame: all recorded, 1/15 s apart, none dropped
    with McapSource(tmp_path / "s.mcap") as session:
        stamps = [frame.timestamp_ns for frame in session]
    assert np.allclose(np.diff(stamps), 1e9 / 15, atol=1)
    assert f"turns: {len(stamps)} frames, 2 fused units, 2 detected, 0 frames and" in stdout


def test_a_port_in_use_is_one_line_and_exit_2_before_anything_is_captured(tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        result = subprocess.run([sys.executable, "-m", "pipeline.cli", "live", "--camera", "virtual",
                                 "--serve-foxglove", f"127.0.0.1:{port}", "--record", str(tmp_path / "s.mcap")],
                                cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1 and f"127.0.0.1:{port}" in result.stderr and "in use" in result.stderr
    assert result.stdout == "" and not list(tmp_path.iterdir())
