"""Code reading by card size: the nine-sample reader against the whole-card reader, and
how far each acceptance rule stands from naming a card wrongly.

Renders scenario frames (`scenes.scenario_frame`) and reads the code of every counted
card through the four true disc centres, as the detector does after refinement, three
ways on the same frames:

- *nine samples* (`identification`): the cells read through the card's homography,
  matched against every code in every rotation under every blur (and, for a card whose
  white is clipped, through the clip as well);
- *whole card* (`code_reader.read_cards`) as the detector uses it: every pixel of the card
  against every printed pattern, the nine-sample read's code known to it;
- *given the blur*: the whole-card fit with the frame's true point-spread function (the
  simulator's smear and defocus) instead of a search: the best this model of the card can
  read, for cards read on the full-resolution image.

The tables give the read rate and the wrong ids by imaged disc diameter; the nine-sample
rule's margin per kind of read (linear: white below `CLIPPED_WHITE_GREY`; clipped: at or
above it) and gap threshold; and the whole-card rule's margin: every card fitted with the
whole set of point-spread functions on its own (no nine-sample read to lean on), accepted
at each margin threshold, and the largest margin of a wrong best code.

Run: ``.venv/bin/python bench/bench_code_read.py`` (~12 min on 2 cores); quick mode
``--frames 200``. Prints markdown tables; progress on stderr.
"""

from __future__ import annotations

import argparse
import sys
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.signal import convolve2d
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from app.core.detection import code_reader, identification  # noqa: E402
from app.core.detection._frame import Pyramid  # noqa: E402
from app.core.detection import as_gray  # noqa: E402
from app.core.detection.verification import _measure  # noqa: E402
from app.core.geometry import homographies  # noqa: E402
from app.core.markers import DEFAULT_FAMILY, get_family  # noqa: E402
from app.sim import degrade, scenes  # noqa: E402
from app.sim.truth import truth_cards  # noqa: E402

CONDITIONS = ("default", "far", "blur", "dark", "bright", "tiny")
GAPS = (0.15, 0.12, 0.10, 0.08, 0.06, 0.05, 0.04, 0.03)
#: Whole-card margin thresholds tabulated (`code_reader.MIN_MARGIN` among them).
MARGINS = (48.0, 24.0, 16.0, 12.0, 8.0, 6.0, 4.0, 2.0)
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
    #: the whole-card read as the detector uses it: accepted, and right
    card_ok: list[bool] = field(default_factory=list)
    card_right: list[bool] = field(default_factory=list)
    #: the whole-card read given the true blur (None: the card is read on a coarser level)
    given_ok: list[bool | None] = field(default_factory=list)
    given_right: list[bool | None] = field(default_factory=list)
    #: the whole-card read on its own (every point-spread function): right, margin, misfit
    alone_right: list[bool] = field(default_factory=list)
    alone_margin: list[float] = field(default_factory=list)
    alone_fit: list[float] = field(default_factory=list)

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


def true_psf(truth: scenes.FrameTruth) -> np.ndarray:
    """The frame's point-spread function in pixels: the simulator's smear and defocus (the
    pixel's own footprint is the reader's)."""
    d = truth.degradation
    k = np.ones((1, 1))
    if d.get("blur_length", 0.0) > 0:
        k = degrade.motion_blur_kernel(d["blur_length"], d["blur_angle"]).astype(np.float64)
    if d.get("defocus_radius", 0.0) > 0:
        k = convolve2d(k, degrade.defocus_kernel(d["defocus_radius"]))
    return (k / k.sum()).astype(np.float32)


def read_frame(image: np.ndarray, truth: scenes.FrameTruth, family: str, reads: dict[str, Reads]) -> None:
    """Read every counted card of a frame from its true disc centres, every way."""
    gray = as_gray(image)
    cards = [c for c in truth_cards(truth, None) if c.counted]
    if not cards:
        return
    quads = np.stack([c.points for c in cards]).astype(np.float64)
    pyr = Pyramid(gray)
    hs = homographies(quads)
    m = _measure(pyr, hs, get_family(family).cells)
    ok, ids, shifts, fit, gap = identification._decode(m.cells, family, m.white)
    clipped = m.white >= identification.CLIPPED_WHITE_GREY
    known = np.where(ok[:, None], np.stack([ids, shifts], axis=1), -1)
    card = code_reader.read_cards(pyr, hs, family, clipped=clipped, known=known)
    alone = code_reader.read_cards(pyr, hs, family, psfs=code_reader.psf_set(), clipped=clipped)
    given = code_reader.read_cards(pyr, hs, family, psfs=[true_psf(truth)], clipped=clipped)
    for k, c in enumerate(cards):
        r = reads["clipped" if clipped[k] else "linear"]
        # the true points are in printed order: the right match is the card's id, shift 0
        r.add(bool(ids[k] == c.id and shifts[k] == 0), float(fit[k]), float(gap[k]), c.disc_px)
        r.card_ok.append(bool(card.ok[k]))
        r.card_right.append(bool(card.ids[k] == c.id and card.shifts[k] == 0))
        level0 = c.side_px <= code_reader.MAX_SIDE_PX
        r.given_ok.append(bool(given.ok[k]) if level0 else None)
        r.given_right.append(bool(given.ids[k] == c.id and given.shifts[k] == 0) if level0 else None)
        r.alone_right.append(bool(alone.ids[k] == c.id and alone.shifts[k] == 0))
        r.alone_margin.append(float(alone.margin[k]))
        r.alone_fit.append(float(alone.fit[k]))


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


def _pooled(reads: dict[str, Reads], name: str) -> np.ndarray:
    return np.concatenate([np.array(getattr(r, name)) for r in reads.values()])


def size_table(reads: dict[str, Reads]) -> str:
    """Read rates by imaged disc size, every kind of read pooled: the nine samples, the
    whole card as the detector reads it, and the whole card given the true blur (cards
    read on the full-resolution image only)."""
    size = _pooled(reads, "disc_px")
    old_ok = np.concatenate([r.accepted() for r in reads.values()])
    old_right = _pooled(reads, "right")
    new_ok, new_right = _pooled(reads, "card_ok"), _pooled(reads, "card_right")
    given_ok, given_right = _pooled(reads, "given_ok"), _pooled(reads, "given_right")
    lines = [("| disc diameter | code cell | reads | nine samples | wrong | whole card | wrong | "
              "given the blur (reads) | wrong |"),
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    rows = [(lo, hi) for lo, hi in zip(SIZE_BINS[:-1], SIZE_BINS[1:], strict=True)] + [(3.0, 5.0), (0.0, np.inf)]
    for lo, hi in rows:
        sel = (size >= lo) & (size < hi)
        if not sel.any():
            continue
        label = "all" if lo == 0 and np.isinf(hi) else f">= {lo:g} px" if np.isinf(hi) else f"{lo:g}-{hi:g} px"
        if (lo, hi) == (3.0, 5.0):
            label = "**3-5 px**"
        cell = "" if label == "all" else f"{0.4 * lo:.1f}+ px" if np.isinf(hi) else f"{0.4 * lo:.1f}-{0.4 * hi:.1f} px"
        n = int(sel.sum())

        def rate(ok: np.ndarray, right: np.ndarray, within: np.ndarray) -> str:
            m = int(within.sum())
            return f"{100.0 * int((ok & right & within).sum()) / max(m, 1):.1f}%"

        g = sel & np.array([v is not None for v in given_ok])
        gok = np.array([bool(v) for v in given_ok])
        gright = np.array([bool(v) for v in given_right])
        lines.append(f"| {label} | {cell} | {n} | {rate(old_ok, old_right, sel)} | {int((old_ok & ~old_right & sel).sum())} | "
                     f"{rate(new_ok, new_right, sel)} | {int((new_ok & ~new_right & sel).sum())} | "
                     f"{rate(gok, gright, g)} ({int(g.sum())}) | {int((gok & ~gright & g).sum())} |")
    clipped = np.concatenate([np.full(len(r.right), kind == "clipped") for kind, r in reads.items()])
    small = (size >= 3.0) & (size < 5.0)
    unread = small & ~(new_ok & new_right)
    lines.append(f"\nOf the {int(small.sum())} cards with 3-5 px discs, the whole card leaves {int(unread.sum())} "
                 f"unread, {int((unread & clipped).sum())} of them with clipped white "
                 f"({int((small & clipped).sum())} clipped in all).")
    return "\n".join(lines)


def margin_table(reads: dict[str, Reads]) -> str:
    """The whole-card rule on its own: every card fitted with every point-spread function,
    accepted when its best is a code at or above each margin threshold (and within the
    misfit limit)."""
    right = _pooled(reads, "alone_right")
    margin, fit = _pooled(reads, "alone_margin"), _pooled(reads, "alone_fit")
    within = fit <= code_reader.MAX_FIT_PER_MARGIN * margin
    wrong = ~right & within
    lines = [f"Best pattern wrong (a wrong code, a wrong rotation or no code): {int((~right).sum())} of {right.size}; "
             f"largest margin of a wrong code: {margin[wrong].max():.1f}.\n" if wrong.any() else
             f"Best pattern wrong: none of {right.size}.\n",
             "| margin threshold | accepted | rate | wrong accepted |", "|---:|---:|---:|---:|"]
    for t in MARGINS:
        acc = within & (margin >= t)
        mark = " (the rule)" if t == code_reader.MIN_MARGIN else ""
        lines.append(f"| {t:g}{mark} | {int(acc.sum())} | {100.0 * acc.sum() / max(right.size, 1):.1f}% | "
                     f"{int((acc & ~right).sum())} |")
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
    print("\n### By imaged disc diameter\n")
    print(f"Nine samples: gap at least {identification.CODE_GAP_MIN}. Whole card: the detector's rule "
          f"(margin at least {code_reader.MIN_MARGIN:g}, or the nine samples' code).\n")
    print(size_table(reads))
    print("\n### The whole-card margin, every card read on its own\n")
    print(margin_table(reads))


if __name__ == "__main__":
    main()
