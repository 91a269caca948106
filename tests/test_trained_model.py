"""The shipped model on held-out synthetic beds: the first 5 beds of val50 (75 caps), made once and
cached (perception.synthetic.dataset.load_preset), both clustering methods: 2-3 s on one torch thread."""

from perception.detect import DEFAULT_WEIGHTS, evaluate_on_scenes
from perception.synthetic.dataset import load_preset
from perception.train import load_weights

FLOORS = {
    # Measured, pooled over val50 beds 0-4 (these) and, for the spread, over beds 5-9:
    #   meanshift  AP@25 100.00 / 100.00 %  AP@50 98.15 / 100.00 %  angle 4.48 / 2.35 deg  scale 3.60 / 4.06 %
    #   dbscan     AP@25 97.30 / 98.85 %    AP@50 94.03 / 97.43 %   angle 4.90 / 2.26 deg  scale 3.12 / 3.64 %
    # Bounds: the worst AP less about two caps of the 75 (2.7 points), rounded down; the worst angle and
    # scale error times 1.5, rounded down.
    "meanshift": {"ap25": 0.97, "ap50": 0.95, "angle_deg": 6.7, "scale_err": 0.06},
    "dbscan": {"ap25": 0.94, "ap50": 0.91, "angle_deg": 7.3, "scale_err": 0.054},
}


def test_shipped_model_finds_the_caps_of_val50_beds():
    model, _ = load_weights(DEFAULT_WEIGHTS)
    scenes = load_preset("val50", progress=False, limit=5)
    assert sum(len(scene.centers) for scene in scenes) == 75  # the beds the floors were measured on
    results = evaluate_on_scenes(model, scenes)
    for method, floor in FLOORS.items():
        result = results[method]
        measured = f"{method} on val50 beds 0-4: {result.as_dict()}"
        assert result.ap25 >= floor["ap25"] and result.ap50 >= floor["ap50"], measured
        assert result.angle_deg <= floor["angle_deg"] and result.scale_err <= floor["scale_err"], measured


def test_shipped_model_is_small_and_says_how_it_was_made():
    assert DEFAULT_WEIGHTS.stat().st_size <= 30e6
    _, meta = load_weights(DEFAULT_WEIGHTS)
    assert meta["network"]["normals"] is True and meta["network"]["offsets"] is True and meta["iterations"] > 0
    # the budget: at most 3 hours of training on 2 cores, all stages together (weights without
    # total_train_seconds come from a single run, whose train_seconds is the total)
    assert 0 < meta.get("total_train_seconds", meta["train_seconds"]) <= 3 * 3600
