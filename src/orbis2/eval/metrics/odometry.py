"""Steering evaluation: inverse dynamics on videos, scale alignment and ADE.

A world model steered with controls (speed, yaw rate) should produce a video whose ego motion
matches those controls. We recover the ego trajectory from the video with an inverse-dynamics
model (by default monocular visual odometry with OpenCV), integrate the commanded controls into
the reference trajectory, align the estimate's unknown global scale by least squares, and
report the average displacement error (ADE) in metres (paper appendix "Counterfactual steering").

Conventions: planar trajectories are ``[T, 2]`` arrays of (x, y) in the frame of the first
camera, x forward and y left (metres for references, arbitrary units for estimates), so the
first point is the origin. Controls follow :mod:`orbis2.sim.ego`: ``speed[k]`` and
``yaw_rate[k]`` (CCW positive) are constant over ``[t_k, t_{k+1})`` and poses are their exact
arc integration.

A learned inverse-dynamics model (e.g. VGGT) plugs in through :class:`InverseDynamics`: any
callable ``model(frames, K) -> [T, 2]`` works with :func:`trajectory_ade`; register it by name
in :data:`INVERSE_DYNAMICS` to make it reachable from :func:`get_inverse_dynamics`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Protocol, runtime_checkable

import cv2
import numpy as np

from orbis2.errors import OrbisError
from orbis2.kinematics import integrate_controls

# ----------------------------------------------------------------------------- controls and geometry


def camera_intrinsics(width: int, height: int, hfov_deg: float = 90.0) -> np.ndarray:
    """Pinhole matrix K of the town camera: square pixels, principal point at the image centre.

    fx = fy = (W / 2) / tan(hfov / 2), cx = (W - 1) / 2, cy = (H - 1) / 2 (pixel centres at
    integer coordinates), matching :class:`orbis2.sim.camera.Camera`.
    """
    if width <= 0 or height <= 0 or not 0 < hfov_deg < 180:
        raise OrbisError(f"bad camera: {width}x{height}, hfov {hfov_deg} deg")
    f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


# ----------------------------------------------------------------------------- metrics


def _check_pair(estimated, reference) -> tuple[np.ndarray, np.ndarray]:
    p = np.asarray(estimated, np.float64)
    q = np.asarray(reference, np.float64)
    if p.ndim != 2 or p.shape[1] != 2 or p.shape != q.shape:
        raise OrbisError(f"trajectories must both be [T, 2]; got {p.shape} and {q.shape}")
    return p, q


def align_scale(estimated, reference) -> float:
    """Least-squares scale s* = <p, q> / <p, p> that best maps the estimate p onto the reference q.

    Inverse-dynamics models recover motion only up to scale; fitting one global scale removes
    that ambiguity while still penalising shape, direction and curvature. Both trajectories
    start at the origin. A degenerate estimate (all points at the origin) gets scale 0.
    """
    p, q = _check_pair(estimated, reference)
    den = float(np.sum(p * p))
    if not den > 1e-24 or not np.isfinite(den):
        return 0.0
    return float(np.sum(p * q) / den)


def ade(estimated, reference) -> float:
    """Average displacement error (same units as reference) after least-squares scale alignment.

    Mean over time steps t = 1..T-1 of ||s* p_t - q_t||. The first point is the shared origin of
    both trajectories and is excluded, as in the scale fit (sums from t = 1), so it neither
    dilutes the error nor counts towards the average.
    """
    p, q = _check_pair(estimated, reference)
    if len(p) < 2:
        raise OrbisError("ADE needs at least two trajectory points")
    s = align_scale(p, q)
    return float(np.mean(np.linalg.norm(s * p[1:] - q[1:], axis=1)))


# ----------------------------------------------------------------------------- inverse dynamics


@runtime_checkable
class InverseDynamics(Protocol):
    """Recovers the planar ego trajectory [T, 2] (x forward, y left, first frame at the origin,
    any global scale) from video frames [T, H, W, 3] uint8 RGB and the 3x3 intrinsics K."""

    def __call__(self, frames: np.ndarray, K: np.ndarray) -> np.ndarray: ...


def _gray(frame: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(np.ascontiguousarray(frame), cv2.COLOR_RGB2GRAY)


@dataclass
class OpenCVOdometry:
    """Monocular visual odometry: corners, KLT tracks, essential matrix (RANSAC), recoverPose.

    Keyframes ``stride`` frames apart are matched pairwise; relative rotations chain into camera
    poses in the frame of the first camera. Monocular geometry gives each step's translation
    only as a direction; its length comes from ``step_scale``:

    * ``"ground"`` (default): triangulate the tracked points in the lower image, fit the road
      plane (RANSAC, normal near the camera's down axis) and set the step length so the camera
      sits ``camera_height`` above it. The global scale stays arbitrary (unit: camera heights
      unless ``camera_height`` is the true mount height in metres) but is consistent across
      steps, so braking and accelerating keep their shape. Steps where the plane cannot be fit
      reuse the previous length.
    * ``"unit"``: every moving step has length 1 (classic up-to-scale VO; adequate at constant
      speed).

    Degenerate steps are handled explicitly: a pair whose median feature motion is below
    ``min_flow_px`` (the car stands still) moves neither position nor heading; a pair whose
    motion is explained by rotation alone (parallax after removing the rotation below
    ``min_flow_px``) turns without moving; a pair with fewer than ``min_tracks`` good tracks or
    a failed essential-matrix fit repeats the previous relative motion (constant velocity).
    """

    max_corners: int = 400
    quality: float = 0.005
    min_distance: float = 6.0
    ground_corners: int = 200
    ransac_threshold_px: float = 0.5
    ransac_confidence: float = 0.999
    stride: int = 1
    min_tracks: int = 12
    min_flow_px: float = 0.5
    flow_percentile: float = 90.0
    scale_window: int = 5
    fb_threshold_px: float = 0.5
    lk_window: int = 15
    lk_levels: int = 3
    step_scale: str = "ground"
    camera_height: float = 1.0
    ground_margin: float = 0.08
    max_slope: float = 0.2

    def __post_init__(self) -> None:
        if self.step_scale not in ("ground", "unit"):
            raise OrbisError(f"step_scale must be 'ground' or 'unit', got {self.step_scale!r}")
        if self.stride < 1:
            raise OrbisError(f"stride must be >= 1, got {self.stride}")

    releases_gil = True  # OpenCV's calls do: videos can be read on one thread per core (no field: a class fact)

    def __call__(self, frames: np.ndarray, K: np.ndarray) -> np.ndarray:
        return visual_odometry(frames, K, self)

    # -- one keyframe pair

    def _detect(self, gray: np.ndarray, cy: float) -> np.ndarray:
        """Corners over the whole image plus a separate quota on the road below the horizon,
        which the strong facade corners would otherwise crowd out (the road fixes the scale)."""
        pts = [cv2.goodFeaturesToTrack(gray, self.max_corners, self.quality, self.min_distance)]
        if self.step_scale == "ground" and self.ground_corners > 0:
            mask = np.zeros_like(gray)
            mask[int(cy + self.ground_margin * gray.shape[0]) + 1:] = 255
            pts.append(cv2.goodFeaturesToTrack(gray, self.ground_corners, self.quality / 2, self.min_distance,
                                               mask=mask))
        pts = [p.reshape(-1, 2) for p in pts if p is not None]
        return np.concatenate(pts, 0).astype(np.float32) if pts else np.zeros((0, 2), np.float32)

    def _track(self, g0: np.ndarray, g1: np.ndarray, p0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """KLT forward and backward; keep tracks that return to within fb_threshold_px."""
        if len(p0) == 0:
            return p0, p0
        lk = dict(winSize=(self.lk_window, self.lk_window), maxLevel=self.lk_levels,
                  criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(g0, g1, p0, None, **lk)
        pb, st2, _ = cv2.calcOpticalFlowPyrLK(g1, g0, p1, None, **lk)
        h, w = g0.shape
        ok = (st1.reshape(-1) == 1) & (st2.reshape(-1) == 1)
        ok &= np.linalg.norm(pb - p0, axis=1) < self.fb_threshold_px
        ok &= (p1[:, 0] >= 0) & (p1[:, 0] <= w - 1) & (p1[:, 1] >= 0) & (p1[:, 1] <= h - 1)
        return p0[ok], p1[ok]

    def _ground_distance(self, K, R, t, p0, p1) -> float | None:
        """Distance from camera 0 to the road plane in units of the (unit-length) baseline."""
        low = p0[:, 1] > K[1, 2] + self.ground_margin * 2 * K[1, 2]
        if low.sum() < 8:
            return None
        P0 = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
        P1 = K @ np.hstack([R, t.reshape(3, 1)])
        X = cv2.triangulatePoints(P0, P1, p0[low].T.astype(np.float64), p1[low].T.astype(np.float64))
        X = (X[:3] / X[3]).T
        X = X[np.isfinite(X).all(1) & (X[:, 2] > 0) & (X[:, 1] > 0)]
        if len(X) < 8:
            return None
        # Road plane Y = a + b Z + c X (camera y points down), fit robustly: RANSAC on three
        # points, then least squares on the inliers. Small slopes: the camera looks along the road.
        rng = np.random.default_rng(0)
        A = np.column_stack([np.ones(len(X)), X[:, 2], X[:, 0]])
        best, best_n = None, 0
        for _ in range(64):
            idx = rng.choice(len(X), 3, replace=False)
            try:
                coef = np.linalg.solve(A[idx], X[idx, 1])
            except np.linalg.LinAlgError:
                continue
            if coef[0] <= 0 or abs(coef[1]) > self.max_slope or abs(coef[2]) > self.max_slope:
                continue
            inl = np.abs(A @ coef - X[:, 1]) < 0.05 * coef[0]
            if inl.sum() > best_n:
                best, best_n = inl, int(inl.sum())
        if best is None or best_n < 6:
            return None
        coef = np.linalg.lstsq(A[best], X[best, 1], rcond=None)[0]
        if coef[0] <= 0:
            return None
        return float(coef[0] / math.sqrt(1.0 + coef[1] ** 2 + coef[2] ** 2))

    def _still(self, p0: np.ndarray, p1: np.ndarray) -> bool:
        """Whether the camera stands still: the ``flow_percentile`` of track motion is below
        ``min_flow_px``. A high percentile rather than the median because distant points (and a
        lead car driving along) barely move in the image even while the ego drives."""
        return bool(np.percentile(np.linalg.norm(p1 - p0, axis=1), self.flow_percentile) < self.min_flow_px)

    def relative_motion(self, g0: np.ndarray, g1: np.ndarray, K: np.ndarray):
        """Motion from keyframe g0 to g1: (R, t_unit, distance or None, status).

        Points map as X1 = R X0 + t. ``distance`` is the camera-to-road distance in baseline units
        ("ground" scale), status is "moving", "static", "rotation" or "lost".
        """
        p0, p1 = self._track(g0, g1, self._detect(g0, K[1, 2]))
        if len(p0) < self.min_tracks:
            return None, None, None, "lost"
        if self._still(p0, p1):
            return np.eye(3), np.zeros(3), None, "static"
        E, mask = cv2.findEssentialMat(p0, p1, K, method=cv2.RANSAC, prob=self.ransac_confidence,
                                       threshold=self.ransac_threshold_px)
        if E is None or E.shape != (3, 3):
            return None, None, None, "lost"
        n, R, t, mask = cv2.recoverPose(E, p0, p1, K, mask=mask)
        inl = mask.reshape(-1) > 0
        if n < self.min_tracks or inl.sum() < self.min_tracks:
            return None, None, None, "lost"
        q0, q1 = p0[inl], p1[inl]
        # Parallax left after undoing the rotation (infinite homography K R K^-1).
        H = K @ R @ np.linalg.inv(K)
        q0r = cv2.perspectiveTransform(q0.reshape(-1, 1, 2).astype(np.float64), H).reshape(-1, 2)
        if np.percentile(np.linalg.norm(q1 - q0r, axis=1), self.flow_percentile) < self.min_flow_px:
            return R, np.zeros(3), None, "rotation"
        t = t.reshape(3) / max(np.linalg.norm(t), 1e-12)
        dist = self._ground_distance(K, R, t, q0, q1) if self.step_scale == "ground" else None
        return R, t, dist, "moving"


def visual_odometry(frames: np.ndarray, K: np.ndarray, config: OpenCVOdometry | None = None,
                    **params) -> np.ndarray:
    """Planar camera positions [T, 2] (x forward, y left, frame 0 at the origin), up to scale.

    Relative poses of consecutive keyframes (``config.stride`` frames apart) are chained into
    camera poses in the first camera's frame; OpenCV's camera axes (x right, y down, z forward)
    map to planar x = z, y = -x. Frames between keyframes are interpolated linearly. Keyword
    ``params`` override fields of ``config`` (see :class:`OpenCVOdometry` for the step-length
    and degenerate-step rules).
    """
    cfg = config or OpenCVOdometry()
    if params:
        cfg = OpenCVOdometry(**{**cfg.__dict__, **params})
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
        raise OrbisError(f"frames must be uint8 [T, H, W, 3], got {frames.dtype} {frames.shape}")
    K = np.asarray(K, np.float64)
    T = len(frames)
    if T == 0:
        return np.zeros((0, 2))
    keys = list(range(0, T, cfg.stride))
    if keys[-1] != T - 1:
        keys.append(T - 1)
    motions = []
    g1 = _gray(frames[keys[0]])
    for b in keys[1:]:
        g0, g1 = g1, _gray(frames[b])
        motions.append(cfg.relative_motion(g0, g1, K))
    lengths = _step_lengths(motions, cfg)
    R_w = np.eye(3)  # camera-to-world rotation of the current keyframe
    C_w = np.zeros(3)  # its centre in the world (= first camera) frame
    centres = [C_w.copy()]
    prev_R, prev_t = np.eye(3), np.zeros(3)
    for (R, t, _, status), length in zip(motions, lengths):
        if status == "lost":  # constant velocity through frames we cannot match
            R, t = prev_R, prev_t
        prev_R, prev_t = R, t
        # X1 = R X0 + t: camera 1 has world rotation R_w R^T and centre C_w - R_w R^T t.
        R_w = R_w @ R.T
        C_w = C_w - R_w @ (t * length)
        centres.append(C_w.copy())
    C = np.asarray(centres)
    planar = np.stack([C[:, 2], -C[:, 0]], 1)
    out = np.empty((T, 2))
    for i in range(2):
        out[:, i] = np.interp(np.arange(T), keys, planar[:, i])
    return out


def _step_lengths(motions: list, cfg: OpenCVOdometry) -> np.ndarray:
    """Translation length of every keyframe step.

    Moving steps take camera_height / (road distance in baseline units), smoothed by a running
    median over ``scale_window`` moving steps because a single pair's triangulation is noisy;
    moving steps without a road fit take the nearest fitted value ("unit" scale: 1). Static and
    rotation-only steps have length 0; lost steps keep the previous length.
    """
    lengths = np.zeros(len(motions))
    moving = [i for i, m in enumerate(motions) if m[3] == "moving"]
    if cfg.step_scale == "unit":
        lengths[moving] = 1.0
    else:
        raw = np.array([cfg.camera_height / motions[i][2] if motions[i][2] else np.nan for i in moving])
        have = np.flatnonzero(np.isfinite(raw))
        if len(have) == 0:
            raw[:] = 1.0
        elif len(have) < len(raw):  # fill gaps with the nearest fitted step
            nearest = np.abs(np.arange(len(raw))[:, None] - have[None]).argmin(1)
            raw = raw[have[nearest]]
        half = max(cfg.scale_window, 1) // 2
        for j, i in enumerate(moving):
            lengths[i] = np.median(raw[max(0, j - half):j + half + 1])
    prev = 1.0 if cfg.step_scale == "unit" or not moving else lengths[moving[0]]
    for i, m in enumerate(motions):
        if m[3] == "moving":
            prev = lengths[i]
        elif m[3] == "lost":
            lengths[i] = prev
    return lengths


def _learned(weights: Path | None = None) -> InverseDynamics:
    """The CNN the ``inverse_dynamics`` stage trains on the town (imported here: it needs torch)."""
    from orbis2.eval.metrics.inverse_dynamics import Instrument

    if weights is None:
        raise OrbisError("the learned inverse-dynamics instrument needs its weights: pass the `inverse_dynamics` "
                         "stage's model.pt")
    return Instrument.load(weights)


def _opencv(weights: Path | None = None) -> InverseDynamics:
    return OpenCVOdometry()


# name -> factory(weights): ``weights`` is the model's file where it has one (None otherwise).
INVERSE_DYNAMICS: dict[str, Callable[[Path | None], InverseDynamics]] = {"opencv": _opencv, "learned": _learned}


def path_length(trajectory: np.ndarray) -> float:
    """Length of a planar trajectory [T, 2] in its own units (before any scale alignment)."""
    return float(np.linalg.norm(np.diff(np.asarray(trajectory, np.float64), axis=0), axis=1).sum())


def endpoint_angle(trajectory: np.ndarray) -> float:
    """Direction (degrees, left positive) of a trajectory's end point seen from its start: how far it turned.

    Scale-free, so it compares monocular odometry (unknown scale) with commanded paths directly.
    """
    x, y = np.asarray(trajectory, np.float64)[-1] - np.asarray(trajectory, np.float64)[0]
    return math.degrees(math.atan2(y, x))


def get_inverse_dynamics(name: str, weights: Path | None = None) -> InverseDynamics:
    """The inverse-dynamics model registered under ``name``: "opencv" (visual odometry) or "learned" (the
    ``inverse_dynamics`` stage's CNN, read from ``weights``, its model.pt)."""
    factory = INVERSE_DYNAMICS.get(name)
    if factory is None:
        raise OrbisError(
            f"unknown inverse-dynamics model {name!r}; available: {sorted(INVERSE_DYNAMICS)}. "
            "Learned models (e.g. VGGT) need their own weights: wrap the model in a callable "
            "model(frames [T,H,W,3] uint8, K 3x3) -> [T,2] planar trajectory (x forward, y left, "
            "frame 0 at the origin, any scale), then register a factory(weights) -> model with "
            "orbis2.eval.metrics.odometry.INVERSE_DYNAMICS[name] = factory, or pass it as `model` to trajectory_ade")
    return factory(weights)


def trajectory_ade(frames: np.ndarray, speed, yaw_rate, fps: float, K: np.ndarray,
                   model: InverseDynamics | None = None) -> dict:
    """ADE (metres) between the trajectory seen in a video and the one its controls command.

    The controls are integrated at the video rate (row k acts over [t_k, t_{k+1})) and the
    reference is sampled at the T frames, i.e. the first T integrated points; at least T - 1
    control rows are needed. ``model`` defaults to :class:`OpenCVOdometry`. Returns
    ``{"ade": metres, "scale": fitted s*, "frames": T, "estimated": [T, 2] (unscaled), "reference": [T, 2]}``.
    """
    frames = np.asarray(frames)
    T = len(frames)
    speed = np.asarray(speed, np.float64).reshape(-1)
    yaw_rate = np.asarray(yaw_rate, np.float64).reshape(-1)
    if T < 2:
        raise OrbisError(f"trajectory ADE needs at least 2 frames, got {T}")
    if len(speed) < T - 1 or len(yaw_rate) < T - 1:
        raise OrbisError(f"{T} frames need at least {T - 1} control rows, got {len(speed)} and {len(yaw_rate)}")
    reference = integrate_controls(speed[:T - 1], yaw_rate[:T - 1], 1.0 / fps)
    estimated = np.asarray((model or OpenCVOdometry())(frames, K), np.float64)
    if estimated.shape != (T, 2):
        raise OrbisError(f"inverse-dynamics model returned {estimated.shape}, expected {(T, 2)}")
    estimated = estimated - estimated[0]
    return {"ade": ade(estimated, reference), "scale": align_scale(estimated, reference), "frames": T,
            "estimated": estimated, "reference": reference[:T]}
