"""Evaluation of cap detections (docs/DESIGN.md section 4): exact oriented-box IoU, AP, scale and axis errors.

A cap's box is ``cap_box(center, R, scales)``. IoU is the exact volume of the intersection of two
oriented boxes over their union. AP pools all detections of all scenes, sorts them by score and
matches them greedily one-to-one to the ground truth of their own scene (VOC all-point interpolation).
Scale and orientation errors are taken over the matches at IoU >= 0.25, as in the paper.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from perception.cap import Caps, OrientedBox, cap_box
from perception.detect import LIVE_READINGS, find_caps, predict
from perception.instances import ClusterConfig
from perception.model import MushroomNet

ORIENTATION_IOU = 0.25
"""IoU threshold whose matches give the scale and orientation errors."""

_EDGES = np.array([(i, i | 1 << b) for b in (2, 1, 0) for i in range(8) if not i >> b & 1])
"""The 12 edges of a box as pairs of ``OrientedBox.vertices`` indices differing in one bit."""
_REL_TOL = 1e-9
"""Tolerance of the inside tests, relative to the size of the boxes."""


def _to_local(box: OrientedBox, points: np.ndarray) -> np.ndarray:
    """Box-frame coordinates R^T (p - c) of parent-frame points (..., 3)."""
    return (points - box.center) @ box.rotation


def _inside(box: OrientedBox, points: np.ndarray, tol: float) -> np.ndarray:
    q = _to_local(box, points)
    return np.all((q >= box.lo - tol) & (q <= box.hi + tol), axis=-1)


def _edge_face_points(a: OrientedBox, b: OrientedBox, tol: float) -> np.ndarray:
    """Points where the 12 edges of ``a`` cross the 6 face planes of ``b``, shape (n, 3)."""
    va = a.vertices()
    start, end = va[_EDGES[:, 0]], va[_EDGES[:, 1]]
    q0 = _to_local(b, start)
    dq = _to_local(b, end) - q0
    bounds = np.stack([b.lo, b.hi])
    crosses = np.abs(dq) > tol
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (bounds[None] - q0[:, None]) / np.where(crosses, dq, 1.0)[:, None]
    valid = crosses[:, None] & (t >= 0.0) & (t <= 1.0)
    points = start[:, None, None] + t[..., None] * (end - start)[:, None, None]
    return points[valid]


def _bounding_sphere(box: OrientedBox) -> tuple[np.ndarray, float]:
    return box.center + box.rotation @ (0.5 * (box.lo + box.hi)), 0.5 * float(np.linalg.norm(box.hi - box.lo))


def intersection_volume(a: OrientedBox, b: OrientedBox) -> float:
    """Exact volume of the intersection of two oriented boxes.

    The intersection is a convex polyhedron whose vertices are among: corners of either box inside the
    other, and crossings of either box's edges with the other's face planes that lie inside both boxes.
    Its volume is that of the convex hull of these points.
    """
    (ca, ra), (cb, rb) = _bounding_sphere(a), _bounding_sphere(b)
    if np.linalg.norm(ca - cb) >= ra + rb:
        return 0.0
    tol = _REL_TOL * max(ra, rb)
    va, vb = a.vertices(), b.vertices()
    a_in_b, b_in_a = _inside(b, va, tol), _inside(a, vb, tol)
    if a_in_b.all():
        return a.volume
    if b_in_a.all():
        return b.volume
    crossings = np.concatenate([_edge_face_points(a, b, tol), _edge_face_points(b, a, tol)])
    crossings = crossings[_inside(a, crossings, tol) & _inside(b, crossings, tol)]
    points = np.concatenate([va[a_in_b], vb[b_in_a], crossings])
    if len(points) < 4:
        return 0.0
    try:
        return float(ConvexHull(points).volume)
    except QhullError:
        return 0.0


def box_iou(a: OrientedBox, b: OrientedBox) -> float:
    """Exact IoU of two oriented boxes: intersection volume / union volume."""
    inter = intersection_volume(a, b)
    union = a.volume + b.volume - inter
    return float(np.clip(inter / union, 0.0, 1.0)) if union > 0 else 0.0


def align_spin(pred_rotation: np.ndarray, gt_rotation: np.ndarray) -> np.ndarray:
    """The predicted rotation re-spun about its own cap axis to best match the ground truth's spin.

    A cap is rotationally symmetric, so a prediction's spin about its axis carries no information, but
    its box is not symmetric (a square spun by 45 degrees overlaps itself by only 83%). The IoU must
    not depend on that arbitrary spin, so the predicted box keeps its axis u and takes as x axis the
    ground truth's x axis projected onto the plane orthogonal to u (the ground truth's y axis when that
    projection vanishes). Broadcasts over leading dimensions: (..., 3, 3).
    """
    pred_rotation, gt_rotation = np.broadcast_arrays(np.asarray(pred_rotation, np.float64),
                                                     np.asarray(gt_rotation, np.float64))
    u = pred_rotation[..., :, 2]

    def project(v: np.ndarray) -> np.ndarray:
        return v - np.sum(v * u, axis=-1, keepdims=True) * u

    x = project(gt_rotation[..., :, 0])
    norm = np.linalg.norm(x, axis=-1, keepdims=True)
    degenerate = norm < 1e-6
    if np.any(degenerate):
        x = np.where(degenerate, project(gt_rotation[..., :, 1]), x)
        norm = np.linalg.norm(x, axis=-1, keepdims=True)
    x = x / norm
    return np.stack([x, np.cross(u, x), u], axis=-1)


def _box_spheres(caps: Caps) -> tuple[np.ndarray, np.ndarray]:
    """Bounding-sphere centres (K, 3) and radii (K,) of the cap boxes (invariant to spin)."""
    scales = np.asarray(caps.scales, np.float64).reshape(-1, 3)
    axes = np.asarray(caps.rotations, np.float64).reshape(-1, 3, 3)[:, :, 2]
    centers = np.asarray(caps.centers, np.float64).reshape(-1, 3) + 0.5 * scales[:, 2:] * axes
    radii = 0.5 * np.linalg.norm(scales * [2.0, 2.0, 1.0], axis=1)
    return centers, radii


def iou_matrix(pred: Caps, gt: Caps) -> np.ndarray:
    """IoU (M, K) of each predicted cap box (spin aligned to the ground truth) with each true cap box."""
    ious = np.zeros((len(pred), len(gt)))
    if ious.size == 0:
        return ious
    (pc, pr), (gc, gr) = _box_spheres(pred), _box_spheres(gt)
    close = np.linalg.norm(pc[:, None] - gc[None], axis=2) < pr[:, None] + gr[None]
    for i, j in zip(*np.nonzero(close)):
        rotation = align_spin(pred.rotations[i], gt.rotations[j])
        ious[i, j] = box_iou(cap_box(pred.centers[i], rotation, pred.scales[i]),
                             cap_box(gt.centers[j], gt.rotations[j], gt.scales[j]))
    return ious


def average_precision(scores: np.ndarray, is_tp: np.ndarray, n_gt: int) -> float:
    """All-point interpolated AP (VOC 2010+) of detections ranked by score (stable, descending).

    Precision is made non-increasing from the right, then AP = sum (r_i - r_{i-1}) p_i. Without ground
    truth, AP is 1.0 when there are also no detections (nothing to find, nothing wrongly found) and 0.0
    otherwise (every detection is a false positive).
    """
    scores = np.asarray(scores, np.float64).ravel()
    is_tp = np.asarray(is_tp, bool).ravel()
    if n_gt == 0:
        return 1.0 if len(scores) == 0 else 0.0
    if len(scores) == 0:
        return 0.0
    tp = np.cumsum(is_tp[np.argsort(-scores, kind="stable")])
    precision = tp / np.arange(1, len(tp) + 1)
    recall = tp / n_gt
    envelope = np.maximum.accumulate(precision[::-1])[::-1]
    return float(np.sum(np.diff(recall, prepend=0.0) * envelope))


def _match(order: np.ndarray, scene_of: np.ndarray, index_of: np.ndarray, ious: list[np.ndarray],
           threshold: float) -> np.ndarray:
    """Greedy matching in ``order``: ground-truth index matched by each pooled detection, -1 if none."""
    matched = [np.zeros(iou.shape[1], bool) for iou in ious]
    match = np.full(len(scene_of), -1)
    for d in order:
        scene, row = scene_of[d], ious[scene_of[d]][index_of[d]]
        if row.size == 0:
            continue
        j = int(np.argmax(np.where(matched[scene], -1.0, row)))
        if not matched[scene][j] and row[j] >= threshold:
            matched[scene][j] = True
            match[d] = j
    return match


@dataclass(frozen=True)
class EvalResult:
    """Detection quality over a set of scenes.

    ``scale_err`` = |s_pred - s_true| / s_pred (the paper's form), ``scale_err_true`` divides by s_true;
    s is the cap radius (mean of the first two semi-axes). ``cosine`` is the mean cosine between the
    predicted and true cap axes, and ``angle_deg`` its angle, arccos of that mean: the paper's "theta
    error" is that (its Table 4 pairs 0.9643 / 15.35, 0.9973 / 4.22 and 0.9828 / 10.63 degrees). A few
    caps far off weigh on it much more than on ``angle_deg_mean``, the mean of the caps' own angles.
    These are over the matches at IoU >= 0.25 (medians alongside), nan without matches. ``ap`` holds
    (threshold, AP) for every threshold evaluated.
    """

    ap25: float
    ap50: float
    scale_err: float
    scale_err_true: float
    cosine: float
    angle_deg: float
    angle_deg_mean: float
    scale_err_median: float
    angle_deg_median: float
    n_gt: int
    n_pred: int
    n_matched: int
    ap: tuple[tuple[float, float], ...] = ()

    def as_dict(self) -> dict[str, float | int]:
        out: dict[str, float | int] = {
            "ap25": float(self.ap25), "ap50": float(self.ap50),
            "scale_err": float(self.scale_err), "cosine": float(self.cosine),
            "angle_deg": float(self.angle_deg), "n_gt": int(self.n_gt), "n_pred": int(self.n_pred),
            "scale_err_true": float(self.scale_err_true),
            "angle_deg_mean": float(self.angle_deg_mean), "scale_err_median": float(self.scale_err_median),
            "angle_deg_median": float(self.angle_deg_median), "n_matched": int(self.n_matched),
        }
        for threshold, ap in self.ap:
            out.setdefault(f"ap{round(100 * threshold)}", float(ap))
        return out


def _stat(values: np.ndarray, fn) -> float:
    return float(fn(values)) if len(values) else float("nan")


def _angle_of_mean_cosine(cosine: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(np.mean(cosine), -1.0, 1.0))))


def evaluate(preds: list[Caps], gts: list[Caps],
             thresholds: tuple[float, ...] = (0.25, 0.5)) -> EvalResult:
    """AP at each IoU threshold (always including 0.25 and 0.5) and scale/axis errors of the matches."""
    if len(preds) != len(gts):
        raise ValueError(f"{len(preds)} predicted scenes but {len(gts)} ground-truth scenes")
    ious = [iou_matrix(p, g) for p, g in zip(preds, gts)]
    n_gt = sum(len(g) for g in gts)
    scene_of = np.concatenate([np.full(len(p), k) for k, p in enumerate(preds)] + [np.zeros(0, int)])
    index_of = np.concatenate([np.arange(len(p)) for p in preds] + [np.zeros(0, int)])
    scores = np.concatenate([p.score_array() for p in preds] + [np.zeros(0)])
    order = np.argsort(-scores, kind="stable")

    all_thresholds = sorted({*map(float, thresholds), ORIENTATION_IOU, 0.5})
    matches = {t: _match(order, scene_of, index_of, ious, t) for t in all_thresholds}
    ap = {t: average_precision(scores, m >= 0, n_gt) for t, m in matches.items()}

    match = matches[ORIENTATION_IOU]
    dets = np.nonzero(match >= 0)[0]
    if len(dets):
        pred_scales = np.array([preds[scene_of[d]].scales[index_of[d]] for d in dets], np.float64)
        gt_scales = np.array([gts[scene_of[d]].scales[match[d]] for d in dets], np.float64)
        pred_axes = np.array([preds[scene_of[d]].rotations[index_of[d]][:, 2] for d in dets], np.float64)
        gt_axes = np.array([gts[scene_of[d]].rotations[match[d]][:, 2] for d in dets], np.float64)
    else:
        pred_scales = gt_scales = pred_axes = gt_axes = np.zeros((0, 3))
    s_pred, s_true = pred_scales[:, :2].mean(axis=1), gt_scales[:, :2].mean(axis=1)
    scale_err = np.abs(s_pred - s_true) / s_pred
    scale_err_true = np.abs(s_pred - s_true) / s_true
    cosine = np.sum(pred_axes * gt_axes, axis=1) / (
        np.linalg.norm(pred_axes, axis=1) * np.linalg.norm(gt_axes, axis=1))
    angle = np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))

    return EvalResult(
        ap25=ap[0.25], ap50=ap[0.5],
        scale_err=_stat(scale_err, np.mean), scale_err_true=_stat(scale_err_true, np.mean),
        cosine=_stat(cosine, np.mean), angle_deg=_stat(cosine, _angle_of_mean_cosine),
        angle_deg_mean=_stat(angle, np.mean),
        scale_err_median=_stat(scale_err, np.median), angle_deg_median=_stat(angle, np.median),
        n_gt=int(n_gt), n_pred=int(len(scores)), n_matched=int(len(dets)),
        ap=tuple((t, ap[t]) for t in all_thresholds),
    )


def detection_outcomes(preds: list[Caps], gts: list[Caps], threshold: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """Every detection's score and whether it matches a true cap at IoU >= ``threshold`` (greedy by
    score over the pooled scenes, as AP matches): what precision, recall and calibration are read from."""
    scores, matched = matched_truth(preds, gts, threshold)
    return scores, matched >= 0


def matched_truth(preds: list[Caps], gts: list[Caps], threshold: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """Every detection's score (the scenes' detections one after another) and the index in its scene's
    truth of the cap it matches at IoU >= ``threshold`` (-1: none), matched as ``detection_outcomes``."""
    ious = [iou_matrix(p, g) for p, g in zip(preds, gts)]
    scene_of = np.concatenate([np.full(len(p), k) for k, p in enumerate(preds)] + [np.zeros(0, int)])
    index_of = np.concatenate([np.arange(len(p)) for p in preds] + [np.zeros(0, int)])
    scores = np.concatenate([p.score_array() for p in preds] + [np.zeros(0)])
    return scores, _match(np.argsort(-scores, kind="stable"), scene_of, index_of, ious, threshold)


# ---- the detector on synthetic scenes

def evaluate_on_scenes(model: MushroomNet, scenes, methods=("meanshift", "dbscan"), height: str = "free",
                       axis: str = "surface", progress: bool = False, zoom: float | None = None,
                       use_ray: bool = False, ray_address: str | None = None, radius: str = "rim",
                       readings: int = LIVE_READINGS) -> dict:
    """The paper's metrics of ``model`` on synthetic scenes, per clustering method (each scene read
    ``readings`` times at ``zoom``, by default the model's own); with ``use_ray`` each scene is read by a
    Ray task (the same caps: a scene's reading depends on the scene and the model alone)."""
    from tqdm import tqdm

    scenes = list(scenes)
    items = [(scene, methods, height, axis, zoom, radius, readings) for scene in scenes]
    if use_ray:
        from common.distributed import ray_map

        read = ray_map(scene_caps, items, ray_address, shared=(model,))
    else:
        read = (scene_caps(model, *item) for item in items)
    preds: dict[str, list] = {m: [] for m in methods}
    gts = []
    for found, truth in tqdm(read, desc="evaluating", unit="scene", total=len(items), disable=not progress,
                             leave=False):
        for method in methods:
            preds[method].append(found[method])
        gts.append(truth)
    return {method: evaluate(preds[method], gts) for method in methods}


def scene_caps(model: MushroomNet, scene, methods, height: str, axis: str, zoom: float | None, radius: str = "rim",
               readings: int = LIVE_READINGS):
    """A synthetic scene's caps per clustering method, and its visible ground truth; a noisy scene is
    smoothed first, as ``detect`` smooths a cloud (``perception.surface_noise``)."""
    from perception.surface_noise import smoothed

    points = smoothed(scene.points, model.point_spacing)[0]
    prediction = predict(model, points, zoom=zoom, readings=readings)
    found = {}
    for method in methods:
        caps = find_caps(prediction, model.config.voxel, ClusterConfig(method=method), height, axis, radius=radius,
                         points=points)[1]
        found[method] = model.calibration.applied(caps, rim_radii=radius == "rim")
    return found, visible_truth(scene)


def visible_truth(scene):
    """A synthetic scene's caps that count as ground truth (``ground_truth_mask``)."""
    from perception.synthetic.dataset import ground_truth_mask

    visible = ground_truth_mask(scene)
    return Caps(scene.centers[visible], scene.rotations[visible], scene.scales[visible])
