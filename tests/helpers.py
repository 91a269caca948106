"""Small readers shared by tests."""

import collections

from rerun.chunk import RrdReader


def rrd_entity_rows(path) -> collections.Counter:
    """Rows logged per entity path in a .rrd file."""
    rows = collections.Counter()
    for chunk in RrdReader(str(path)).stream().to_chunks():
        rows[str(chunk.entity_path)] += chunk.num_rows
    return rows
