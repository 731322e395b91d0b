"""Run cache shared by the reproduction reports: one ``.npz`` per run holding the arrays and a JSON
header that says what produced them (parameters, report version). A run is reused when the stored
header equals the one the report would write now; anything else — missing, unreadable, other
header — means run again."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np


def _canonical(header: dict[str, Any]) -> str:
    return json.dumps(header, sort_keys=True)


def _open(path: Path, header: dict[str, Any]) -> Any:
    """The lazily read npz at ``path`` if its header equals ``header`` (compared as JSON), else None."""
    if not path.exists():
        return None
    try:
        z = np.load(path, allow_pickle=False)
        if _canonical(json.loads(str(z["header"]))) != _canonical(json.loads(_canonical(header))):
            return None
        return z
    except Exception:  # noqa: BLE001 - an unreadable cache entry is simply run again
        return None


def is_cached(path: Path, header: dict[str, Any]) -> bool:
    """Does ``path`` hold a run made with ``header``? (Reads the header only.)"""
    return _open(path, header) is not None


def load_npz(path: Path, header: dict[str, Any]) -> dict[str, np.ndarray] | None:
    """The arrays stored at ``path`` if its header equals ``header``, else None."""
    z = _open(path, header)
    try:
        return None if z is None else {k: z[k] for k in z.files if k != "header"}
    except Exception:  # noqa: BLE001 - a damaged array: run again
        return None


def save_npz(path: Path, header: dict[str, Any], data: dict[str, Any]) -> None:
    """Store ``data`` (arrays) with ``header`` at ``path`` atomically (write, then rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, header=_canonical(header), **{k: np.asarray(v) for k, v in data.items()})
    tmp.replace(path)


def reusable_run(scn: Any, run_dir: Path, npz_name: str, version: int, *, summary_version_key: str | None = None,
                 reject_verdicts: tuple[str, ...] = ()) -> bool:
    """May a report reuse the ``canbrake run`` in ``run_dir``? Yes when it ran exactly this
    scenario (its resolved ``scenario.yaml``), ended with status ok (and a verdict not in
    ``reject_verdicts``), and its reduced trace ``npz_name`` (and, if given, the summary's
    ``summary_version_key``) carry ``version``. Anything missing or unreadable: run again."""
    import json

    try:
        if (run_dir / "scenario.yaml").read_text() != scn.to_yaml():
            return False
        s = json.loads((run_dir / "summary.json").read_text())
        if s.get("status") != "ok" or s.get("verdict") in reject_verdicts:
            return False
        if summary_version_key is not None and s.get(summary_version_key) != version:
            return False
        with np.load(run_dir / npz_name) as z:
            return int(z["version"]) == version
    except (OSError, ValueError, KeyError):
        return False
