"""Aligning an estimated camera track to the truth, and its errors.

Structure from motion gives poses in a frame and scale of its own: the estimate is brought
onto the truth by the similarity (scale, rotation, translation) that best maps its camera
centres onto the true ones, in least squares (Umeyama 1991), before anything is compared.
Poses are camera-to-world [..., 4, 4] transforms.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from evcap.errors import InputError

if TYPE_CHECKING:
    from evcap.records import Poses

DEGENERATE = 1e-9  # second singular value of the cross-covariance, relative to the first
CHUNK = 1024  # camera centres per block when finding the largest distance between them


def align_similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """The similarity (scale, R [3, 3], t [3]) that minimises the squared distances between
    ``s R src + t`` and ``dst`` (both [N, 3]). Raises InputError when it is not unique:
    fewer than 3 points, points not finite, or either set all on one line."""
    src, dst = _points(src, "src"), _points(dst, "dst")
    if len(src) != len(dst):
        raise InputError(f"cannot align {len(src)} points to {len(dst)}")
    if len(src) < 3:
        raise InputError(f"a similarity needs at least 3 point pairs, got {len(src)}")
    mu_src, mu_dst = src.mean(0), dst.mean(0)
    a, b = src - mu_src, dst - mu_dst
    cov = b.T @ a / len(src)
    U, d, Vt = np.linalg.svd(cov)
    # rank 1 or less: any rotation about the line fits as well as any other
    if not d[1] > DEGENERATE * d[0]:
        raise InputError(
            "cannot align: the points lie on one line (or on one point), so the rotation "
            "about that line is undetermined"
        )
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:  # the best orthogonal map is a reflection
        S[2, 2] = -1.0
    R = U @ S @ Vt
    scale = float((d * np.diag(S)).sum() / (a * a).sum() * len(src))
    return scale, R, mu_dst - scale * R @ mu_src


def apply_similarity(T: np.ndarray, scale: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Camera-to-world poses [..., 4, 4] moved by the similarity x -> scale R x + t: the
    cameras turn by R and their centres move; their own axes keep unit length."""
    T = np.asarray(T, np.float64)
    if T.shape[-2:] != (4, 4):
        raise InputError(f"poses must be [..., 4, 4], got {T.shape}")
    R = np.asarray(R, np.float64)
    out = T.copy()
    out[..., :3, :3] = R @ T[..., :3, :3]
    out[..., :3, 3] = scale * T[..., :3, 3] @ R.T + np.asarray(t, np.float64)
    return out


def pose_errors(T_est: np.ndarray, T_true: np.ndarray, by: str = "centres") -> dict:
    """The errors of estimated poses [N, 4, 4] against the true ones at the same times, after
    aligning the estimate onto the truth by a similarity: ``by="centres"`` fits it to the
    camera centres alone (Umeyama); ``by="poses"`` takes its rotation from the cameras'
    orientations (their chordal mean difference) and its scale and shift from the centres,
    which a path whose centres lie near a line or a plane does not leave open to a tilt.

    Returns a dict: ``rotation_deg`` [N] (the angle of R_true^T R_aligned) and
    ``translation_pct`` [N] (the distance between aligned and true centres, in percent of the
    extent), ``rotation_median_deg``, ``rotation_rms_deg``, ``translation_median_pct``,
    ``translation_rms_pct``, ``extent`` (the largest distance between two
    true camera centres: the trajectory's diameter, which unlike a bounding box does not
    depend on the world's axes), and the similarity ``scale``, ``R``, ``t``.

    If the centres lie on a line (or are only two), they leave the rotation about it open: it
    is then the mean of the cameras' rotation differences; ``aligned_by`` says which.
    """
    T_est, T_true = np.asarray(T_est, np.float64), np.asarray(T_true, np.float64)
    if T_est.ndim != 3 or T_est.shape[1:] != (4, 4) or T_true.shape != T_est.shape:
        raise InputError(f"poses must be two [N, 4, 4] arrays: {T_est.shape}, {T_true.shape}")
    c_est = _points(T_est[:, :3, 3], "estimated camera centres")
    c_true = _points(T_true[:, :3, 3], "true camera centres")
    extent = _diameter(c_true)
    if not extent > 0:
        raise InputError("the true camera centres are all at one point: no extent to measure by")
    if by not in ("centres", "poses"):
        raise InputError(f"align by 'centres' or 'poses', not {by!r}")
    aligned_by = "centres+rotations"
    if by == "centres":
        try:
            scale, R, t = align_similarity(c_est, c_true)
            aligned_by = "centres"
        except InputError:  # the input is checked: fewer than 3 centres, or all on one line
            pass
    if aligned_by != "centres":
        scale, R, t = _align_line(T_est, T_true)
    aligned = apply_similarity(T_est, scale, R, t)
    rot = _angle_deg(np.swapaxes(T_true[:, :3, :3], 1, 2) @ aligned[:, :3, :3])
    trans = np.linalg.norm(aligned[:, :3, 3] - c_true, axis=1) / extent * 100
    return {
        "rotation_deg": rot,
        "translation_pct": trans,
        "rotation_median_deg": float(np.median(rot)),
        "rotation_rms_deg": float(np.sqrt(np.mean(rot**2))),
        "translation_median_pct": float(np.median(trans)),
        "translation_rms_pct": float(np.sqrt(np.mean(trans**2))),
        "extent": extent,
        "scale": scale,
        "R": R,
        "t": t,
        "aligned_by": aligned_by,
    }


def errors_against_truth(estimate: Poses, truth: Poses) -> dict:
    """`pose_errors` (by the poses) of ``estimate`` at the truth's own times within its span,
    the estimate interpolated there, never the truth (a truth of a few views is exact only at
    them); ``compared``: how many true poses, ``seconds`` [N] their times. The one comparison
    the demo prints and the report shows."""
    inside = (truth.t >= estimate.start) & (truth.t <= estimate.end)
    errors = pose_errors(estimate.at(truth.t[inside]), truth.T_world_cam[inside], by="poses")
    errors["compared"] = int(inside.sum())
    errors["seconds"] = truth.t[inside] / 1e6
    return errors


def _points(p: np.ndarray, what: str) -> np.ndarray:
    p = np.asarray(p, np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise InputError(f"{what} must be [N, 3], got {p.shape}")
    if not np.isfinite(p).all():
        raise InputError(f"{what} are not all finite")
    return p


def _align_line(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """The similarity for centres on a line: R the chordal mean of R_true R_est^T (projected
    onto the rotations), then scale and t by least squares with R fixed."""
    M = (T_true[:, :3, :3] @ np.swapaxes(T_est[:, :3, :3], 1, 2)).sum(0)
    U, _, Vt = np.linalg.svd(M)
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ S @ Vt
    a = T_est[:, :3, 3] - T_est[:, :3, 3].mean(0)
    b = T_true[:, :3, 3] - T_true[:, :3, 3].mean(0)
    norm = (a * a).sum()
    if not norm > 0:
        raise InputError("the estimated camera centres are all at one point: no scale to align")
    scale = float(((a @ R.T) * b).sum() / norm)
    return scale, R, T_true[:, :3, 3].mean(0) - scale * R @ T_est[:, :3, 3].mean(0)


def _angle_deg(R: np.ndarray) -> np.ndarray:
    """[N] the angles of rotations [N, 3, 3], precise near 0 and 180 degrees (atan2)."""
    w = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], 1)
    cos = (np.trace(R, axis1=1, axis2=2) - 1) / 2
    return np.degrees(np.arctan2(np.linalg.norm(w, axis=1) / 2, cos))


def _diameter(p: np.ndarray) -> float:
    """The largest distance between two of the points [N, 3], in blocks to bound memory."""
    best = 0.0
    for i in range(0, len(p), CHUNK):
        d2 = ((p[i : i + CHUNK, None] - p[None]) ** 2).sum(-1)
        best = max(best, float(d2.max()))
    return float(np.sqrt(best))
