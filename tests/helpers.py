"""Small readers shared by tests."""

import collections

import numpy as np
from rerun.chunk import RrdReader


def rrd_entity_rows(path) -> collections.Counter:
    """Rows logged per entity path in a .rrd file."""
    rows = collections.Counter()
    for chunk in RrdReader(str(path)).stream().to_chunks():
        rows[str(chunk.entity_path)] += chunk.num_rows
    return rows


def tiny_network_config():
    """A network small enough for fast tests (the real presets take seconds per scene)."""
    from perception.network import NetworkConfig

    return NetworkConfig(channels=(8, 8, 8, 8), up_channels=(8, 8, 8, 8), first_kernel=3, head_hidden=(8, 8))


def write_tiny_weights(path):
    """An untrained tiny network saved as a weights file, biased to see few caps so clustering stays quick."""
    import torch

    from perception.model import MushroomNet
    from perception.synthetic.scene import SceneConfig
    from perception.weights import save_weights

    model = MushroomNet(tiny_network_config(), point_spacing=SceneConfig().spacing).eval()
    with torch.no_grad():
        model.head[-1].bias[0] = -3.0
    save_weights(model, path, iterations=0)
    return path


def rrd_timelines(path, entity: str) -> set[str]:
    """The timelines an entity's rows of a .rrd file are logged on."""
    names = set()
    for chunk in RrdReader(str(path)).stream().to_chunks():
        if str(chunk.entity_path) == entity:
            names.update(chunk.timeline_names)
    return names


def rrd_values(path, entity: str, component: str) -> list[tuple[dict[str, int], list]]:
    """Every row of one component (``"Archetype:field"``, e.g. ``"Transform3D:translation"``) logged on
    ``entity`` in a .rrd file, in logging order: (times, value) with times {timeline: int} (sequence
    numbers; nanoseconds for timestamps; empty for static rows) and value the row's list of instances."""
    rows = []
    for chunk in RrdReader(str(path)).stream().to_chunks():
        if str(chunk.entity_path) != entity:
            continue
        batch = chunk.to_record_batch()
        if component not in batch.schema.names:
            continue
        times = {name: batch.column(name).cast("int64").to_pylist() for name in chunk.timeline_names}
        for index, value in enumerate(batch.column(component).to_pylist()):
            if value is not None:
                rows.append(({name: column[index] for name, column in times.items()}, value))
    return sorted(rows, key=lambda row: row[0].get("log_time", -1))


def rerun_matrix(value) -> np.ndarray:
    """A Transform3D:mat3x3 instance (Rerun stores 3x3 matrices column by column) as a 3x3 array."""
    return np.asarray(value, np.float64).reshape(3, 3).T
