"""Training on a fresh synthetic bed per iteration (paper Sec. 4), on CPU or GPU, resumable exactly.

Scene generation runs in a worker process that feeds a bounded queue, so the network and the
generator keep both cores busy; with Ray (``ray_address``) it runs as Ray tasks, a bounded window of
them ahead of the trainer, on a local Ray or a cluster's workers. Iteration i always trains on the scene and augmentation drawn from
seed (run seed, i), and a checkpoint holds model, optimiser, schedule and torch RNG state: a
resumed run continues exactly where it stopped.
"""

from __future__ import annotations

import csv
import json
import multiprocessing as mp
import queue as queues
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable, Protocol

import numpy as np
import torch
import torch.nn.functional as F
from torch.optim.swa_utils import AveragedModel
from tqdm import tqdm

from common.files import write_atomically
from common.geometry import turn_about_z
from fusion.integrate import IntegrationConfig
from perception.cap import cap_rotation
from perception.encoding import encode
from perception.model import MushroomNet
from perception.network import INFERENCE_ZOOM, LENGTH_UNIT, NETWORK_PRESETS, NetworkConfig, voxel_features
from perception.sparse import SparseTensor
from perception.synthetic.scene import SceneConfig, generate_scene
from perception.weights import (UNRECORDED_ZOOM, WeightsWriteError, all_finite, load_weights, provenance, save_weights,
                                 scene_spacing, write_payload)


@dataclass(frozen=True)
class TrainConfig:
    """The paper's recipe (Sec. 4) with our augmentations; every field is a ``mushroom-pose train`` flag
    (``scene`` by its spacing, scale and jitter)."""

    iterations: int = 20000
    """Training steps, each on a fresh synthetic bed (the paper's 20000)."""
    lr: float = 1e-3
    """Adam's learning rate."""
    milestones: tuple[float, ...] = (0.6, 0.85)
    """Fractions of ``iterations`` where the learning rate drops by ``gamma``."""
    gamma: float = 0.1
    """Factor on the learning rate at each of ``milestones``."""
    weight_existence: float = 1.0
    """Weight of the existence loss (the paper's 1)."""
    weight_residual: float = 100.0
    """Weight of the residual-centre loss (the paper's 100)."""
    weight_orientation: float = 1.0
    """Weight of the orientation loss (the paper's 1)."""
    orientation_on_caps: bool = False
    """Average the orientation MSE over cap voxels only (the paper's loss averages over every voxel,
    most of them soil with target 0, so the term that sets cap tilt is the weakest of the three)."""
    cap_balance: bool = False
    """Weight cap voxels so that every cap counts the same in the existence and orientation losses,
    whatever its size: the caps the model misses or tilts wrongly are the small ones, a few voxels each.
    The orientation loss is then over cap voxels only, as with ``orientation_on_caps``."""
    average_from: float | None = None
    """From this fraction of the run on, keep the running mean of the weights after every step (and of
    the batch-norm statistics alike): stochastic weight averaging (Izmailov et al. 2018). The run's
    model.pt is then the mean, and validation reads it."""
    init_weights: str | None = None
    """Start from these weights (a model.pt) instead of random ones: fine-tuning with a new loss. The
    run is read at ``zoom``, not at its start's zoom."""
    zoom: float | None = None
    """The zoom the model is read at (``MushroomNet.inference_zoom``): its weights record it and
    validation reads at it. It belongs with ``scale_jitter``: a network trained on beds scaled by
    1.05-1.35 is read at 1.2. None: ``INFERENCE_ZOOM``, for the default jitter."""
    network: str = "slim-no"
    """Network preset (perception.network.NETWORK_PRESETS): slim-no, the shipped model's (slim U-Net fed normals
    and each centroid's place in its voxel); slim-n (normals only); slim (occupancy only, as the paper);
    wide-no (slim-no with wider coarse levels); slim-no-k5 (slim-no with a 5^3 first convolution);
    lean-no (slim-no with 32 channels in the full-resolution up block); fcgf (the paper's full backbone)."""
    seed: int = 0
    """Run seed: iteration i trains on the bed and augmentation drawn from seed (run seed, i)."""
    checkpoint_every: int = 200
    """Iterations between checkpoints, which a resumed run continues from."""
    validate_every: int = 1000
    """Iterations between validations."""
    validation_scenes: int = 5
    """val50 scenes scored at each validation (0: none)."""
    queue_size: int = 6
    """Generated beds that may wait for the network (the generator runs in a process of its own)."""
    rotate_z: bool = True
    """Turn each bed by a random angle about the vertical."""
    scale_jitter: tuple[float, float] = (0.9, 1.1)
    """Scale each bed by a factor drawn from [low, high] (the shipped model was fine-tuned at 1.05 1.35)."""
    point_dropout: tuple[float, float] = (0.0, 0.2)
    """Drop a fraction of each bed's points, drawn from [low, high]."""
    tilt_deg: float = 3.0
    """Random tilt of the whole bed, as left by an imperfect bed-plane estimate."""
    noise: float = 0.0005
    """Standard deviation (metres) of Gaussian jitter on the points."""
    scene: SceneConfig = field(default_factory=SceneConfig)
    """The synthetic beds trained on."""
    fused_share: float = 0.0
    """Share of the training beds made as the product makes a scan instead: the virtual camera's noisy
    frames from 2-6 viewpoints, merged as fusion merges them, at its 2 mm voxel. The model then also
    sees a scan's artefacts: rims smoothed into the soil, holes at grazing angles, stereo shadows."""
    stereo_share: float = 0.0
    """Share of those scanned beds seen by the noisier OAK-class stereo model (``capture.virtual``'s
    ``SENSOR_MODELS["oak"]``: more range noise, speckle, flying pixels) instead of the scene's sensor."""

    def __post_init__(self) -> None:
        if self.stereo_share > 0 and self.fused_share == 0:
            raise ValueError("stereo_share picks among the scanned beds: give a fused_share too")

    @property
    def averaging_start(self) -> int | None:
        """The iteration after which each step joins the weights' mean (None: no averaging)."""
        return None if self.average_from is None else int(self.average_from * self.iterations)

    def to_dict(self) -> dict:
        values = asdict(self)
        values["scene"] = {k: v for k, v in values["scene"].items() if k != "sensor"}
        return values


FUSED_BEDS = {"visibility": "fused", "views": (2, 6), "spacing": IntegrationConfig().voxel}
"""What sets a ``fused_share`` bed apart from ``TrainConfig.scene``: 2-6 viewpoints merged at fusion's own voxel."""


def scene_config(config: TrainConfig, seed: int) -> SceneConfig:
    """The scene configuration of the bed drawn from ``seed``: ``config.scene``, or for a share
    ``fused_share`` of the seeds, the same with ``FUSED_BEDS``, seen for a share ``stereo_share`` of
    those by the OAK-class stereo sensor."""
    if config.fused_share > 0 and np.random.default_rng(seed + 2).random() < config.fused_share:
        if config.stereo_share > 0 and np.random.default_rng(seed + 3).random() < config.stereo_share:
            from capture.virtual import SENSOR_MODELS

            return replace(config.scene, **FUSED_BEDS, sensor=SENSOR_MODELS["oak"])
        return replace(config.scene, **FUSED_BEDS)
    return config.scene


def iteration_seed(run_seed: int, iteration: int) -> int:
    return int(np.random.SeedSequence([run_seed, iteration]).generate_state(1)[0])


def augmented_sample(config: TrainConfig, iteration: int) -> dict[str, np.ndarray]:
    """Points and per-point targets of iteration ``iteration``'s scene after augmentation."""
    seed = iteration_seed(config.seed, iteration)
    scene = generate_scene(seed, scene_config(config, seed))
    rng = np.random.default_rng(seed + 1)
    rotation = np.eye(3)
    if config.rotate_z:
        rotation = turn_about_z(rng.uniform(0, 2 * np.pi))
    tilt = np.radians(config.tilt_deg)
    if tilt > 0:
        rotation = cap_rotation(rng.uniform(-tilt, tilt), rng.uniform(-tilt, tilt)) @ rotation
    scale = rng.uniform(*config.scale_jitter)
    keep = rng.random(len(scene.points)) >= rng.uniform(*config.point_dropout)
    points = scale * scene.points[keep].astype(np.float64) @ rotation.T
    points += rng.normal(0.0, config.noise, points.shape)
    centers = scale * scene.centers @ rotation.T
    rotations = rotation @ scene.rotations
    targets = encode(points, scene.instance[keep], scene.is_cap[keep], centers, rotations, scale * scene.scales)
    instance = np.where(targets.existence > 0, scene.instance[keep], -1).astype(np.int64)
    return {"iteration": iteration, "points": points.astype(np.float32), "existence": targets.existence,
            "residual": targets.residual, "orientation": targets.orientation, "instance": instance,
            "axis": np.where(instance[:, None] >= 0, rotations[np.maximum(instance, 0), :, 2], 0.0).astype(np.float32)}


def _differences(saved: dict, asked: dict, prefix: str = "") -> str:
    """'name: saved there, asked here' for each field that differs, nested fields as scene.spacing."""
    found = []
    for name in sorted(set(saved) | set(asked)):
        there, here = saved.get(name), asked.get(name)
        if isinstance(there, dict) and isinstance(here, dict):
            found.append(_differences(there, here, f"{prefix}{name}."))
        elif there != here:
            found.append(f"{prefix}{name}: {there} there, {here} here")
    return ", ".join(f for f in found if f)


def resumed_config(saved: dict, asked: TrainConfig) -> TrainConfig:
    """The configuration a resumed run goes on with: the checkpoint's (``saved``, a ``to_dict``) where
    ``asked`` leaves a field at its default, so that ``train --resume`` needs no flag repeated; a
    ValueError names each field ``asked`` sets to another value than the run's."""
    default = TrainConfig().to_dict()
    saved = {**default, **saved}  # a checkpoint without a field ran with its default
    saved["scene"] = {**default["scene"], **saved["scene"], "spacing": scene_spacing(saved)}
    saved["scene"].pop("voxel", None)
    wanted = asked.to_dict()
    merged = {name: saved[name] if value == default[name] else value
              for name, value in wanted.items() if name != "scene"}
    merged["scene"] = {name: saved["scene"][name] if value == default["scene"][name] else value
                       for name, value in wanted["scene"].items()}
    differ = _differences(saved, merged)
    if differ:
        raise ValueError(f"the run was made with a different configuration ({differ}); resume with its flags, or "
                         "none of them, or use a new run folder")

    def tuples(values: dict) -> dict:
        return {name: tuple(value) if isinstance(value, list) else value for name, value in values.items()}

    scene = SceneConfig(**tuples(merged.pop("scene")), sensor=asked.scene.sensor)
    return TrainConfig(**tuples(merged), scene=scene)


class TrainingError(RuntimeError):
    """A run that cannot go on: its scene generator died, or its loss stopped being finite."""


def _resolve_device(device: str | None) -> str:
    if device is None:
        return "cuda" if torch.cuda.is_available() else "cpu"
    try:
        kind = torch.device(device).type
    except RuntimeError:
        raise ValueError(f"unknown device {device!r}: use cpu or cuda") from None
    if kind == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {device!r}: this torch ({torch.__version__}) sees no CUDA GPU; use cpu")
    return device


_CHECKPOINT_KEYS = {"model", "optimizer", "scheduler", "torch_rng", "iteration", "elapsed_s", "train_config"}


def _load_checkpoint(path: Path, device: str) -> dict:
    try:
        state = torch.load(path, map_location=device, weights_only=False)
        missing = _CHECKPOINT_KEYS - set(state)
    except Exception as error:
        raise ValueError(f"{path} is not a readable checkpoint ({type(error).__name__}); restore it, or start "
                         "again in a new run folder") from None
    if missing:
        raise ValueError(f"{path} is not a training checkpoint (no {', '.join(sorted(missing))}); a model.pt "
                         "cannot be resumed, only fine-tuned with --init")
    return state


SAMPLE_PATIENCE_S = 600.0
"""A scene takes well under a second; a generator silent this long is stuck."""


def training_sample(config: TrainConfig, network: NetworkConfig, iteration: int) -> dict[str, np.ndarray]:
    """Network input and voxel targets of iteration ``iteration``: what the trainer's step consumes."""
    sample = augmented_sample(config, iteration)
    coords, existence, residual, orientation, centroids, cap_weight = voxel_targets(sample, network.voxel)
    if network.encoding != "implicit":
        residual, orientation = explicit_targets(network.encoding, sample, network.voxel, existence, residual,
                                                 orientation, centroids)
    return {"iteration": iteration, "coords": coords.numpy(), "features": voxel_features(network, centroids),
            "existence": existence.numpy(), "residual": residual.numpy(), "orientation": orientation.numpy(),
            "cap_weight": cap_weight.numpy()}


def _producer(config: TrainConfig, network: NetworkConfig, start: int, stop: int, queue: mp.Queue) -> None:
    """Worker process: the samples of iterations ``start`` to ``stop``, in order, into ``queue``."""
    torch.set_num_threads(1)
    for iteration in range(start, stop):
        queue.put(training_sample(config, network, iteration))


def _ray_training_sample(config: TrainConfig, network: NetworkConfig, iteration: int) -> dict[str, np.ndarray]:
    """``training_sample`` as a one-CPU Ray task."""
    torch.set_num_threads(1)
    return training_sample(config, network, iteration)


class ProcessScenes:
    """The samples of iterations ``start`` to ``stop`` from a worker process through a bounded queue."""

    def __init__(self, config: TrainConfig, network: NetworkConfig, start: int, stop: int) -> None:
        context = mp.get_context("fork")
        self._queue = context.Queue(maxsize=config.queue_size)
        self._process = context.Process(target=_producer, daemon=True,
                                        args=(config, network, start, stop, self._queue))
        self._process.start()

    def next(self, iteration: int) -> dict:
        """The next sample; an error, not a wait without end, if the producer died or hangs."""
        waited = 0.0
        while True:
            try:
                return self._queue.get(timeout=5)
            except queues.Empty:
                waited += 5
                if not self._process.is_alive():
                    raise TrainingError(f"the scene generator stopped (exit code {self._process.exitcode}) before "
                                        f"iteration {iteration + 1}; its error is printed above") from None
                if waited >= SAMPLE_PATIENCE_S:
                    raise TrainingError(f"no scene for iteration {iteration + 1} in {waited:.0f} s: the scene "
                                        "generator is stuck") from None

    def close(self) -> None:
        self._process.terminate()


class RayScenes:
    """The samples of iterations ``start`` to ``stop`` as Ray tasks, at most ``config.queue_size`` ahead of
    the trainer, on a local Ray (``address`` None) or the cluster at ``address``."""

    def __init__(self, config: TrainConfig, network: NetworkConfig, start: int, stop: int,
                 address: str | None) -> None:
        from common.distributed import ray_map

        self._samples = ray_map(_ray_training_sample, [(i,) for i in range(start, stop)], address,
                                in_flight=config.queue_size, shared=(config, network))

    def next(self, iteration: int) -> dict:
        try:
            return next(self._samples)
        except Exception as error:  # a worker's error, or the cluster gone: one line, not Ray's traceback
            first = str(error).strip().splitlines()[-1] if str(error).strip() else type(error).__name__
            raise TrainingError(f"the Ray scene generator failed before iteration {iteration + 1}: {first}") from None

    def close(self) -> None:
        self._samples.close()


def voxel_targets(sample: dict, voxel: float):
    """Voxels and their targets (means over each voxel's points): coords, existence, residual
    (LENGTH_UNITs), orientation, the voxel centroids (metres, numpy), and the cap-balancing weight
    (0 off caps; 1 / the voxels of the voxel's cap, scaled to mean 1 over cap voxels)."""
    from perception.detect import network_input

    coords, point_to_voxel, centroids = map(torch.from_numpy, network_input(sample["points"], voxel))
    counts = torch.bincount(point_to_voxel, minlength=len(coords)).clamp_(min=1).float()[:, None]

    def mean(values: np.ndarray) -> torch.Tensor:
        values = torch.from_numpy(values).float().reshape(len(point_to_voxel), -1)
        return torch.zeros(len(coords), values.shape[1]).index_add_(0, point_to_voxel, values) / counts

    points = torch.from_numpy(sample["points"]).double()
    # residual of a voxel: its points' mean cap centre minus the voxel centroid, in LENGTH_UNITs
    center_of_point = (points + torch.from_numpy(sample["residual"]).double()).float().numpy()
    existence = mean(sample["existence"])[:, 0]
    center_sum = mean(center_of_point * sample["existence"][:, None])
    residual = torch.where(existence[:, None] > 0, center_sum / existence.clamp(min=1e-6)[:, None]
                           - centroids.float(), torch.zeros(1)) / LENGTH_UNIT
    orientation = mean(sample["orientation"])[:, 0] / existence.clamp(min=1e-6)
    # a voxel shared by two caps goes to the higher instance number
    cap_of_voxel = torch.full((len(coords),), -1, dtype=torch.int64).scatter_reduce_(
        0, point_to_voxel, torch.from_numpy(sample["instance"]).long(), "amax")
    on_cap = cap_of_voxel >= 0
    _, cap_index, voxels_per_cap = torch.unique(cap_of_voxel[on_cap], return_inverse=True, return_counts=True)
    cap_weight = torch.zeros(len(coords))
    cap_weight[on_cap] = on_cap.sum() / (len(voxels_per_cap) * voxels_per_cap[cap_index].float())
    return (coords, existence, residual * (existence[:, None] > 0), orientation * (existence > 0),
            centroids.numpy(), cap_weight)


def explicit_targets(encoding: str, sample: dict, voxel: float, existence: torch.Tensor, residual: torch.Tensor,
                     orientation: torch.Tensor, centroids: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """The targets of the paper's Table 2 ablations from the implicit ones: ``explicit-centre`` gives
    cap voxels their cap's centre (LENGTH_UNITs, bed frame) in place of the residual to it;
    ``explicit-orientation`` gives them their cap's unit axis (V, 3) in place of the orientation value."""
    from perception.detect import network_input

    on_cap = existence[:, None] > 0
    if encoding == "explicit-centre":
        centre = residual + torch.from_numpy(centroids).float() / LENGTH_UNIT
        return torch.where(on_cap, centre, torch.zeros(1)), orientation
    point_to_voxel = torch.from_numpy(network_input(sample["points"], voxel)[1])
    axis = torch.zeros(len(existence), 3).index_add_(0, point_to_voxel, torch.from_numpy(sample["axis"]).float())
    axis = axis / axis.norm(dim=1, keepdim=True).clamp(min=1e-9)
    return residual, torch.where(on_cap, axis, torch.zeros(1))


def loss_terms(output: torch.Tensor, existence: torch.Tensor, residual: torch.Tensor, orientation: torch.Tensor,
               config: TrainConfig, cap_weight: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """The paper's multi-task loss: BCE on existence, MSE on residual centre and orientation. Cap voxels
    weigh 1, or ``cap_weight`` (from ``voxel_targets``) with ``config.cap_balance``."""
    on_cap = existence > 0
    if config.cap_balance:
        if cap_weight is None:
            raise ValueError("cap_balance needs the cap weights of voxel_targets")
    else:
        cap_weight = on_cap.to(output.dtype)
    voxel_weight = torch.where(on_cap, cap_weight, torch.ones_like(cap_weight))
    bce = F.binary_cross_entropy_with_logits(output[:, 0], existence, reduction="none")
    predicted = output[:, 4] if orientation.dim() == 1 else output[:, 4:]  # a value, or an axis (explicit)
    terms = {"existence": (voxel_weight * bce).mean(),
             "residual": F.mse_loss(output[:, 1:4], residual),
             "orientation": (_weighted_mse(predicted, orientation, cap_weight)
                             if config.orientation_on_caps or config.cap_balance
                             else F.mse_loss(predicted, orientation))}
    terms["total"] = (config.weight_existence * terms["existence"] + config.weight_residual * terms["residual"]
                      + config.weight_orientation * terms["orientation"])
    return terms


def _weighted_mse(prediction: torch.Tensor, target: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    squared = (prediction - target) ** 2
    if squared.dim() > 1:
        squared = squared.sum(1)
    return (weight * squared).sum() / weight.sum().clamp(min=1.0)


def validate(model: MushroomNet, scenes) -> dict[str, float]:
    """The metrics of ``model`` read as it will be (perception.detect, at its own zoom)."""
    from perception.evaluate import evaluate_on_scenes

    metrics = evaluate_on_scenes(model, scenes, methods=("meanshift",))["meanshift"].as_dict()
    model.train()
    return metrics


LOSS_TERMS = ("total", "existence", "residual", "orientation")
VALIDATION_METRICS = ("ap25", "ap50", "angle_deg", "scale_err")
HISTORY_COLUMNS = ("iteration", "lr", *LOSS_TERMS, "seconds", *(f"val_{name}" for name in VALIDATION_METRICS))
"""history.csv: one row per iteration; the validation columns are empty between validations."""


class MetricsLog(Protocol):
    """Where a training session's losses and validation metrics go besides history.csv (the command's:
    ``pipeline.viewer.TrainingLog``, a Rerun recording beside the checkpoint)."""

    def losses(self, iteration: int, losses: dict[str, float]) -> None: ...
    def validation(self, iteration: int, metrics: dict[str, float]) -> None: ...
    def close(self) -> None: ...


def train(config: TrainConfig, run_dir: Path, resume: bool = False, device: str | None = None,
          progress: bool = True, metrics_log: Callable[[Path], MetricsLog] | None = None,
          stop_at: int | None = None, max_minutes: float | None = None,
          ray_address: str | None = None) -> Path | None:
    """Train (or continue training) into ``run_dir``; returns the final weights, or None when the run
    stopped early (at iteration ``stop_at`` or after ``max_minutes``) with a checkpoint to resume. With
    ``ray_address`` ("local", or a cluster's address) the scenes are made as Ray tasks: the same scenes,
    so the same run. ``metrics_log`` opens a session's log at the path it is given (a .rrd beside the
    checkpoint, named by the iteration the session starts from)."""
    if resume and (run_dir / "checkpoint.pt").is_file():
        config = resumed_config(_load_checkpoint(run_dir / "checkpoint.pt", "cpu")["train_config"], config)
    run = TrainingRun(config, run_dir, _resolve_device(device), resume, ray_address)
    end = config.iterations if stop_at is None else min(stop_at, config.iterations)
    reached = run.iterate(end, progress=progress, metrics_log=metrics_log, max_minutes=max_minutes)
    return run.export() if reached == config.iterations else None


class TrainingRun:
    """The training in a run folder: model, optimiser, learning-rate schedule and the weights' running
    mean, set up afresh (random or ``config.init_weights``) or resumed from the folder's checkpoint.
    ``iterate`` trains and checkpoints, ``export`` writes model.pt from the last checkpoint."""

    def __init__(self, config: TrainConfig, run_dir: Path, device: str, resume: bool,
                 ray_address: str | None = None) -> None:
        self.config, self.run_dir, self.device, self.ray_address = config, run_dir, device, ray_address
        self.checkpoint_path = run_dir / "checkpoint.pt"
        if resume and not self.checkpoint_path.is_file():
            raise ValueError(f"no checkpoint to resume in {run_dir}: check --out, or drop --resume to start a new run")
        run_dir.mkdir(parents=True, exist_ok=True)
        self.network_config = NETWORK_PRESETS[config.network]
        torch.manual_seed(config.seed)
        self.model = MushroomNet(self.network_config, point_spacing=config.scene.spacing,
                                 inference_zoom=INFERENCE_ZOOM if config.zoom is None else config.zoom).to(device)
        self.init = self._load_init_weights() if config.init_weights and not resume else None
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=config.lr)
        milestones = [int(f * config.iterations) for f in config.milestones]
        self.scheduler = torch.optim.lr_scheduler.MultiStepLR(self.optimizer, milestones, config.gamma)
        self.averaged = AveragedModel(self.model, use_buffers=True) if config.average_from is not None else None
        self.start, self.elapsed_before, self.saved_at = 0, 0.0, None
        if resume:
            self._resume()
        else:
            (run_dir / "history.csv").unlink(missing_ok=True)
        (run_dir / "train_config.json").write_text(json.dumps(config.to_dict(), indent=1))
        self.session_start = time.perf_counter()

    def _load_init_weights(self) -> dict:
        """Put ``config.init_weights`` into the model; returns their provenance."""
        path = Path(self.config.init_weights)
        initial, meta = load_weights(path, self.device)
        if initial.config != self.network_config:
            raise ValueError(f"{self.config.init_weights} holds a different network than {self.config.network!r}; "
                             "pass the --network it was trained with")
        self.model.load_state_dict(initial.state_dict())
        return provenance(path, meta)

    def _resume(self) -> None:
        """Model, optimiser, schedule, weights' mean and torch RNG as the checkpoint left them."""
        state = _load_checkpoint(self.checkpoint_path, self.device)  # its configuration is ours (resumed_config)
        self.model.load_state_dict(state["model"])
        self.model.inference_zoom = state.get("inference_zoom", UNRECORDED_ZOOM)
        if self.averaged is not None:
            self.averaged.module.inference_zoom = self.model.inference_zoom
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        torch.set_rng_state(state["torch_rng"])
        if self.averaged is not None:
            self.averaged.load_state_dict(state["average"])
        self.start, self.elapsed_before, self.saved_at = state["iteration"], state["elapsed_s"], state["iteration"]
        self.init = state.get("init")
        _trim_history(self.run_dir / "history.csv", self.start)

    def iterate(self, end: int, progress: bool, metrics_log: Callable[[Path], MetricsLog] | None,
                max_minutes: float | None) -> int:
        """Train up to iteration ``end``, or until ``max_minutes`` have passed, with a row of history.csv
        per iteration, validations and checkpoints on the way and a checkpoint where it stops; returns
        the iteration reached."""
        validation = _validation_scenes(self.config)
        log = None if metrics_log is None else metrics_log(self.run_dir / f"train_from_{self.start:06d}.rrd")
        scenes = self._start_scene_generator()
        history = open(self.run_dir / "history.csv", "a", newline="")
        writer = csv.writer(history)
        if self.start == 0:
            writer.writerow(HISTORY_COLUMNS)
        self.model.train()
        bar = tqdm(total=self.config.iterations, initial=self.start, desc="train", unit="it", disable=not progress,
                   dynamic_ncols=True)
        self.session_start = time.perf_counter()
        deadline = None if max_minutes is None else self.session_start + 60 * max_minutes
        try:
            for iteration in range(self.start, end):
                if deadline is not None and time.perf_counter() > deadline:
                    end = iteration
                    break
                losses = self._step(scenes.next(iteration), iteration)
                row = [iteration + 1, self.scheduler.get_last_lr()[0], *(losses[name] for name in LOSS_TERMS),
                       round(self._elapsed(), 1)]
                if log is not None:
                    log.losses(iteration + 1, losses)
                metrics = {}
                if validation is not None and (iteration + 1) % self.config.validate_every == 0:
                    metrics = self._validate(iteration + 1, validation, log)
                writer.writerow(row + [metrics.get(name, "") for name in VALIDATION_METRICS])
                _show_losses(bar, losses)
                if (iteration + 1) % self.config.checkpoint_every == 0:
                    history.flush()
                    self.save_checkpoint(iteration + 1)
            self.save_checkpoint(end)
        finally:
            bar.close()
            history.close()
            scenes.close()
            if log is not None:
                log.close()
        return end

    def _start_scene_generator(self) -> ProcessScenes | RayScenes:
        """The samples of the iterations to come: a worker process, or Ray tasks with ``ray_address``."""
        if self.ray_address is None:
            return ProcessScenes(self.config, self.network_config, self.start, self.config.iterations)
        address = None if self.ray_address == "local" else self.ray_address
        return RayScenes(self.config, self.network_config, self.start, self.config.iterations, address)

    def _step(self, sample: dict, iteration: int) -> dict[str, float]:
        """One optimiser step on iteration ``iteration``'s sample; returns the loss terms."""
        assert sample["iteration"] == iteration
        # a sample from Ray's object store is read-only: copied then, used in place otherwise
        tensors = {k: torch.from_numpy(np.require(v, requirements="W")).to(self.device)
                   for k, v in sample.items() if k != "iteration"}
        output = self.model(SparseTensor(tensors["features"], tensors["coords"]))
        terms = loss_terms(output, tensors["existence"], tensors["residual"], tensors["orientation"], self.config,
                           tensors["cap_weight"])
        if not torch.isfinite(terms["total"]):
            raise TrainingError(f"the loss is no longer finite at iteration {iteration + 1}; {self._diverged()}")
        self.optimizer.zero_grad(set_to_none=True)
        terms["total"].backward()
        self.optimizer.step()
        self.scheduler.step()
        if self.averaged is not None and iteration + 1 > self.config.averaging_start:
            self.averaged.update_parameters(self.model)
        return {k: v.item() for k, v in terms.items()}

    def _validate(self, iteration: int, scenes, log: MetricsLog | None) -> dict[str, float]:
        """The validation metrics of the model model.pt would hold now, printed and logged."""
        metrics = validate(self.shipped_model(), scenes)
        tqdm.write(f"iteration {iteration}: val AP@25 {metrics['ap25']:.3f}  AP@50 {metrics['ap50']:.3f}  "
                   f"angle {metrics['angle_deg']:.2f} deg  scale err {metrics['scale_err']:.3f}")
        if log is not None:
            log.validation(iteration, {name: metrics[name] for name in VALIDATION_METRICS})
        return metrics

    def shipped_model(self) -> MushroomNet:
        """What model.pt will hold: the weights' running mean once it has begun."""
        return self.averaged.module if self.averaged is not None and self.averaged.n_averaged > 0 else self.model

    def save_checkpoint(self, iteration: int) -> None:
        """Everything a resumed run needs to go on exactly as this one would, written atomically."""
        if not all_finite(self.model):
            raise TrainingError(f"the weights are no longer finite at iteration {iteration}; {self._diverged()}")
        payload = {"model": self.model.state_dict(), "optimizer": self.optimizer.state_dict(),
                   "scheduler": self.scheduler.state_dict(), "torch_rng": torch.get_rng_state(),
                   "iteration": iteration, "elapsed_s": self._elapsed(), "train_config": self.config.to_dict(),
                   "network": self.network_config.to_dict(), "init": self.init,
                   "inference_zoom": self.model.inference_zoom,
                   "average": None if self.averaged is None else self.averaged.state_dict()}
        try:
            write_payload(payload, self.checkpoint_path)
        except WeightsWriteError as error:
            kept = f"the checkpoint of iteration {self.saved_at} is kept" if self.saved_at is not None \
                else "no checkpoint was kept"
            raise TrainingError(f"{error}; {kept}") from None
        self.saved_at = iteration

    def export(self) -> Path:
        """model.pt from the last checkpoint: its weights (their mean, with averaging) and the training
        cost behind them, a fine-tuned model's including the run it started from."""
        state = torch.load(self.checkpoint_path, map_location="cpu", weights_only=False)
        self.model.load_state_dict(state["model"])
        if self.averaged is not None:
            self.averaged.load_state_dict(state["average"])
            self.model.load_state_dict(self.shipped_model().state_dict())
        meta = {"train_config": state["train_config"], "iterations": state["iteration"],
                "train_seconds": state["elapsed_s"], "total_iterations": state["iteration"],
                "total_train_seconds": state["elapsed_s"]}
        if state.get("init"):
            meta["init"] = state["init"]
            meta["total_iterations"] += state["init"]["total_iterations"]
            meta["total_train_seconds"] += state["init"]["total_train_seconds"]
        weights = self.run_dir / "model.pt"
        save_weights(self.model, weights, **meta)
        return weights

    def _elapsed(self) -> float:
        """Training seconds of the run so far, earlier sessions included."""
        return self.elapsed_before + time.perf_counter() - self.session_start

    def _diverged(self) -> str:
        """What to do about a diverged run, and which checkpoint it kept."""
        kept = f"the checkpoint in {self.run_dir} is from iteration {self.saved_at}" if self.saved_at is not None \
            else "no checkpoint was kept"
        return f"start a new run with a smaller learning rate or loss weights ({kept})"


def _trim_history(path: Path, iteration: int) -> None:
    """history.csv as the checkpoint of ``iteration`` left it: rows an interrupted run wrote after its
    last checkpoint are dropped, since the resumed run trains those iterations again."""
    if not path.is_file():
        return
    lines = path.read_text().splitlines(keepends=True)
    kept = lines[:1] + [line for line in lines[1:] if line.split(",", 1)[0].isdigit()
                        and int(line.split(",", 1)[0]) <= iteration]
    if len(kept) < len(lines):
        write_atomically(path, "".join(kept))


def _validation_scenes(config: TrainConfig):
    """The first ``config.validation_scenes`` val50 scenes at the training spacing (None: no validation)."""
    if config.validation_scenes <= 0:
        return None
    from perception.synthetic.dataset import load_preset

    return load_preset("val50", progress=False, limit=config.validation_scenes, spacing=config.scene.spacing)


def _show_losses(bar: tqdm, losses: dict[str, float]) -> None:
    bar.set_postfix(loss=f"{losses['total']:.3f}", ex=f"{losses['existence']:.3f}", res=f"{losses['residual']:.4f}",
                    ori=f"{losses['orientation']:.4f}", refresh=False)
    bar.update(1)


