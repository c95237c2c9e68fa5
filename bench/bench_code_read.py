"""Code reading: how far the identification's acceptance rule (`CODE_FIT_MAX`,
`CODE_GAP_MIN`, `CLIPPED_GAP_MIN`) can be loosened before it names a card wrongly.

Renders scenario frames (`scenes.scenario_frame`) and reads the code of every counted
card through the four true disc centres, as `identify` does after refinement: the cells
read through the card's homography, then matched against every code in every rotation
under every blur (and, for a card whose white is clipped, through the clip as well). Each
read's best match is right or wrong by the truth; its fit and gap say whether the rule
would accept it. The tables give, per kind of read (linear: white below
`CLIPPED_WHITE_GREY`; clipped: at or above it) and per gap threshold, how many reads are
accepted and how many of those are wrong, and the smallest gap of any wrong best match
within the fit limit: the margin a threshold keeps.

Run: ``.venv/bin/python bench/bench_code_read.py`` (~4 min on 2 cores); quick mode
``--frames 200``. Prints markdown tables; progress on stderr.
"""

from __future__ import annotations

import argparse
import sys
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from app.core.detection import identification  # noqa: E402
from app.core.detection._frame import Pyramid  # noqa: E402
from app.core.detection.candidates import as_gray  # noqa: E402
from app.core.detection.verification import _measure  # noqa: E402
from app.core.geometry import homographies  # noqa: E402
from app.core.markers import DEFAULT_FAMILY, get_family  # noqa: E402
from app.sim import scenes  # noqa: E402
from app.sim.truth import truth_cards  # noqa: E402

CONDITIONS = ("default", "far", "blur", "dark", "bright", "tiny")
GAPS = (0.15, 0.12, 0.10, 0.08, 0.06, 0.05, 0.04, 0.03)
#: Imaged disc diameter bins (px) of the read rate by size: a code cell is 0.4 disc
#: diameters wide (`CODE_SIZE` / 3 of a card whose discs are `DISC_RADIUS` * 2).
SIZE_BINS = (0.0, 3.0, 3.5, 4.0, 5.0, 8.0, np.inf)


@dataclass
class Reads:
    """Every read of one kind: the best match right or wrong, its fit and its gap."""

    right: list[bool] = field(default_factory=list)
    fit: list[float] = field(default_factory=list)
    gap: list[float] = field(default_factory=list)
    disc_px: list[float] = field(default_factory=list)

    def add(self, right: bool, fit: float, gap: float, disc_px: float) -> None:
        self.right.append(right)
        self.fit.append(fit)
        self.gap.append(gap)
        self.disc_px.append(disc_px)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return np.array(self.right, bool), np.array(self.fit), np.array(self.gap)

    def accepted(self) -> np.ndarray:
        """The reads the current rule accepts, right or wrong."""
        _, fit, gap = self.arrays()
        return (fit <= identification.CODE_FIT_MAX) & (gap >= identification.CODE_GAP_MIN)


def read_frame(image: np.ndarray, truth: scenes.FrameTruth, family: str, reads: dict[str, Reads]) -> None:
    """Read every counted card of a frame from its true disc centres."""
    gray = as_gray(image)
    cards = [c for c in truth_cards(truth, None) if c.counted]
    if not cards:
        return
    quads = np.stack([c.points for c in cards]).astype(np.float64)
    m = _measure(Pyramid(gray), homographies(quads), get_family(family).cells)
    _, ids, shifts, fit, gap = identification._decode(m.cells, family, m.white)
    for k, card in enumerate(cards):
        kind = "clipped" if m.white[k] >= identification.CLIPPED_WHITE_GREY else "linear"
        # the true points are in printed order: the right match is the card's id, shift 0
        reads[kind].add(bool(ids[k] == card.id and shifts[k] == 0), float(fit[k]), float(gap[k]), card.disc_px)


def table(reads: dict[str, Reads]) -> str:
    lines = ["| read | gap threshold | reads | accepted | rate | wrong accepted |",
             "|---|---:|---:|---:|---:|---:|"]
    for kind, r in reads.items():
        right, fit, gap = r.arrays()
        within = fit <= identification.CODE_FIT_MAX
        for g in GAPS:
            acc = within & (gap >= g)
            lines.append(f"| {kind} | {g:.2f} | {right.size} | {int(acc.sum())} | "
                         f"{100.0 * acc.sum() / max(right.size, 1):.1f}% | {int((acc & ~right).sum())} |")
    return "\n".join(lines)


def margins(reads: dict[str, Reads]) -> str:
    lines = ["| read | reads | best match wrong | wrong within fit limit | largest gap of a wrong match |",
             "|---|---:|---:|---:|---:|"]
    for kind, r in reads.items():
        right, fit, gap = r.arrays()
        wrong = ~right & (fit <= identification.CODE_FIT_MAX)
        largest = f"{gap[wrong].max():.3f}" if wrong.any() else "-"
        lines.append(f"| {kind} | {right.size} | {int((~right).sum())} | {int(wrong.sum())} | {largest} |")
    return "\n".join(lines)


def size_table(reads: dict[str, Reads]) -> str:
    """The read rate of the current rule by imaged disc size, every kind of read pooled:
    what the code itself allows with perfect disc centres."""
    right = np.concatenate([r.arrays()[0] for r in reads.values()])
    accepted = np.concatenate([r.accepted() for r in reads.values()])
    size = np.concatenate([np.array(r.disc_px) for r in reads.values()])
    fit = np.concatenate([r.arrays()[1] for r in reads.values()])
    unfit = fit > identification.CODE_FIT_MAX  # refused for the fit; the others for the gap
    lines = ["| disc diameter | code cell | reads | read right | rate | read wrong | refused: fit / gap |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for lo, hi in zip(SIZE_BINS[:-1], SIZE_BINS[1:], strict=True):
        sel = (size >= lo) & (size < hi)
        if not sel.any():
            continue
        label = f">= {lo:g} px" if np.isinf(hi) else f"{lo:g}-{hi:g} px"
        cell = f"{0.4 * lo:.1f}+ px" if np.isinf(hi) else f"{0.4 * lo:.1f}-{0.4 * hi:.1f} px"
        ok = int((accepted & right & sel).sum())
        refused = ~accepted & sel
        lines.append(f"| {label} | {cell} | {int(sel.sum())} | {ok} | {100.0 * ok / sel.sum():.1f}% | "
                     f"{int((accepted & ~right & sel).sum())} | {int((refused & unfit).sum())} / "
                     f"{int((refused & ~unfit).sum())} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=1500, help="frames per condition")
    parser.add_argument("--conditions", nargs="+", default=list(CONDITIONS), choices=list(scenes.SCENARIOS))
    parser.add_argument("--seed", type=int, default=1, help="seed (bench_detect uses 0: keep them apart)")
    args = parser.parse_args(argv)
    reads = {"linear": Reads(), "clipped": Reads()}
    with tqdm(total=args.frames * len(args.conditions), desc="frames", unit="fr", file=sys.stderr) as bar:
        for condition in args.conditions:
            bar.set_postfix_str(condition)
            for i in range(args.frames):
                rng = np.random.default_rng([args.seed, zlib.crc32(condition.encode()), i])
                try:
                    image, truth = scenes.scenario_frame(condition, rng)
                except ValueError:
                    bar.update()
                    continue
                read_frame(image, truth, DEFAULT_FAMILY, reads)
                bar.update()
    print(f"## Code reads from true disc centres, {args.frames} frames per condition "
          f"({', '.join(args.conditions)}), seed {args.seed}\n")
    print(f"Fit limit `CODE_FIT_MAX` = {identification.CODE_FIT_MAX}; a read is clipped when the "
          f"card's white reads {identification.CLIPPED_WHITE_GREY:.0f} or more.\n")
    print(margins(reads))
    print()
    print(table(reads))
    print("\nThe current rule (gap at least "
          f"{identification.CODE_GAP_MIN}) by imaged disc diameter:\n")
    print(size_table(reads))


if __name__ == "__main__":
    main()
