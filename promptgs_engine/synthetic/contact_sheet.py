"""Contact sheet of a generated dataset: a few views with every drone circled, and zoomed
crops of the drones, so one picture shows whether the scene reads as mountains, flames and
tiny drones.

    python -m promptgs_engine.synthetic.contact_sheet DATASET OUT.png [--views 4] [--scale 2]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

CROP = 8  # crop half-size in image pixels
ZOOM = 10  # nearest-neighbour enlargement of the crops
MAX_CROPS = 6  # per view


def contact_sheet(root: Path, n_views: int = 4, scale: int = 2) -> Image.Image:
    """The sheet: ``n_views`` views spread over the sequence (2 per row), circles around the
    drones each mask holds, then a strip of zoomed drone crops (without circles) per view."""
    scene = json.loads((root / "scene.json").read_text())
    cams = scene["cameras"]
    picks = [cams[int(i)] for i in np.linspace(0, len(cams) - 1, n_views).round()]
    drones = {d["id"]: d for d in scene["drones"]}
    tiles = []
    for cam in picks:
        image = Image.open(root / "images" / cam["name"]).convert("RGB")
        mask = np.asarray(Image.open(root / "object_masks" / cam["name"]), dtype=np.int64)
        big = image.resize((image.width * scale, image.height * scale), Image.LANCZOS)
        draw = ImageDraw.Draw(big)
        crops = []
        for drone_id in sorted(set(np.unique(mask)) - {0}):
            ys, xs = np.nonzero(mask == drone_id)
            cx, cy = xs.mean() + 0.5, ys.mean() + 0.5
            r = 7 * scale
            draw.ellipse((cx * scale - r, cy * scale - r, cx * scale + r, cy * scale + r), outline=(255, 40, 200), width=2)
            x0, y0 = int(round(cx)) - CROP, int(round(cy)) - CROP
            if len(crops) < MAX_CROPS:
                crop = image.crop((x0, y0, x0 + 2 * CROP, y0 + 2 * CROP)).resize((2 * CROP * ZOOM, 2 * CROP * ZOOM), Image.NEAREST)
                ImageDraw.Draw(crop).text((3, 2), f"#{drone_id} {drones[drone_id]['color_name']}", fill=(255, 255, 255))
                crops.append(crop)
        n_circled = len(set(np.unique(mask)) - {0})
        draw.text((6, 4), f"{cam['name']} ({cam['split']}), {n_circled} drones circled", fill=(255, 255, 255))
        strip_h = 2 * CROP * ZOOM
        per_row = max(1, big.width // strip_h)
        rows = (len(crops) + per_row - 1) // per_row
        tile = Image.new("RGB", (big.width, big.height + rows * strip_h), (20, 20, 20))
        tile.paste(big, (0, 0))
        for k, crop in enumerate(crops):
            tile.paste(crop, ((k % per_row) * strip_h, big.height + (k // per_row) * strip_h))
        tiles.append(tile)
    width = max(t.width for t in tiles)
    cols = 2
    row_heights = [max(t.height for t in tiles[i : i + cols]) for i in range(0, len(tiles), cols)]
    sheet = Image.new("RGB", (cols * width + (cols - 1) * 6, sum(row_heights) + 6 * (len(row_heights) - 1)), (255, 255, 255))
    y = 0
    for r, h in enumerate(row_heights):
        for c, tile in enumerate(tiles[r * cols : (r + 1) * cols]):
            sheet.paste(tile, (c * (width + 6), y))
        y += h + 6
    return sheet


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m promptgs_engine.synthetic.contact_sheet")
    parser.add_argument("dataset", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--views", type=int, default=4)
    parser.add_argument("--scale", type=int, default=2)
    args = parser.parse_args(argv)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    sheet = contact_sheet(args.dataset, args.views, args.scale)
    # 256 colours keep the PNG small enough for the repository; the drones' colours survive
    sheet.quantize(colors=256, method=Image.Quantize.FASTOCTREE).save(args.out, optimize=True)
    print(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
