"""Camera poses of a sequence of frames by structure from motion (pycolmap, CPU).

The frames go to a COLMAP database as one camera whose intrinsics are the calibration's and
stay fixed: SIFT features, sequential matching (each frame against the next ``OVERLAP``, and
COLMAP's quadratic neighbours i + 2^k), loop-closure pairs, then incremental mapping; the
largest model is kept, with those that share a frame with it joined (poses/model_join.py), and
the frames it left out are registered against its points where they can be (poses/resection.py).
When frames are left out, the same database is mapped again with laxer thresholds from a few
seeds, and the best model kept: one whose points fit their sightings before one with more frames.

Loop closures: every ``loop_every``-th frame is a keyframe, and each keyframe is matched
against every other keyframe farther apart than the sequential overlap. Exhaustive matching
among keyframes finds a revisit whatever the frames look like and needs no vocabulary (COLMAP's
vocabulary-tree loop detection needs a file that would have to be downloaded); it costs
keyframes^2 / 2 pairs, which for a few hundred frames is a few hundred pairs of small images,
and the spacing widens beyond ``MAX_KEYFRAMES`` keyframes to keep it so.

Pixel coordinates: evcap's intrinsics are OpenCV's (pixel centres at integers), COLMAP puts the
centre of the top-left pixel at (0.5, 0.5): the principal point moves by half a pixel.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from evcap.errors import InputError, PosesError
from evcap.poses.model_join import Piece, join_pieces, piece_of
from evcap.poses.resection import register_rest

OVERLAP = 10  # sequential matching: each frame against the next 10
MAX_FEATURES = 4000  # SIFT features per frame
MAX_KEYFRAMES = 40  # loop closure: at most 40 * 39 / 2 = 780 keyframe pairs
MIN_MATCHES = 15  # verified matches for a pair to count (COLMAP's default)
INIT_MIN_INLIERS = 100  # to start a model; COLMAP halves it twice before giving up
FEW_FEATURES = 100  # fewer per frame on average: name too little texture as the cause
MIN_FRAMES = 3  # fewer registered: no poses worth returning
# when fewer than this share of the frames register, mapping is tried again with laxer
# thresholds, and the model with more frames kept: on the demo's orbit, 30 -> 48 of 59 frames;
# at 1.0 any frame left out is a reason to try again
RETRY_BELOW = 1.0
# the laxer mapping is tried from this many seeds (its first image pair and RANSAC's draws)
# and the best model kept (`_rank`): one seed can start from a pair that bends the model
# (the demo's orbit: 39 of 56 frames at a mean 2.85 px from one seed, 45 at 0.83 px from
# the next two); a mapping takes a few seconds beside the features and matches it shares
RELAXED_SEEDS = 3
# a model whose points lie further on average from where they were seen is bent, whatever its
# frames (COLMAP keeps a point within 4 px of each sighting)
GOOD_REPROJECTION_PX = 1.5
RELAXED_INIT_TRI_ANGLE = 4.0  # degrees (COLMAP's default 16)
RELAXED_ABS_POSE_INLIERS = 15  # 2D-3D matches to register a frame (COLMAP's default 30)
# degrees between the rays of a point to triangulate and keep it (COLMAP's default 1.5): the
# event frames' features live a few frames, a degree or two apart on a fast orbit
RELAXED_TRI_ANGLE = 1.0
SEED = 0  # RANSAC and mapping: the same frames give the same poses (with one thread)
# a global bundle adjustment each time the model grows by 40 % (COLMAP: 10 %): on a 240-frame
# orbit, mapping takes about a third less time with the same errors (the local adjustment
# still runs at every frame, and a global one at the end)
GLOBAL_BA_GROWTH = 1.4


@dataclass
class Observations:
    """Which registered frame saw which 3D point where, one row per sighting."""

    frame: np.ndarray  # [O] int64, index into SfmResult's registered frames
    point: np.ndarray  # [O] int64, index into SfmResult.points_xyz
    xy: np.ndarray  # [O, 2] float64, pixel (OpenCV: the top-left pixel's centre at 0, 0), distorted


@dataclass
class SfmResult:
    """The registered frames of the largest model (and those joined to it), in time order."""

    t_us: np.ndarray  # [M] int64, times of the registered frames
    T_world_cam: np.ndarray  # [M, 4, 4] float64 camera-to-world, OpenCV camera axes
    registered: int  # M
    total: int  # N, frames given
    mean_reprojection_px: float  # over the model's 3D points
    points: int  # 3D points in the model
    model_count: int  # models COLMAP made (pieces of the path)
    seconds: float  # wall time of the whole run
    unregistered_times: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # [N-M]
    # the model's points and where the registered frames saw them, for refining the poses
    points_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # [P, 3]
    observations: Observations | None = None
    joined: int = 0  # models joined to the largest through a frame they share
    resected: int = 0  # frames the mapping left out, registered afterwards (poses/resection.py)


def run_sfm(
    images: list[np.ndarray],
    times_us: np.ndarray,
    K: np.ndarray,
    dist: np.ndarray,
    *,
    workdir: Path | None = None,
    loop_every: int = 10,
    threads: int = 1,
    progress: Callable[[int, int, str], None] | None = None,
) -> SfmResult:
    """Poses of ``images`` (uint8, gray [H, W] or RGB [H, W, 3], all one size) taken at
    ``times_us`` by the camera ``K`` (3 x 3) with distortion ``dist`` (OpenCV order k1 k2 p1 p2
    [k3 [k4 k5 k6]]; empty: none). Scale and world frame are arbitrary. Frames that do not
    register are left out (``unregistered_times``). ``workdir`` keeps what COLMAP was given and
    made (images/, database.db, loop_pairs.txt, sparse/: an earlier run's are replaced); by
    default a temporary folder is used.
    ``threads``: COLMAP's threads (0: every core). With one, the same frames give the same
    poses bit for bit; with more it is faster, but COLMAP's matching and mapping then vary
    from run to run (a few frames more or fewer registered).
    ``progress(done, total, stage)`` follows the run. Raises PosesError when no model of at
    least 3 frames can be made, naming why."""
    import pycolmap

    started = time.perf_counter()
    images, times_us = _check_frames(images, times_us)
    colmap_camera(K, dist)  # K and dist checked before COLMAP runs
    K, dist = np.asarray(K, np.float64), np.asarray(dist, np.float64).ravel()
    if loop_every < 1:
        raise InputError(f"loop_every must be at least 1, got {loop_every}")
    if threads < 0:
        raise InputError(f"threads must be 0 (every core) or more, got {threads}")
    threads = threads or _cores()
    report = progress or (lambda done, total, stage: None)
    n = len(images)
    level = pycolmap.logging.minloglevel
    # COLMAP logs every frame and step at INFO, and its failures are told by PosesError
    pycolmap.logging.minloglevel = max(int(level), int(pycolmap.logging.FATAL))
    try:
        best, stats, count, joined, resected = _best_model(
            pycolmap, images, K, dist, workdir, loop_every, threads, report
        )
    finally:
        pycolmap.logging.minloglevel = level

    registered = len(best.frames) if best is not None else 0
    if registered < MIN_FRAMES:
        raise PosesError(_failure(n, registered, stats))
    frames = best.frames
    report(n, n, f"mapping: {len(frames)} of {n} frames registered")
    return SfmResult(
        t_us=times_us[frames],
        T_world_cam=best.T_world_cam,
        registered=len(frames),
        total=n,
        mean_reprojection_px=reprojection_px(best, K, dist),
        points=len(best.xyz),
        model_count=count,
        seconds=time.perf_counter() - started,
        unregistered_times=times_us[np.setdiff1d(np.arange(n), frames)],
        points_xyz=best.xyz,
        observations=Observations(np.searchsorted(frames, best.frame), best.point, best.xy),
        joined=joined,
        resected=resected,
    )


def reprojection_px(piece: Piece, K: np.ndarray, dist: np.ndarray) -> float:
    """Mean distance (pixels) between where the points were seen and where they project."""
    import cv2

    d = np.asarray(dist, np.float64).ravel()
    errors = []
    for f, T in zip(piece.frames, piece.T_world_cam, strict=True):
        seen = piece.frame == f
        if not seen.any():
            continue
        T_cw = np.linalg.inv(T)
        rvec = cv2.Rodrigues(T_cw[:3, :3])[0]
        xy = cv2.projectPoints(piece.xyz[piece.point[seen]], rvec, T_cw[:3, 3], K, d)[0]
        errors.append(np.linalg.norm(xy.reshape(-1, 2) - piece.xy[seen], axis=1))
    return float(np.concatenate(errors).mean()) if errors else float("nan")


def colmap_camera(K: np.ndarray, dist: np.ndarray) -> tuple[str, list[float]]:
    """COLMAP's camera model and parameters for OpenCV intrinsics ``K`` and distortion
    ``dist``: PINHOLE without distortion, OPENCV (fx fy cx cy k1 k2 p1 p2) with it, FULL_OPENCV
    when k3..k6 are not all zero. The principal point moves by half a pixel (see the module)."""
    K = np.asarray(K, np.float64)
    if K.shape != (3, 3) or not np.isfinite(K).all():
        raise InputError(f"K must be a finite 3 x 3 matrix, got shape {K.shape}")
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5
    if not (fx > 0 and fy > 0):
        raise InputError(f"K's focal lengths must be positive, got fx={fx}, fy={fy}")
    d = np.asarray(dist, np.float64).ravel()
    if not np.isfinite(d).all():
        raise InputError("the distortion coefficients are not all finite")
    if d.size > 8 and np.any(d[8:]):
        raise InputError(
            f"distortion with {d.size} coefficients: thin-prism and tilt terms (after k6) are "
            "not supported"
        )
    d = np.concatenate([d[:8], np.zeros(8 - min(d.size, 8))])
    pinhole = [float(v) for v in (fx, fy, cx, cy)]
    if not d.any():
        return "PINHOLE", pinhole
    if not d[4:].any():
        return "OPENCV", pinhole + [float(v) for v in d[:4]]
    return "FULL_OPENCV", pinhole + [float(v) for v in d]


def loop_pairs(n: int, loop_every: int) -> list[tuple[int, int]]:
    """Frame index pairs for loop closure: keyframes (every ``loop_every``-th frame, spaced
    wider when there would be more than MAX_KEYFRAMES) against each other, where farther apart
    than the sequential overlap."""
    step = max(loop_every, -(-n // MAX_KEYFRAMES))
    keys = range(0, n, step)
    return [(i, j) for i in keys for j in keys if j - i > OVERLAP]


def _check_frames(images: list[np.ndarray], times_us: np.ndarray) -> tuple[list, np.ndarray]:
    images = [np.asarray(im) for im in images]
    times_us = np.asarray(times_us)
    if len(images) < MIN_FRAMES:
        raise InputError(
            f"structure from motion needs at least {MIN_FRAMES} frames, got {len(images)}"
        )
    if times_us.shape != (len(images),):
        raise InputError(f"{len(images)} frames but times of shape {times_us.shape}")
    if not np.issubdtype(times_us.dtype, np.integer):
        raise InputError(f"times must be integer microseconds, got {times_us.dtype}")
    shape = images[0].shape
    for i, im in enumerate(images):
        if im.dtype != np.uint8:
            raise InputError(f"frame {i} is {im.dtype}; frames must be uint8")
        if im.shape != shape or not (im.ndim == 2 or (im.ndim == 3 and im.shape[2] == 3)):
            raise InputError(
                f"frame {i} has shape {im.shape}; frames must all be [H, W] or [H, W, 3] "
                f"like the first, {shape}"
            )
    return images, times_us.astype(np.int64)


def _cores() -> int:
    # COLMAP's -1 means every hardware thread, which in a container is the host's count
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def _best_model(pycolmap, images, K, dist, workdir, loop_every, threads, report):
    """(the best model (`_rank`) of the mappings tried on one database: the largest model of
    each, with those that share a frame with it joined (poses/model_join.py) and the frames it
    left out registered where they can be (poses/resection.py), or None; the database's
    statistics, how many models that mapping made, how many were joined, how many resected)."""
    n = len(images)
    with tempfile.TemporaryDirectory(prefix="evcap-sfm-") as tmp:
        work = Path(workdir) if workdir is not None else Path(tmp)
        names = _database(pycolmap, images, K, dist, work, loop_every, threads, report)
        stats = _match_stats(pycolmap, work / "database.db", n)
        best, rank = (None, stats, 0, 0, 0), None
        tries = [(False, SEED)] + [(True, SEED + k) for k in range(RELAXED_SEEDS)]
        for relaxed, seed in tries:
            if rank is not None and rank[0] and rank[1] >= RETRY_BELOW * n:
                break  # every frame, and the points fit
            recs = _mapping(pycolmap, work, n, threads, report, relaxed, seed)
            found = _largest(pycolmap, recs, names, work, K, dist)
            if found[0] is not None and (rank is None or _rank(found[0], K, dist) > rank):
                best, rank = (found[0], stats, len(recs), *found[1:]), _rank(found[0], K, dist)
    return best


def _largest(pycolmap, recs, names, work, K, dist):
    """(the largest of the mapping's models with those joined to it and the frames it left out
    registered where they can be, or None; how many were joined; how many resected)."""
    index = {name: i for i, name in enumerate(names)}
    pieces = [piece_of(r, index) for r in recs.values() if r.num_reg_images()]
    if not pieces:
        return None, 0, 0
    best, joined = join_pieces(pieces)
    with pycolmap.Database.open(work / "database.db") as db:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        image_id = [ids[name] for name in names]

        def keypoints(f: int) -> np.ndarray:
            return db.read_keypoints(image_id[f])[:, :2] - 0.5  # COLMAP's centres at 0.5

        def matches(f: int, g: int) -> np.ndarray:
            return db.read_two_view_geometry(image_id[f], image_id[g]).inlier_matches

        best, resected = register_rest(best, len(names), keypoints, matches, K, dist)
    return best, joined, resected


def _rank(piece: Piece, K: np.ndarray, dist: np.ndarray) -> tuple[bool, int, float]:
    """What makes a model better, in order: its points fit their sightings
    (`GOOD_REPROJECTION_PX`), more frames, a closer fit."""
    error = reprojection_px(piece, K, dist)
    return (error <= GOOD_REPROJECTION_PX, len(piece.frames), -error)


def _database(pycolmap, images, K, dist, work, loop_every, threads, report) -> list[str]:
    """COLMAP's database in ``work``: the frames (written to work/images), their SIFT features,
    their sequential and loop-closure matches, verified; returns the image names."""
    import cv2

    n = len(images)
    folder, database = work / "images", work / "database.db"
    shutil.rmtree(folder, ignore_errors=True)
    database.unlink(missing_ok=True)
    folder.mkdir(parents=True)
    names = [f"{i:06d}.png" for i in range(n)]  # sequential matching follows name order
    report(0, n, "writing frames")
    for name, im in zip(names, images, strict=True):
        if im.ndim == 3:
            im = cv2.cvtColor(im, cv2.COLOR_RGB2BGR)
        cv2.imwrite(str(folder / name), im, [cv2.IMWRITE_PNG_COMPRESSION, 1])

    report(0, n, "features")
    model, params = colmap_camera(K, dist)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = model
    reader.camera_params = ",".join(repr(v) for v in params)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = threads
    extraction.sift.max_num_features = MAX_FEATURES
    pycolmap.extract_features(
        database,
        folder,
        image_names=names,
        camera_mode=pycolmap.CameraMode.SINGLE,
        reader_options=reader,
        extraction_options=extraction,
        device=pycolmap.Device.cpu,
    )

    report(0, n, "matching")
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = threads
    verification = pycolmap.TwoViewGeometryOptions()
    verification.min_num_inliers = MIN_MATCHES
    verification.ransac.random_seed = SEED
    sequential = pycolmap.SequentialPairingOptions()
    sequential.overlap = OVERLAP
    sequential.num_threads = threads
    pycolmap.match_sequential(
        database,
        matching_options=matching,
        pairing_options=sequential,
        verification_options=verification,
        device=pycolmap.Device.cpu,
    )
    pairs = loop_pairs(n, loop_every)
    if pairs:
        pair_list = work / "loop_pairs.txt"
        pair_list.write_text("".join(f"{names[i]} {names[j]}\n" for i, j in pairs))
        imported = pycolmap.ImportedPairingOptions()
        imported.match_list_path = pair_list
        pycolmap.match_image_pairs(
            database,
            matching_options=matching,
            pairing_options=imported,
            verification_options=verification,
            device=pycolmap.Device.cpu,
        )
    return names


def _mapping(pycolmap, work, n: int, threads, report, relaxed: bool, seed: int) -> dict:
    """COLMAP's incremental mapping of the database of ``n`` frames in ``work`` (its models in
    work/sparse, an earlier mapping's replaced): the reconstructions, a dict, maybe empty."""
    folder, database, sparse = work / "images", work / "database.db", work / "sparse"
    shutil.rmtree(sparse, ignore_errors=True)
    sparse.mkdir()
    report(0, n, "mapping")
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = threads
    options.random_seed = seed
    options.min_num_matches = MIN_MATCHES
    options.extract_colors = False
    options.ba_global_frames_ratio = GLOBAL_BA_GROWTH
    options.ba_global_points_ratio = GLOBAL_BA_GROWTH
    # the calibration is better than what a few hundred small frames could say about it
    options.ba_refine_focal_length = False
    options.ba_refine_principal_point = False
    options.ba_refine_extra_params = False
    options.mapper.abs_pose_refine_focal_length = False
    options.mapper.abs_pose_refine_extra_params = False
    options.mapper.init_min_num_inliers = INIT_MIN_INLIERS
    if relaxed:
        options.mapper.init_min_tri_angle = RELAXED_INIT_TRI_ANGLE
        options.mapper.abs_pose_min_num_inliers = RELAXED_ABS_POSE_INLIERS
        options.triangulation.min_angle = RELAXED_TRI_ANGLE
        options.mapper.filter_min_tri_angle = RELAXED_TRI_ANGLE
    options.mapper.num_threads = threads
    options.mapper.random_seed = seed
    done = [0]

    def registered() -> None:
        done[0] += 1
        report(min(done[0], n), n, "mapping")

    return pycolmap.incremental_mapping(
        database, folder, sparse, options=options, next_image_callback=registered
    )


def _match_stats(pycolmap, database: Path, n: int) -> dict:
    """What the database says about the frames: features per frame, the verified pairs and
    the best pair's verified matches."""
    with pycolmap.Database.open(database) as db:
        features = db.num_keypoints() / max(n, 1)
        _, inliers = db.read_two_view_geometry_num_inliers()
    inliers = np.asarray(inliers, np.int64)
    return {
        "features": features,
        "pairs": int((inliers >= MIN_MATCHES).sum()),
        "best": int(inliers.max()) if len(inliers) else 0,
    }


def _failure(n: int, registered: int, stats: dict) -> str:
    """One line: why no model came out, from what the database says."""
    features, pairs, best = stats["features"], stats["pairs"], stats["best"]
    least = INIT_MIN_INLIERS // 4  # after COLMAP's two relaxations
    texture = "too little texture, or frames too blurred or too dark"
    few = f"only {features:.0f} features per frame on average"
    if not features:
        few = "no features in any frame"
    share = (
        f"no two of the {n} frames share enough matches to start a model (best pair {best} "
        f"verified matches, {least} needed)"
    )
    if best < least and features < FEW_FEATURES:
        return f"structure from motion failed: {few} and {share}: {texture}"
    if best < least:
        return (
            f"structure from motion failed: {features:.0f} features per frame but {share}: "
            "the frames may not overlap, or differ too much (blur, exposure, fast motion)"
        )
    if registered == 0:
        return (
            f"structure from motion failed: {pairs} pairs of the {n} frames match (best pair "
            f"{best} verified matches) but none sees the scene from far enough apart to start "
            "a model: the camera must move, not only turn"
            + (f" ({few}: {texture})" if features < FEW_FEATURES else "")
        )
    return (
        f"structure from motion failed: only {registered} of the {n} frames could be registered "
        f"together ({pairs} matching pairs, {features:.0f} features per frame; {MIN_FRAMES} "
        f"frames needed): the frames may be too far apart, or the scene too plain ({texture})"
    )
