"""``occ-console``'s command line: what it refuses before serving anything."""

from __future__ import annotations

import pytest

from occ_console.cli import build_parser, main


def test_needs_a_daemon(capsys: pytest.CaptureFixture[str]) -> None:
    assert main([]) == 2
    assert "--connect" in capsys.readouterr().err


@pytest.mark.parametrize("host", ["0.0.0.0", "192.168.1.5", "example.org"])
def test_serves_on_loopback_only(host: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(["--connect", "127.0.0.1:18947", "--host", host])
    assert exc.value.code == 2
    assert "loopback" in capsys.readouterr().err


def test_loopback_hosts_accepted() -> None:
    for host, want in (("127.0.0.1", "127.0.0.1"), ("localhost", "127.0.0.1"), ("::1", "::1")):
        args = build_parser().parse_args(["--connect", "h:1", "--host", host])
        assert args.host == want


@pytest.mark.parametrize(
    ("argv", "why"),
    [
        (["--connect", "nonsense"], "HOST:PORT"),
        (["--connect", "h:1", "--poll-hz", "50"], "--poll-hz"),
        (["--connect", "h:1", "--window-s", "0"], "--window-s"),
        (["--connect", "h:1", "--auth-key-file", "/nonexistent/key"], "--auth-key-file"),
    ],
)
def test_bad_arguments_are_refused(
    argv: list[str], why: str, capsys: pytest.CaptureFixture[str]
) -> None:
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse's own refusals
        code = int(exc.code or 0)
    assert code == 2
    assert why in capsys.readouterr().err
