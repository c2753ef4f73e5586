"""Map files: ROS map_server PGM + YAML (trinary, as map_saver writes them) and a PNG."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from slam2d.grid.probability_grid import ProbabilityGrid

FREE, UNKNOWN, OCCUPIED = 254, 205, 0


#: rows converted at a time when exporting
BAND_ROWS = 512


def occupancy_image(grid: ProbabilityGrid, occupied_thresh: float, free_thresh: float):
    """(image rows top-first as uint8, origin x, origin y of the lower-left pixel), cropped to known cells."""
    b = grid.known_bounds()
    if b is None:
        return np.full((1, 1), UNKNOWN, dtype=np.uint8), float(grid.origin[0]), float(grid.origin[1])
    r0, r1, c0, c1 = b
    img = np.full((r1 - r0, c1 - c0), UNKNOWN, dtype=np.uint8)  # image rows top-first: grid row r1 - 1 first
    for a in range(r0, r1, BAND_ROWS):  # in bands of rows: a large map never exists as floats at once
        z = min(a + BAND_ROWS, r1)
        p = grid.probability_rows(a, z, unknown_value=np.nan)[::-1, c0:c1]
        band = img[r1 - z:r1 - a]
        band[p > occupied_thresh] = OCCUPIED
        band[p < free_thresh] = FREE
    ox = float(grid.origin[0] + c0 * grid.resolution)
    oy = float(grid.origin[1] + r0 * grid.resolution)
    return img, ox, oy


def write_pgm(path, img: np.ndarray) -> None:
    h, w = img.shape
    with open(path, "wb") as f:
        f.write(f"P5\n# slam2d map\n{w} {h}\n255\n".encode())
        f.write(np.ascontiguousarray(img, dtype=np.uint8).data)  # no copy of a large map


def read_pgm(path) -> np.ndarray:
    data = Path(path).read_bytes()
    tokens, pos = [], 0
    while len(tokens) < 4:
        while data[pos:pos + 1].isspace():
            pos += 1
        if data[pos:pos + 1] == b"#":
            pos = data.index(b"\n", pos) + 1
            continue
        end = pos
        while not data[end:end + 1].isspace():
            end += 1
        tokens.append(data[pos:end].decode())
        pos = end
    pos += 1
    if tokens[0] != "P5":
        raise ValueError(f"{path}: not a binary PGM")
    w, h = int(tokens[1]), int(tokens[2])
    return np.frombuffer(data[pos:pos + w * h], dtype=np.uint8).reshape(h, w)


def write_map(out_dir, grid: ProbabilityGrid, occupied_thresh: float, free_thresh: float, stem="map", suffix="",
              cells: tuple[float, float] | None = None):
    """Write ``stem.pgm``, ``stem.yaml``, ``stem.png`` (names get ``suffix`` while a run is in progress).
    ``occupied_thresh`` / ``free_thresh`` go to the YAML; ``cells``: the (occupied, free) probability
    thresholds that classify the cells (default: the same)."""
    out_dir = Path(out_dir)
    img, ox, oy = occupancy_image(grid, *(cells or (occupied_thresh, free_thresh)))
    write_pgm(out_dir / f"{stem}.pgm{suffix}", img)
    yaml_text = (f"image: {stem}.pgm\nmode: trinary\nresolution: {grid.resolution}\n"
                 f"origin: [{ox:.6f}, {oy:.6f}, 0.0]\nnegate: 0\n"
                 f"occupied_thresh: {occupied_thresh}\nfree_thresh: {free_thresh}\n")
    (out_dir / f"{stem}.yaml{suffix}").write_text(yaml_text)
    from PIL import Image

    with open(out_dir / f"{stem}.png{suffix}", "wb") as f:
        Image.fromarray(img, mode="L").save(f, format="PNG")
    return [out_dir / f"{stem}.{e}" for e in ("pgm", "yaml", "png")]


def replace(paths, suffix):
    for p in paths:
        os.replace(f"{p}{suffix}", p)
