"""Alignment of a surveyed map to world coordinates (replaces the map in one transaction)."""

from __future__ import annotations

import numpy as np
from sqlalchemy.orm import Session

from app.core.geometry import Similarity, similarity_from_points, target_origin_alignment
from app.schemas import AlignmentRequest, AlignmentResidual, AlignmentResult, MapDocument
from app.services import environments
from app.services.errors import Invalid


def _transform(document: MapDocument, similarity: Similarity) -> MapDocument:
    data = document.model_dump(mode="json")
    for target in data["targets"]:
        discs = np.asarray(target["discs"], np.float64)
        target["discs"] = similarity.apply(discs).tolist()
        if target.get("std_m") is not None:
            target["std_m"] = [float(similarity.scale * s) for s in target["std_m"]]
    data["frame"] = "world"
    return MapDocument.model_validate(data)


def align(session: Session, environment_id: int, spec: AlignmentRequest) -> AlignmentResult:
    document = environments.get_map(session, environment_id)
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
        else:
            assert spec.origin_target_id is not None
            if spec.origin_target_id not in discs:
                raise Invalid(f"origin_target_id: target {spec.origin_target_id} is not in the map")
            similarity = target_origin_alignment(discs[spec.origin_target_id])
    except ValueError as exc:
        raise Invalid(f"points: {exc}") from None
    aligned = _transform(document, similarity)
    environments.put_map(session, environment_id, aligned)
    rms = float(np.sqrt(np.mean([r.residual_m**2 for r in residuals]))) if residuals else 0.0
    return AlignmentResult(scale=float(similarity.scale), R=np.asarray(similarity.R).tolist(),
                           t=np.asarray(similarity.t).tolist(), residuals=residuals, rms_m=rms, map=aligned)
