"""pipeline.clouds reading PCD files without Open3D, against what Open3D reads from them."""

import subprocess
import sys

import numpy as np
import open3d as o3d
import pytest

from pipeline.clouds import load_cloud, read_pcd


def _cloud(n=500, seed=0, colours=True):
    rng = np.random.default_rng(seed)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(rng.uniform(-0.3, 0.3, (n, 3))))
    if colours:
        cloud.colors = o3d.utility.Vector3dVector(rng.uniform(0, 1, (n, 3)))
        cloud.normals = o3d.utility.Vector3dVector(rng.normal(size=(n, 3)))
    return cloud


@pytest.mark.parametrize("ascii", [False, True], ids=["binary", "ascii"])
@pytest.mark.parametrize("colours", [False, True], ids=["xyz", "xyz normals rgb"])
def test_pcd_points_are_those_open3d_reads(tmp_path, ascii, colours):
    path = tmp_path / "bed.pcd"
    assert o3d.io.write_point_cloud(str(path), _cloud(colours=colours), write_ascii=ascii)
    got = read_pcd(path)
    expected = np.asarray(o3d.io.read_point_cloud(str(path)).points)
    assert got.shape == expected.shape == (500, 3)
    np.testing.assert_array_equal(got, expected)


def test_a_pcd_written_by_hand_with_padding_and_double_fields(tmp_path):
    """PCL's layouts Open3D does not write: a padding field, doubles, x, y, z in another order (Open3D
    reads double fields as zeros, so the truth is the reference here)."""
    rng = np.random.default_rng(1)
    xyz = rng.uniform(-1, 1, (40, 3))
    record = np.dtype([("z", "<f8"), ("_", "u1", (4,)), ("x", "<f8"), ("y", "<f8"), ("i", "<u2")])
    table = np.zeros(40, record)
    table["x"], table["y"], table["z"] = xyz.T
    header = ("VERSION 0.7\nFIELDS z _ x y intensity\nSIZE 8 1 8 8 2\nTYPE F U F F U\nCOUNT 1 4 1 1 1\n"
              "WIDTH 40\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 40\nDATA binary\n")
    path = tmp_path / "pcl.pcd"
    path.write_bytes(header.encode() + table.tobytes())
    np.testing.assert_array_equal(read_pcd(path), xyz)


def test_a_bad_pcd_is_one_clear_error(tmp_path):
    path = tmp_path / "cut.pcd"
    assert o3d.io.write_point_cloud(str(path), _cloud(), write_ascii=False)
    path.write_bytes(path.read_bytes()[:-100])
    with pytest.raises(ValueError, match="cut short"):
        load_cloud(path)
    ascii_path = tmp_path / "cut_ascii.pcd"
    assert o3d.io.write_point_cloud(str(ascii_path), _cloud(), write_ascii=True)
    ascii_path.write_text(ascii_path.read_text()[:-200])
    with pytest.raises(ValueError, match="cut short"):
        load_cloud(ascii_path)
    garbled = tmp_path / "garbled.pcd"
    garbled.write_text("VERSION 0.7\nFIELDS a b c\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nPOINTS 1\nDATA ascii\n1 2 3\n")
    with pytest.raises(ValueError, match="not a readable PCD"):
        load_cloud(garbled)
    for header in ("FIELDS x y z\nSIZE 1 4 4\nTYPE F F F\nCOUNT 1 1 1\nPOINTS 1\nDATA binary\n",
                   "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nPOINTS -1\nDATA ascii\n"):
        odd = tmp_path / "odd.pcd"
        odd.write_bytes(header.encode() + bytes(64))
        with pytest.raises(ValueError, match="not a readable PCD"):
            load_cloud(odd)
    word = tmp_path / "word.pcd"
    word.write_text("FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nPOINTS 1\nDATA ascii\n1 two 3\n")
    with pytest.raises(ValueError, match="not a number"):
        load_cloud(word)


def test_a_compressed_pcd_is_left_to_open3d(tmp_path):
    path = tmp_path / "packed.pcd"
    cloud = _cloud()
    assert o3d.io.write_point_cloud(str(path), cloud, write_ascii=False, compressed=True)
    assert read_pcd(path) is None
    np.testing.assert_allclose(load_cloud(path, "m").points, np.asarray(cloud.points), atol=1e-6)


def test_detect_on_a_pcd_imports_neither_torch_nor_open3d(tmp_path):
    """What ``detect`` starts up with on a PCD file: its network runs in numpy and its bed plane and
    voxel normals are fitted without Open3D (``bench/detect.py`` times it)."""
    from perception.synthetic.scene import SceneConfig, generate_scene

    scene = generate_scene(1, SceneConfig(mushrooms=(5, 5)))
    path = tmp_path / "bed.pcd"
    assert o3d.io.write_point_cloud(str(path), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(scene.points)))
    code = ("import sys; from pipeline.cli import main; "
            f"code = main(['detect', {str(path)!r}, '--out', {str(tmp_path / 'd.json')!r}]); "
            "print(code, sorted(m for m in ('open3d', 'rerun', 'torch') if m in sys.modules))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.stdout.strip().splitlines()[-1] == "0 []", result.stderr
