"""Contact sheets: a grid of images with column titles, as one PNG-ready array."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mvgeo.common.deps import cv2

__all__ = ["contact_sheet"]


def _fit(img: np.ndarray | None, width_px: int, height_px: int) -> np.ndarray:
    tile = np.full((height_px, width_px, 3), 0.5, np.float32)  # grey = missing
    if img is None:
        return tile
    h, w = img.shape[:2]
    scale = min(width_px / w, height_px / h)
    nw, nh = max(1, round(w * scale)), max(1, round(h * scale))
    small = cv2.resize(np.clip(img, 0, 1).astype(np.float32), (nw, nh), interpolation=cv2.INTER_AREA)
    y0, x0 = (height_px - nh) // 2, (width_px - nw) // 2
    tile[y0:y0 + nh, x0:x0 + nw] = small
    return tile


def contact_sheet(rows: Sequence[Sequence[np.ndarray | None]], *, titles: Sequence[str],
                  row_labels: Sequence[str] | None = None, tile_width_px: int = 256, gap_px: int = 4) -> np.ndarray:
    """Arrange `rows[i][j]` (H x W x 3 float in [0, 1], or None for a grey tile) in a grid.

    Args:
        rows: one sequence per row, `len(titles)` images each.
        titles: column titles, drawn above the first row.
        row_labels: optional text drawn in each row's first tile (e.g. the view name).
        tile_width_px: width of each tile; the height follows the first image's aspect ratio.
        gap_px: white gap between tiles.

    Returns:
        (H, W, 3) float32 image.
    """
    first = next((im for row in rows for im in row if im is not None), None)
    aspect = first.shape[0] / first.shape[1] if first is not None else 0.75
    tw, th = tile_width_px, max(1, round(tile_width_px * aspect))
    ncol = len(titles)
    header_px = 24
    height = header_px + len(rows) * (th + gap_px)
    width = ncol * (tw + gap_px) - gap_px
    # uint8 canvas: OpenCV draws text on 8-bit images only.
    sheet = np.full((height, width, 3), 255, np.uint8)
    for j, title in enumerate(titles):
        cv2.putText(sheet, title, (j * (tw + gap_px) + 4, 17), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1,
                    cv2.LINE_AA)
    for i, row in enumerate(rows):
        if len(row) != ncol:
            raise ValueError(f"row {i} has {len(row)} images, expected {ncol}")
        y = header_px + i * (th + gap_px)
        for j, img in enumerate(row):
            x = j * (tw + gap_px)
            sheet[y:y + th, x:x + tw] = np.rint(_fit(img, tw, th) * 255).astype(np.uint8)
        if row_labels is not None:
            cv2.putText(sheet, str(row_labels[i]), (4, y + th - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 0),
                        1, cv2.LINE_AA)
    return sheet.astype(np.float32) / 255.0
