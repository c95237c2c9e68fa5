"""Alignment of a surveyed map to world coordinates (replaces the map in one transaction,
keeping the one it replaces as a version). The fit is made under the map's write lock
(`environments.replace_map`), on the map as it is then: never on one a write has replaced
meanwhile.

A fit that cannot be right is refused unless forced: a point the fit leaves far from
where it was said to be (a wrong card id, disc number or coordinate), or a fitted scale
far from 1 (a surveyed map is metric: its scale comes from the printed card size)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from sqlalchemy.orm import Session

from app.core.geometry import Similarity, similarity_from_points, target_origin_alignment
from app.schemas import AlignmentRequest, AlignmentResidual, AlignmentResult, MapChange, MapDocument
from app.services import environments
from app.services.errors import Invalid, NoMap

#: A point's residual is refused beyond this many metres: a world position measured with a
#: tape, a laser or a total station is good to a centimetre or better...
MIN_TOLERANCE_M = 0.02
#: ...or beyond this many times the survey's own standard deviation of that disc, when larger.
RESIDUAL_SIGMAS = 10.0
#: A fitted scale is refused further than this from 1.
MAX_SCALE_CHANGE = 0.05
#: Points a refusal names, the worst first.
NAMED_POINTS = 5


def _transform(document: MapDocument, similarity: Similarity) -> MapDocument:
    data = document.model_dump(mode="json")
    for target in data["targets"]:
        discs = np.asarray(target["discs"], np.float64)
        target["discs"] = similarity.apply(discs).tolist()
        if target.get("std_m") is not None:
            target["std_m"] = [float(similarity.scale * s) for s in target["std_m"]]
    data["frame"] = "world"
    return MapDocument.model_validate(data)


class Alignment(NamedTuple):
    """An alignment stored: its result, and the revision of the map it stored."""

    result: AlignmentResult
    revision: int


def align(session: Session, environment_id: int, spec: AlignmentRequest, *,
          if_match: environments.IfMatch | None = None) -> Alignment:
    """Fit `spec` to the environment's current map and store the map moved into the world
    (`environments.replace_map`: PreconditionFailed when the map does not meet `if_match`)."""
    fitted: list[AlignmentResult] = []

    def aligned(document: MapDocument | None) -> MapDocument:
        if document is None:
            raise NoMap(environment_id)
        fitted.append(_fit(document, spec))
        return fitted[-1].map

    stored = environments.replace_map(session, environment_id, MapChange.ALIGNMENT, aligned, if_match=if_match)
    return Alignment(fitted[-1], stored.revision)


def _fit(document: MapDocument, spec: AlignmentRequest) -> AlignmentResult:
    """The transform `spec` asks for, fitted to `document`, and the map it moves."""
    discs = {t.id: np.asarray(t.discs, np.float64) for t in document.targets}
    residuals: list[AlignmentResidual] = []
    try:
        if spec.points is not None:
            missing = sorted({p.target_id for p in spec.points if p.target_id not in discs})
            if missing:
                raise Invalid(f"points: targets {missing[:10]} are not in the map")
            source = np.array([discs[p.target_id][p.disc] for p in spec.points])
            world = np.array([p.world for p in spec.points], np.float64)
            similarity = similarity_from_points(source, world, with_scale=spec.allow_scale)
            moved = similarity.apply(source)
            residuals = [AlignmentResidual(target_id=p.target_id, disc=p.disc,
                                           residual_m=float(np.linalg.norm(m - w)))
                         for p, m, w in zip(spec.points, moved, world, strict=True)]
            if not spec.force:
                _refuse_implausible(document, residuals, similarity.scale)
        else:
            assert spec.origin_target_id is not None
            if spec.origin_target_id not in discs:
                raise Invalid(f"origin_target_id: target {spec.origin_target_id} is not in the map")
            similarity = target_origin_alignment(discs[spec.origin_target_id])
    except ValueError as exc:
        raise Invalid(f"points: {exc}") from None
    rms = float(np.sqrt(np.mean([r.residual_m**2 for r in residuals]))) if residuals else 0.0
    return AlignmentResult(scale=float(similarity.scale), R=np.asarray(similarity.R).tolist(),
                           t=np.asarray(similarity.t).tolist(), residuals=residuals, rms_m=rms,
                           map=_transform(document, similarity))


def _refuse_implausible(document: MapDocument, residuals: list[AlignmentResidual], scale: float) -> None:
    """Invalid when a point's residual is beyond its tolerance, or the scale far from 1."""
    std = {t.id: t.std_m for t in document.targets}

    def tolerance(r: AlignmentResidual) -> float:
        sigma = std[r.target_id][r.disc] if std.get(r.target_id) else 0.0
        return max(MIN_TOLERANCE_M, RESIDUAL_SIGMAS * sigma)

    beyond = sorted((r for r in residuals if r.residual_m > tolerance(r)), key=lambda r: -r.residual_m)
    if beyond:
        named = "; ".join(f"card {r.target_id} disc {r.disc} off by {r.residual_m:.3f} m (tolerance "
                          f"{tolerance(r):.3f} m)" for r in beyond[:NAMED_POINTS])
        more = f" and {len(beyond) - NAMED_POINTS} more" if len(beyond) > NAMED_POINTS else ""
        raise Invalid(f"points: the fit leaves {len(beyond)} of {len(residuals)} points beyond their tolerance: "
                      f"{named}{more}. Check their card ids, disc numbers (0-3) and coordinates (metres), "
                      "or send force=true to store the fit anyway")
    if abs(scale - 1.0) > MAX_SCALE_CHANGE:
        raise Invalid(f"points: the fitted scale {scale:.3f} is more than {MAX_SCALE_CHANGE:.0%} from 1, but a "
                      "surveyed map is metric (its scale comes from the printed card size): check the points and "
                      "the environment's card size, or send force=true to store the fit anyway")
