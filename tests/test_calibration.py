"""A model's calibration (perception/calibration.py): diameters and scores mapped to what they mean,
stored in the weights file, applied where caps are found."""

import numpy as np
import pytest

from perception.calibration import UNCALIBRATED, Calibration, fit_diameters, fit_scores
from perception.cap import Caps


def caps_of(radii_m, scores):
    n = len(radii_m)
    scales = np.column_stack([radii_m, radii_m, 0.5 * np.asarray(radii_m)])
    return Caps(np.zeros((n, 3)), np.repeat(np.eye(3)[None], n, 0), scales, np.asarray(scores, np.float64))


def test_the_diameter_line_is_recovered_from_measurements_that_compress():
    rng = np.random.default_rng(0)
    true = rng.uniform(15, 70, 400)
    measured = 0.9 * true + 2.0 + rng.normal(0, 0.5, len(true))
    scale, offset = fit_diameters(measured, true)
    # the least-squares line of true on measured: near the inverse of the compression
    assert scale == pytest.approx(1 / 0.9, rel=0.02) and offset == pytest.approx(-2.0 / 0.9, abs=0.5)
    with pytest.raises(ValueError, match="two sizes"):
        fit_diameters(np.full(3, 40.0), np.full(3, 41.0))


def test_calibrated_scores_say_how_often_a_cap_is_right_and_keep_the_ranking():
    rng = np.random.default_rng(1)
    raw = rng.uniform(0.5, 1.0, 5000)
    truth = np.clip(2 * (raw - 0.5), 0, 1)  # raw 0.5 is never right, raw 1.0 always
    correct = rng.uniform(size=len(raw)) < truth
    knots, values = fit_scores(raw, correct)
    calibration = Calibration(knots, values)
    assert np.all(np.diff(values) > 0) and 0 <= values[0] and values[-1] <= 1
    mapped = calibration.scores(raw)
    assert np.array_equal(np.argsort(mapped, kind="stable"), np.argsort(raw, kind="stable"))
    for low in (0.1, 0.4, 0.7):
        inside = (mapped >= low) & (mapped < low + 0.2)
        assert correct[inside].mean() == pytest.approx(mapped[inside].mean(), abs=0.05)
    assert np.abs(raw - truth).mean() > 0.2  # the raw scores were far from it


def test_applied_calibration_moves_rim_radii_and_scores_only():
    caps = caps_of([0.01, 0.025], [0.6, 0.9])
    calibration = Calibration((0.5, 1.0), (0.2, 0.99), diameter_scale=1.1, diameter_offset_mm=-1.5)
    out = calibration.applied(caps)
    assert np.allclose(2000 * out.radii, 1.1 * np.array([20.0, 50.0]) - 1.5)
    assert np.allclose(out.scales[:, 2], caps.scales[:, 2]) and np.array_equal(out.centers, caps.centers)
    assert np.allclose(out.scores, np.interp([0.6, 0.9], (0.5, 1.0), (0.2, 0.99)))
    same = UNCALIBRATED.applied(caps)
    assert np.allclose(same.scales, caps.scales) and np.allclose(same.scores, caps.scores)
    fitted = calibration.applied(caps, rim_radii=False)  # the ellipsoid's s: the line is not its
    assert np.allclose(fitted.scales, caps.scales) and np.allclose(fitted.scores, out.scores)


@pytest.mark.parametrize("fields, message", [
    (dict(raw_scores=(0.5, 0.6), calibrated_scores=(0.3,)), "one calibrated score per knot"),
    (dict(raw_scores=(0.5, 0.6), calibrated_scores=(0.3, 0.3)), "strictly increasing"),
    (dict(diameter_scale=0.0), "positive")])
def test_a_calibration_that_means_nothing_is_refused(fields, message):
    with pytest.raises(ValueError, match=message):
        Calibration(**fields)


def test_the_calibration_travels_in_the_weights_file(tmp_path):
    import torch

    from helpers import write_tiny_weights
    from perception.weights import load_weights, save_weights, write_payload

    path = write_tiny_weights(tmp_path / "tiny.pt")
    model, meta = load_weights(path)
    assert model.calibration == UNCALIBRATED
    model.calibration = Calibration((0.5, 0.9), (0.1, 0.95), 1.05, -0.5)
    save_weights(model, tmp_path / "calibrated.pt", **meta)
    assert load_weights(tmp_path / "calibrated.pt")[0].calibration == model.calibration
    payload = torch.load(tmp_path / "calibrated.pt", weights_only=False)
    del payload["calibration"]  # a file made before calibrations were stored
    write_payload(payload, tmp_path / "older.pt")
    assert load_weights(tmp_path / "older.pt")[0].calibration == UNCALIBRATED


def test_detect_gives_the_caps_of_its_models_calibration():
    from dataclasses import replace

    from perception.detect import detect_points
    from perception.synthetic.scene import SceneConfig, generate_scene
    from perception.weights import DEFAULT_WEIGHTS, load_weights

    model, _ = load_weights(DEFAULT_WEIGHTS)
    points = generate_scene(3, SceneConfig(mushrooms=(5, 5))).points.astype(np.float64)
    model.calibration = UNCALIBRATED
    raw = detect_points(model, points, readings=1).caps
    model.calibration = Calibration((0.0, 1.0), (0.1, 0.2), diameter_scale=1.2, diameter_offset_mm=1.0)
    calibrated = detect_points(model, points, readings=1).caps
    assert len(raw) == len(calibrated) == 5
    assert np.allclose(2000 * calibrated.radii, 1.2 * 2000 * raw.radii + 1.0)
    assert np.allclose(calibrated.scores, 0.1 + 0.1 * raw.scores)
    assert np.allclose(replace(calibrated, scales=raw.scales).centers, raw.centers)


def test_the_fit_recovers_the_diameter_line_and_ranks_false_caps_low():
    from perception.calibration_fit import fit_calibration

    rng = np.random.default_rng(2)
    found = {}
    for name in ("real-domes", "spacing-1mm", "flats"):
        preds, gts = [], []
        for _ in range(4):
            radii = rng.uniform(0.008, 0.035, 12)
            centers = np.column_stack([np.arange(12) * 0.1, np.zeros(12), np.zeros(12)])
            truth = caps_of(radii, np.ones(12))
            truth = Caps(centers, truth.rotations, truth.scales)
            measured = (2000 * radii - 2.0) / 1.1 / 2000  # true = 1.1 measured + 2 mm
            found_caps = caps_of(np.concatenate([measured, [0.02, 0.02]]), np.concatenate([rng.uniform(0.8, 1, 12),
                                                                                            [0.55, 0.6]]))
            found_caps = Caps(np.concatenate([centers, [[5.0, 5.0, 0.0], [6.0, 5.0, 0.0]]]), found_caps.rotations,
                              found_caps.scales, found_caps.scores)
            if name == "flats":  # not a domed family: its caps read far smaller and must not bend the line
                found_caps = Calibration(diameter_scale=0.8).applied(found_caps)
            preds.append(found_caps)
            gts.append(truth)
        found[name] = (preds, gts)
    calibration = fit_calibration(found, diameters=True)
    assert calibration.diameter_scale == pytest.approx(1.1, rel=1e-6)
    assert calibration.diameter_offset_mm == pytest.approx(2.0, abs=1e-4)
    assert calibration.scores([0.55, 0.6]).max() < 0.01 and calibration.scores([0.85, 0.95]).min() > 0.9
    assert fit_calibration(found).diameter_scale == 1.0  # the shipped kind: scores only
