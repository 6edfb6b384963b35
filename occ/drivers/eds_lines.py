"""The lines of an EDS file (CiA 306 electronic data sheet) that stop it loading, for a
refusal a person can act on: ``drive.eds:123: [6064] DataType=0xZZ is not a number``.

``canopen.import_od`` reads an EDS with the standard library's ``RawConfigParser`` and then
converts the values it needs; when either fails it says ``invalid literal for int() with base
0: '0xZZ'`` or ``'DataType'``, with no file and no line. This module reads the file again, line
by line as that parser does (sections, ``key=value`` or ``key: value``, ``;`` and ``#`` comments,
an inline ``;`` comment after white space, an indented line continuing the value above it), and
checks what canopen 2.4 would trip on, each problem with its line:

- a line that is neither a ``[section]`` nor a ``key=value``, one before any section, a key
  with no name, a section or a key given twice, text that is not in the locale's encoding;
- in an object's section (``[6064]``, ``[1600sub1]``): a missing ``ParameterName``, and for a
  variable a missing ``DataType`` or ``AccessType`` (on the section's line); a value canopen
  converts to a number that is none (``ObjectType``, ``DataType``, ``PDOMapping``; on its line);
  a sub-object before or without its object; a ``[....Name]`` section without its entries;
- the numbers of ``[DeviceInfo]``, ``[DeviceComissioning]``, ``[DummyUsage]``, ``[Comments]``.

It decides nothing about a drive: the driver calls it only when canopen refused the file, and
falls back to canopen's words when it finds no line (occ/drivers/cia402_setup.py).
"""

from __future__ import annotations

import locale
import re
from dataclasses import dataclass, field
from pathlib import Path

#: canopen's section patterns (canopen/objectdictionary/eds.py)
INDEX = re.compile(r"^[0-9A-Fa-f]{4}$")
SUB = re.compile(r"^([0-9A-Fa-f]{4})[S|s]ub([0-9A-Fa-f]+)$")
NAMES = re.compile(r"^([0-9A-Fa-f]{4})Name")
DUMMY = re.compile(r"^[Dd]ummy[Uu]sage$")
#: the parser's section and option patterns (configparser.RawConfigParser)
HEADER = re.compile(r"\[(?P<header>.+)\]")
OPTION = re.compile(r"(?P<option>.*?)\s*(?P<vi>=|:)\s*(?P<value>.*)$")

VAR, DOMAIN, ARRAY, RECORD = 7, 2, 8, 9
#: [DeviceInfo]'s keys canopen reads as numbers (base prefix allowed)
DEVICE_NUMBERS = (
    "VendorNumber", "ProductNumber", "RevisionNumber", "SimpleBootUpMaster",
    "SimpleBootUpSlave", "Granularity", "DynamicChannelsSupported", "GroupMessaging",
    "NrOfRXPDO", "NrOfTXPDO", "LSS_Supported",
)  # fmt: skip
MAX_REPORTED = 5


@dataclass
class Section:
    name: str
    line: int
    keys: dict[str, tuple[int, list[str]]] = field(default_factory=dict)

    def value(self, key: str) -> str | None:
        got = self.keys.get(key)
        return None if got is None else "\n".join(got[1]).rstrip()

    def line_of(self, key: str) -> int:
        got = self.keys.get(key)
        return self.line if got is None else got[0]


def _number(text: str, base: int = 0) -> bool:
    try:
        int(text, base)
    except ValueError:
        return False
    return True


def _strip_comment(line: str) -> str:
    """The line without its comment, as the parser sees it: a whole-line ``;`` or ``#``
    comment, or an inline ``;`` at the start or after white space."""
    if line.strip().startswith((";", "#")):
        return ""
    at = line.find(";")
    while at > 0 and not line[at - 1].isspace():
        at = line.find(";", at + 1)
    return (line if at < 0 else line[:at]).strip()


class _Reader:
    """One pass over the file's lines: its sections, and the problems of its syntax."""

    def __init__(self, lines: list[str]) -> None:
        self.sections: dict[str, Section] = {}
        self.problems: list[tuple[int, str]] = []
        section: Section | None = None
        key: str | None = None
        indent = 0
        for n, raw in enumerate(lines, 1):
            text = _strip_comment(raw)
            if not text:
                if section is not None and key is not None and not raw.strip():
                    section.keys[key][1].append("")
                continue
            here = len(raw) - len(raw.lstrip())
            if section is not None and key is not None and here > indent:
                section.keys[key][1].append(text)  # a continuation of the value above
                continue
            indent = here
            header = HEADER.match(text)
            if header:
                name = header.group("header")
                first = self.sections.get(name)
                if first is not None:
                    self.problems.append((n, f"[{name}] again (first on line {first.line})"))
                    section = first
                else:
                    section = self.sections[name] = Section(name, n)
                key = None
                continue
            option = OPTION.match(text)
            if section is None:
                self.problems.append((n, f"{text!r} comes before any [section]"))
            elif option is None:
                self.problems.append((n, f"[{section.name}] {text!r} is neither a [section] nor "
                                         "a key=value line"))  # fmt: skip
            elif not option.group("option"):
                self.problems.append((n, f"[{section.name}] {text!r} has no key before its "
                                         f"{option.group('vi')!r}"))  # fmt: skip
            else:
                key = option.group("option").rstrip()
                if key in section.keys:
                    first_line = section.keys[key][0]
                    self.problems.append(
                        (n, f"[{section.name}] {key} again (first on line {first_line})")
                    )
                section.keys[key] = (n, [option.group("value").strip()])


class _Checker:
    """canopen's reading of the sections, in its order, noting what it would trip on."""

    def __init__(self, sections: dict[str, Section]) -> None:
        self.sections = sections
        self.problems: list[tuple[int, str]] = []
        #: the objects canopen would have made so far: index -> object type
        self.objects: dict[int, int] = {}
        #: the objects with a sub-object 1 so far (a ``[....Name]`` section copies it)
        self.members: set[int] = set()

    def need(self, s: Section, key: str, why: str = "") -> str | None:
        value = s.value(key)
        if value is None:
            near = next((k for k in s.keys if k.lower() == key.lower()), None)
            hint = f" (it has {near}: keys are case-sensitive)" if near else ""
            self.problems.append((s.line, f"[{s.name}] lacks {key}{why}{hint}"))
        return value

    def number(self, s: Section, key: str, value: str | None, base: int = 0) -> int | None:
        if value is None:
            return None
        if not _number(value, base):
            kind = "a decimal number" if base == 10 else "a number"
            shown = value.replace("\n", "\\n")
            self.problems.append((s.line_of(key), f"[{s.name}] {key}={shown} is not {kind}"))
            return None
        return int(value, base)

    def optional_number(self, s: Section, key: str, base: int = 0) -> int | None:
        return self.number(s, key, s.value(key), base)

    def variable(self, s: Section, why: str) -> None:
        self.need(s, "ParameterName")
        data_type = self.number(s, "DataType", self.need(s, "DataType", why))
        self.need(s, "AccessType", why)
        if data_type is not None and data_type > 0x1B:
            # canopen looks the type up in a section of its own, when there is one
            defined = self.sections.get(f"{data_type:X}sub1")
            if defined is not None:
                what = f" (the definition of data type {data_type:#06x})"
                self.number(defined, "DefaultValue", self.need(defined, "DefaultValue", what))
        self.optional_number(s, "PDOMapping")

    def head(self) -> None:
        comments = self.sections.get("Comments")
        if comments is not None:
            count = self.number(comments, "Lines", self.need(comments, "Lines"))
            for k in range(1, (count or 0) + 1):
                self.need(comments, f"Line{k}", f" (Lines={count})")
        info = self.sections.get("DeviceInfo")
        if info is not None:
            for rate in (10, 20, 50, 125, 250, 500, 800, 1000):
                self.optional_number(info, f"BaudRate_{rate}")
            for key in DEVICE_NUMBERS:
                self.optional_number(info, key)
        commissioning = self.sections.get("DeviceComissioning")
        if commissioning is not None:
            self.optional_number(commissioning, "Baudrate", 10)
            self.optional_number(commissioning, "NodeID")

    def body(self) -> None:
        for name, s in self.sections.items():
            if DUMMY.match(name):
                for k in range(1, 8):
                    key = f"Dummy{k:04d}"
                    if self.number(s, key, self.need(s, key), 10) == 1:
                        self.objects[k] = VAR
            elif INDEX.match(name):
                self.index(s)
            elif sub := SUB.match(name):
                self.sub(s, int(sub.group(1), 16), int(sub.group(2), 16))
            elif names := NAMES.match(name):
                self.names(s, int(names.group(1), 16))

    def index(self, s: Section) -> None:
        self.need(s, "ParameterName")
        raw = s.value("ObjectType")
        kind = VAR if raw is None else self.number(s, "ObjectType", raw)
        index = int(s.name, 16)
        if kind in (VAR, DOMAIN):
            self.variable(s, " (required of a variable, ObjectType 0x7)")
        elif kind == ARRAY and "CompactSubObj" in s.keys:
            self.variable(s, " (required of a compact array, CompactSubObj)")
            self.members.add(index)
        if kind in (VAR, DOMAIN, ARRAY, RECORD):
            self.objects[index] = kind

    def sub(self, s: Section, index: int, subindex: int) -> None:
        kind = self.objects.get(index)
        if kind is None:
            self.problems.append((s.line, self.missing(s, index)))
        elif kind in (ARRAY, RECORD):
            self.variable(s, " (required of a sub-object)")
            if subindex == 1:
                self.members.add(index)

    def names(self, s: Section, index: int) -> None:
        count = self.number(s, "NrOfEntries", self.need(s, "NrOfEntries"), 10)
        if index not in self.objects:
            self.problems.append((s.line, self.missing(s, index)))
        elif index not in self.members:
            self.problems.append(
                (s.line, f"[{s.name}] names entries copied from sub-object 1 of {index:#06x}, "
                         "which has none")
            )  # fmt: skip
        for k in range(1, (count or 0) + 1):
            self.need(s, str(k), f" (NrOfEntries={count})")

    def missing(self, s: Section, index: int) -> str:
        parent = next((p for p in self.sections.values() if INDEX.match(p.name)
                       and int(p.name, 16) == index), None)  # fmt: skip
        if parent is None:
            return f"[{s.name}] has no object [{index:04X}]"
        if parent.line > s.line:
            return f"[{s.name}] comes before its object [{parent.name}] (line {parent.line})"
        return f"[{s.name}]: its object [{parent.name}] has an ObjectType canopen makes nothing of"


def eds_problems(path: str | Path) -> list[tuple[int, str]]:
    """What in the EDS file ``path`` stops canopen loading it: (line, what), by line."""
    data = Path(path).read_bytes()
    encoding = locale.getpreferredencoding(False)
    try:
        text = data.decode(encoding)
    except UnicodeDecodeError as err:
        line = data[: err.start].count(b"\n") + 1
        byte = data[err.start]
        return [(line, f"byte {byte:#04x} is not text in {encoding}")]
    reader = _Reader(text.splitlines())
    checker = _Checker(reader.sections)
    checker.head()
    checker.body()
    return sorted(set(reader.problems + checker.problems))


def eds_refusal(path: str | Path, err: BaseException) -> str:
    """Why the EDS ``path`` does not load, for a person: ``FILE:LINE: what`` for each line
    found (the first few), else canopen's own words (``err``) after the file's name."""
    try:
        found = eds_problems(path)
    except OSError as read_err:
        return f"eds {str(path)!r} does not load: {err} (and cannot be read: {read_err})"
    if not found:
        return f"eds {str(path)!r} does not load: {err}"
    shown = "; ".join(f"{path}:{line}: {what}" for line, what in found[:MAX_REPORTED])
    more = len(found) - MAX_REPORTED
    return shown + (f" (and {more} more)" if more > 0 else "")
