"""``mushroom-pose cameras``: the RealSense and OAK cameras attached."""

from __future__ import annotations

import argparse

NAME = "cameras"
HELP = "list attached RealSense and OAK cameras"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``cameras`` takes no arguments."""


def run(args: argparse.Namespace) -> int:
    from capture.cameras import find_cameras

    cameras = find_cameras()
    if not cameras:
        print("no RealSense or OAK camera attached (the virtual camera is always available: --camera virtual)")
    for camera in cameras:
        print(f"{camera.kind:<10} {camera.serial:<24} {camera.name}")
    return 0
