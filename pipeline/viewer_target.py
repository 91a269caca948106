"""Where a run's Rerun stream goes, apart from ``pipeline.viewer`` so that a command shown in no
viewer never loads rerun-sdk."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class ViewerTarget:
    """Where a run's Rerun stream goes: a .rrd file, a viewer spawned beside the run, a web viewer served
    for a headless machine; any of them together, or none."""

    rrd: Path | None = None
    spawn: bool = False
    serve: bool = False
    hold: bool = False
    """With ``serve``: keep serving after the run ends, until Ctrl-C (a command that ends on its own)."""

    def __post_init__(self) -> None:
        if self.spawn and self.serve:
            raise ValueError("a run either spawns a viewer or serves one, not both")

    @property
    def wanted(self) -> bool:
        return self.rrd is not None or self.spawn or self.serve
