"""The one cap type: its detection document round-trips through JSON text, and it moves between frames."""

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from perception.cap import Caps


def _caps(n: int, seed: int = 0) -> Caps:
    rng = np.random.default_rng(seed)
    radii = rng.uniform(0.01, 0.04, n)
    return Caps(rng.uniform(-0.2, 0.2, (n, 3)), Rotation.random(n, random_state=seed).as_matrix(),
                np.column_stack([radii, radii, radii * rng.uniform(0.5, 0.8, n)]), rng.uniform(0, 1, n),
                rng.integers(1, 500, n))


def test_the_detection_document_round_trips_through_json_text():
    caps = _caps(7)
    document = json.loads(json.dumps(caps.to_document("world", 1)))
    assert document["frame"] == "world" and document["units"] == "m"
    assert [c["id"] for c in document["mushrooms"]] == list(range(7))
    back = Caps.from_document(document)
    for name in ("centers", "rotations", "scales", "scores", "members"):
        np.testing.assert_array_equal(getattr(back, name), getattr(caps, name), err_msg=name)
    first = document["mushrooms"][0]
    np.testing.assert_array_equal(first["axis"], caps.rotations[0][:, 2])
    assert first["cap_diameter_mm"] == pytest.approx(2000 * caps.scales[0, 0])


def test_no_caps_round_trip_too():
    back = Caps.from_document(json.loads(json.dumps(Caps.none().to_document("bed", 1))))
    assert len(back) == 0 and back.centers.shape == (0, 3) and back.rotations.shape == (0, 3, 3)


def test_moving_caps_moves_centres_and_axes_and_keeps_sizes():
    caps = _caps(5, seed=1)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [0.3, -0.2, 1.1]).as_matrix()
    T[:3, 3] = [0.5, -0.1, 0.9]
    moved = caps.moved(T)
    for k in range(5):  # cap by cap, each point of its frame taken through T by hand
        np.testing.assert_allclose(moved.centers[k], T[:3, :3] @ caps.centers[k] + T[:3, 3])
        np.testing.assert_allclose(moved.axes[k], T[:3, :3] @ caps.axes[k])
    np.testing.assert_array_equal(moved.scales, caps.scales)
    np.testing.assert_allclose(moved.moved(np.linalg.inv(T)).centers, caps.centers, atol=1e-12)


@pytest.mark.parametrize("document", [{}, {"mushrooms": [{"center": [0, 0, 0]}]},
                                      {"mushrooms": [{"center": [0, 0], "rotation": np.eye(3).tolist(),
                                                      "radius": 0.02, "height": 0.01, "score": 1}]}])
def test_a_malformed_document_is_a_one_line_error(document):
    with pytest.raises(ValueError, match="not a detection document") as error:
        Caps.from_document(document)
    assert "\n" not in str(error.value)
