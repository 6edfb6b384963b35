"""The output scheduler's table of what is due at each tick sends exactly what testing every
output at every tick would, in the configured order (and falls back to that test when the
outputs' common period is too long for a table)."""

from __future__ import annotations

from typing import Any

import pytest

import occ.net.outputs as outputs_mod
from occ.net.outputs import Output, OutputScheduler


class _Iface:
    def __init__(self, name: str, sent: list[tuple[int, str]]) -> None:
        self.name = name
        self._sent = sent
        self.k = 0

    def send(self, msg: Any) -> int:
        self._sent.append((self.k, msg))
        return 1


def _run(everies: list[int], ticks: int) -> list[tuple[int, str]]:
    sent: list[tuple[int, str]] = []
    iface = _Iface("i", sent)
    outs = [Output(iface, "STRING", f"d{n}", "src", every, 2) for n, every in enumerate(everies)]
    sched = OutputScheduler(outs, {"src": lambda out, now: out.device})  # type: ignore[dict-item]
    for k in range(ticks):
        iface.k = k
        sched.send_due(0.0, k, None)
    return sent


def _expected(everies: list[int], ticks: int) -> list[tuple[int, str]]:
    return [(k, f"d{n}") for k in range(ticks) for n, e in enumerate(everies) if k % e == 0]


@pytest.mark.parametrize(
    "everies", [[100, 100, 100, 2], [2, 100, 50, 20], [3, 7, 1], [5], [], [333, 2, 7]]
)
def test_the_schedule_sends_what_each_output_is_due(
    everies: list[int], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(outputs_mod, "Message", str)  # the test's "messages" are strings
    assert _run(everies, 1000) == _expected(everies, 1000)


def test_a_long_common_period_falls_back_to_testing_each_output(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(outputs_mod, "Message", str)
    monkeypatch.setattr(outputs_mod, "SCHEDULE_MAX", 100)
    everies = [7, 11, 13]  # common period 1001 > 100
    assert _run(everies, 3000) == _expected(everies, 3000)
