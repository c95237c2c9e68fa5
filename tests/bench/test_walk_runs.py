"""Judging a surveyed map against the truth (`walk_runs.check_map`): which cards are wrong,
and whether a warning names them, with a fit that the wrong cards do not pull."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from app.core.survey import MapWarning, SurveyedTarget, WarningKind
from bench.walk_runs import WRONG_M, check_map, disc_rms_mm, robust_fit


def _room(n: int, rng: np.random.Generator) -> dict[int, np.ndarray]:
    """`n` cards' discs (4, 3), 0.14 m apart on a card, spread over a room's walls."""
    square = 0.07 * np.array([[-1.0, 0.0, -1.0], [1.0, 0.0, -1.0], [1.0, 0.0, 1.0], [-1.0, 0.0, 1.0]])
    return {i: rng.uniform([0.0, 0.0, 0.7], [8.0, 6.0, 2.3]) + square for i in range(n)}


def _fake_result(discs: dict[int, np.ndarray], std_m: float, warned: dict[int, WarningKind]) -> Any:
    """What `check_map` reads of a survey's result: its targets and typed map warnings."""
    targets = [SurveyedTarget(i, d, np.full(4, std_m), 10, 20.0) for i, d in discs.items()]
    warnings = [MapWarning(kind, (i,), f"card {i}: ...") for i, kind in warned.items()]
    return SimpleNamespace(targets=targets, map_warnings=warnings)


def test_wrong_cards_are_counted_named_or_not_and_do_not_pull_the_fit() -> None:
    rng = np.random.default_rng(3)
    truth = _room(10, rng)
    # The survey's frame: another scale, rotation and origin, and 1 mm of noise.
    R, scale, t = Rotation.from_rotvec([0.3, -1.2, 0.5]).as_matrix(), 1.7, np.array([4.0, -2.0, 9.0])
    surveyed = {i: (d @ R.T) * scale + t + rng.normal(0.0, 0.001 / np.sqrt(3), (4, 3)) for i, d in truth.items()}
    surveyed[2] = surveyed[2] + scale * np.array([0.37, 0.0, 0.0])  # 0.37 m off, named by a warning
    surveyed[5] = surveyed[5] + scale * np.array([0.0, 0.08, 0.0])  # 8 cm off, named by none
    surveyed[7] = surveyed[7] + scale * np.array([0.0, 0.0, 0.02])  # 2 cm off: within 5 cm, but 10 sigma
    surveyed[40] = surveyed[1] + 0.5  # an id that is no card of the room
    result = _fake_result(surveyed, 0.002, {2: WarningKind.NARROW, 9: WarningKind.FEW_VIEWS})

    check = check_map(result, truth)

    assert check.wrong == {2, 5, 7, 40}
    assert check.wrong_named == {2}
    assert check.wrong_silent == {5, 7, 40}
    assert check.inliers == set(range(10)) - {2, 5}
    assert abs(check.fit.scale - 1 / scale) < 1e-3
    errors = dict(zip([t.id for t in result.targets], check.errors_m.reshape(-1, 4), strict=True))
    # Not pulled by the cards 0.37 m and 8 cm off (a plain fit puts the others 2-7 cm off);
    # card 7, 2 cm off, fits and pulls its share.
    assert max(errors[i].max() for i in check.inliers - {7}) < 0.01
    assert 0.36 < errors[2].min() and WRONG_M < errors[5].min()
    assert np.isnan(errors[40]).all()


def test_a_right_map_has_no_wrong_card_and_the_fit_takes_it_whole() -> None:
    rng = np.random.default_rng(4)
    truth = _room(6, rng)
    surveyed = {i: d + np.array([1.0, 2.0, 3.0]) + rng.normal(0.0, 0.0005, (4, 3)) for i, d in truth.items()}

    check = check_map(_fake_result(surveyed, 0.002, {}), truth)

    assert check.wrong == set() and check.inliers == set(truth)
    fit, inliers = robust_fit(surveyed, truth, with_scale=False)
    assert inliers == set(truth) and abs(fit.scale - 1.0) < 1e-12
    assert disc_rms_mm(surveyed, truth) < 1.5
