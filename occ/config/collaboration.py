"""The ``collaboration`` section: several masters for one slave, one owns the motion."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from occ.config.base import Name, _Model


class CollabMaster(_Model):
    """One master of a collaborative slave: its stream interface and its operators' console."""

    input: Name = Field(
        description="Interface of this master's POSITION stream (a `stream` input); it gets a "
        "loss monitor of its own with `safety.loss`'s parameters."
    )
    console: Name | None = Field(
        None,
        description="Operator interface on which this master's operator (its surgeon) sends "
        "commands: a `Handover` from there speaks for this master. null = none.",
    )


class CollaborationConfig(_Model):
    """Collaborative control (the SAW's mentoring): several masters, one owns the motion."""

    masters: tuple[CollabMaster, ...] = Field(
        min_length=1, description="The masters that may drive this slave, each on its own stream."
    )
    owner: Name | None = Field(
        None, description="The master (its `input`) in control at start; null = the first."
    )
    supervisor: Name | None = Field(
        None,
        description="The master whose console may always hand control over, to itself "
        "(take it back) or to anyone; null = none.",
    )
    request: tuple[Name, ...] = Field(
        (), description="Masters whose console may take control for itself without a grant."
    )
    grant: tuple[Name, ...] | None = Field(
        None,
        description="Masters whose console may give control away while it has it; null = all.",
    )
    others: Literal["supervisor", "refuse"] = Field(
        "supervisor",
        description="What an operator on an operator interface that is no master's console "
        "(the bedside's port) may do: hand over like the `supervisor`, or nothing (`refuse`).",
    )

    def names(self) -> tuple[str, ...]:
        return tuple(m.input for m in self.masters)
