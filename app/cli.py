"""The ``fidotrack`` command: ``fidotrack serve`` and ``fidotrack markers``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from tqdm import tqdm


def _serve(args: argparse.Namespace) -> int:
    import uvicorn

    from app.settings import Settings

    settings = Settings()
    uvicorn.run(
        "app.main:app",
        host=args.host or settings.host,
        port=args.port or settings.port,
        workers=args.workers,
        ws="websockets",
        proxy_headers=True,
    )
    return 0


def _markers(args: argparse.Namespace) -> int:
    from app.services import markers
    from app.services.errors import ServiceError

    with tqdm(desc="cards", unit="card", disable=args.quiet) as bar:

        def progress(done: int, total: int) -> None:
            bar.total = total
            bar.n = done
            bar.refresh()

        try:
            pdf = markers.sheet(args.family, args.ids, args.size_mm, progress)
        except ServiceError as exc:
            print(f"fidotrack markers: {exc.detail}", file=sys.stderr)
            return 2
    args.output.write_bytes(pdf)
    print(f"wrote {args.output} ({len(pdf)} bytes)", file=sys.stderr)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="fidotrack", description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True)

    serve = commands.add_parser("serve", help="run the HTTP/WebSocket service")
    serve.add_argument("--host", help="default: FIDOTRACK_HOST or 127.0.0.1")
    serve.add_argument("--port", type=int, help="default: FIDOTRACK_PORT or 8000")
    serve.add_argument("--workers", type=int, default=1)
    serve.set_defaults(run=_serve)

    cards = commands.add_parser("markers", help="write printable marker cards as an A4 PDF")
    cards.add_argument("--ids", default="0-11", help='ids, e.g. "0-11" or "0,3,5-7"')
    cards.add_argument("--size-mm", type=float, default=150.0, help="side of each card in mm")
    cards.add_argument("--family", default="fido3x3")
    cards.add_argument("-o", "--output", type=Path, default=Path("markers.pdf"))
    cards.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    cards.set_defaults(run=_markers)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return int(args.run(args))


if __name__ == "__main__":
    raise SystemExit(main())
