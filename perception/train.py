"""Training on a fresh synthetic bed per iteration (paper Sec. 4), on CPU or GPU, resumable exactly.

Scene generation runs in a worker process that feeds a bounded queue, so the network and the
generator keep both cores busy. Iteration i always trains on the scene and augmentation drawn from
seed (run seed, i), and a checkpoint holds model, optimiser, schedule and torch RNG state: a
resumed run continues exactly where it stopped.
"""

from __future__ import annotations

import csv
import json
import multiprocessing as mp
import os
import queue as queues
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import rerun as rr
import torch
import torch.nn.functional as F
from torch.optim.swa_utils import AveragedModel
from tqdm import tqdm

from perception.cap import cap_rotation
from perception.encoding import encode
from perception.model import (INFERENCE_ZOOM, LENGTH_UNIT, PRESETS as NETWORK_PRESETS, MushroomNet,
                              NetworkConfig, voxel_features)
from perception.sparse import SparseTensor
from perception.synthetic.scene import SceneConfig, generate_scene


@dataclass(frozen=True)
class TrainConfig:
    """The paper's recipe (Sec. 4) with our augmentations; every field is a CLI flag."""

    iterations: int = 20000
    lr: float = 1e-3
    milestones: tuple[float, ...] = (0.6, 0.85)
    """Fractions of ``iterations`` where the learning rate drops by ``gamma``."""
    gamma: float = 0.1
    weight_existence: float = 1.0
    weight_residual: float = 100.0
    weight_orientation: float = 1.0
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
    """Start from these weights (a model.pt) instead of random ones: fine-tuning with a new loss."""
    zoom: float | None = None
    """The zoom the model is read at (``MushroomNet.inference_zoom``): its weights record it and
    validation reads at it. It belongs with ``scale_jitter``: a network trained on beds scaled by
    1.05-1.35 is read at 1.2. None: ``INFERENCE_ZOOM``, for the default jitter."""
    network: str = "slim"
    seed: int = 0
    checkpoint_every: int = 200
    validate_every: int = 1000
    validation_scenes: int = 5
    queue_size: int = 6
    rotate_z: bool = True
    scale_jitter: tuple[float, float] = (0.9, 1.1)
    point_dropout: tuple[float, float] = (0.0, 0.2)
    tilt_deg: float = 3.0
    """Random tilt of the whole bed, as left by an imperfect bed-plane estimate."""
    noise: float = 0.0005
    """Standard deviation (metres) of Gaussian jitter on the points."""
    scene: SceneConfig = field(default_factory=SceneConfig)

    @property
    def averaging_start(self) -> int | None:
        """The iteration after which each step joins the weights' mean (None: no averaging)."""
        return None if self.average_from is None else int(self.average_from * self.iterations)

    def to_dict(self) -> dict:
        values = asdict(self)
        values["scene"] = {k: v for k, v in values["scene"].items() if k != "sensor"}
        return values


def iteration_seed(run_seed: int, iteration: int) -> int:
    return int(np.random.SeedSequence([run_seed, iteration]).generate_state(1)[0])


def augmented_sample(config: TrainConfig, iteration: int) -> dict[str, np.ndarray]:
    """Points and per-point targets of iteration ``iteration``'s scene after augmentation."""
    seed = iteration_seed(config.seed, iteration)
    scene = generate_scene(seed, config.scene)
    rng = np.random.default_rng(seed + 1)
    rotation = np.eye(3)
    if config.rotate_z:
        angle = rng.uniform(0, 2 * np.pi)
        c, s = np.cos(angle), np.sin(angle)
        rotation = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
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
    return {"iteration": iteration, "points": points.astype(np.float32), "existence": targets.existence,
            "residual": targets.residual, "orientation": targets.orientation,
            "instance": np.where(targets.existence > 0, scene.instance[keep], -1).astype(np.int64)}


def _differences(saved: dict, asked: dict, prefix: str = "") -> str:
    """'name: saved there, asked here' for each field that differs, nested fields as scene.voxel."""
    found = []
    for name in sorted(set(saved) | set(asked)):
        there, here = saved.get(name), asked.get(name)
        if isinstance(there, dict) and isinstance(here, dict):
            found.append(_differences(there, here, f"{prefix}{name}."))
        elif there != here:
            found.append(f"{prefix}{name}: {there} there, {here} here")
    return ", ".join(f for f in found if f)


def _all_finite(model: torch.nn.Module) -> bool:
    """Whether every weight and running statistic is a finite number (a diverged run's are not)."""
    return all(torch.isfinite(value).all() for value in model.state_dict().values() if value.is_floating_point())


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


def _next_sample(samples: mp.Queue, producer: mp.Process, iteration: int) -> dict:
    """The producer's next sample; an error, not a wait without end, if the producer died or hangs."""
    waited = 0.0
    while True:
        try:
            return samples.get(timeout=5)
        except queues.Empty:
            waited += 5
            if not producer.is_alive():
                raise TrainingError(f"the scene generator stopped (exit code {producer.exitcode}) before "
                                    f"iteration {iteration + 1}; its error is printed above") from None
            if waited >= SAMPLE_PATIENCE_S:
                raise TrainingError(f"no scene for iteration {iteration + 1} in {waited:.0f} s: the scene "
                                    "generator is stuck") from None


def _producer(config: TrainConfig, network: NetworkConfig, start: int, stop: int, queue: mp.Queue) -> None:
    """Worker process: scenes, targets and network input for iterations ``start`` to ``stop``, in order."""
    torch.set_num_threads(1)
    for iteration in range(start, stop):
        coords, existence, residual, orientation, centroids, cap_weight = voxel_targets(
            augmented_sample(config, iteration), network.voxel)
        queue.put({"iteration": iteration, "coords": coords.numpy(), "features": voxel_features(network, centroids),
                   "existence": existence.numpy(), "residual": residual.numpy(), "orientation": orientation.numpy(),
                   "cap_weight": cap_weight.numpy()})


def voxel_targets(sample: dict, voxel: float):
    """Voxels and their targets (means over each voxel's points): coords, existence, residual
    (LENGTH_UNITs), orientation, the voxel centroids (metres, numpy), and the cap-balancing weight
    (0 off caps; 1 / the voxels of the voxel's cap, scaled to mean 1 over cap voxels)."""
    from perception.detect import network_input

    coords, point_to_voxel, centroids = network_input(sample["points"], voxel)
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
    terms = {"existence": (voxel_weight * bce).mean(),
             "residual": F.mse_loss(output[:, 1:4], residual),
             "orientation": (_weighted_mse(output[:, 4], orientation, cap_weight)
                             if config.orientation_on_caps or config.cap_balance
                             else F.mse_loss(output[:, 4], orientation))}
    terms["total"] = (config.weight_existence * terms["existence"] + config.weight_residual * terms["residual"]
                      + config.weight_orientation * terms["orientation"])
    return terms


def _weighted_mse(prediction: torch.Tensor, target: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    return (weight * (prediction - target) ** 2).sum() / weight.sum().clamp(min=1.0)


def _atomic_save(payload: dict, path: Path) -> None:
    tmp = path.with_name(path.name + ".partial")
    torch.save(payload, tmp)
    os.replace(tmp, path)


def validate(model: MushroomNet, scenes) -> dict[str, float]:
    """The metrics of ``model`` read as it will be (perception.detect, at its own zoom)."""
    from perception.detect import evaluate_on_scenes

    metrics = evaluate_on_scenes(model, scenes, methods=("meanshift",))["meanshift"].as_dict()
    model.train()
    return metrics


def train(config: TrainConfig, run_dir: Path, resume: bool = False, device: str | None = None,
          progress: bool = True, rerun: bool = True, stop_at: int | None = None,
          max_minutes: float | None = None) -> Path | None:
    """Train (or continue training) into ``run_dir``; returns the final weights, or None when the run
    stopped early (at iteration ``stop_at`` or after ``max_minutes``) with a checkpoint to resume."""
    device = _resolve_device(device)
    checkpoint_path = run_dir / "checkpoint.pt"
    if resume and not checkpoint_path.is_file():
        raise ValueError(f"no checkpoint to resume in {run_dir}: check --out, or drop --resume to start a new run")
    run_dir.mkdir(parents=True, exist_ok=True)
    network_config = NETWORK_PRESETS[config.network]
    torch.manual_seed(config.seed)
    model = MushroomNet(network_config, point_spacing=config.scene.voxel,
                        inference_zoom=INFERENCE_ZOOM if config.zoom is None else config.zoom).to(device)
    init = None
    if config.init_weights and not resume:
        initial, base = load_weights(Path(config.init_weights), device)
        if initial.config != network_config:
            raise ValueError(f"{config.init_weights} holds a different network than {config.network!r}; "
                             "pass the --network it was trained with")
        model.load_state_dict(initial.state_dict())
        init = _provenance(Path(config.init_weights), base)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.lr)
    milestones = [int(f * config.iterations) for f in config.milestones]
    scheduler = torch.optim.lr_scheduler.MultiStepLR(optimizer, milestones, config.gamma)
    averaged = AveragedModel(model, use_buffers=True) if config.average_from is not None else None
    start, elapsed_before = 0, 0.0
    if resume:
        state = _load_checkpoint(checkpoint_path, device)
        # a checkpoint without a field ran with its default
        differ = _differences({**TrainConfig().to_dict(), **state["train_config"]}, config.to_dict())
        if differ:
            raise ValueError(f"{checkpoint_path} was made with a different configuration ({differ}); "
                             "resume with the same flags or use a new run folder")
        model.load_state_dict(state["model"])
        model.inference_zoom = state.get("inference_zoom", UNRECORDED_ZOOM)
        if averaged is not None:
            averaged.module.inference_zoom = model.inference_zoom
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
        torch.set_rng_state(state["torch_rng"])
        if averaged is not None:
            averaged.load_state_dict(state["average"])
        start, elapsed_before = state["iteration"], state["elapsed_s"]
        init = state.get("init")
    else:
        (run_dir / "history.csv").unlink(missing_ok=True)
    (run_dir / "train_config.json").write_text(json.dumps(config.to_dict(), indent=1))

    validation = None
    if config.validation_scenes > 0:
        from perception.synthetic.dataset import load_preset
        validation = load_preset("val50", progress=False, limit=config.validation_scenes,
                                 spacing=config.scene.voxel)

    rec = None
    if rerun:
        rec = rr.RecordingStream("mushroom-pose-train")
        rec.save(run_dir / f"train_from_{start:06d}.rrd")

    context = mp.get_context("fork")
    queue = context.Queue(maxsize=config.queue_size)
    producer = context.Process(target=_producer, args=(config, network_config, start, config.iterations, queue),
                               daemon=True)
    producer.start()
    history = open(run_dir / "history.csv", "a", newline="")
    writer = csv.writer(history)
    if start == 0:
        writer.writerow(["iteration", "lr", "total", "existence", "residual", "orientation", "seconds",
                         "val_ap25", "val_ap50", "val_angle_deg", "val_scale_err"])
    model.train()
    bar = tqdm(total=config.iterations, initial=start, desc="train", unit="it", disable=not progress,
               dynamic_ncols=True)
    session_start = time.perf_counter()

    saved_at = start if resume else None

    def shipped_model() -> MushroomNet:
        """What model.pt will hold: the weights' running mean once it has begun."""
        return averaged.module if averaged is not None and averaged.n_averaged > 0 else model

    def save(iteration: int) -> None:
        nonlocal saved_at
        if not _all_finite(model):
            raise TrainingError(f"the weights are no longer finite at iteration {iteration}; {diverged()}")
        _atomic_save({"model": model.state_dict(), "optimizer": optimizer.state_dict(),
                      "scheduler": scheduler.state_dict(), "torch_rng": torch.get_rng_state(),
                      "iteration": iteration, "elapsed_s": elapsed_before + time.perf_counter() - session_start,
                      "train_config": config.to_dict(), "network": network_config.to_dict(), "init": init,
                      "inference_zoom": model.inference_zoom,
                      "average": None if averaged is None else averaged.state_dict()},
                     checkpoint_path)
        saved_at = iteration

    def diverged() -> str:
        kept = f"the checkpoint in {run_dir} is from iteration {saved_at}" if saved_at is not None else \
            "no checkpoint was kept"
        return f"start a new run with a smaller learning rate or loss weights ({kept})"

    end = config.iterations if stop_at is None else min(stop_at, config.iterations)
    deadline = None if max_minutes is None else session_start + 60 * max_minutes
    try:
        for iteration in range(start, end):
            if deadline is not None and time.perf_counter() > deadline:
                end = iteration
                break
            sample = _next_sample(queue, producer, iteration)
            assert sample["iteration"] == iteration
            tensors = {k: torch.from_numpy(v).to(device) for k, v in sample.items() if k != "iteration"}
            output = model(SparseTensor(tensors["features"], tensors["coords"]))
            terms = loss_terms(output, tensors["existence"], tensors["residual"], tensors["orientation"], config,
                               tensors["cap_weight"])
            if not torch.isfinite(terms["total"]):
                raise TrainingError(f"the loss is no longer finite at iteration {iteration + 1}; {diverged()}")
            optimizer.zero_grad(set_to_none=True)
            terms["total"].backward()
            optimizer.step()
            scheduler.step()
            if averaged is not None and iteration + 1 > config.averaging_start:
                averaged.update_parameters(model)
            values = {k: v.item() for k, v in terms.items()}
            row = [iteration + 1, scheduler.get_last_lr()[0], values["total"], values["existence"],
                   values["residual"], values["orientation"],
                   round(elapsed_before + time.perf_counter() - session_start, 1)]
            if rec is not None:
                rec.set_time("iteration", sequence=iteration + 1)
                for name, value in values.items():
                    rec.log(f"stats/loss/{name}", rr.Scalars(value))
            metrics = {}
            if validation is not None and (iteration + 1) % config.validate_every == 0:
                metrics = validate(shipped_model(), validation)
                tqdm.write(f"iteration {iteration + 1}: val AP@25 {metrics['ap25']:.3f}  AP@50 {metrics['ap50']:.3f}  "
                           f"angle {metrics['angle_deg']:.2f} deg  scale err {metrics['scale_err']:.3f}")
                if rec is not None:
                    for name in ("ap25", "ap50", "angle_deg", "scale_err"):
                        rec.log(f"stats/val/{name}", rr.Scalars(metrics[name]))
            writer.writerow(row + [metrics.get("ap25", ""), metrics.get("ap50", ""), metrics.get("angle_deg", ""),
                                   metrics.get("scale_err", "")])
            bar.set_postfix(loss=f"{values['total']:.3f}", ex=f"{values['existence']:.3f}",
                            res=f"{values['residual']:.4f}", ori=f"{values['orientation']:.4f}", refresh=False)
            bar.update(1)
            if (iteration + 1) % config.checkpoint_every == 0:
                history.flush()
                save(iteration + 1)
        save(end)
    finally:
        bar.close()
        history.close()
        producer.terminate()
        if rec is not None:
            rec.flush()
    if end < config.iterations:
        return None
    weights = run_dir / "model.pt"
    state = torch.load(checkpoint_path, map_location="cpu", weights_only=False)
    model.load_state_dict(state["model"])
    if averaged is not None:
        averaged.load_state_dict(state["average"])
        model.load_state_dict(shipped_model().state_dict())
    meta = {"train_config": state["train_config"], "iterations": state["iteration"],
            "train_seconds": state["elapsed_s"], "total_iterations": state["iteration"],
            "total_train_seconds": state["elapsed_s"]}
    if state.get("init"):
        # a fine-tuned model's cost includes the run it started from
        meta["init"] = state["init"]
        meta["total_iterations"] += state["init"]["total_iterations"]
        meta["total_train_seconds"] += state["init"]["total_train_seconds"]
    save_weights(model, weights, **meta)
    return weights


def _provenance(path: Path, meta: dict) -> dict:
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
    """Every training run behind a weights file (a ``_provenance`` node): [seconds, iterations] by the
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
    if len(paths) < 2:
        raise ValueError("averaging needs two weights files or more")
    loaded = [load_weights(Path(path)) for path in paths]
    first = loaded[0][0]
    for path, (model, _) in zip(paths[1:], loaded[1:]):
        if model.config != first.config or model.point_spacing != first.point_spacing:
            raise ValueError(f"{path} holds a different network than {paths[0]}; only models of one network average")
        if model.inference_zoom != first.inference_zoom:
            raise ValueError(f"{path} is read at zoom {model.inference_zoom}, {paths[0]} at {first.inference_zoom}")
    nodes = [_provenance(Path(path), meta) for path, (_, meta) in zip(paths, loaded)]
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


UNRECORDED_ZOOM = 1.1
"""The zoom weights and checkpoints without an ``inference_zoom`` entry are read at: the zoom such
models are tuned for."""


def save_weights(model: MushroomNet, path: Path, **meta) -> None:
    """The shipped form of a model: its weights, its network config and how it was made."""
    _atomic_save({**meta, "model": model.state_dict(), "network": model.config.to_dict(),
                  "point_spacing": model.point_spacing, "inference_zoom": model.inference_zoom}, Path(path))


def load_weights(path: Path, device: str = "cpu") -> tuple[MushroomNet, dict]:
    """A trained network and its metadata from a weights file (model.pt) or a checkpoint."""
    try:
        state = torch.load(path, map_location=device, weights_only=False)
        network = NetworkConfig.from_dict(state["network"])
        spacing = state.get("point_spacing") or ((state.get("train_config") or {}).get("scene") or {}).get("voxel")
        model = MushroomNet(network, point_spacing=spacing,
                            inference_zoom=state.get("inference_zoom", UNRECORDED_ZOOM)).to(device)
        model.load_state_dict(state["model"])
    except FileNotFoundError:
        raise
    except Exception as error:
        raise ValueError(f"{path} is not a mushroom-pose weights file ({type(error).__name__})") from None
    if not _all_finite(model):
        raise ValueError(f"{path} holds weights that are not finite numbers (a training run that diverged)")
    model.eval()
    return model, {k: v for k, v in state.items() if k not in ("model", "optimizer", "scheduler", "torch_rng")}

