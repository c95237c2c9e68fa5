"""Run the live detector of another checkout of fidotrack, frame by frame, for a benchmark
that compares it with this tree's on the same frames in the same run
(`peers.CheckoutDetector`).

Started as ``python bench/detector_worker.py`` with ``PYTHONPATH`` set to the other
checkout (so ``app`` is that tree's). It reads pickled uint8 greyscale frames from stdin
and writes back, pickled, for each: the targets found as ``[(id, points (4, 2))]``, the
wall time of ``Detector.detect`` in ms, and its ``timing_ms`` by stage. A ``None`` frame
ends it. Single-threaded like the benchmark (OpenCV, BLAS).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import pickle  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402


def main() -> None:
    cv2.setNumThreads(1)
    from app.core.detection import warm_up
    from app.core.detection.candidates import load_default_classifier
    from app.core.detection.detector import Detector

    warm_up()
    detector = Detector(load_default_classifier())
    stdin, stdout = sys.stdin.buffer, sys.stdout.buffer
    pickle.dump("ready", stdout)
    stdout.flush()
    while True:
        frame = pickle.load(stdin)
        if frame is None:
            return
        start = time.perf_counter()
        found = detector.detect(frame)
        ms = (time.perf_counter() - start) * 1e3
        targets = [(int(t.id), np.asarray(t.discs, np.float64).reshape(4, 2)) for t in found.targets]
        pickle.dump((targets, ms, dict(found.timing_ms)), stdout)
        stdout.flush()


if __name__ == "__main__":
    main()
