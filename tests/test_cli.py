"""The ``fidotrack`` command: ``markers`` writes printable sheets offline; ``serve`` checks its settings."""

from __future__ import annotations

from pathlib import Path

import pytest

from app.cli import main


def test_markers_writes_a_pdf(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "sheet.pdf"
    assert main(["markers", "--ids", "0-11", "--size-mm", "150", "-o", str(out)]) == 0
    assert out.read_bytes().startswith(b"%PDF")
    assert "wrote" in capsys.readouterr().err


@pytest.mark.parametrize(
    "args,message",
    [(["--ids", "0-99"], "not in family"), (["--ids", "x"], "ids"), (["--size-mm", "500"], "size_mm")],
)
def test_markers_refuses_bad_arguments(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], message: str
) -> None:
    out = tmp_path / "sheet.pdf"
    assert main(["markers", *args, "-o", str(out), "-q"]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_serve_refuses_a_certificate_without_its_key(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("FIDOTRACK_TLS_CERTFILE", str(tmp_path / "cert.pem"))
    assert main(["serve"]) == 2
    assert "FIDOTRACK_TLS_KEYFILE" in capsys.readouterr().err


@pytest.mark.parametrize("command", [["serve"], ["keys", "list"]])
def test_settings_that_cannot_be_used_are_said_without_a_traceback(
        command: list[str], capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("FIDOTRACK_DATABASE_URL", "mysql+nodriver://db/fidotrack")
    assert main(command) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"fidotrack {command[0]}: ") and "database_url" in err and "Traceback" not in err
