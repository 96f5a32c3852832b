"""Blender as a Python module (the ``bpy`` package from PyPI), for testing that the rigs
tpscore writes open in Blender.

``bpy`` is installed on first use with pip, into a folder of its own inside the running
environment rather than into the environment itself: its wheels pin NumPy below 2 (and
exist for one Python version each), so installing it beside tpscore would downgrade the
NumPy the whole suite runs on. Blender runs in a subprocess that puts that folder first
on its path, with the NumPy it was built for. The outcome of the install is kept (the
folder, or a file saying why it failed), so it is tried once per environment.
"""
from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
from pathlib import Path

#: Where bpy and its dependencies are installed, and where a failed install is recorded.
SITE = Path(sys.prefix) / "tpscore-test-blender"
FAILED = Path(sys.prefix) / "tpscore-test-blender.failed"
_INSTALL_SECONDS = 1800  # the wheel is about 370 MB


def _works(environment: dict) -> str | None:
    """None when ``import bpy`` works in a subprocess with this environment, else why not."""
    try:
        run = subprocess.run([sys.executable, "-c", "import bpy; print(bpy.app.version_string)"], env=environment,
                             capture_output=True, text=True, timeout=300)
    except (subprocess.SubprocessError, OSError) as exc:
        return f"import bpy failed: {exc}"
    if run.returncode != 0:
        return "import bpy failed: " + (run.stderr.strip().splitlines() or ["no message"])[-1]
    return None


def _with_site(environment: dict) -> dict:
    paths = [str(SITE), environment.get("PYTHONPATH", "")]
    return dict(environment, PYTHONPATH=os.pathsep.join(p for p in paths if p))


def blender_environment() -> tuple[dict | None, str]:
    """(the environment a subprocess imports bpy with, "") or (None, why it cannot be had).

    bpy already importable here is used as it is; else the folder of an earlier install;
    else pip installs it there now, unless an earlier install failed (delete
    :data:`FAILED` to try again) or TPSCORE_NO_BLENDER_INSTALL is set.
    """
    environment = dict(os.environ)
    if importlib.util.find_spec("bpy") is not None and _works(environment) is None:
        return environment, ""
    if (SITE / "bpy").is_dir():
        why = _works(_with_site(environment))
        return (_with_site(environment), "") if why is None else (None, why)
    if FAILED.is_file():
        return None, f"{FAILED.read_text().strip()} (an earlier install failed; delete {FAILED} to try again)"
    if os.environ.get("TPSCORE_NO_BLENDER_INSTALL"):
        return None, "bpy is not installed and TPSCORE_NO_BLENDER_INSTALL forbids installing it"
    return _install(environment)


def _install(environment: dict) -> tuple[dict | None, str]:
    partial = SITE.with_name(SITE.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    try:
        run = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--disable-pip-version-check",
                              "--target", str(partial), "bpy"], capture_output=True, text=True,
                             timeout=_INSTALL_SECONDS)
        why = None if run.returncode == 0 else "pip install bpy failed: " + " ".join(
            line for line in run.stderr.splitlines() if line.startswith("ERROR"))[:500]
    except (subprocess.SubprocessError, OSError) as exc:
        why = f"pip install bpy failed: {exc}"
    if why is None:
        # the whole folder or none of it: an interrupted install leaves only the partial one
        partial.rename(SITE)
        why = _works(_with_site(environment))
        if why is None:
            return _with_site(environment), ""
        shutil.rmtree(SITE, ignore_errors=True)
    shutil.rmtree(partial, ignore_errors=True)
    try:
        FAILED.write_text(why + "\n")
    except OSError:
        pass
    return None, why


def run_blender(environment: dict, script: str, *arguments, timeout: float = 600) -> subprocess.CompletedProcess:
    """Run a Python script with bpy importable; its output is returned, a failure raised
    with Blender's own messages."""
    run = subprocess.run([sys.executable, "-c", script, *map(str, arguments)], env=environment,
                         capture_output=True, text=True, timeout=timeout)
    if run.returncode != 0:
        raise AssertionError(f"Blender's script failed ({run.returncode}):\n{run.stdout[-3000:]}\n{run.stderr[-3000:]}")
    return run
