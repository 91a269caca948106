"""The camera registry (``capture.cameras``): every kind resolves to its config and source, and listing
the kinds loads no backend."""

import dataclasses
import subprocess
import sys

import pytest

from capture.cameras import CAMERA_KINDS, CAMERAS, camera_kind
from capture.source import Source


def test_every_kind_names_a_config_dataclass_and_a_source_whose_device_field_exists():
    for name in CAMERAS:
        kind = camera_kind(name)
        config, source = kind.classes()
        assert dataclasses.is_dataclass(config) and issubclass(source, Source), name
        if kind.device_field is not None:
            assert kind.device_field in {field.name for field in dataclasses.fields(config)}, name


def test_listing_the_kinds_imports_no_camera_library_and_no_numpy():
    code = ("import sys, capture.cameras; "
            "print(sorted(m for m in ('pyrealsense2', 'depthai', 'numpy') if m in sys.modules))")
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert loaded.strip() == "[]"


def test_an_unknown_kind_is_refused_with_the_kinds_there_are():
    with pytest.raises(ValueError, match="unknown camera 'kinect'; choose one of " + ", ".join(CAMERA_KINDS)):
        camera_kind("kinect")
