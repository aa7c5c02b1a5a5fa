"""The JSON-lines event stream and snapshot files the Blender add-on follows.

The protocol is documented in ``docs/interfaces.md`` (section "Trainer events"). With
``promptgs train --events`` each event is one JSON object on its own stdout line; without
it, events go nowhere and the CLI shows a tqdm bar instead.
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path
from typing import IO, Any

import numpy as np
import torch

from .gaussians import sh_to_rgb


def _clean(value: Any) -> Any:
    """JSON has no NaN/inf: send them as null so every reader can parse the line."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    return value


class EventWriter:
    """Writes events as JSON lines to a stream, or drops them when disabled."""

    def __init__(self, stream: IO[str] | None = None):
        self.stream = stream

    @classmethod
    def stdout(cls) -> "EventWriter":
        return cls(sys.stdout)

    @property
    def enabled(self) -> bool:
        return self.stream is not None

    def emit(self, event: str, **fields: Any) -> None:
        if self.stream is None:
            return
        record = {"event": event, "time": time.time(), **_clean(fields)}
        self.stream.write(json.dumps(record) + "\n")
        self.stream.flush()


def write_snapshot(
    path: Path,
    params: torch.nn.ParameterDict,
    score: torch.Tensor | None = None,
    error: torch.Tensor | None = None,
    field: dict[str, np.ndarray] | None = None,
) -> None:
    """Write the per-Gaussian arrays the add-on shows (atomically: no half-written file)."""
    with torch.no_grad():
        n = params["means"].shape[0]
        quats = params["quats"].detach()
        arrays = {
            "means": params["means"].detach(),
            "opacity": torch.sigmoid(params["opacities"].detach()),
            "scale": torch.exp(params["scales"].detach()),
            "rotation": quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12),
            "color": sh_to_rgb(params["sh0"].detach().reshape(n, 3)).clamp(0, 1),
            "score": score.detach() if score is not None else torch.zeros(n),
            "error": error.detach() if error is not None else torch.zeros(n),
        }
        out = {k: v.cpu().float().numpy() for k, v in arrays.items()}
    if field:
        out.update({k: np.asarray(v, dtype=np.float32) for k, v in field.items()})
    tmp = path.with_name(path.stem + ".tmp.npz")
    np.savez(tmp, **out)
    tmp.replace(path)
