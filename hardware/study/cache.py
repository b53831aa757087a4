"""Finished trials on disk, keyed by what decides their figures.

A trial's key is the hash of its specification (knobs, scenes, frames, seed, closed-loop run)
and of the code version: the hash of every source file of ``hapticloud.core``, so an edit to the
algorithms misses the cache while a study rerun or resumed after Ctrl-C finds every trial it
finished. One small JSON file per trial: an interrupted write loses only that trial.
"""

from __future__ import annotations

import hashlib
import json
import os
from functools import cache
from pathlib import Path
from typing import Any

import hapticloud.core
from hapticloud.core.studies.trade.evaluate import TrialResult, TrialSpec


@cache
def code_version() -> str:
    """Hash of the core's sources (what computes every figure)."""
    root = Path(hapticloud.core.__file__).parent
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        digest.update(str(path.relative_to(root)).encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def default_cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "hapticloud" / "study"


def trial_key(spec: TrialSpec) -> str:
    text = json.dumps({"spec": spec.to_json(), "code": code_version()}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:24]


class TrialCache:
    """Trials by :func:`trial_key` in ``folder`` (``None``: no cache, nothing read or written)."""

    def __init__(self, folder: Path | None) -> None:
        self.folder = folder
        if folder is not None:
            folder.mkdir(parents=True, exist_ok=True)

    def _path(self, spec: TrialSpec) -> Path | None:
        return None if self.folder is None else self.folder / f"{trial_key(spec)}.json"

    def get(self, spec: TrialSpec) -> TrialResult | None:
        path = self._path(spec)
        if path is None or not path.exists():
            return None
        try:
            data: dict[str, Any] = json.loads(path.read_text())
        except (OSError, ValueError):
            return None  # a torn write: measure again
        return TrialResult.from_json(data, cached=True)

    def put(self, spec: TrialSpec, result: TrialResult) -> None:
        path = self._path(spec)
        if path is None:
            return
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(result.to_json()))
        tmp.replace(path)


__all__ = ["TrialCache", "code_version", "default_cache_dir", "trial_key"]
