"""Compile the control loop's hot path with mypyc, in place (occ/_native.py says what and why).

    python scripts/build_native.py          # build if missing or stale; exit 0 when compiled
    python scripts/build_native.py --force  # rebuild
    python scripts/build_native.py --clean  # remove the build: the pure sources run

Needs mypy (with mypyc) and setuptools >= 77 (the ``native`` extra) and a C compiler. The C
sources go to build/mypyc-*; the extension modules next to their sources, with the group's
shared library at the project root; then occ/_native.json records the hashes of the sources
compiled. A fresh interpreter must then report the compiled build, or this fails and removes
what it built. Takes about 80 s on the project's 2-core machine.
"""

from __future__ import annotations

import argparse
import importlib.machinery
import json
import os
import shutil
import subprocess
import sys
import sysconfig
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ["OCC_PURE"] = "1"  # this process only reads the module list
from occ import _native  # noqa: E402


def group_libraries() -> list[Path]:
    suffix = importlib.machinery.EXTENSION_SUFFIXES[0]
    return sorted(ROOT.glob(f"*__mypyc{suffix}"))


def clean() -> None:
    _native.MANIFEST.unlink(missing_ok=True)
    for m in _native.MODULES:
        _native.extension_path(m).unlink(missing_ok=True)
    for lib in group_libraries():
        lib.unlink()


def check() -> str:
    """The build a fresh interpreter picks, and whether the hot modules are extensions."""
    code = (
        "import occ._native as n, importlib;"
        "mods = [importlib.import_module(m) for m in n.MODULES];"
        "print(n.BUILD, all(n.is_compiled(m) for m in mods), n.REASON)"
    )
    env = {k: v for k, v in os.environ.items() if k != "OCC_PURE"}
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True
    )
    if out.returncode != 0:
        return f"import failed: {out.stderr.strip()[-2000:]}"
    return out.stdout.strip()


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--force", action="store_true", help="rebuild even if up to date")
    p.add_argument("--clean", action="store_true", help="remove the build and stop")
    p.add_argument("--quiet", "-q", action="store_true", help="only problems and the result")
    args = p.parse_args()
    if args.clean:
        clean()
        print("[native] removed: the pure sources run")
        return 0
    if not args.force:
        status = check()
        if status.startswith("compiled True"):
            if not args.quiet:
                print(f"[native] up to date: {status.split(' ', 2)[2]}")
            return 0
    include = Path(sysconfig.get_paths()["include"], "Python.h")
    if not include.is_file():
        print(
            f"[native] no {include}: install this Python's headers (python3-dev)", file=sys.stderr
        )
        return 1
    import setuptools

    if int(setuptools.__version__.split(".")[0]) < 77:
        print(
            f"[native] setuptools {setuptools.__version__} cannot read pyproject.toml's SPDX "
            "licence: pip install 'setuptools>=77' (the native extra)",
            file=sys.stderr,
        )
        return 1
    if not (shutil.which("cc") or shutil.which("gcc")):
        print("[native] no C compiler (cc, gcc) on PATH", file=sys.stderr)
        return 1
    clean()
    hashes = _native.source_hashes()  # before compiling: what the extensions are built from
    sources = [str(_native.source_path(m).relative_to(ROOT)) for m in _native.MODULES]
    build_dir = ROOT / "build"
    log = build_dir / "native-build.log"
    build_dir.mkdir(exist_ok=True)
    print(f"[native] compiling {len(sources)} modules with mypyc (about 80 s) ...", flush=True)
    t0 = time.monotonic()
    env = dict(os.environ, OCC_PURE="1")
    with log.open("w") as out:
        rc = subprocess.call(
            [sys.executable, "-m", "mypyc", *sources], cwd=ROOT, env=env, stdout=out, stderr=out
        )
    if rc != 0:
        clean()
        sys.stderr.write(log.read_text()[-4000:])
        print(
            f"[native] mypyc failed (exit {rc}; log {log}): the pure sources run", file=sys.stderr
        )
        return 1
    import mypy.version

    libs = group_libraries()
    if len(libs) != 1:
        clean()
        print(f"[native] expected one group library, found {libs}", file=sys.stderr)
        return 1
    _native.MANIFEST.write_text(
        json.dumps(
            {
                "soabi": importlib.machinery.EXTENSION_SUFFIXES[0],
                "mypyc": mypy.version.__version__,
                "group": libs[0].name,
                "modules": hashes,
            },
            indent=1,
        )
        + "\n"
    )
    status = check()
    if not status.startswith("compiled True"):
        clean()
        print(f"[native] the build does not load: {status}", file=sys.stderr)
        return 1
    print(f"[native] compiled in {time.monotonic() - t0:.0f} s: {status.split(' ', 2)[2]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
