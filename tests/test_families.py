"""The robustness suite's beds: the OAK-class sensor's flying pixels and speckle, tilted beds, each
family's caps as its description states, and suite seeds apart from every training run's."""

import numpy as np
import pytest

from capture.virtual import SENSOR_MODELS, Render, SensorModel, apply_sensor_model
from perception.cap import CAP_RADIUS_AT_UNIT_SCALE
from perception.synthetic.families import FAMILIES, family_seeds
from perception.synthetic.scene import SceneConfig, generate_scene
from perception.train import iteration_seed
from test_detect_cli import one_line_error, run

STEP_NEAR, STEP_FAR = 0.30, 0.50


def step_render(size: int = 64) -> Render:
    """A depth step down the middle of the image: near on the left, far on the right."""
    depth = np.full((size, size), STEP_FAR, np.float32)
    depth[:, : size // 2] = STEP_NEAR
    return Render(depth, np.zeros((size, size), np.int64), np.ones((size, size), np.float32))


def quiet(**fields) -> SensorModel:
    return SensorModel(noise_at_1m=0.0, dropout=0.0, depth_scale=1e-6, **fields)


def test_far_side_of_a_step_drops_out_or_flies_between_the_sides():
    render = step_render()
    edge = render.depth.shape[1] // 2
    dropped = apply_sensor_model(render, quiet(), np.random.default_rng(0))
    assert (dropped[:, edge] == 0).all() and (dropped[:, edge + 1:] == np.float32(STEP_FAR)).all()
    flying = apply_sensor_model(render, quiet(flying_pixels=1.0), np.random.default_rng(0))
    assert ((flying[:, edge] > STEP_NEAR) & (flying[:, edge] < STEP_FAR)).all()
    assert (flying[:, :edge] == np.float32(STEP_NEAR)).all() and (flying[:, edge + 1:] == np.float32(STEP_FAR)).all()


def test_speckle_is_range_error_correlated_between_neighbours():
    render = Render(np.full((128, 128), STEP_FAR, np.float32), np.zeros((128, 128), np.int64),
                    np.ones((128, 128), np.float32))
    error = apply_sensor_model(render, quiet(speckle_at_1m=0.01), np.random.default_rng(1)) - STEP_FAR
    assert np.std(error) == pytest.approx(0.01 * STEP_FAR**2, rel=0.05)
    assert np.corrcoef(error[:, :-1].ravel(), error[:, 1:].ravel())[0, 1] > 0.8
    assert SENSOR_MODELS["oak"].noise_at_1m > SENSOR_MODELS["d405"].noise_at_1m


def test_a_tilted_bed_is_the_same_bed_turned():
    flat = generate_scene(5, SceneConfig(mushrooms=(8, 8)))
    tilted = generate_scene(5, SceneConfig(mushrooms=(8, 8), bed_tilt_deg=12.0))

    def pairwise(centers):
        return np.linalg.norm(centers[:, None] - centers[None], axis=-1)

    np.testing.assert_allclose(pairwise(tilted.centers), pairwise(flat.centers), atol=1e-9)
    soil = tilted.points[tilted.instance < 0].astype(np.float64)
    normal = np.linalg.svd(soil - soil.mean(0), full_matrices=False)[2][2]
    tilt = np.degrees(np.arccos(abs(normal[2])))
    assert 5.0 < tilt < 13.0
    u, _, vt = np.linalg.svd((tilted.centers - tilted.centers.mean(0)).T @ (flat.centers - flat.centers.mean(0)))
    turn = u @ vt  # the rotation that carries the flat bed's caps onto the tilted ones
    np.testing.assert_allclose(tilted.rotations, turn @ flat.rotations, atol=1e-6)
    assert np.degrees(np.arccos(turn[2, 2])) == pytest.approx(tilt, abs=2.0)


@pytest.mark.parametrize("name, diameters_mm, height_ratios", [
    ("shallow-domes", None, (0.33, 0.45)), ("real-domes", None, (0.45, 0.70)), ("flats", (50, 80), (0.2, 0.3)),
    ("large-brown", (80, 120), (0.4, 0.6)), ("dense-pins", (7.2, 16.5), None)])
def test_shape_families_make_the_caps_they_state(name, diameters_mm, height_ratios):
    scene = generate_scene(family_seeds(name, 1)[0], FAMILIES[name].config)
    radii = scene.scales[:, :2].mean(1)
    if diameters_mm:
        assert (2000 * radii >= diameters_mm[0] - 1e-6).all() and (2000 * radii <= diameters_mm[1] + 1e-6).all()
    if height_ratios:
        ratio = scene.scales[:, 2] / radii
        assert (ratio >= height_ratios[0] - 1e-9).all() and (ratio <= height_ratios[1] + 1e-9).all()
    assert len(scene.centers) and CAP_RADIUS_AT_UNIT_SCALE == 0.020


def test_suite_and_calibration_beds_are_apart_per_family_and_from_the_recipe_training_beds():
    suite = [seed for name in FAMILIES for seed in family_seeds(name, 50)]
    assert len(set(suite)) == len(suite)
    recipe = {0: 10000, 5: 2400, 15: 1300, 19: 600}  # the model card's run seeds and iterations
    trained = {iteration_seed(run_seed, i) for run_seed, count in recipe.items() for i in range(count)}
    assert not trained & set(suite)
    from perception.calibration import CALIBRATION_SEED

    calibration = {seed for name in FAMILIES for seed in family_seeds(name, 50, CALIBRATION_SEED)}
    assert len(calibration) == 50 * len(FAMILIES) and not calibration & (set(suite) | trained)
    with pytest.raises(ValueError, match="unknown bed family"):
        family_seeds("truffles", 1)


def test_synth_family_writes_its_beds_and_refuses_a_wrong_name(tmp_path):
    out = tmp_path / "beds"
    result = run("synth", "--family", "spacing-8mm", "--scenes", "2", "--out", out, "--no-ply", "--quiet")
    assert result.returncode == 0, result.stderr
    scenes = sorted(out.glob("scene_*.npz"))
    assert len(scenes) == 2
    from perception.synthetic.scene import SyntheticScene

    assert all(0.0064 <= SyntheticScene.load(path).spacing <= 0.0096 for path in scenes)
    wrong = run("synth", "--family", "truffles", "--out", tmp_path / "other")
    one_line_error(wrong, "unknown bed family 'truffles'; choose one of shallow-domes")
    assert "casing-soil" in wrong.stderr
    assert not (tmp_path / "other").exists()


def test_synth_help_names_every_family():
    """``--help`` lists the families without importing the generator, so the list is written out: it
    must name every family there is."""
    import argparse

    from pipeline.commands import synth

    parser = argparse.ArgumentParser()
    synth.add_arguments(parser)
    help_text = next(action.help for action in parser._actions if "--family" in action.option_strings)
    assert [name for name in FAMILIES if name not in help_text.replace(",", " ").split()] == []


def test_the_diameter_line_is_fit_on_the_domed_families_inside_the_range():
    from perception.calibration_fit import DIAMETER_FAMILIES

    assert set(DIAMETER_FAMILIES) == {name for name, family in FAMILIES.items() if family.in_range} - {"flats"}
