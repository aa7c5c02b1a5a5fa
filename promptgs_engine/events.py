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

from .errors import PromptGSError
from .gaussians import make_params, rgb_to_sh, sh_to_rgb


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


SNAPSHOT_KEYS = ("means", "opacity", "scale", "rotation", "color")


def read_snapshot_params(path: Path) -> torch.nn.ParameterDict:
    """Gaussians to render from a snapshot file: positions, shapes, opacities, and the
    DC colour only (a snapshot keeps no view-dependent SH terms, so it renders with
    degree 0). One-line :class:`PromptGSError` for a missing or incomplete file."""
    path = Path(path)
    try:
        with np.load(path) as npz:
            missing = [key for key in SNAPSHOT_KEYS if key not in npz.files]
            if missing:
                raise PromptGSError(f"{path}: not a PromptGS snapshot (no {', '.join(missing)})")
            arrays = {key: torch.from_numpy(np.asarray(npz[key], np.float32)) for key in SNAPSHOT_KEYS}
    except FileNotFoundError:
        raise PromptGSError(f"{path}: no such snapshot file") from None
    except (OSError, ValueError) as exc:
        raise PromptGSError(f"{path}: cannot read snapshot ({exc})") from None
    n = arrays["means"].shape[0]
    opacity = arrays["opacity"].clamp(1e-6, 1 - 1e-6)
    return make_params(
        means=arrays["means"],
        scales=torch.log(arrays["scale"].clamp_min(1e-12)),
        quats=arrays["rotation"],
        opacities=torch.log(opacity / (1 - opacity)),
        sh0=rgb_to_sh(arrays["color"]).reshape(n, 1, 3),
        shN=torch.zeros(n, 0, 3),
    )
