"""Steps b-d of :func:`identification.nls.fit_nls`: memory features, normalisation on the training
block, and the affine start (a weighted ridge fit of z on the features)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from identification.features import (
    BoucWenFeatures,
    FeatureMap,
    PastInputFeatures,
    PlayFeatures,
    default_bouc_wen_levels,
    default_play_radii,
)
from identification.nls.training_settings import TrainingSettings

__all__ = ["Normalised", "feature_map_for", "normalisation", "ridge_skip"]


def feature_map_for(settings: TrainingSettings, u_range: tuple[float, float]) -> FeatureMap:
    """The memory feature map of ``settings`` over the input range ``u_range`` (V)."""
    rest = settings.initial_input
    if settings.features == "play":
        radii = settings.radii
        if radii is None:
            radii = default_play_radii(u_range, settings.n_play)
        return PlayFeatures(radii=tuple(np.sort(np.asarray(radii, float))), initial_input=rest)
    if settings.features == "bouc-wen":
        levels = settings.levels
        if levels is None:
            levels = default_bouc_wen_levels(u_range, settings.n_bouc_wen)
        return BoucWenFeatures(levels=tuple(np.sort(np.asarray(levels, float))), initial_input=rest)
    return PastInputFeatures(n_past=settings.n_past, initial_input=rest)


@dataclass(frozen=True, eq=False)
class Normalised:
    """Features and target in the network's normalized coordinates, with the normalization.

    Attributes
    ----------
    x : numpy.ndarray, shape (T, n_f)
        Normalized features ``(F - feature_mean) / feature_scale`` of the whole record.
    t : numpy.ndarray, shape (T,)
        Normalized target ``(z - z_mean) / z_scale``.
    feature_mean, feature_scale : numpy.ndarray, shape (n_f,)
        Feature mean and standard deviation on the training block (1 where constant), V.
    z_mean, z_scale : float
        Mean and standard deviation of ``z`` on the training block (1 if constant), equiv. V.
    """

    x: np.ndarray
    t: np.ndarray
    feature_mean: np.ndarray
    feature_scale: np.ndarray
    z_mean: float
    z_scale: float


def normalisation(
    feature_map: FeatureMap, u: np.ndarray, z: np.ndarray, n_train: int
) -> Normalised:
    """Features of ``u`` from rest, and features and ``z`` normalized on the training block."""
    feats, _ = feature_map.features(u, feature_map.initial_state())
    f_train, z_train = feats[:n_train], z[:n_train]
    feature_mean = f_train.mean(axis=0)
    feature_scale = f_train.std(axis=0)
    feature_scale[feature_scale < 1e-12] = 1.0
    z_mean = float(z_train.mean())
    z_scale = float(z_train.std()) or 1.0
    x = (feats - feature_mean) / feature_scale
    t = (z - z_mean) / z_scale
    return Normalised(x, t, feature_mean, feature_scale, z_mean, z_scale)


def ridge_skip(x: np.ndarray, t: np.ndarray, w: np.ndarray, ridge: float) -> np.ndarray:
    """Weighted ridge fit ``t ~ x @ coef[:-1] + coef[-1]``; column 0 (u) and the offset free."""
    n, n_f = x.shape
    design = np.column_stack([x, np.ones(n)])
    gram = design.T @ (design * w[:, None])
    rhs = design.T @ (w * t)
    penalty = np.full(n_f + 1, ridge * float(w.sum()))
    penalty[0] = penalty[-1] = 0.0
    return np.linalg.lstsq(gram + np.diag(penalty), rhs, rcond=None)[0]
