"""Finished rows kept on disk, so a killed report resumes at the row it was on and a new row costs only itself.

A row's scores are cached under a key made of what they depend on: the row's id (what generates
it: bundle digest, noise seed, streaming settings, precision; see
:mod:`~world_model.eval.report.lineup`), the clips (name and recording fingerprint), the
:class:`ReportConfig`, the judge's and the segmenter's weights and :data:`REPORT_VERSION`. A file whose key differs
is regenerated, never reused.
"""

from __future__ import annotations

import hashlib
import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from world_model.data import Clip
from world_model.data.clips import clip_fingerprint, write_json_atomic
from world_model.eval.judge import CnnJudge, JudgeBackend
from world_model.eval.report.config import ReportConfig
from world_model.eval.report.results import RowScores
from world_model.eval.segmenter import Segmenter

log = logging.getLogger(__name__)
# Part of every cached row's key: bump when rows or scoring change what a row's scores are.
REPORT_VERSION = 9


def row_cache_key(
    row_id: str, clips: Sequence[Clip], config: ReportConfig, judge: JudgeBackend, segmenter: Segmenter
) -> str:
    """Identity of one row's scores: generator id, clips (name + recording fingerprint), config,
    judge and segmenter."""
    blob = json.dumps(
        [
            REPORT_VERSION,
            row_id,
            [(c.name, clip_fingerprint(c)) for c in clips],
            config.to_json(),
            judge_identity(judge),
            segmenter_identity(segmenter),
        ],
        sort_keys=True,
    )
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def judge_identity(judge: JudgeBackend) -> str:
    """The CNN judge's weights and thresholds digest; other backends: their class name."""
    if not isinstance(judge, CnnJudge):
        return type(judge).__qualname__
    h = hashlib.sha256(json.dumps(judge.thresholds.__dict__, sort_keys=True, default=str).encode())
    for net in (judge.crop_net, judge.scene_net):
        _add_weights(h, net)
    return h.hexdigest()[:16]


def segmenter_identity(segmenter: Segmenter) -> str:
    """Digest of the segmenter's weights."""
    h = hashlib.sha256()
    _add_weights(h, segmenter.net)
    return h.hexdigest()[:16]


def _add_weights(h: hashlib._Hash, net: Any) -> None:
    """Feed every named tensor of ``net``'s state dict (an ``nn.Module``) into the digest ``h``."""
    for name, tensor in sorted(net.state_dict().items()):
        h.update(name.encode())
        h.update(tensor.detach().float().contiguous().numpy().tobytes())


@dataclass(frozen=True)
class RowCache:
    """``<folder>/<row>.json`` files holding ``{"key", "row_id", "result"}``, written atomically."""

    folder: Path

    def path(self, row: str) -> Path:
        return self.folder / f"{row}.json"

    def load(self, row: str, key: str) -> RowScores | None:
        """The row's cached scores when they were made under ``key``; None otherwise."""
        path = self.path(row)
        if not path.exists():
            return None
        try:
            saved = json.loads(path.read_text())
        except json.JSONDecodeError as err:
            log.warning("report row %s: unreadable cache %s (%s); generating again", row, path, err)
            return None
        if saved.get("key") != key:
            return None
        log.info("report row %s: reused from %s", row, path)
        return RowScores.from_json(saved["result"])

    def save(self, row: str, key: str, row_id: str, scores: RowScores) -> None:
        self.folder.mkdir(parents=True, exist_ok=True)
        write_json_atomic(self.path(row), {"key": key, "row_id": row_id, "result": scores.to_json()})
