"""The ``environment`` section: the simulated tissue the tool of ``sim`` drives presses on."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, field_validator

from occ.config.base import Float, Name, PosFloat, Vec3, _Model


class ContactConfig(_Model):
    """One simulated tissue the tool presses on (patient frame, mm; occ/haptics/contact.py)."""

    name: Name = Field("tissue", description="Its name (statistics, alerts, Slicer).")
    kind: Literal["wall", "sphere"] = Field(
        description="`wall`: tissue behind a plane (a half-space); `sphere`: tissue inside a ball."
    )
    point_mm: Vec3 = Field(
        description="`wall`: a point on its surface; `sphere`: its centre (patient frame, mm)."
    )
    normal: Vec3 = Field(
        (0.0, 0.0, 1.0),
        description="`wall`: the surface normal pointing out of the tissue, toward the tool "
        "(made unit length).",
    )
    radius_mm: PosFloat = Field(10.0, description="`sphere`: its radius (mm).")
    stiffness: Annotated[Float, Field(ge=0)] = Field(
        0.5, description="N per mm of penetration (soft tissue: 0.05-1)."
    )
    damping: Annotated[Float, Field(ge=0)] = Field(
        0.0,
        description="N s/mm, while penetrating; the force never pulls the tool in "
        "(it is clamped at zero).",
    )

    @field_validator("normal")
    @classmethod
    def _nonzero(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        if not any(abs(c) > 0.0 for c in v):
            raise ValueError("the normal must not be zero")
        return v


class EnvironmentConfig(_Model):
    """What the simulated drives touch: tissue that pushes back on the tool (issue 27). The
    contact force acts on the simulated joints (``J^T F``, the robot's kinematic model), so a
    position servo feels it as a load and reports the effort that holds it."""

    contacts: tuple[ContactConfig, ...] = Field((), description="Tissue, in the patient frame.")
