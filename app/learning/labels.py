"""How windows are labelled around true discs: shared by training on the simulator
(`training`) and adaptation to a site's own images (`adapt`), which must not load the
simulator."""

from __future__ import annotations

from app.core.detection import candidates as cand

__all__ = ["NEGATIVE_RADII", "PEAK_REACH", "disc_levels"]

#: Windows stage 1a proposes within this many level pixels of a true disc centre count
#: as that disc (its peak can sit off the centre when the disc is foreshortened, blurred
#: or close to the card edge).
PEAK_REACH = 1.5
#: A window is a negative only beyond this many disc radii from every disc.
NEGATIVE_RADII = 1.5

def disc_levels(diameter: float) -> list[int]:
    """Pyramid levels whose trained diameter range (`candidates.DIAMETER_RANGE`) holds a
    disc of `diameter` full-resolution pixels."""
    lo, hi = cand.DIAMETER_RANGE
    return [level for level in range(cand.LEVELS) if lo <= diameter / 2.0**level <= hi]
