"""Ridge probes of ego-motion read from latents: speed and yaw rate over 0.5 s from two latents 0.5 s apart.

The ``eval_conditioning`` stage (``orbis2.eval.protocols.conditioning``) fits one on real latent pairs to measure how
much ego-motion a latent set keeps, then reads the steered predictor's predictions with it. Ridge on
standardised features, its penalty chosen per target on held-out train clips, R^2 with clip-bootstrap
intervals on val.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from orbis2.eval.metrics.stats import bootstrap_statistic

EGO_MOTION_TARGETS = ("speed", "yaw_rate")  # the probe's target columns, in odometry order


def probe_features(latents: np.ndarray, strips: int) -> np.ndarray:
    """[N, C, h, w] -> [N, C * strips]: channel means over ``strips`` vertical strips (left to right);
    ``strips`` = 0 keeps the whole grid, [N, C * h * w]. A 16-channel latent loses most of the
    turn when pooled to strips (which suit a 768-channel teacher map), so the default is 0."""
    if strips == 0:
        return np.asarray(latents, np.float64).reshape(len(latents), -1)
    parts = np.array_split(np.asarray(latents, np.float64), strips, axis=-1)
    return np.concatenate([p.mean(axis=(-2, -1)) for p in parts], axis=1)


def ego_motion_pairs(latents: list[np.ndarray], odometry: list[np.ndarray], labels: list[str], step: int,
                     stride: int, strips: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Features (strips of the latents at t and t + step), targets (mean speed, yaw rate over [t, t + step)), clips."""
    xs, ys, cs = [], [], []
    for lat, odo, label in zip(latents, odometry, labels):
        feats = probe_features(lat, strips)
        for t in range(0, len(lat) - step, stride):
            y = np.asarray(odo[t:t + step], np.float64).mean(axis=0)
            if np.isfinite(y).all():
                xs.append(np.concatenate([feats[t], feats[t + step]]))
                ys.append(y)
                cs.append(label)
    if not xs:
        raise ValueError("no ego-motion pairs: every clip is shorter than the step or lacks odometry")
    return np.stack(xs), np.stack(ys), np.asarray(cs)


def standardised_svd(x: np.ndarray) -> tuple[np.ndarray, ...]:
    """The features' mean and scale, and the thin SVD (U, S, V^T) of the standardised features, which every
    ridge fit on these features shares whatever its targets and penalty."""
    mean, scale = x.mean(axis=0), x.std(axis=0) + 1e-8
    u, s, vt = np.linalg.svd((x - mean) / scale, full_matrices=False)
    return mean, scale, u, s, vt


def ridge_path(x: np.ndarray, y: np.ndarray, penalties,
               svd: tuple[np.ndarray, ...] | None = None) -> list[tuple[np.ndarray, ...]]:
    """Ridge regression on standardised features (intercept unpenalised), one (mean, scale, weights, bias)
    per penalty, all from one thin SVD of the features (``svd``: :func:`standardised_svd` of ``x``, when
    another fit on the same features made it).

    With z = U S V^T, the ridge weights (z^T z + p I)^-1 z^T y are V diag(s / (s^2 + p)) U^T y: the
    same solution as solving the normal equations, which the probe's few hundred pairs of thousands of
    features made a D x D solve per penalty and fold (the conditioning stage's largest cost).
    """
    if min(penalties) <= 0:
        raise ValueError(f"ridge penalties must be > 0, got {list(penalties)}")
    mean, scale, u, s, vt = standardised_svd(x) if svd is None else svd
    bias = y.mean(axis=0)
    projected = u.T @ (y - bias)
    return [(mean, scale, vt.T @ ((s / (s ** 2 + penalty))[:, None] * projected), bias) for penalty in penalties]


def ridge_fit(x: np.ndarray, y: np.ndarray, penalties,
              svd: tuple[np.ndarray, ...] | None = None) -> tuple[np.ndarray, ...]:
    """Ridge with one penalty per target column (``penalties``: a sequence, or one value for every column;
    ``svd`` as :func:`ridge_path`'s)."""
    penalties = np.broadcast_to(np.asarray(penalties, np.float64), (y.shape[1],))
    unique = sorted(set(penalties.tolist()))
    path = dict(zip(unique, ridge_path(x, y, unique, svd)))
    mean, scale, _, bias = path[unique[0]]
    weights = np.stack([path[p][2][:, j] for j, p in enumerate(penalties.tolist())], axis=1)
    return mean, scale, weights, bias


def ridge_predict(model: tuple[np.ndarray, ...], x: np.ndarray) -> np.ndarray:
    mean, scale, weights, bias = model
    return (x - mean) / scale @ weights + bias


def weighted_r2(y: np.ndarray, pred: np.ndarray, weights: np.ndarray) -> float:
    centre = weights @ y / weights.sum()
    return float(1.0 - weights @ (y - pred) ** 2 / (weights @ (y - centre) ** 2))


def select_penalty(x: np.ndarray, y: np.ndarray, clips, penalties, folds: int,
                   seed: int) -> tuple[list[float], list[dict[float, float]]]:
    """Per target column, the ridge penalty whose probe predicts held-out train clips best (R^2 over ``folds``
    folds of whole clips), and each candidate's score per target. Thousands of features on a few thousand
    pairs: a penalty too weak overfits the clips it saw, so it is chosen on train, never on val; and per
    target, since the targets need not share their best penalty (speed wants a stronger one here)."""
    labels = np.asarray([str(c) for c in clips])
    unique = np.random.default_rng(seed).permutation(np.unique(labels))
    if len(unique) < folds:
        raise ValueError(f"choosing the probe's penalty over {folds} folds needs >= {folds} train clips, "
                         f"got {len(unique)}")
    fold = dict(zip(unique, np.arange(len(unique)) % folds))
    assigned = np.array([fold[c] for c in labels])
    candidates = [float(p) for p in penalties]
    r2 = np.zeros((len(candidates), y.shape[1], folds))
    for k in range(folds):
        held = assigned == k
        for i, model in enumerate(ridge_path(x[~held], y[~held], candidates)):
            pred = ridge_predict(model, x[held])
            r2[i, :, k] = [weighted_r2(y[held, j], pred[:, j], np.ones(int(held.sum()))) for j in range(y.shape[1])]
    scores = r2.mean(axis=2)
    best = [candidates[i] for i in scores.argmax(axis=0)]
    return best, [dict(zip(candidates, scores[:, j].tolist())) for j in range(y.shape[1])]


def ego_motion_probe(train: tuple[np.ndarray, np.ndarray], val: tuple[np.ndarray, np.ndarray], val_clips,
                     penalty, reps: int, seed: int,
                     names=EGO_MOTION_TARGETS) -> tuple[dict[str, Any], tuple[np.ndarray, ...]]:
    """Val R^2 (clip-bootstrap interval) of a ridge probe per target, and of the same probe on shuffled targets;
    also the fitted probe. ``penalty``: one per target (:func:`select_penalty`) or one for all.

    The shuffled control trains on train targets permuted across pairs: what R^2 a probe
    reaches without any real relation (about zero or below). Both fits share one SVD of the train features.
    """
    svd = standardised_svd(train[0])  # the probe and its control read the same features
    model = ridge_fit(*train, penalty, svd)
    pred = ridge_predict(model, val[0])
    rng = np.random.default_rng(seed)
    control = ridge_predict(ridge_fit(train[0], train[1][rng.permutation(len(train[1]))], penalty, svd), val[0])
    out: dict[str, Any] = {"train_pairs": len(train[0]), "val_pairs": len(val[0])}
    for k, name in enumerate(names):
        y = val[1][:, k]
        iv = bootstrap_statistic(val_clips, lambda w, k=k, y=y: weighted_r2(y, pred[:, k], w), reps, seed=seed)
        out[name] = {"r2": iv.estimate, "low": iv.low, "high": iv.high,
                     "shuffled_r2": weighted_r2(y, control[:, k], np.ones(len(y)))}
    return out, model
