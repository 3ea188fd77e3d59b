"""Headless raster drawing in numpy for the ``rgb_array`` render mode (no pygame, no matplotlib).

A :class:`Canvas` maps a world rectangle ``[x_min, x_max] × [y_min, y_max]`` (y up) onto an ``(H, W, 3)`` uint8
image (row 0 at the top). Each primitive is a mask over the pixel centres, in world units:

    disc     ‖q − c‖ ≤ r
    segment  dist(q, [a, b]) ≤ w / 2,   dist = ‖q − a − clip(⟨q − a, b − a⟩ / ‖b − a‖², 0, 1) (b − a)‖

which is a few vectorised passes over the image per frame: slow next to a GPU rasteriser, fast enough for videos
of environments that step at 20 Hz.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

Color = Sequence[int]

BACKGROUND = (255, 255, 255)


class Canvas:
    """An image of ``width × height`` pixels showing the world box ``bounds = (x_min, x_max, y_min, y_max)``.

    Pixels are square: the world box is widened about its centre to the image's aspect ratio.
    """

    def __init__(self, width: int, height: int, bounds: Sequence[float], background: Color = BACKGROUND):
        x_min, x_max, y_min, y_max = (float(b) for b in bounds)
        # one scale for both axes so discs stay round
        scale = min(width / (x_max - x_min), height / (y_max - y_min))
        cx, cy = 0.5 * (x_min + x_max), 0.5 * (y_min + y_max)
        self.scale = scale
        self.image = np.empty((height, width, 3), dtype=np.uint8)
        self.image[...] = np.asarray(background, dtype=np.uint8)
        cols = (np.arange(width) + 0.5 - 0.5 * width) / scale + cx
        rows = (0.5 * height - np.arange(height) - 0.5) / scale + cy
        self._x = np.broadcast_to(cols[None, :], (height, width))
        self._y = np.broadcast_to(rows[:, None], (height, width))

    def _paint(self, mask: np.ndarray, color: Color) -> None:
        self.image[mask] = np.asarray(color, dtype=np.uint8)

    def _at_least_a_pixel(self, length: float) -> float:
        # keep thin or small features visible however far the view is zoomed out
        return max(float(length), 1.5 / self.scale)

    def disc(self, center: Sequence[float], radius: float, color: Color) -> None:
        """Fill the disc of ``radius`` (world units) about ``center``."""
        r = self._at_least_a_pixel(radius)
        self._paint((self._x - center[0]) ** 2 + (self._y - center[1]) ** 2 <= r * r, color)

    def segment(self, start: Sequence[float], end: Sequence[float], width: float, color: Color) -> None:
        """Fill the segment from ``start`` to ``end`` drawn ``width`` wide (world units), with round caps."""
        ax, ay = float(start[0]), float(start[1])
        dx, dy = float(end[0]) - ax, float(end[1]) - ay
        qx, qy = self._x - ax, self._y - ay
        length2 = dx * dx + dy * dy
        t = np.clip((qx * dx + qy * dy) / length2, 0.0, 1.0) if length2 > 0.0 else np.zeros_like(qx)
        half = 0.5 * self._at_least_a_pixel(width)
        self._paint((qx - t * dx) ** 2 + (qy - t * dy) ** 2 <= half * half, color)
