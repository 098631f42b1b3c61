"""Run the Khronos glTF-Validator (npm ``gltf-validator``) on a file, from Python tests.

The validator is installed from the committed lock file with ``npm ci --prefix tools``;
:func:`validate` runs ``node tools/validate_gltf.mjs <path> --json`` and returns the
report's issue summary.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

TOOLS = Path(__file__).resolve().parent.parent / "tools"
SCRIPT = TOOLS / "validate_gltf.mjs"
INSTALL_HINT = "install the Khronos glTF validator with: npm ci --prefix tools"


class ValidatorUnavailable(RuntimeError):
    """node or the npm package is missing; the message says how to install it."""


def unavailable_reason() -> str | None:
    """Why the validator cannot run here, or None when it can."""
    if shutil.which("node") is None:
        return f"node is not on PATH (Node.js >= 18 needed); then {INSTALL_HINT}"
    if not (TOOLS / "node_modules" / "gltf-validator").is_dir():
        return f"{TOOLS / 'node_modules'} has no gltf-validator: {INSTALL_HINT}"
    return None


def validate(path) -> dict:
    """Validate a ``.glb``/``.gltf`` file with the real Khronos validator.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    dict
        ``numErrors``, ``numWarnings``, ``numInfos``, ``numHints`` (int) and ``messages``
        (list of dict with ``code``, ``message``, ``severity`` (0 error … 3 hint), ``pointer``).

    Raises
    ------
    ValidatorUnavailable
        When node or the npm package is missing (with the install command).
    RuntimeError
        When the validator cannot read the file at all.
    """
    reason = unavailable_reason()
    if reason:
        raise ValidatorUnavailable(reason)
    run = subprocess.run(
        ["node", str(SCRIPT), str(Path(path).resolve()), "--json"],
        capture_output=True, text=True, timeout=120, check=False,
    )
    if run.returncode not in (0, 1):
        raise RuntimeError(f"glTF validator failed on {path} (exit {run.returncode}): {run.stderr.strip()}")
    issues = json.loads(run.stdout)["issues"]
    keys = ("numErrors", "numWarnings", "numInfos", "numHints", "messages")
    return {key: issues[key] for key in keys}
