"""Turned readings (``predict(readings=N)``): each voxel's encoding is the mean of N readings of the
cloud, each turned a further 360/N degrees about the vertical, with their centres turned back; the
setting reaches detection from the runner, the perception process (test_perception_process.py), detect
and eval (test_detect_cli.py) and replay."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from common.geometry import voxel_representatives
from helpers import tiny_network_config
from perception.detect import detect_points, predict
from perception.instances import ClusterConfig
from perception.model import MushroomNet
from perception.network import ENCODINGS
from perception.synthetic.scene import SceneConfig, generate_scene

ZOOM = 1.1


@pytest.fixture(scope="module", params=ENCODINGS)
def model(request):
    torch.manual_seed(0)
    return MushroomNet(replace(tiny_network_config(), encoding=request.param)).eval()


@pytest.fixture(scope="module")
def bed_points():
    """A bed with one point per voxel of the network's grid, so that a point's values are its voxel's."""
    points = generate_scene(4, SceneConfig(mushrooms=(6, 6))).points.astype(np.float64)
    return points[voxel_representatives(points, tiny_network_config().voxel / ZOOM)]


def _turn(angle_deg: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("z", angle_deg, degrees=True).as_matrix()


@pytest.mark.parametrize("readings", [2, 3])
def test_each_point_takes_the_mean_of_the_turned_readings(model, bed_points, readings):
    averaged = predict(model, bed_points, thin=False, zoom=ZOOM, readings=readings)
    pivot = bed_points.mean(0)
    existence, centers, orientation = [], [], []
    for k in range(readings):  # the same readings made one at a time, through the public call
        rotation = _turn(360.0 * k / readings)
        one = predict(model, (bed_points - pivot) @ rotation.T + pivot, thin=False, zoom=ZOOM)
        existence.append(one.existence[one.point_to_voxel])
        centers.append((one.centers[one.point_to_voxel] - pivot) @ rotation + pivot)
        turned_back = one.orientation[one.point_to_voxel]
        orientation.append(turned_back @ rotation if turned_back.ndim == 2 else turned_back)  # axis vectors turn
    np.testing.assert_allclose(averaged.existence[averaged.point_to_voxel], np.mean(existence, 0), atol=1e-9)
    np.testing.assert_allclose(averaged.centers[averaged.point_to_voxel], np.mean(centers, 0), atol=1e-9)
    np.testing.assert_allclose(averaged.orientation[averaged.point_to_voxel], np.mean(orientation, 0), atol=1e-9)
    # the turned readings differ from the first one: the mean is not one reading repeated
    assert np.abs(np.mean(centers, 0) - centers[0]).max() > 1e-4


def test_fewer_than_one_or_more_than_twelve_readings_are_refused(model, bed_points):
    for readings in (0, 13):
        with pytest.raises(ValueError, match="readings must be 1-12"):
            predict(model, bed_points, readings=readings)


def _frames_and_documents(path, documents):
    """A session with the first two frames of a recording and these detection documents."""
    from capture.mcap.reader import McapSource
    from capture.mcap.schema import DETECTIONS_TOPIC
    from capture.mcap.writer import McapRecorder
    from pipeline.recordings import RECORDINGS_DIR

    with McapSource(RECORDINGS_DIR / "single-view.mcap") as frames, McapRecorder(path) as recorder:
        for frame, _ in zip(frames, range(2)):
            recorder.write(frame)
        for k, document in enumerate(documents):
            recorder.write_json(DETECTIONS_TOPIC, document, frame.timestamp_ns + k)
    return path


@pytest.fixture()
def chain_readings(monkeypatch):
    """The readings each run of the chain was asked for; the chain itself stops at once."""
    import pipeline.chain

    class ChainReached(Exception):
        pass

    asked = []

    def chain(frames, model, config, outputs, **options):
        asked.append(config.perception.readings)
        raise ChainReached

    monkeypatch.setattr(pipeline.chain, "run_chain", chain)
    return asked, ChainReached


def test_replay_reads_as_often_as_the_session_was_read_unless_told(tmp_path, chain_readings):
    from perception.weights import DEFAULT_WEIGHTS
    from perception.weights import load_weights
    from pipeline.recordings import RECORDINGS_DIR
    from pipeline.replay import ReplayError, ReplayOptions, run_replay
    from pipeline.runner import PerceptionStage

    asked, reached = chain_readings
    model = load_weights(DEFAULT_WEIGHTS)[0]
    three = _frames_and_documents(tmp_path / "three.mcap", [{"readings": 3, "frame": "world", "mushrooms": []}])
    unsaid = RECORDINGS_DIR / "turntable-12.mcap"  # its detections do not say: read once
    for session, options in ((three, ReplayOptions()), (three, ReplayOptions(perception=PerceptionStage(readings=2), readings_as_recorded=False)), (unsaid, ReplayOptions())):
        with pytest.raises(reached):
            run_replay(session, model, tmp_path / "out", None, options, quiet=True)
    assert asked == [3, 2, 1]
    mixed = _frames_and_documents(tmp_path / "mixed.mcap", [{"readings": 3, "mushrooms": []},
                                                             {"readings": 1, "mushrooms": []}])
    with pytest.raises(ReplayError, match=r"do not say one number of readings \(1, 3\); give --readings"):
        run_replay(mixed, model, tmp_path / "out", None, ReplayOptions(), quiet=True)
    garbled = _frames_and_documents(tmp_path / "garbled.mcap", [{"readings": [4], "mushrooms": []}])
    with pytest.raises(ReplayError, match=r"\(\[4\]\); give --readings"):
        run_replay(garbled, model, tmp_path / "out", None, ReplayOptions(), quiet=True)


def test_detect_on_a_raw_session_hands_its_readings_to_the_chain(tmp_path, chain_readings):
    from pipeline.cli import build_parser
    from pipeline.commands import detect

    asked, reached = chain_readings
    raw = _frames_and_documents(tmp_path / "frames.mcap", [])  # frames alone: detect fuses them first
    with pytest.raises(reached):
        detect.run(build_parser().parse_args(["detect", str(raw), "--readings", "2", "--out", str(tmp_path / "d.json")]))
    assert asked == [2]


def test_the_runner_reads_as_many_times_as_its_perception_stage_says():
    from capture.source import Source
    from perception.weights import DEFAULT_WEIGHTS
    from perception.weights import load_weights
    from pipeline.runner import PerceptionStage, RunConfig, Runner
    from capture.virtual import VirtualCameraConfig
    from pipeline.sources import VirtualBed, virtual_bed_source

    shipped = load_weights(DEFAULT_WEIGHTS)[0]
    frames, _ = virtual_bed_source(VirtualBed(seed=5, camera=VirtualCameraConfig(views=2)))
    frames = list(frames)

    class Frames(Source):
        def __init__(self):
            self.left = iter(frames)

        def read(self):
            return next(self.left, None)

    found = {}
    for readings in (1, 3):
        summary = Runner(Frames(), shipped, RunConfig(perception=PerceptionStage(readings=readings)), []).run()
        cloud = summary.last_unit.cloud
        found[readings] = summary.last_detection.result
        assert summary.last_detection.document["readings"] == readings  # the document says how it was read
        direct = detect_points(shipped, cloud.points, ClusterConfig(), readings=readings)
        np.testing.assert_allclose(found[readings].voxels.existence, direct.voxels.existence, atol=1e-9)
    assert not np.allclose(found[1].voxels.existence, found[3].voxels.existence)
