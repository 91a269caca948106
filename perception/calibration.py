"""What a model's cap scores and rim diameters mean, measured on synthetic beds with full truth.

A raw score is the mean existence over a cap's voxels: it ranks caps well but is no probability (caps
scored 0.6 are right about half the time, caps over 0.9 nearly always). ``Calibration`` maps it to
what it means: a score of p is a cap found at IoU >= 0.25 with frequency about p (an isotonic fit,
made strictly increasing so that the caps' ranking, and so AP, stays). It can also map measured rim
diameters to the synthetic truth (a line fit of true on measured diameters of the domed caps found);
the shipped model keeps its diameters as measured, since on the real cloud such a line makes caps read
larger than their labels (model card). It is fit on beds of every family of
``perception.synthetic.families`` drawn from ``CALIBRATION_SEED``, apart from the suite's and the
benches' beds (``perception.calibration_fit``), and stored in the weights file; ``perception.detect``
applies it.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from perception.cap import Caps

CALIBRATION_SEED = 2026_1207
"""Base seed of the calibration beds (family k draws from the k-th seed derived from it), apart from
the suite's ``SUITE_SEED``."""
SCORE_STEP = 1e-4
"""The least rise between the calibrated scores of two raw scores a knot apart: an isotonic fit is
flat over stretches, and ties there would lose the ranking the raw scores hold."""


@dataclass(frozen=True)
class Calibration:
    raw_scores: tuple[float, ...] = ()
    """Knots of the score map (raw score), increasing; none: scores are kept as they are."""
    calibrated_scores: tuple[float, ...] = ()
    """The score each knot maps to, strictly increasing; scores between knots are interpolated and
    scores outside the knots take the end knots' values."""
    diameter_scale: float = 1.0
    diameter_offset_mm: float = 0.0
    """The calibrated rim diameter: ``diameter_scale`` times the measured one plus this."""

    def __post_init__(self) -> None:
        if len(self.raw_scores) != len(self.calibrated_scores):
            raise ValueError("a score map needs one calibrated score per knot")
        if np.any(np.diff(self.raw_scores) <= 0) or np.any(np.diff(self.calibrated_scores) <= 0):
            raise ValueError("a score map must be strictly increasing")
        if not self.diameter_scale > 0:
            raise ValueError(f"the diameter scale must be positive, got {self.diameter_scale}")

    def scores(self, raw: np.ndarray) -> np.ndarray:
        """Calibrated scores of raw ones."""
        raw = np.asarray(raw, np.float64)
        return np.interp(raw, self.raw_scores, self.calibrated_scores) if self.raw_scores else raw

    def applied(self, caps: Caps, rim_radii: bool = True) -> Caps:
        """The caps with calibrated scores and, when their radii are rim radii (the diameter line is fit
        on those), calibrated radii; heights and poses as measured."""
        scores = None if caps.scores is None else self.scores(caps.scores)
        if not rim_radii or (self.diameter_scale, self.diameter_offset_mm) == (1.0, 0.0):
            return replace(caps, scores=scores)
        scales = np.array(caps.scales, np.float64, copy=True)
        rim_mm = 2000 * scales[:, :2]
        scales[:, :2] = np.maximum(self.diameter_scale * rim_mm + self.diameter_offset_mm, 1.0) / 2000
        return replace(caps, scales=scales, scores=scores)

    def to_dict(self) -> dict:
        return {"raw_scores": list(self.raw_scores), "calibrated_scores": list(self.calibrated_scores),
                "diameter_scale": self.diameter_scale, "diameter_offset_mm": self.diameter_offset_mm}

    @classmethod
    def from_dict(cls, values: dict | None) -> Calibration:
        values = values or {}
        return cls(tuple(values.get("raw_scores", ())), tuple(values.get("calibrated_scores", ())),
                   float(values.get("diameter_scale", 1.0)), float(values.get("diameter_offset_mm", 0.0)))


UNCALIBRATED = Calibration()


def fit_diameters(measured_mm: np.ndarray, true_mm: np.ndarray) -> tuple[float, float]:
    """Scale and offset of the least-squares line of true diameters on measured ones."""
    if len(measured_mm) < 2 or np.ptp(measured_mm) == 0:
        raise ValueError("fitting diameters needs caps of at least two sizes")
    scale, offset = np.polyfit(np.asarray(measured_mm, np.float64), np.asarray(true_mm, np.float64), 1)
    return float(scale), float(offset)


def fit_scores(raw: np.ndarray, correct: np.ndarray) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Knots of the isotonic fit of ``correct`` (0/1) on raw scores, raised by at least ``SCORE_STEP``
    from knot to knot so that the map is strictly increasing."""
    from sklearn.isotonic import IsotonicRegression

    raw, correct = np.asarray(raw, np.float64), np.asarray(correct, np.float64)
    if len(raw) < 2 or np.ptp(raw) == 0:
        raise ValueError("fitting scores needs detections of at least two scores")
    fit = IsotonicRegression(y_min=0.0, y_max=1.0, out_of_bounds="clip").fit(raw, correct)
    knots = np.asarray(fit.X_thresholds_, np.float64)
    values = np.asarray(fit.y_thresholds_, np.float64)
    # each knot at least SCORE_STEP over the one before, the top ones pressed down to stay under 1
    rising = np.maximum.accumulate(values - SCORE_STEP * np.arange(len(values))) + SCORE_STEP * np.arange(len(values))
    rising = np.minimum(rising, 1.0 - SCORE_STEP * np.arange(len(values))[::-1])
    keep = np.concatenate([[True], np.diff(knots) > 0])
    return tuple(knots[keep].tolist()), tuple(rising[keep].tolist())
