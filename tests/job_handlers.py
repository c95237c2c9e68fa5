"""Job handlers used by the tests to drive the job runner (run in worker processes)."""

from __future__ import annotations

import time
from typing import Any


def count(context: Any) -> dict[str, Any]:
    steps = int(context.params.get("steps", 5))
    for step in range(steps):
        context.progress("counting", step / steps)
        time.sleep(float(context.params.get("sleep", 0.05)))
    return {"counted": steps}


def fail(context: Any) -> dict[str, Any]:
    context.progress("failing", 0.5)
    raise ValueError("the survey video holds no markers")
