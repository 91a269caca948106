"""Weights files: the shipped model, loading, saving and averaging trained networks, and the zoom a
file's model is read at. Imports no training code, so ``detect`` loads its model without the
synthetic generator, fusion or Rerun; torch loads when a file is read or written, so that a command
names the shipped file (and refuses a bad output) before it pays for torch."""

from __future__ import annotations

import io
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from common.files import write_atomically

if TYPE_CHECKING:
    import torch

    from perception.inference import InferenceNet
    from perception.model import MushroomNet
    from perception.network import NetworkConfig

DEFAULT_WEIGHTS = Path(__file__).parent / "weights" / "default.pt"
"""The shipped model."""

UNRECORDED_ZOOM = 1.1
"""The zoom weights and checkpoints without an ``inference_zoom`` entry are read at: the zoom such
models are tuned for."""


class WeightsWriteError(RuntimeError):
    """A weights file or checkpoint that could not be written whole (a full disk); the earlier file stands."""


def write_payload(payload: dict, path: Path) -> None:
    """``payload`` in ``path`` whole, or ``path`` as it was and a WeightsWriteError that says why.
    Serialised in memory first: torch reports a failed write (a full disk) only as an opaque RuntimeError."""
    import torch

    buffer = io.BytesIO()
    torch.save(payload, buffer)
    try:
        write_atomically(path, buffer.getvalue())
    except OSError as error:
        raise WeightsWriteError(f"cannot write {path}: {error.strerror or error}") from None


def all_finite(model: torch.nn.Module) -> bool:
    """Whether every weight and running statistic is a finite number (a diverged run's are not)."""
    import torch

    return all(torch.isfinite(value).all() for value in model.state_dict().values() if value.is_floating_point())


def save_weights(model: MushroomNet, path: Path, **meta) -> None:
    """The shipped form of a model: its weights, its network config and how it was made."""
    write_payload({**meta, "model": model.state_dict(), "network": model.config.to_dict(),
                   "point_spacing": model.point_spacing, "inference_zoom": model.inference_zoom,
                   "calibration": model.calibration.to_dict()}, Path(path))


def scene_spacing(train_config: dict) -> float | None:
    """The training beds' point spacing a saved TrainConfig gives (older run files name it ``voxel``)."""
    scene = train_config.get("scene") or {}
    return scene.get("spacing", scene.get("voxel"))


def load_weights(path: Path, device: str = "cpu") -> tuple[MushroomNet, dict]:
    """A trained network and its metadata from a weights file (model.pt) or a checkpoint."""
    import torch

    from perception.model import MushroomNet

    try:
        state = torch.load(path, map_location=device, weights_only=False)
        network, recorded = _recorded(state)
        model = MushroomNet(network, point_spacing=recorded["point_spacing"],
                            inference_zoom=recorded["inference_zoom"]).to(device)
        model.load_state_dict(state["model"])
        model.calibration = recorded["calibration"]
    except FileNotFoundError:
        raise
    except Exception as error:
        raise ValueError(f"{path} is not a mushroom-pose weights file ({type(error).__name__})") from None
    if not all_finite(model):
        raise ValueError(f"{path} holds weights that are not finite numbers (a training run that diverged)")
    model.eval()
    return model, _metadata(state)


def load_inference_net(path: Path) -> tuple[InferenceNet, dict]:
    """A trained network for inference in numpy (``perception.inference``) and its metadata, from a
    weights file or a checkpoint, read without torch; the same refusals as ``load_weights``."""
    from perception.inference import InferenceNet

    try:
        state = read_payload(path)
        network, recorded = _recorded(state)
        values = state["model"]
        finite = all(np.isfinite(value).all() for value in values.values() if value.dtype.kind == "f")
        net = InferenceNet.from_state_dict(network, values, **recorded)
        net(np.zeros((1, 4), np.int64), np.ones((1, network.in_channels), np.float32))  # weights fit the config
    except FileNotFoundError:
        raise
    except Exception as error:
        raise ValueError(f"{path} is not a mushroom-pose weights file ({type(error).__name__})") from None
    if not finite:
        raise ValueError(f"{path} holds weights that are not finite numbers (a training run that diverged)")
    return net, _metadata(state)


def _recorded(state: dict) -> tuple[NetworkConfig, dict]:
    """The network config of a weights payload, and what it records about reading it."""
    from perception.calibration import Calibration
    from perception.network import NetworkConfig

    spacing = state.get("point_spacing") or scene_spacing(state.get("train_config") or {})
    return NetworkConfig.from_dict(state["network"]), {
        "point_spacing": spacing, "inference_zoom": state.get("inference_zoom", UNRECORDED_ZOOM),
        "calibration": Calibration.from_dict(state.get("calibration"))}


def _metadata(state: dict) -> dict:
    """A weights payload without its tensors and training state."""
    return {k: v for k, v in state.items() if k not in ("model", "optimizer", "scheduler", "torch_rng")}


STORAGE_DTYPES = {"FloatStorage": np.float32, "DoubleStorage": np.float64, "HalfStorage": np.float16,
                  "LongStorage": np.int64, "IntStorage": np.int32, "ShortStorage": np.int16,
                  "CharStorage": np.int8, "ByteStorage": np.uint8, "BoolStorage": np.bool_}
"""numpy's dtype for each torch storage type a weights file can hold."""


def read_payload(path: Path) -> dict:
    """What ``write_payload`` wrote (torch's zip format: a pickle whose tensors point at raw little-endian
    storages beside it), read without torch: tensors come back as numpy arrays. Only plain Python
    values, ordered dicts, counters and tensors are unpickled; anything else in the file is refused."""
    import pickle
    import zipfile
    from collections import Counter, OrderedDict

    with zipfile.ZipFile(path) as archive:
        pickled = next(name for name in archive.namelist() if name.endswith("/data.pkl"))
        folder = pickled[:-len("data.pkl")]
        order = archive.read(folder + "byteorder").strip() if folder + "byteorder" in archive.namelist() else b""
        if order not in (b"", b"little"):  # files without the record are little-endian, as torch reads them
            raise ValueError("weights stored big-endian")

        def rebuild(storage: np.ndarray, offset: int, size: tuple, stride: tuple, *_) -> np.ndarray:
            if not isinstance(storage, np.ndarray):
                raise pickle.UnpicklingError("a tensor without a storage")
            # np.ndarray checks that the view lies inside the storage's bytes
            return np.ndarray(tuple(size), storage.dtype, storage, offset * storage.itemsize,
                              tuple(step * storage.itemsize for step in stride)).copy()

        class Unpickler(pickle.Unpickler):
            def find_class(self, module: str, name: str):
                if (module, name) == ("torch._utils", "_rebuild_tensor_v2"):
                    return rebuild
                if module == "torch" and name in STORAGE_DTYPES:
                    return STORAGE_DTYPES[name]
                if (module, name) in (("collections", "OrderedDict"), ("collections", "Counter")):
                    return OrderedDict if name == "OrderedDict" else Counter  # a checkpoint's scheduler holds one
                raise pickle.UnpicklingError(f"{module}.{name} is no part of a weights file")

            def persistent_load(self, pid):
                _, dtype, key, _, _ = pid
                return np.frombuffer(archive.read(f"{folder}data/{key}"), dtype)

        return Unpickler(io.BytesIO(archive.read(pickled))).load()


def provenance(path: Path, meta: dict) -> dict:
    """What a fine-tuning run started from, kept in its checkpoint (the file at ``path`` may change or
    move later): the file's SHA-256 and its training cost so far. A checkpoint as the start counts
    what it had done."""
    import hashlib

    iterations = meta.get("total_iterations", meta.get("iterations", meta.get("iteration", 0)))
    seconds = meta.get("total_train_seconds", meta.get("train_seconds", meta.get("elapsed_s", 0.0)))
    return {"path": str(path), "sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
            "total_iterations": int(iterations or 0), "total_train_seconds": float(seconds or 0.0),
            "train_config": meta.get("train_config"), "init": meta.get("init"), "runs": meta.get("runs")}


def _runs(node: dict) -> dict[str, list]:
    """Every training run behind a weights file (a ``provenance`` node): [seconds, iterations] by the
    SHA-256 of the file the run made. An averaged model lists its runs itself."""
    if node.get("runs"):
        return {sha: list(cost) for sha, cost in node["runs"].items()}
    parent = node.get("init")
    behind = _runs(parent) if parent else {}
    own = [node["total_train_seconds"] - (parent["total_train_seconds"] if parent else 0.0),
           node["total_iterations"] - (parent["total_iterations"] if parent else 0)]
    return {**behind, node["sha256"]: own}


def average_weights(paths: list[Path]) -> tuple[MushroomNet, dict]:
    """The mean of the weights and batch-norm statistics of models fine-tuned from one start (a "model
    soup", Wortsman et al. 2022): runs that share a start stay in one basin of the loss, where the mean
    of their weights is a working model, often better than either, read at no extra cost (MODEL_CARD.md:
    the ``long10k`` soup of two fine-tunes); runs from separate starts do not, so they are refused. The
    mean's training cost is every run behind it, a shared one counted once."""
    import torch

    from perception.model import MushroomNet

    if len(paths) < 2:
        raise ValueError("averaging needs two weights files or more")
    loaded = [load_weights(Path(path)) for path in paths]
    first = loaded[0][0]
    for path, (model, _) in zip(paths[1:], loaded[1:]):
        if model.config != first.config or model.point_spacing != first.point_spacing:
            raise ValueError(f"{path} holds a different network than {paths[0]}; only models of one network average")
        if model.inference_zoom != first.inference_zoom:
            raise ValueError(f"{path} is read at zoom {model.inference_zoom}, {paths[0]} at {first.inference_zoom}")
    nodes = [provenance(Path(path), meta) for path, (_, meta) in zip(paths, loaded)]
    runs = [_runs(node) for node in nodes]
    if not set.intersection(*(set(behind) for behind in runs)):
        raise ValueError(f"{' and '.join(map(str, paths))} were not trained from one start: the weights of "
                         "separate runs do not average into a working model")
    states = [model.state_dict() for model, _ in loaded]
    stacked = {name: torch.stack([state[name] for state in states]) for name in states[0]}
    # integer buffers are batch-norm step counts: the largest stands for the mean model's
    mean = {name: values.mean(0) if values.is_floating_point() else values.amax(0) for name, values in stacked.items()}
    model = MushroomNet(first.config, point_spacing=first.point_spacing, inference_zoom=first.inference_zoom)
    model.load_state_dict(mean)
    model.eval()
    every_run = {sha: cost for behind in runs for sha, cost in behind.items()}
    seconds, iterations = (sum(cost[i] for cost in every_run.values()) for i in (0, 1))
    meta = {"averaged": nodes, "runs": every_run, "iterations": int(iterations), "train_seconds": float(seconds),
            "total_iterations": int(iterations), "total_train_seconds": float(seconds)}
    return model, meta
