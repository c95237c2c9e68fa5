"""Conditional map writes over HTTP: the map's revision as its ``ETag``, and ``If-Match``
read into the precondition the services check (`environments.IfMatch`)."""

from __future__ import annotations

import re
from typing import Annotated, Any

from fastapi import Depends, Header, Response

from app.services.environments import IfMatch

__all__ = ["IfMatchDep", "etag", "map_etag_reply", "parse_if_match", "set_map_etag"]

#: One entity tag of an If-Match list: strong ("7") or weak (W/"7"); a weak tag never
#: matches (If-Match compares strongly).
_TAG = re.compile(r'\s*(W/)?"([^"]*)"\s*(?:,|$)')


def etag(revision: int) -> str:
    """The map's ETag at `revision`: strong, quoted."""
    return f'"{revision}"'


def set_map_etag(response: Response, revision: int) -> None:
    response.headers["ETag"] = etag(revision)


def parse_if_match(value: str) -> IfMatch:
    """An If-Match header as a precondition: ``*``, or the revisions of its strong tags
    (anything else in the list matches no map)."""
    if value.strip() == "*":
        return IfMatch(any_map=True)
    revisions = {int(tag) for weak, tag in _TAG.findall(value) if not weak and tag.isdigit() and len(tag) <= 18}
    return IfMatch(revisions=frozenset(revisions))


def _if_match(if_match: Annotated[str | None, Header(description=(
        'Write only if the map is still at this revision: the ETag of the reply that showed it (e.g. "7"), or * for '
        "any map. 412 when the map has changed since (nothing is written). Without it the write happens whatever "
        "the map is now."))] = None) -> IfMatch | None:
    return parse_if_match(if_match) if if_match is not None else None


#: The precondition of a route that writes the map (None: unconditional).
IfMatchDep = Annotated[IfMatch | None, Depends(_if_match)]


def map_etag_reply(description: str) -> dict[int | str, dict[str, Any]]:
    """A route's 200 reply with the map's revision in its ETag header."""
    return {200: {"description": description, "headers": {"ETag": {
        "description": 'The revision of the map now stored, quoted (e.g. "7"): send it back in If-Match.',
        "schema": {"type": "string"}}}}}
