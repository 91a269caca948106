"""A disk that fills: every command stops at once with one line that says what it kept, exits 1, and
leaves whole files only (nothing the next run trips over). Needs a small tmpfs: skipped where this
process may not mount one."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from capture.mcap.reader import McapSource
from capture.mcap.recovery import recover_recording
from capture.mcap.writer import McapRecorder, RecordingError

RECORDINGS = Path(__file__).resolve().parents[1] / "recordings"


@pytest.fixture
def small_disk(tmp_path):
    """A 1 MB tmpfs, unmounted afterwards."""
    mount = tmp_path / "disk"
    mount.mkdir()
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("mounting a tmpfs needs root and mount(8)")
    made = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mount)], capture_output=True,
                          text=True)
    if made.returncode:
        pytest.skip(f"cannot mount a tmpfs here: {made.stderr.strip()}")
    yield mount
    subprocess.run(["umount", "-l", str(mount)], capture_output=True)


def bed_frames(count: int) -> list:
    """``count`` depth frames of one synthetic bed, from the virtual camera."""
    from capture.virtual import VirtualCameraConfig
    from pipeline.sources import VirtualBed, virtual_bed_source

    return list(virtual_bed_source(VirtualBed(seed=3, camera=VirtualCameraConfig(views=count)))[0])


def cli(*args, timeout: float = 180) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pipeline.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout)


def error_line(result: subprocess.CompletedProcess) -> str:
    """The command's one error line (other libraries may print their own lines about the disk)."""
    lines = [line for line in result.stderr.splitlines() if line.startswith("mushroom-pose")]
    assert len(lines) == 1, result.stderr
    assert "Traceback" not in result.stderr
    return lines[0]


def test_record_on_a_full_disk_keeps_a_valid_recording_of_what_it_wrote(small_disk):
    out = small_disk / "r.mcap"
    result = cli("record", "--camera", "virtual", "--out", out, "--quiet")
    assert result.returncode == 1
    line = error_line(result)
    assert "is full" in line and str(out) in line
    frames = list(McapSource(out))  # finalised: read through its index, no truncation warning
    assert 1 <= len(frames) < 18
    assert [p.name for p in small_disk.iterdir()] == ["r.mcap"]


def test_a_write_that_fails_all_the_same_leaves_the_partial_file_for_recover(small_disk, tmp_path, monkeypatch):
    """Another process filled the disk: foxglove-sdk's failed write becomes a RecordingError naming the
    .partial file, which recover makes whole, and which ``overwrite`` replaces."""
    monkeypatch.setattr(McapRecorder, "room_needed", lambda self, message_bytes: 0)
    path = small_disk / "r.mcap"
    recorder = McapRecorder(path)
    written = 0
    with pytest.raises(RecordingError) as failure:
        with recorder:
            for frame in bed_frames(40):
                recorder.write(frame)
                written += 1
    assert "mushroom-pose recover" in str(failure.value) and "\n" not in str(failure.value)
    assert not path.exists() and recorder.partial_path.exists()
    copy = tmp_path / "copy.mcap.partial"
    shutil.copy(recorder.partial_path, copy)
    recovered = recover_recording(copy)
    assert 1 <= recovered.depth_images <= written and len(list(McapSource(recovered.path))) >= 1
    with McapRecorder(path, overwrite=True) as again:  # the stale .partial does not block the next run
        again.write(bed_frames(1)[0])
    assert len(list(McapSource(path))) == 1 and not recorder.partial_path.exists()


def test_synth_on_a_full_disk_leaves_only_whole_scenes(small_disk):
    from perception.synthetic.scene import SyntheticScene

    out = small_disk / "beds"
    result = cli("synth", "--scenes", 4, "--out", out, "--quiet")
    assert result.returncode == 1
    line = error_line(result)
    assert "cannot write scene" in line and ("no scene was written" in line or "is whole" in line
                                             or "are whole" in line)
    names = sorted(p.name for p in out.iterdir())
    assert not [name for name in names if "partial" in name]
    stems = {Path(name).stem for name in names}
    for stem in stems:  # a scene is there with both its files, whole, or not at all
        assert {f"{stem}.npz", f"{stem}.ply"} <= set(names)
        SyntheticScene.load(out / f"{stem}.npz")


def test_demo_on_a_full_disk_leaves_its_folder_as_it_was(small_disk):
    out = small_disk / "demo"
    out.mkdir()
    (out / "notes.txt").write_text("the user's")
    result = cli("demo", "--out", out, "--quiet", "--views", 6)
    assert result.returncode == 1
    assert "is full" in error_line(result)
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def test_replay_on_a_full_disk_says_what_it_kept(small_disk):
    out = small_disk / "replay"
    result = cli("replay", RECORDINGS / "single-view.mcap", "--out", out, "--quiet")
    assert result.returncode == 1
    line = error_line(result)
    assert "is full" in line
    for name in ("replay.mcap", "detections.json", "replay.rrd"):
        assert (name in line) == (out / name).exists()
    assert not [p for p in out.iterdir() if "partial" in p.name]


def test_train_on_a_full_disk_stops_at_its_first_checkpoint_and_exits(small_disk):
    """Without its own serialisation torch reports the failed write opaquely, and Rerun's dead file
    writer held the process on exit: the run must end, in one line, well within the timeout."""
    out = small_disk / "run"
    result = cli("train", "--out", out, "--iterations", 4, "--checkpoint-every", 1, "--validation-scenes", 0,
                 "--threads", 1, "--quiet", timeout=240)
    assert result.returncode == 1
    line = error_line(result)
    assert "checkpoint.pt" in line and "No space left on device" in line and "no checkpoint was kept" in line
    assert not [p for p in out.iterdir() if "partial" in p.name]
