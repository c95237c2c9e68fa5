"""Train the default disc classifier from the simulator and ship it with the package.

Runs ``app.learning.training.train_default(seed)`` (deterministic, ~80 s on two cores),
writes ``app/data/default_classifier.npz`` (``np.savez_compressed``, no pickle: every
parameter as an array, the training statistics as a JSON string in a 0-d array) and
prints the statistics as a markdown table.

Run: ``.venv/bin/python scripts/train_default_classifier.py [--seed 0] [--out PATH]``
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from app.core.detection import DiscClassifier  # noqa: E402
from app.learning.training import train_default  # noqa: E402

DEFAULT_OUT = ROOT / "app" / "data" / "default_classifier.npz"


def save(classifier: DiscClassifier, path: Path) -> None:
    arrays = classifier.to_arrays()
    arrays["stats_json"] = np.array(json.dumps(classifier.stats, sort_keys=True, default=_plain))
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez_compressed(tmp, **arrays)
    tmp.replace(path)


def _plain(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"not JSON-able: {type(value)}")


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, (list, tuple)):
        return ", ".join(_fmt(v) for v in value)
    return str(value)


def stats_table(stats: dict[str, Any]) -> str:
    rows = [
        ("Positive / negative windows collected", f"{stats.get('positive_windows')} / {stats.get('negative_windows')}"),
        ("Stage 1a per-disc recall (training frames)", _fmt(stats.get("stage1a_disc_recall"))),
        ("Stage 1b (screen) false negatives, held-out disc windows", _fmt(stats.get("screen_fn_rate_heldout"))),
        ("Stage 1+2 false negatives, held-out disc windows", _fmt(stats.get("heldout_fn_rate_stage1_and_2"))),
        ("Disc recall of stages 1+2, calibration frames", _fmt(stats.get("calibration_disc_recall_stage1_and_2"))),
        ("... by condition", ", ".join(f"{k} {v:.4f}" for k, v in
                                       (stats.get("calibration_disc_recall_by_condition") or {}).items())),
        ("Stage 1a rejection factor (marker-free photos)", _fmt(stats.get("stage1a_rejection_factor"))),
        ("Stage 1 rejection factor (marker-free photos; paper ~3000)", _fmt(stats.get("stage1_rejection_factor"))),
        ("All windows / candidates reported (marker-free photos)", _fmt(stats.get("candidate_rejection_factor"))),
        ("Condensation: examples -> Hart -> Gates prototypes",
         f"{stats.get('condensation_examples')} -> {stats.get('condensation_hart_prototypes')} -> "
         f"{stats.get('condensation_prototypes')} ({stats.get('condensation_positive_prototypes')} discs)"),
        ("Held-out agreement, condensed vs full 1-NN", _fmt(stats.get("heldout_agreement_condensed_vs_full"))),
        ("Thresholds: blob / screen / nn", f"{_fmt(stats.get('blob_thresholds'))} / "
         f"{_fmt(stats.get('calibration_screen_threshold'))} / {_fmt(stats.get('calibration_nn_threshold'))}"),
        ("Training time (s)", _fmt(stats.get("training_seconds"))),
    ]
    lines = ["| statistic | value |", "|---|---|"]
    lines += [f"| {name} | {value} |" for name, value in rows]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args()

    bar = tqdm(total=1000, unit="‰", desc="training", bar_format="{l_bar}{bar}| {elapsed} {postfix}")

    def progress(stage: str, fraction: float) -> None:
        target = int(round(1000 * min(max(fraction, 0.0), 1.0)))
        if target > bar.n:
            bar.update(target - bar.n)
        bar.set_postfix_str(stage)

    start = time.perf_counter()
    classifier = train_default(seed=args.seed, progress=progress)
    bar.close()
    stats = dict(classifier.stats)
    save(classifier, args.out)
    size_kb = args.out.stat().st_size / 1024
    print(f"\nwrote {args.out} ({size_kb:.0f} kB) in {time.perf_counter() - start:.0f} s\n")
    print(stats_table(stats))


if __name__ == "__main__":
    main()
