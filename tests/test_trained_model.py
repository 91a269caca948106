"""The shipped model on held-out synthetic beds: the first 5 beds of val50 (75 caps), made once and
cached (perception.synthetic.dataset.load_preset), both clustering methods: 2-3 s on one torch thread."""

from perception.evaluate import evaluate_on_scenes

from perception.weights import DEFAULT_WEIGHTS
from perception.synthetic.dataset import load_preset
from perception.weights import load_weights

FLOORS = {
    # Measured, read once (the library's default), over val50 beds 0-4 (these) and, for the spread, 5-9:
    #   meanshift  AP@25 100.00 / 99.99 %   AP@50 100.00 / 99.99 %  angle 3.80 / 2.55 deg  scale 3.48 / 4.14 %
    #   dbscan     AP@25 97.28 / 98.85 %    AP@50 97.28 / 97.54 %   angle 3.90 / 2.48 deg  scale 2.88 / 3.85 %
    # Bounds: the worst AP less about two caps of the 75 (2.7 points), rounded down; the worst angle and
    # scale error times 1.5, rounded down.
    "meanshift": {"ap25": 0.97, "ap50": 0.97, "angle_deg": 5.7, "scale_err": 0.062},
    "dbscan": {"ap25": 0.94, "ap50": 0.94, "angle_deg": 5.8, "scale_err": 0.057},
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
