"""Persistence of what the service learns: motion parameters and the filter's slow states.

One JSON file ``<state_dir>/learned_state.json``::

    {"schema_version": 1, "t_s": <data time>, "params": {MotionParams fields},
     "slow_states": {estimator.slow_states()}, "vehicle": "<name>"}

Written atomically — temp file in the same directory, ``fsync``, ``os.replace``, then
``fsync`` of the directory — so a crash (SIGKILL, power loss) leaves either the old or
the new file, never a torn one. Reading tolerates a corrupt, partial or foreign file:
it is logged and ignored (the service then starts from the configured defaults).
"""
from __future__ import annotations

import json
import logging
import math
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from adaptnav.files import atomic_write_bytes
from adaptnav.fusion.motion_model import MotionParams

log = logging.getLogger(__name__)

SCHEMA_VERSION = 1
FILENAME = "learned_state.json"


@dataclass(frozen=True)
class LearnedState:
    """What is restored on start: data time, params (may be None) and slow states."""

    t_s: float
    params: MotionParams | None
    slow_states: dict[str, Any]


def _finite_json(obj: Any) -> Any:
    """Make ``obj`` strict JSON: numpy → Python, non-finite floats → None."""
    if isinstance(obj, dict):
        return {str(k): _finite_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite_json(v) for v in obj]
    if hasattr(obj, "tolist"):  # numpy arrays and scalars
        return _finite_json(obj.tolist())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def save_state(state_dir: str | Path, t_s: float, params: MotionParams | None,
               slow_states: dict[str, Any], vehicle: str = "") -> Path:
    """Persist the learned state; returns the file written."""
    doc = {
        "schema_version": SCHEMA_VERSION,
        "vehicle": vehicle,
        "t_s": float(t_s),
        "params": params.to_dict() if params is not None else None,
        "slow_states": _finite_json(slow_states),
    }
    path = Path(state_dir) / FILENAME
    atomic_write_bytes(path, json.dumps(doc, allow_nan=False, sort_keys=True).encode())
    return path


def state_dir_problem(state_dir: str | Path) -> str:
    """Why the learned state could not be written into ``state_dir`` ("" when it can): the
    folder made if missing and a temporary file created and removed there. The daemon asks at
    start, so an operator learns it then, not at the first save minutes later or at shutdown
    (a root-owned bind mount, a read-only card, a user without ``/var/lib/adaptnav``)."""
    try:
        folder = Path(state_dir)
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as e:
        return f"{type(e).__name__}: {e.strerror or e}"
    return ""


def load_state(state_dir: str | Path) -> LearnedState | None:
    """Read the learned state, or ``None`` when absent or unusable (logged, never raised)."""
    path = Path(state_dir) / FILENAME
    try:
        doc = json.loads(path.read_bytes())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as e:  # truncated/garbled JSON, unreadable file
        log.warning("ignoring persisted state %s: %s", path, e)
        return None
    try:
        if not isinstance(doc, dict) or doc.get("schema_version") != SCHEMA_VERSION:
            raise ValueError(f"schema_version {doc.get('schema_version') if isinstance(doc, dict) else None!r}")
        params = MotionParams.from_dict(doc["params"]) if doc.get("params") is not None else None
        slow = doc.get("slow_states") or {}
        if not isinstance(slow, dict):
            raise ValueError("slow_states is not an object")
        return LearnedState(float(doc.get("t_s", 0.0)), params, slow)
    except (KeyError, TypeError, ValueError) as e:
        log.warning("ignoring persisted state %s: %s", path, e)
        return None
