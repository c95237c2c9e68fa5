"""The /track session's parts without a server: connection slots, the token bucket and
the refusals' close codes."""

from __future__ import annotations

import time

from app.schemas import TrackCloseCode, TrackRefusal
from app.services.streaming import Refused, TokenBucket


def test_token_bucket_allows_a_burst_then_the_rate() -> None:
    bucket = TokenBucket(rate=10.0, burst=3.0)
    for _ in range(3):
        assert bucket.wait_time() == 0.0
        bucket.take()
    wait = bucket.wait_time()
    assert 0.0 < wait <= 0.1
    time.sleep(wait + 0.01)
    assert bucket.wait_time() == 0.0


def test_refusals_close_with_1013_when_full_else_1008() -> None:
    assert Refused("too_many_connections", "full").refusal.close_code == TrackCloseCode.TRY_AGAIN_LATER == 1013
    for code in ("bad_request", "unknown_environment", "no_map"):
        refusal = TrackRefusal(code=code, message="why")
        assert refusal.close_code == TrackCloseCode.POLICY_VIOLATION == 1008
        assert refusal.model_dump() == {"type": "error", "code": code, "message": "why"}
