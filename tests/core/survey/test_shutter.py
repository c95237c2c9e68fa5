"""The survey through a rolling shutter (app.core.survey.shutter): detections where the
simulator's rolling shutter puts the discs (app.sim.shutter), never the model's own."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from app.core.detection import DetectedTarget
from app.core.geometry import RollingShutter, similarity_from_points
from app.core.survey import SurveyError, survey
from app.sim.scenes import frame_truth
from app.sim.shutter import rolling_projection
from tests.core.survey.conftest import SURVEY_ROOM, Frames

READOUT_S = 0.020


@functools.cache
def _rolling_walk() -> tuple[tuple[tuple[DetectedTarget, ...], ...], float]:
    walk = SURVEY_ROOM.walk(7, 300)
    assert walk.walk is not None
    camera = SURVEY_ROOM.camera
    rng = np.random.default_rng(0)
    discs = {t.id: t.discs for t in walk.scene.targets}
    frames = []
    for pose, readout in zip(walk.poses, walk.walk.readouts(READOUT_S), strict=True):
        truth = frame_truth(camera, pose, walk.scene)
        frames.append(tuple(DetectedTarget(t.id, rolling_projection(camera, readout, discs[t.id])
                                           + rng.normal(0, 0.05, (4, 2)), 1.0) for t in truth.visible_targets()))
    return tuple(frames), walk.walk.fps


@pytest.fixture(scope="module")
def rolling_walk() -> tuple[Frames, float]:
    """The small room's 300-frame walk (about 1.2 m/s) read out over 20 ms: the discs
    where the rolling shutter puts them, plus 0.05 px of noise; and its frame rate."""
    frames, fps = _rolling_walk()
    return [list(f) for f in frames], fps


def _disc_rms_mm(result) -> float:
    truth = {t.id: t.discs for t in SURVEY_ROOM.walk(7, 300).scene.targets}
    mapped = np.concatenate([t.discs for t in result.targets])
    true = np.concatenate([truth[t.id] for t in result.targets])
    fit = similarity_from_points(mapped, true)
    return 1000 * float(np.sqrt(np.mean(np.sum((fit.apply(mapped) - true) ** 2, axis=1))))


def test_a_survey_that_models_the_readout_maps_and_calibrates_through_it(rolling_walk) -> None:
    frames, fps = rolling_walk
    camera = SURVEY_ROOM.camera
    result = survey(frames, camera.width, camera.height, SURVEY_ROOM.marker_size_m,
                    shutter=RollingShutter.from_seconds(READOUT_S, fps))
    # Read as a global shutter this walk's map is some 40 mm off with the true lens and
    # its self-calibration is refused (the lens check); modelled, about a millimetre.
    assert len(result.targets) == 16
    assert _disc_rms_mm(result) < 2.0
    assert result.camera.fx == pytest.approx(camera.fx, rel=0.005)
    assert result.rms_px < 0.1


def test_frame_numbers_must_place_every_frame_in_order(rolling_walk) -> None:
    frames, fps = rolling_walk
    camera = SURVEY_ROOM.camera
    shutter = RollingShutter.from_seconds(READOUT_S, fps)
    with pytest.raises(SurveyError, match="frame_numbers"):
        survey(frames, camera.width, camera.height, SURVEY_ROOM.marker_size_m, intrinsics=camera, shutter=shutter,
               frame_numbers=np.arange(len(frames) - 1))
    with pytest.raises(SurveyError, match="frame_numbers"):
        survey(frames, camera.width, camera.height, SURVEY_ROOM.marker_size_m, intrinsics=camera, shutter=shutter,
               frame_numbers=np.zeros(len(frames)))
