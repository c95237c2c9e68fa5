"""Registering frames against the map (resection, survey step 3).

A frame that sees 2+ placed targets gets its pose by PnP, robust over the targets
(`app.core.geometry.nonlinear`): targets it refuses are set aside in that frame. A frame
that rests on one card takes a tilt its image does not refute and that fits the
camera's motion (its neighbours' poses), which also refuses a card with a misread code.
"""

from __future__ import annotations

import cv2
import numpy as np

from app.core.geometry import Pose, PoseUndetermined, TargetObservation, nonlinear, rotation_angle
from app.core.survey.prune import noise_variance
from app.core.survey.state import SurveyState


def continuity(state: SurveyState, f: int, pose: Pose) -> float:
    """How well a pose of frame ``f`` fits the camera's motion.

    A pose that rests on one card is checked against the video's motion: a card seen
    from far has two tilts that fit (poses metres apart), and a card with a misread code
    fits perfectly somewhere else in the room. A hand-held camera moves smoothly, so the
    pose must lie near its neighbours'.

    Parameters
    ----------
    state : SurveyState
        The survey.
    f : int
        The frame.
    pose : Pose
        A candidate pose for it.

    Returns
    -------
    float
        How far ``pose`` is from the nearest frame registered on 2+ targets, in units of
        the camera's typical motion over that many frames (movement and turn added);
        inf when implausible or when there is no such frame within 10 frames.
    """
    rec = state.reconstruction
    strong = np.flatnonzero(rec.registered() & ~state.weak)
    strong = strong[strong != f]
    if not len(strong):
        return np.inf
    nearest = int(strong[np.argmin(np.abs(strong - f))])
    gap = abs(nearest - f)
    if gap > 10:
        return np.inf
    # The camera's motion per frame, from consecutive frames registered on 2+ targets.
    pairs = strong[:-1][np.diff(strong) == 1]
    if len(pairs) >= 3:
        steps = np.array([np.linalg.norm(rec.pose(int(a)).position - rec.pose(int(a) + 1).position)
                          for a in pairs[:: max(1, len(pairs) // 50)]])
        angles = np.array([rotation_angle(rec.pose(int(a)), rec.pose(int(a) + 1))
                           for a in pairs[:: max(1, len(pairs) // 50)]])
        step, turn = float(np.median(steps)), float(np.median(angles))
    else:
        step, turn = np.inf, np.inf
    ref = rec.pose(nearest)
    depth = float(np.linalg.norm(ref.position - rec.X[np.isfinite(rec.X[:, 0])].mean(axis=0)))
    max_move = max(3 * gap * step, 0.05 * depth) if np.isfinite(step) else 0.5 * depth
    max_turn = max(3 * gap * turn, np.radians(5)) if np.isfinite(turn) else np.radians(30)
    move = float(np.linalg.norm(pose.position - ref.position))
    angle = rotation_angle(pose, ref)
    if move > max_move or angle > max_turn:
        return np.inf
    return move / max_move + angle / max_turn


def single_target_pose(state: SurveyState, f: int, ob: TargetObservation, noise_px2: float) -> Pose | None:
    """The pose of frame ``f`` from one placed target.

    Of the two poses the card allows, those the image does not refute (a fit worse than
    the other's by more than 25 in chi^2, with the map's residual variance), then the
    one closest to the nearest registered frame of the video (`continuity`). The image
    judges first: neighbouring frames registered on 2+ targets can be 9 frames away, the
    camera having turned 40 degrees meanwhile, and the wrong tilt (2 m and 50 degrees
    off) can then be the closer one though it fits the card 12 times worse than the
    right one (0.94 against 0.08 px^2 at 0.1 px noise).

    Parameters
    ----------
    state : SurveyState
        The survey.
    f : int
        The frame.
    ob : TargetObservation
        The target's discs in the image and in the map.
    noise_px2 : float
        The map's residual variance, px^2 per coordinate (`noise_variance`).

    Returns
    -------
    Pose or None
        The pose; None when neither tilt fits the image within ``state.pose_fit_px``
        or the camera's motion.
    """
    camera = state.reconstruction.camera
    registered = np.flatnonzero(state.reconstruction.registered())
    # IPPE wants exactly coplanar points: use the card's best-fit plane (the
    # surveyed discs are a little off it), then refine on the 3D discs.
    centre = ob.map.mean(axis=0)
    _, _, Vt = np.linalg.svd(ob.map - centre)
    if np.linalg.det(Vt) < 0:
        Vt[2] *= -1
    planar = np.c_[((ob.map - centre) @ Vt.T)[:, :2], np.zeros(4)]
    try:
        _, rvecs, tvecs, _ = cv2.solvePnPGeneric(planar, ob.image, camera.K, camera.dist, flags=cv2.SOLVEPNP_IPPE)
    except cv2.error:
        return None
    fits: list[tuple[Pose, float]] = []
    for rvec, tvec in zip(rvecs, tvecs, strict=False):
        plane_pose = Pose.from_rvec_tvec(rvec, tvec)
        pose = Pose(plane_pose.R @ Vt, plane_pose.t - plane_pose.R @ Vt @ centre)
        rvec, tvec = cv2.solvePnPRefineLM(ob.map, ob.image, camera.K, camera.dist,
                                          pose.rvec.reshape(3, 1).copy(), pose.t.reshape(3, 1).copy())
        pose = Pose.from_rvec_tvec(rvec, tvec)
        residual = camera.project_map(ob.map, pose) - ob.image
        in_front = (pose.transform(ob.map)[:, 2] > 0).all()
        if in_front and np.abs(residual).max() < state.pose_fit_px:
            fits.append((pose, float((residual**2).sum())))
    if not fits or not len(registered):
        return None
    closest = min(sse for _, sse in fits)
    poses = [pose for pose, sse in fits if sse - closest < 25 * noise_px2]
    best = min(poses, key=lambda p: continuity(state, f, p))
    return best if np.isfinite(continuity(state, f, best)) else None


def register_frames(state: SurveyState, min_targets: int) -> int:
    """Register (PnP) every unregistered frame that sees ``min_targets`` placed targets.

    Frames are tried most targets first, each again only once it sees more placed
    targets than when last tried (``state.attempted``). With 2+ targets: a robust PnP
    over the targets; the targets it refuses are set aside in that frame (the final
    rounds may take them back). With one target (``min_targets`` 1), or two that
    disagree: the card whose `single_target_pose` fits the camera's motion best, the
    other views set aside.

    Parameters
    ----------
    state : SurveyState
        The survey; frames are registered in its reconstruction, ``weak`` marks those
        resting on one target, ``usable`` loses the views set aside.
    min_targets : int
        1 or 2: the fewest placed targets a frame must see.

    Returns
    -------
    int
        The number of frames registered.
    """
    rec, views, usable = state.reconstruction, state.views, state.usable
    outlier_px = state.settings.outlier_px
    noise_px2 = noise_variance(state) if min_targets < 2 else 1.0
    placed = rec.placed()[0::4]
    registered = rec.registered()
    candidates = []
    for f in np.flatnonzero(~registered):
        seen = [v for v in views.of_frame[f] if placed[views.target[v]] and usable[v]]
        if len(seen) >= min_targets and state.attempted.get(int(f), -1) < len(seen):
            candidates.append((len(seen), int(f), seen))
    added = 0
    for count, f, seen in sorted(candidates, reverse=True):
        state.attempted[f] = count
        obs = [TargetObservation(int(views.target[v]), views.uv[v], rec.discs(views.target[v])) for v in seen]
        est = None
        if count >= 2:
            try:
                est = nonlinear(obs, rec.camera, outlier_px=max(outlier_px, 4.0))
            except (PoseUndetermined, cv2.error):
                est = None
            # The map is still coarse while it grows: accept a loose fit, BA tightens it.
            if est is not None and est.rms_px > state.pose_fit_px:
                est = None
            # A pose that rests on one card after all must fit the camera's motion.
            if est is not None and len(est.target_ids) < 2 and not np.isfinite(continuity(state, f, est.pose)):
                est = None
        if est is not None:
            rec.set_pose(f, est.pose)
            state.weak[f] = len(est.target_ids) < 2
            # Targets that do not fit the others here (misidentified?) are not used in
            # this frame; the last rounds of the bundle adjustment may take them back.
            rejected = set(est.rejected_ids)
            for v, ob in zip(seen, obs, strict=True):
                if ob.id in rejected:
                    usable[v] = False
            added += 1
            continue
        if min_targets > 1:
            continue
        # One card at a time (a frame with one placed target, or two that disagree):
        # the card whose pose fits the camera's motion best, the others set aside.
        found = [(continuity(state, f, pose), k, pose) for k, ob in enumerate(obs)
                 if (pose := single_target_pose(state, f, ob, noise_px2)) is not None]
        if not found:
            continue
        _, k, pose = min(found, key=lambda c: c[0])
        rec.set_pose(f, pose)
        state.weak[f] = True
        for j, v in enumerate(seen):
            if j != k:
                usable[v] = False
        added += 1
    return added
