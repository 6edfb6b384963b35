"""``occ-record plot``: one PNG of a recording (trajectories, tracking error, states, timing).

What a recording holds (occ/recording/record.py) is enough for four panels:

1. **Trajectories**: the robot's measured tip (X, Y, Z in mm, from its state rows) and, when the
   recording has an input stream (a slave's recording holds every POSITION it took from its
   master), the master's positions on their own axis.
2. **Tracking error**, per axis, in mm:

   - *master vs slave*, when the recording has a POSITION input stream: the ideal tip
     ``slave_ref + scale * (master - master_ref)`` minus the measured tip, at every state row
     while RUNNING. ``master_ref`` is the first POSITION with ``run=1`` the robot took after it
     entered RUNNING (where the teleop-slave re-indexes), ``slave_ref`` the measured tip at the
     last state row before it (the slave holds still until then), ``master`` the stream
     interpolated at the row's time; ``scale`` is ``--scale`` (the shipped slave's 0.1).
     ``--master MASTER_RECORDING`` takes the master's own outbound POSITION stream instead of
     what reached the slave (every packet, the lost ones too). A re-index later in the
     recording (after a stop, a clutch) starts a new reference;
   - *setpoint vs measured* otherwise (a master's recording, or any robot): setpoint minus
     measured position of every joint (joint units: rad or m).

3. **State timeline with causes**: the state of every row (by name) and every state STATUS the
   robot sent, its cause written beside it (the first 12; all of them are in ``messages.csv`` of
   ``occ-record export``).
4. **Loop timing**: the interval between state rows (the recording rate: a row is written on the
   first tick at or after its due time, so lateness and missed ticks show up as longer
   intervals) and the inter-arrival of the input stream at the loop (the tick that took each
   packet), as histograms.

5. **Forces** (a recording that has them: bilateral teleoperation, issue 27): the force on the
   instrument (the slave's contact force, the ``force_n`` its return channel ``SlaveTip``
   carries: sent in a slave's recording, received in a master's; N, the patient frame) and the
   force on the hand (the master's displayed force, its ``Force`` output; N, the master's
   axes; from ``--master MASTER_RECORDING`` when the recording is a slave's), as magnitudes and
   the x components, with the RMS of their difference where both exist (the hand's resampled at
   the instrument's times; with a force scale other than 1 the hand's is scaled).

matplotlib is an optional dependency (``pip install 'occ-igtl[plot]'``); without it
``occ-record plot`` says so and exits with 2.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from occ.net.decoders import message_force
from occ.recording.record import STATE_CODES, STATE_DEVICE, STATE_NAMES, iter_recording

__all__ = ["PlotError", "RecordingSummary", "plot_recording", "summarize_recording"]

#: at most this many causes are written on the state timeline
MAX_CAUSES = 12
#: the messages a force comes in (occ.net.decoders.message_force)
_FORCE_TYPES = ("POSITION", "TRANSFORM", "SENSOR", "NDARRAY")


class PlotError(Exception):
    """The recording cannot be plotted: ``code`` 1 (no state rows, no master stream) or 2
    (matplotlib missing)."""

    def __init__(self, message: str, code: int = 1) -> None:
        super().__init__(message)
        self.code = code


@dataclass
class RecordingSummary:
    """The numbers behind the plot (also what the tests check)."""

    path: Path
    columns: list[str]
    #: state rows: t (s, the robot's loop clock), state code, then the other columns
    rows: np.ndarray
    #: STATUS messages the robot sent: (t, name, cause)
    statuses: list[tuple[float, str, str]] = field(default_factory=list)
    #: input POSITION stream: loop time (s), position (mm), run flag
    in_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    in_pos: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    in_run: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    #: tracking error (N x 3 mm, master vs slave) or (N x joints, setpoint - measured)
    error_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    error: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    error_kind: str = ""
    error_labels: list[str] = field(default_factory=list)
    reindexes: int = 0
    #: the force on the instrument (the slave's contact force, N, patient frame): t, N x 3
    cf_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    cf: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    #: the force on the hand (the master's displayed force, N, its axes): t, N x 3
    hand_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    hand: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    def col(self, name: str) -> np.ndarray:
        return self.rows[:, self.columns.index(name)]

    @property
    def t(self) -> np.ndarray:
        return self.rows[:, 0]

    @property
    def state_names(self) -> list[str]:
        return [STATE_NAMES.get(int(c), "?") for c in self.rows[:, 1].tolist()]

    def force_stats(self) -> dict[str, float]:
        """Peaks of both forces (N) and, where both exist, the RMS of the hand's minus the
        instrument's (the hand's interpolated at the instrument's times, inside its span)."""
        out: dict[str, float] = {}
        if len(self.cf_t):
            out["instrument_peak_n"] = float(np.linalg.norm(self.cf, axis=1).max())
        if len(self.hand_t):
            out["hand_peak_n"] = float(np.linalg.norm(self.hand, axis=1).max())
        if len(self.cf_t) and len(self.hand_t) > 1:
            sel = (self.cf_t >= self.hand_t[0]) & (self.cf_t <= self.hand_t[-1])
            if sel.any():
                hand = np.column_stack(
                    [np.interp(self.cf_t[sel], self.hand_t, self.hand[:, c]) for c in range(3)]
                )
                diff = hand - self.cf[sel]
                out["rms_difference_n"] = float(np.sqrt((diff**2).sum(axis=1).mean()))
        return out

    def error_stats(self) -> dict[str, dict[str, float]]:
        """mean |e|, p99 |e| and max |e| per error column."""
        out = {}
        for i, label in enumerate(self.error_labels):
            a = np.abs(self.error[:, i])
            if len(a):
                out[label] = {
                    "mean": float(a.mean()),
                    "p99": float(np.percentile(a, 99)),
                    "max": float(a.max()),
                }
        return out


def _stream(path: Path, direction: str) -> tuple[list[float], list[tuple[float, ...]], list[bool]]:
    ts: list[float] = []
    pos: list[tuple[float, ...]] = []
    run: list[bool] = []
    for m in iter_recording(path):
        meta = m.metadata
        if m.message_type == "POSITION" and meta.get("rec.dir") == direction and "rec.t" in meta:
            ts.append(float(meta["rec.t"]))
            pos.append(tuple(float(v) for v in m.position))  # type: ignore[attr-defined]
            run.append(meta.get("run", "1") == "1")
    return ts, pos, run


def summarize_recording(
    path: str | Path, *, scale: float = 0.1, master: str | Path | None = None
) -> RecordingSummary:
    """Read a recording (and optionally its master's) into the plot's numbers."""
    path = Path(path)
    rows: list[np.ndarray] = []
    columns = ""
    statuses: list[tuple[float, str, str]] = []
    in_t: list[float] = []
    in_pos: list[tuple[float, ...]] = []
    in_run: list[bool] = []
    # (kind, device) -> times, forces; each kind's stream with the most samples is plotted (a
    # slave sends its force at 500 Hz on SlaveTip and at 10 Hz to Slicer)
    forces: dict[tuple[str, str], tuple[list[float], list[tuple[float, float, float]]]] = {}
    for m in iter_recording(path):
        meta = m.metadata
        if m.message_type == "NDARRAY" and m.device_name == STATE_DEVICE:
            rows.append(np.asarray(m.array, dtype=np.float64).ravel())  # type: ignore[attr-defined]
            columns = meta.get("columns", columns)
        elif m.message_type == "STATUS" and meta.get("rec.if") == "*" and "rec.t" in meta:
            # the robot's broadcasts (state changes with their cause, stream alerts); replies
            # to one operator's GET_STATUS are addressed to an interface, not "*"
            name = m.error_name  # type: ignore[attr-defined]
            text = m.status_message  # type: ignore[attr-defined]
            statuses.append((float(meta["rec.t"]), name, text))
        elif (
            m.message_type == "POSITION"
            and meta.get("rec.dir") == "in"
            and "rec.t" in meta
            and "map" not in meta  # a slave's return channel is not a master's stream
        ):
            in_t.append(float(meta["rec.t"]))
            in_pos.append(tuple(float(v) for v in m.position))  # type: ignore[attr-defined]
            in_run.append(meta.get("run", "1") == "1")
        if "rec.t" in meta and m.message_type in _FORCE_TYPES:
            force = message_force(m)
            if force is not None:
                kind = "instrument" if force[0] == "patient" else "hand"
                ft, fv = forces.setdefault((kind, m.device_name), ([], []))
                ft.append(float(meta["rec.t"]))
                fv.append(force[1])
    if not rows:
        raise PlotError(f"{path}: no state rows ({STATE_DEVICE}): not an occd recording?")
    cols = columns.split(",")
    width = min(len(r) for r in rows)
    table = np.vstack([r[:width] for r in rows])
    s = RecordingSummary(path, cols[:width], table, statuses)
    s.in_t = np.asarray(in_t)
    s.in_pos = np.asarray(in_pos, dtype=np.float64).reshape(-1, 3)
    s.in_run = np.asarray(in_run, dtype=bool)
    if master is not None and not any(k[0] == "hand" for k in forces):
        for m in iter_recording(Path(master)):
            meta = m.metadata
            if meta.get("rec.dir") == "out" and "rec.t" in meta and m.device_name == "Force":
                force = message_force(m)
                if force is not None and force[0] == "base":
                    ft, fv = forces.setdefault(("hand", "Force"), ([], []))
                    ft.append(float(meta["rec.t"]))
                    fv.append(force[1])
    for kind in ("instrument", "hand"):
        best = max((v for k, v in forces.items() if k[0] == kind), key=lambda v: len(v[0]),
                   default=None)  # fmt: skip
        if best is None:
            continue
        t_arr = np.asarray(best[0])
        v_arr = np.asarray(best[1], dtype=np.float64).reshape(-1, 3)
        if kind == "instrument":
            s.cf_t, s.cf = t_arr, v_arr
        else:
            s.hand_t, s.hand = t_arr, v_arr
    tips = ("tip.x_mm", "tip.y_mm", "tip.z_mm")
    if len(s.in_t) and all(c in s.columns for c in tips):
        _master_vs_slave(s, scale, master)
    else:
        _setpoint_vs_measured(s)
    return s


def _master_vs_slave(s: RecordingSummary, scale: float, master: str | Path | None) -> None:
    ref_t, ref_pos = s.in_t, s.in_pos
    source = "the POSITION stream the robot took"
    if master is not None:
        mt, mp, _ = _stream(Path(master), "out")
        if len(mt) < 2:
            raise PlotError(f"{master}: no outbound POSITION stream (a master's recording?)")
        ref_t, ref_pos = np.asarray(mt), np.asarray(mp, dtype=np.float64)
        source = "the master's recorded POSITION stream"
    t = s.t
    tip = np.column_stack([s.col(c) for c in ("tip.x_mm", "tip.y_mm", "tip.z_mm")])
    running = s.rows[:, 1] == STATE_CODES["RUNNING"]
    # re-index points: the first run=1 sample taken after each entry into RUNNING
    entries = [i for i in range(len(t)) if running[i] and (i == 0 or not running[i - 1])]
    segs_t: list[np.ndarray] = []
    segs_e: list[np.ndarray] = []
    for n, i in enumerate(entries):
        end = entries[n + 1] if n + 1 < len(entries) else len(t)
        t_in = t[i - 1] if i > 0 else t[i]  # RUNNING from some tick after the previous row
        taken = np.flatnonzero((s.in_t >= t_in) & s.in_run)
        if not len(taken):
            continue
        t_re = s.in_t[taken[0]]
        mref = s.in_pos[taken[0]]
        before = np.flatnonzero(t[:end] <= t_re)
        if not len(before):
            continue
        sref = tip[before[-1]]
        sel = np.arange(len(t)) < end
        sel &= (t > t_re) & running & (t >= ref_t[0]) & (t <= ref_t[-1])
        if not sel.any():
            continue
        hand = np.column_stack([np.interp(t[sel], ref_t, ref_pos[:, c]) for c in range(3)])
        ideal = sref + scale * (hand - mref)
        segs_t.append(t[sel])
        segs_e.append(ideal - tip[sel])
        s.reindexes += 1
    if segs_t:
        s.error_t = np.concatenate(segs_t)
        s.error = np.vstack(segs_e)
    s.error_kind = (
        f"master vs slave (mm): slave_ref + {scale:g} x (master - master_ref) - measured tip; "
        f"master from {source}"
    )
    s.error_labels = ["X", "Y", "Z"]


def _setpoint_vs_measured(s: RecordingSummary) -> None:
    qs = [c for c in s.columns if c.startswith("q.")]
    pairs = [(c, "sp." + c[2:]) for c in qs if "sp." + c[2:] in s.columns]
    running = s.rows[:, 1] == STATE_CODES["RUNNING"]
    s.error_t = s.t[running]
    s.error = (
        np.column_stack([s.col(sp)[running] - s.col(q)[running] for q, sp in pairs])
        if pairs
        else np.zeros((int(running.sum()), 0))
    )
    s.error_kind = "setpoint - measured, per joint (rad or m), while RUNNING"
    s.error_labels = [q[2:] for q, _ in pairs]


def plot_recording(
    path: str | Path,
    out: str | Path | None = None,
    *,
    scale: float = 0.1,
    master: str | Path | None = None,
    dpi: int = 90,
) -> Path:
    """Write the PNG (default: the recording's path + ``.png``); returns its path."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as err:
        raise PlotError(
            "occ-record plot needs matplotlib: pip install 'occ-igtl[plot]' (or matplotlib)", 2
        ) from err
    s = summarize_recording(path, scale=scale, master=master)
    out = Path(out) if out is not None else Path(str(path) + ".png")
    t0 = float(s.t[0])
    has_forces = bool(len(s.cf_t) or len(s.hand_t))
    ratios = [3, 2.2, 1.6, 2] + ([2.2] if has_forces else [])
    fig, axes = plt.subplots(
        len(ratios), 1, figsize=(11, 12 + 2.6 * has_forces), gridspec_kw={"height_ratios": ratios}
    )
    ax_tr, ax_err, ax_st, ax_tm = axes[:4]
    if has_forces:
        _plot_forces(axes[4], s, t0)
    _plot_trajectories(ax_tr, s, t0)
    _plot_error(ax_err, s, t0)
    _plot_states(ax_st, s, t0)
    _plot_timing(ax_tm, s)
    for ax in (ax_tr, ax_err, ax_st):
        ax.set_xlabel("time since the first state row (s)", fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=dpi)
    plt.close(fig)
    return out


def _plot_trajectories(ax_tr: Any, s: RecordingSummary, t0: float) -> None:
    """Panel 1: the tip's X and Y (Z, mostly far from both, would flatten them: its range is
    in the legend), and the input stream on a second axis."""
    colors = ("tab:blue", "tab:orange", "tab:green")
    for c, color in zip(("tip.x_mm", "tip.y_mm"), colors, strict=False):
        if c in s.columns:
            ax_tr.plot(s.t - t0, s.col(c), color=color, linewidth=1.0, label=f"tip {c[4]} (mm)")
    if "tip.z_mm" in s.columns:
        z = s.col("tip.z_mm")
        ax_tr.plot([], [], " ", label=f"tip z {z.min():.2f}..{z.max():.2f} mm")
    ax_tr.set_ylabel("measured tip (mm)")
    ax_tr.set_title(f"{s.path.name}: trajectories")
    if len(s.in_t):
        tw = ax_tr.twinx()
        for i, (a, color) in enumerate(zip("XY", colors, strict=False)):
            tw.plot(
                s.in_t - t0,
                s.in_pos[:, i],
                color=color,
                linestyle=":",
                linewidth=0.9,
                label=f"input {a} (mm)",
            )
        tw.set_ylabel("input stream (mm, dotted)")
        h1, l1 = ax_tr.get_legend_handles_labels()
        h2, l2 = tw.get_legend_handles_labels()
        ax_tr.legend(h1 + h2, l1 + l2, fontsize=7, ncol=5, loc="upper right")
    else:
        ax_tr.legend(fontsize=7, ncol=3, loc="upper right")


def _plot_error(ax_err: Any, s: RecordingSummary, t0: float) -> None:
    """Panel 2: the tracking error."""
    stats = s.error_stats()
    for i, label in enumerate(s.error_labels):
        st = stats.get(label)
        extra = f" (mean |e| {st['mean']:.4g}, max {st['max']:.4g})" if st else ""
        ax_err.plot(s.error_t - t0, s.error[:, i], linewidth=0.8, label=f"{label}{extra}")
    ax_err.axhline(0.0, color="k", linewidth=0.5)
    ax_err.set_ylabel("tracking error")
    ax_err.set_title(s.error_kind, fontsize=9)
    if s.error_labels:
        ax_err.legend(fontsize=7, loc="upper right")
    if not len(s.error_t):
        ax_err.text(
            0.5, 0.5, "no tracking error: never RUNNING", ha="center", transform=ax_err.transAxes
        )


def _plot_states(ax_st: Any, s: RecordingSummary, t0: float) -> None:
    """Panel 3: the state timeline, with the STATUS the robot sent and their causes."""
    order = list(STATE_CODES)
    ax_st.step(s.t - t0, s.rows[:, 1], where="post", color="k", linewidth=1.0)
    ax_st.set_yticks(range(len(order)))
    ax_st.set_yticklabels(order, fontsize=7)
    ax_st.set_ylim(-0.5, len(order) - 0.5)
    ax_st.set_title("state (rows) and the STATUS the robot sent, with their causes", fontsize=9)
    changes = [st for st in s.statuses if st[1] in STATE_CODES]
    others = [st for st in s.statuses if st[1] not in STATE_CODES]
    for n, (ts, name, cause) in enumerate(changes):
        if n >= MAX_CAUSES:
            ax_st.text(
                0.99,
                0.02,
                f"+{len(changes) - MAX_CAUSES} more",
                ha="right",
                transform=ax_st.transAxes,
                fontsize=7,
            )
            break
        ax_st.axvline(ts - t0, color="tab:red", linewidth=0.6, alpha=0.6)
        text = f"{name}: {cause}" if cause else name
        ax_st.text(
            ts - t0,
            STATE_CODES[name],
            " " + (text if len(text) <= 70 else text[:67] + "..."),
            fontsize=6,
            va="bottom",
            color="tab:red",
        )
    if others:
        # alerts that change no state (a held stream resuming...): marks, the first one's text
        ax_st.plot(
            [st[0] - t0 for st in others],
            [len(order) - 0.8] * len(others),
            "|",
            color="tab:purple",
            markersize=8,
            label=f"{len(others)} other alerts, e.g. {others[0][1]}: {others[0][2][:60]}",
        )
        ax_st.legend(fontsize=6, loc="lower right")


def _plot_timing(ax_tm: Any, s: RecordingSummary) -> None:
    """Panel 4: the loop timing."""
    ax_tm.set_title("loop timing", fontsize=9)
    rows_ms = np.diff(s.t) * 1e3
    if len(rows_ms):
        lo, hi = float(rows_ms.min()), float(np.percentile(rows_ms, 99.9))
        ax_tm.hist(
            rows_ms,
            bins=np.linspace(lo, max(hi, lo + 1e-3), 60),
            alpha=0.6,
            label=f"interval between state rows (ms), max {rows_ms.max():.2f}",
        )
    if len(s.in_t) > 1:
        gaps = np.diff(s.in_t) * 1e3
        ax_tm.hist(
            gaps,
            bins=np.arange(0.0, max(8.0, math.ceil(float(gaps.max()))) + 0.5, 0.5),
            alpha=0.6,
            label=f"input stream inter-arrival at the loop (ms), max {gaps.max():.2f}",
        )
    ax_tm.set_yscale("log")
    ax_tm.set_xlabel("ms")
    ax_tm.set_ylabel("count")
    ax_tm.legend(fontsize=7)


def _plot_forces(ax: object, s: RecordingSummary, t0: float) -> None:
    """Panel 5: the force on the instrument and on the hand (module docstring)."""
    a: Any = ax
    st = s.force_stats()
    if len(s.cf_t):
        peak = st["instrument_peak_n"]
        a.plot(s.cf_t - t0, np.linalg.norm(s.cf, axis=1), color="tab:red", linewidth=1.0,
               label=f"|instrument| (slave's contact force), peak {peak:.2f} N")  # fmt: skip
        a.plot(s.cf_t - t0, s.cf[:, 0], color="tab:red", linewidth=0.6, linestyle=":",
               label="instrument x (patient frame)")  # fmt: skip
    if len(s.hand_t):
        peak = st["hand_peak_n"]
        a.plot(s.hand_t - t0, np.linalg.norm(s.hand, axis=1), color="tab:blue", linewidth=1.0,
               label=f"|hand| (master's displayed force), peak {peak:.2f} N")  # fmt: skip
        a.plot(s.hand_t - t0, s.hand[:, 0], color="tab:blue", linewidth=0.6, linestyle=":",
               label="hand x (master's axes)")  # fmt: skip
    a.axhline(0.0, color="k", linewidth=0.5)
    a.set_ylabel("force (N)")
    a.set_xlabel("time since the first state row (s)", fontsize=8)
    title = "forces: hand vs instrument"
    if "rms_difference_n" in st:
        title += f" (hand - instrument, RMS {st['rms_difference_n']:.3f} N)"
    a.set_title(title, fontsize=9)
    a.legend(fontsize=7, loc="upper right", ncol=2)
