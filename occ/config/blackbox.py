"""The flight recorder: ``black_box`` (occ/recording/blackbox.py)."""

from __future__ import annotations

from typing import Annotated

from pydantic import Field

from occ.config.base import Bool, Int, OutputPath, PosFloat, _Model


class BlackBoxConfig(_Model):
    """The flight recorder: the last seconds of everything the loop read and did, kept in a
    preallocated ring and written to a directory when the robot stops for a safety reason,
    faults, is emergency-stopped, or an operator asks (`DumpBlackBox`)."""

    enabled: Bool = Field(True, description="Keep the ring and dump it (on by default).")
    seconds: Annotated[PosFloat, Field(le=600)] = Field(
        30.0,
        description="How many seconds of ticks the ring keeps (rows = seconds x `rate_hz`, "
        "preallocated; at most 600 s).",
    )
    events_per_s: Annotated[Int, Field(ge=100, le=100_000)] = Field(
        4000,
        description="Message and event slots per second of ring (preallocated; a burst beyond "
        "them shortens the window of messages, and the dump says from which tick on it is "
        "whole).",
    )
    dir: OutputPath = Field(
        "black_box",
        validate_default=True,
        description="Where dumps go (`<robot>-<time>-<cause>/`), relative to the config "
        "file's directory.",
    )
    max_dumps: Annotated[Int, Field(ge=1, le=10_000)] = Field(
        20, description="Dumps kept in `dir`; the oldest are removed."
    )
    max_mb: PosFloat = Field(
        500.0,
        description="Disk the dumps in `dir` may use (MB); the oldest are removed (the newest "
        "is always kept).",
    )
