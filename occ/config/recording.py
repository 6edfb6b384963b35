"""Recording, timing statistics and the State Data Table."""

from __future__ import annotations

from typing import Annotated

from pydantic import Field

from occ.config.base import Bool, OutputPath, PosFloat, _Model


class RecordingConfig(_Model):
    """Recording of robot state (and optionally messages) to a file."""

    path: OutputPath | None = Field(
        None, description="Output file, relative to the config file's directory; null = off."
    )
    rate_hz: PosFloat = Field(
        100.0, description="Sampling rate of robot state in Hz; <= `robot.rate_hz`."
    )
    include_messages: Bool = Field(True, description="Also record IGTL messages in and out.")
    directory: OutputPath = Field(
        "recordings",
        validate_default=True,
        description="Where recordings started at run time go (`StartRecording`'s "
        "`OutputFilename`, a bare file name), relative to the config file's directory.",
    )


class StatsConfig(_Model):
    """Timing statistics (always collected)."""

    log_every_s: PosFloat = Field(10.0, description="Log a statistics summary this often (s).")


class StateTableConfig(_Model):
    """The State Data Table: the last seconds of the robot's state at the loop rate."""

    seconds: Annotated[PosFloat, Field(le=600)] | None = Field(
        None,
        description="How many seconds of state the table keeps (rows = seconds x `rate_hz`, "
        "preallocated; at most 600 s); read with the `GetStateTable` command (a reply holds "
        "at most 65535 rows, the newest). null = no table.",
    )
