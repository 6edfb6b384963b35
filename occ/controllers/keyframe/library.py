"""The trajectory library's commands (issue 28): ``KeyframeSave``, ``KeyframeLoad Set=``,
``KeyframeDelete`` and ``KeyframeLibrary`` (package docstring, "The trajectory library").

The storage is :mod:`occ.kinematics.trajlib`; this is what the keyframe controller does with it:
what may be saved (the acknowledged set, while it is still the stored one), what a load installs,
the listing, the refusals. The file work runs as jobs on the planner thread; what they need of the
controller is :class:`LibraryPort`."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Protocol

from occ.controllers.keyframe.plan import CheckedPlan
from occ.controllers.keyframe.sets import KeyframeSet, PlanSettings, make_set
from occ.errors import CommandError, LibraryError
from occ.kinematics.trajlib import Library, SavedSet, check_name
from occ.net.commands import Deferred

#: most sets KeyframeLibrary lists (a reply is one command message)
MAX_LIBRARY_LINES = 200
_FLAGS = {"1": True, "true": True, "yes": True, "0": False, "false": False, "no": False}


class LibraryPort(Protocol):
    """What the library commands use of the keyframe controller."""

    def install_unless_changed(self, kset: KeyframeSet, generation: int) -> bool:
        """Make ``kset`` the stored set unless the set changed since ``generation``."""
        ...

    def record(self, counter: str, error: str | None = None) -> None:
        """Count ``counter`` (and keep ``error`` as the last one) under the controller's lock."""
        ...

    def start(self, job: Callable[[Deferred], None]) -> Deferred:
        """Run ``job`` on the planner thread; CommandError "busy" when it has one."""
        ...


@dataclasses.dataclass
class LibraryCommands:
    """The library commands of one keyframe controller; ``library`` None: refused."""

    port: LibraryPort
    library: Library | None = None
    robot: str = ""  # the robot's name, saved with a set and required to load it
    digest: str = ""  # its kinematic configuration's hash (occ.kinematics.trajlib.config_hash)
    joint_names: tuple[str, ...] = ()
    max_keyframes: int = 100

    def _need_library(self, command: str) -> Library:
        if self.library is None:
            raise CommandError(
                f"{command}: there is no trajectory library in the configuration (the keyframe "
                "controller's `library` parameter)"
            )
        return self.library

    @staticmethod
    def _name_arg(command: str, args: dict[str, str]) -> str:
        if not args.get("set", "").strip():
            raise CommandError(f"{command} needs Set (the set's name in the library)")
        try:
            return check_name(args["set"])
        except LibraryError as err:
            raise CommandError(f"{command}: {err}") from None

    def _refused(self, answer: Deferred, text: str) -> None:
        self.port.record("library_refused", text)
        answer.fail(text)

    def save(
        self, args: dict[str, str], acked: CheckedPlan | None, kset: KeyframeSet | None
    ) -> Deferred:
        """KeyframeSave Set=N [Replace=1]: the set of the plan acknowledged last (``acked``),
        with its plan settings, while it is still the stored set (``kset``)."""
        library = self._need_library("KeyframeSave")
        name = self._name_arg("KeyframeSave", args)
        flag = args.get("replace", "0").strip().lower()
        if flag not in _FLAGS:
            raise CommandError(f"KeyframeSave: Replace must be 1 or 0, got {flag!r}")
        replace = _FLAGS[flag]
        if acked is None or acked.kset is None or acked.settings is None:
            raise CommandError(
                "KeyframeSave: only a planned and acknowledged set is saved: KeyframePlan, "
                "KeyframeAck, then KeyframeSave"
            )
        if acked.kset is not kset:
            raise CommandError(
                f"KeyframeSave: the keyframes changed since plan {acked.id} was acknowledged; "
                "plan and acknowledge them before saving"
            )
        st = acked.settings
        saved = SavedSet(
            name=name,
            robot=self.robot,
            config_hash=self.digest,
            space=kset.space,
            interpolation=st.interpolation,
            mode=st.mode,
            steepness=st.steepness,
            ramp=st.ramp,
            duration_s=acked.traj.duration,
            keyframes=tuple(
                (k.t, k.pose, label, k.rotation)
                for k, label in zip(kset.keyframes, kset.names, strict=True)
            ),
            joint_names=self.joint_names,
            source=kset.source,
        )

        def job(answer: Deferred) -> None:
            try:
                stored, replaced = library.save(saved, replace=replace)
            except LibraryError as err:
                self._refused(answer, f"KeyframeSave refused: {err}")
                return
            self.port.record("library_saved")
            answer.resolve(
                f"{'replaced' if replaced else 'saved'} {name!r}: {len(saved.keyframes)} "
                f"keyframes ({saved.space}, {st.interpolation}, {st.mode}), "
                f"{saved.duration_s:.3f} s, plan {acked.id}, robot {saved.robot!r} (config "
                f"{saved.config_hash[:12]}), at {stored.saved_at}"
            )

        return self.port.start(job)

    def load(self, args: dict[str, str], generation: int) -> Deferred:
        """KeyframeLoad Set=N: a saved set becomes the stored one (never run on load), unless
        the stored set changes after ``generation`` meanwhile."""
        library = self._need_library("KeyframeLoad Set=...")
        name = self._name_arg("KeyframeLoad", args)
        joints, cap = len(self.joint_names), self.max_keyframes
        robot, digest = self.robot, self.digest

        def job(answer: Deferred) -> None:
            try:
                saved = library.load(robot, name, digest)
                kset = make_set(
                    saved.space,  # type: ignore[arg-type]
                    list(saved.keyframes),
                    f"library {name}",
                    joints=joints,
                    max_keyframes=cap,
                )
                if saved.interpolation not in ("linear", "spline") or saved.mode not in (
                    "stop",
                    "continuous",
                ):
                    raise ValueError(f"unknown plan settings {saved.interpolation}/{saved.mode}")
            except (LibraryError, ValueError) as err:
                self._refused(answer, f"KeyframeLoad refused: {err}")
                return
            settings = PlanSettings(
                saved.interpolation,  # type: ignore[arg-type]
                saved.mode,  # type: ignore[arg-type]
                saved.steepness,
                saved.ramp,
            )
            kset = dataclasses.replace(kset, settings=settings)
            if not self.port.install_unless_changed(kset, generation):
                answer.fail("KeyframeLoad: the keyframes changed meanwhile; load again")
                return
            self.port.record("library_loaded")
            answer.resolve(
                f"{len(kset.keyframes)} keyframes ({kset.space}) from the library: {name!r}, "
                f"saved {saved.saved_at} ({saved.interpolation}, {saved.mode}, "
                f"{saved.duration_s:.3f} s); it does not run by itself: send KeyframePlan, "
                "look at the preview, then KeyframeAck"
            )

        return self.port.start(job)

    def delete(self, args: dict[str, str]) -> Deferred:
        """KeyframeDelete Set=N: one of this robot's sets."""
        library = self._need_library("KeyframeDelete")
        name = self._name_arg("KeyframeDelete", args)
        robot = self.robot

        def job(answer: Deferred) -> None:
            try:
                library.delete(robot, name)
            except LibraryError as err:
                self._refused(answer, f"KeyframeDelete refused: {err}")
                return
            self.port.record("library_deleted")
            answer.resolve(f"deleted {name!r} (robot {robot!r}) from the library")

        return self.port.start(job)

    def listing(self) -> Deferred:
        """KeyframeLibrary: the file's sets, marked when this robot may not load them."""
        library = self._need_library("KeyframeLibrary")
        robot, digest = self.robot, self.digest

        def job(answer: Deferred) -> None:
            try:
                entries, total = library.entries(MAX_LIBRARY_LINES)
            except LibraryError as err:
                self._refused(answer, f"KeyframeLibrary: {err}")
                return
            sets = "1 saved set" if total == 1 else f"{total} saved sets"
            lines = [f"{sets} in {library.path.name}; this robot: {robot!r}"]
            for e in entries:
                if e.robot != robot:
                    mark = " [another robot: not loadable here]"
                elif e.config_hash != digest:
                    mark = " [another kinematic configuration: refused]"
                else:
                    mark = ""
                lines.append(
                    f"  {e.name}: robot {e.robot!r}, {e.keyframe_count} keyframes ({e.space}, "
                    f"{e.interpolation}, {e.mode}), {e.duration_s:.3f} s, saved {e.saved_at}"
                    f"{mark}"
                )
            if total > len(entries):
                lines.append(f"  ... and {total - len(entries)} more")
            answer.resolve("\n".join(lines))

        return self.port.start(job)
