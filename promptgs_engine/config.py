"""Training settings: one dataclass, written to ``cfg.json`` in every run folder."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .errors import PromptGSError
from .render.projection import EPS2D

# The screen-space filter of full-size renders: a variance in pixels² added to every
# projected Gaussian (gsplat's ``eps2d``). 3DGS's 0.3 draws even the smallest Gaussian
# about three pixels across. PromptGS uses 0.1, close to the variance of a one-pixel box
# filter (1/12), so an object one pixel wide can be drawn one pixel wide (docs/promptgs.md).
BASELINE_SCREEN_FILTER = EPS2D  # 0.3, the rasterizers' default
PROMPTGS_SCREEN_FILTER = 0.1
# An antialiased filter scales each Gaussian's opacity so the filter keeps its screen-space
# energy (render.projection.filter_compensation): an object smaller than a pixel then
# covers its pixel in proportion to its projected area from every distance and at every
# resolution, as in the ground truth. Off by default: over the benchmark grid it did not
# raise recall and cost whole-image PSNR (docs/promptgs.md, "Antialiased").


@dataclass
class TrainConfig:
    dataset: str
    out: str
    images: str = "images"
    iterations: int = 7000
    backend: str = "auto"  # auto | cpu | cuda
    seed: int = 0
    resolution_scale: float = 1.0  # images are downscaled by the whole factor round(1 / scale)
    strategy: str = "3dgs"  # 3dgs | absgs | promptgs
    sh_degree: int = 3
    ssim_lambda: float = 0.2
    test_every: int = 8
    init_opacity: float = 0.1
    # Learning rates of the 3DGS paper; `means_lr` is multiplied by the scene extent and
    # decays exponentially to 1% of its start over the run.
    means_lr: float = 1.6e-4
    scales_lr: float = 5e-3
    quats_lr: float = 1e-3
    opacities_lr: float = 5e-2
    sh0_lr: float = 2.5e-3
    shN_lr: float = 2.5e-3 / 20
    budget: int | str | None = None  # maximum number of Gaussians; None: no limit; "auto": stop growing when it stops paying
    snapshot_every: int = 0  # write a snapshot .npz every N steps (0: only at the end when events are on)
    checkpoint_every: int = 1000
    progress_every: int = 10
    save_test_renders: bool = False  # keep the test-view renders of the final evaluation in RUN/renders/
    # PromptGS options (see docs/promptgs.md); unused by the baselines.
    prompts: Any = None  # path of a prompt file, or the prompt object itself
    center_prompt: bool = False
    auto_prompts: int = 0
    propose_prompts: bool = False  # add prompts where views agree the render misses a small object (propose.py)
    progressive: bool | None = None  # None: on for promptgs, off for the baselines
    screen_filter: float | None = None  # px² at full size; None: PROMPTGS_SCREEN_FILTER for promptgs, else BASELINE_SCREEN_FILTER
    antialiased: bool = False  # opacity compensation of the screen filter (--antialiased), any strategy
    compact: bool = False  # remove the least contributing Gaussians when growth ends (compaction.py)
    sky: bool = True  # start a far shell of Gaussians where the cameras see background (see sky.py)
    # Views per optimisation step, over all ranks; None: one per rank. The learning rates,
    # Adam and the schedule follow batch.py's rules; `iterations` counts views.
    batch_size: int | None = None
    # Start from the Gaussians of a PLY, SPZ or glTF file instead of the SfM points (and
    # no sky shell); write the final Gaussians in more formats beside the PLY (formats/).
    init: str | None = None
    export: list = field(default_factory=list)  # of "spz", "gltf", "ply"
    extra: dict = field(default_factory=dict)

    @property
    def budget_cap(self) -> int | None:
        """The fixed budget, or None (no limit, or found automatically)."""
        return None if self.budget in (None, "auto") else int(self.budget)

    @property
    def effective_screen_filter(self) -> float:
        """The screen-space filter (px²) of this run's full-size renders, training and evaluation."""
        if self.screen_filter is not None:
            return float(self.screen_filter)
        return PROMPTGS_SCREEN_FILTER if self.strategy == "promptgs" else BASELINE_SCREEN_FILTER

    @property
    def rasterize_mode(self) -> str:
        """``render()``'s rasterize_mode for every render of this run: "antialiased" or "classic"."""
        return "antialiased" if self.antialiased else "classic"

    @property
    def downscale(self) -> int:
        if not 0 < self.resolution_scale <= 1:
            raise PromptGSError(f"--resolution-scale must be in (0, 1], got {self.resolution_scale}")
        return max(1, round(1.0 / self.resolution_scale))

    def validate(self) -> None:
        if self.iterations < 1:
            raise PromptGSError(f"--iterations must be at least 1, got {self.iterations}")
        if self.backend not in ("auto", "cpu", "cuda"):
            raise PromptGSError(f"unknown backend {self.backend!r} (use auto, cpu or cuda)")
        from .strategies import STRATEGY_NAMES

        if self.strategy not in STRATEGY_NAMES:
            raise PromptGSError(f"unknown strategy {self.strategy!r} (use {', '.join(STRATEGY_NAMES)})")
        if not 0 <= self.sh_degree <= 3:
            raise PromptGSError(f"--sh-degree must be 0..3, got {self.sh_degree}")
        if self.budget is not None and self.budget != "auto":
            if isinstance(self.budget, bool) or not isinstance(self.budget, int) or self.budget < 1:
                raise PromptGSError(f"--budget must be a positive whole number or 'auto', got {self.budget!r}")
        if self.screen_filter is not None and (
            isinstance(self.screen_filter, bool) or not isinstance(self.screen_filter, (int, float))
            or not 0 < self.screen_filter < 100
        ):
            raise PromptGSError(f"--screen-filter must be a variance in pixels² between 0 and 100 (3DGS: 0.3), got {self.screen_filter!r}")
        if not isinstance(self.propose_prompts, bool):
            raise PromptGSError(f"propose_prompts must be true or false, got {self.propose_prompts!r}")
        asked = self.prompt_options()
        if asked and self.strategy != "promptgs":
            hint = "; `promptgs propose RUN` proposes from any finished run" if self.propose_prompts else ""
            raise PromptGSError(f"{' and '.join(asked)} needs --strategy promptgs (got {self.strategy!r}): "
                                f"3DGS and AbsGS train without prompts{hint}")
        if self.batch_size is not None and (
            isinstance(self.batch_size, bool) or not isinstance(self.batch_size, int) or self.batch_size < 1
        ):
            raise PromptGSError(f"--batch-size must be a positive whole number of views, got {self.batch_size!r}")
        if not isinstance(self.antialiased, bool):
            raise PromptGSError(f"antialiased must be true or false, got {self.antialiased!r}")
        if not isinstance(self.compact, bool):
            raise PromptGSError(f"compact must be true or false, got {self.compact!r}")
        self.downscale  # validates resolution_scale
        from .formats import check_init, export_formats

        self.export = export_formats(self.export)
        check_init(self.init)

    def prompt_options(self) -> list[str]:
        """The options asking for prompt boxes (a prompt file or inline boxes, the centre
        box, automatic or proposed prompts), as the command line names them. An inline
        prompt object without boxes asks for none."""
        if isinstance(self.prompts, dict):
            has_boxes = bool(self.prompts.get("prompts"))
        elif isinstance(self.prompts, list):
            has_boxes = bool(self.prompts)
        else:  # a path, or None
            has_boxes = self.prompts is not None
        asked = [
            ("--prompts", has_boxes),
            ("--center-prompt", bool(self.center_prompt)),
            ("--auto-prompts", bool(self.auto_prompts)),
            ("--propose-prompts", self.propose_prompts),
        ]
        return [flag for flag, on in asked if on]

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, data: dict) -> "TrainConfig":
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise PromptGSError(f"unknown training settings: {', '.join(unknown)}")
        return cls(**data)

    @classmethod
    def load(cls, path: Path) -> "TrainConfig":
        try:
            data = json.loads(Path(path).read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise PromptGSError(f"{path}: cannot read training settings ({exc})") from exc
        if isinstance(data, dict):
            # Runs written before the setting existed rendered with 3DGS's filter (and, with no
            # `antialiased` key, the classic mode: the field's default).
            data.setdefault("screen_filter", BASELINE_SCREEN_FILTER)
            # ... and with one view a step.
            data.setdefault("batch_size", 1)
            # Runs of 3DGS or AbsGS written before prompts were refused for them (the
            # add-on sent its boxes with every strategy) trained without them.
            if data.get("strategy", "3dgs") != "promptgs":
                data.update(prompts=None, center_prompt=False, auto_prompts=0, propose_prompts=False)
        return cls.from_json(data)
