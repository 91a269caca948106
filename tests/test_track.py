"""A bed over days: the synthetic truth grows, appears and is picked as configured; the tracker aligns
the scans on the soil, keeps each cap's id, fits its growth and forecasts the grades to come."""

import numpy as np
import pytest

from perception.cap import Caps
from perception.grades import Grade, GradeTable
from perception.synthetic.days import GrowthConfig, bed_over_days
from perception.synthetic.scene import SceneConfig
from perception.track import NotOneBed, Scan, TrackConfig, forecast, track_bed

CONFIG = SceneConfig(mushrooms=(8, 12), spacing=0.004)


@pytest.fixture(scope="module")
def history():
    return bed_over_days(11, CONFIG, GrowthConfig(days=4, pick_mm=40.0, pick_probability=0.5))


def truth_scans(history):
    return [Scan(s.time_s, s.points.astype(np.float64), Caps(s.centers, s.rotations, s.scales), f"day {s.day}")
            for s in history.scans]


def test_caps_grow_at_their_rates_appear_as_pins_and_are_picked(history):
    growth = GrowthConfig(days=4, pick_mm=40.0, pick_probability=0.5)
    d = history.diameters_mm
    seen = ~np.isnan(d)
    steps = np.diff(d, axis=1)
    both = seen[:, 1:] & seen[:, :-1]
    np.testing.assert_allclose(steps[both], np.broadcast_to(history.growth_mm_per_day[:, None], steps.shape)[both])
    assert (d[seen] >= growth.pin_mm).all()
    assert (~seen[:, 0] & seen[:, -1]).any(), "a pin appears later"
    for cap in np.flatnonzero(history.picked_on >= 0):
        assert not seen[cap, history.picked_on[cap]:].any() and d[cap, history.picked_on[cap] - 1] >= growth.pick_mm
    assert (history.picked_on >= 0).any()
    for scan in history.scans:
        assert scan.cap_ids.tolist() == np.flatnonzero(seen[:, scan.day]).tolist()
        np.testing.assert_allclose(scan.diameters_mm, 2000 * scan.scales[:, :2].mean(1))


def test_the_same_seed_gives_the_same_days_and_the_rig_moves_each_day(history):
    again = bed_over_days(11, CONFIG, GrowthConfig(days=4, pick_mm=40.0, pick_probability=0.5))
    np.testing.assert_array_equal(again.scans[2].points, history.scans[2].points)
    shifts = [np.linalg.norm(s.T_scan_bed[:2, 3] - history.scans[0].T_scan_bed[:2, 3]) for s in history.scans[1:]]
    assert min(shifts) > 0


def test_scans_align_on_the_soil_and_every_cap_keeps_its_id(history):
    tracks = track_bed(truth_scans(history))
    for scan, T in zip(history.scans, tracks.T_first_scan):
        truth = history.scans[0].T_scan_bed @ np.linalg.inv(scan.T_scan_bed)
        assert np.abs(T[:3, 3] - truth[:3, 3]).max() < 0.001
        assert np.degrees(np.arccos(np.clip((np.trace(T[:3, :3].T @ truth[:3, :3]) - 1) / 2, -1, 1))) < 0.1
    seen_ids = []
    for track in tracks.tracks:
        ids = {int(history.scans[s].cap_ids[c]) for s, c in zip(track.scans, track.caps)}
        assert len(ids) == 1
        cap = ids.pop()
        seen_ids.append(cap)
        present = np.flatnonzero(~np.isnan(history.diameters_mm[cap]))
        assert list(track.scans) == present.tolist()  # it starts when it appears and ends when picked
        assert track.present == (present[-1] == len(history.scans) - 1)
        if len(track.scans) >= 2:
            assert track.growth_mm_per_day == pytest.approx(history.growth_mm_per_day[cap], abs=1e-6)
    assert sorted(seen_ids) == list(range(len(history.diameters_mm)))


def test_scans_of_two_beds_are_refused(history):
    other = bed_over_days(12, CONFIG, GrowthConfig(days=1))
    scans = truth_scans(history)[:1] + truth_scans(other)
    with pytest.raises(NotOneBed, match="are not of one bed"):
        track_bed(scans)


def test_the_ready_day_and_the_forecast_follow_the_fitted_growth():
    """Two caps seen on days 0-2: one growing 4 mm/day from 30 mm, one 2 mm/day from 20 mm."""
    rotation = np.eye(3)[None].repeat(2, 0)
    scans = []
    ground = np.stack(np.meshgrid(np.linspace(-0.2, 0.2, 80), np.linspace(-0.2, 0.2, 80)), -1).reshape(-1, 2)
    bumps = 0.004 * np.sin(ground[:, 0] * 40) * np.cos(ground[:, 1] * 30)
    soil = np.column_stack([ground, bumps])
    for day in range(3):
        radii = np.array([30 + 4 * day, 20 + 2 * day]) / 2000
        caps = Caps(np.array([[0.05, 0.0, 0.01], [-0.08, 0.05, 0.01]]), rotation,
                    np.column_stack([radii, radii, 0.6 * radii]))
        scans.append(Scan(day * 86400.0, soil, caps))
    tracks = track_bed(scans, GradeTable((Grade("small", 0), Grade("big", 45))), TrackConfig(pick_mm=50, horizon_days=3))
    fast, slow = tracks.tracks
    assert fast.ready_day == pytest.approx(5.0) and slow.ready_day == pytest.approx(15.0)
    assert tracks.forecast["days"] == [3.0, 4.0, 5.0]
    # day 3: 42 and 26 mm; day 4: 46 and 28; day 5: 50 and 30
    assert tracks.forecast["grades"] == {"small": [2, 1, 1], "big": [0, 1, 1]}
    assert forecast([], 2.0, GradeTable(), 2)["grades"]["button"] == [0, 0]


def test_synth_days_writes_each_scan_and_the_history(tmp_path):
    import subprocess
    import sys

    from perception.synthetic.dataset import scene_seeds

    out = tmp_path / "days"
    result = subprocess.run([sys.executable, "-m", "pipeline.cli", "synth", "--days", "2", "--scenes", "1",
                             "--mushrooms", "8", "12", "--out", str(out), "--quiet"], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    seed = scene_seeds(0, 1)[0]
    expected = bed_over_days(seed, SceneConfig(mushrooms=(8, 12)), GrowthConfig(days=2))
    history = np.load(out / f"bed_{seed}_history.npz")
    np.testing.assert_array_equal(history["diameters_mm"], expected.diameters_mm)
    for scan in expected.scans:
        saved = np.load(out / f"bed_{seed}_day_{scan.day}.npz")
        np.testing.assert_array_equal(saved["points"], scan.points)
        np.testing.assert_array_equal(saved["cap_ids"], scan.cap_ids)
        np.testing.assert_allclose(saved["T_scan_bed"], scan.T_scan_bed)
