"""A dependency-free PNG line chart: ops/s against N (log scale) for stack, floor and peers.

Decision: ``--plot`` never needs matplotlib. No new runtime dependency for a chart, and an
optional one would give two code paths of which CI tests one; a 24-bit RGB canvas, Bresenham
lines, a 3x5 pixel font and ``zlib`` + ``struct`` for the PNG container are about 200 lines and
give the same picture on every machine, byte for byte (so the test can check the file).
"""

from __future__ import annotations

import itertools
import math
import struct
import zlib
from collections.abc import Sequence
from dataclasses import dataclass

__all__ = ["Canvas", "ChartSeries", "encode_png", "line_chart"]

RGB = tuple[int, int, int]

_FONT_ROWS = {
    "0": "111101101101111", "1": "010110010010111", "2": "111001111100111",
    "3": "111001111001111", "4": "101101111001001", "5": "111100111001111",
    "6": "111100111101111", "7": "111001010010010", "8": "111101111101111",
    "9": "111101111001111", "A": "010101111101101", "B": "110101110101110",
    "C": "011100100100011", "D": "110101101101110", "E": "111100110100111",
    "F": "111100110100100", "G": "011100101101011", "H": "101101111101101",
    "I": "111010010010111", "J": "001001001101010", "K": "101101110101101",
    "L": "100100100100111", "M": "101111111101101", "N": "110101101101101",
    "O": "010101101101010", "P": "110101110100100", "Q": "010101101110011",
    "R": "110101110101101", "S": "011100010001110", "T": "111010010010010",
    "U": "101101101101111", "V": "101101101101010", "W": "101101111111101",
    "X": "101101010101101", "Y": "101101010010010", "Z": "111001010100111",
    " ": "000000000000000", ".": "000000000000010", "/": "001001010100100",
    "+": "000010111010000", "-": "000000111000000", ":": "000010000010000",
    "=": "000111000111000", "(": "001010010010001", ")": "100010010010100",
    "_": "000000000000111", ",": "000000000010100", "%": "101001010100101",
    "?": "111001010000010",
}  # fmt: skip

PALETTE: list[RGB] = [
    (31, 119, 180), (214, 39, 40), (44, 160, 44), (148, 103, 189),
    (255, 127, 14), (23, 190, 207), (140, 86, 75), (127, 127, 127),
]  # fmt: skip


def encode_png(width: int, height: int, rgb: bytes) -> bytes:
    """PNG file bytes for 8-bit RGB pixels (rows top to bottom, no interlace)."""
    if len(rgb) != width * height * 3:
        raise ValueError("pixel buffer does not match width x height x 3")
    stride = width * 3
    raw = b"".join(b"\x00" + rgb[y * stride : (y + 1) * stride] for y in range(height))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        )

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(raw, 9))
        + chunk(b"IEND", b"")
    )


class Canvas:
    """A white RGB canvas with the few drawing primitives a line chart needs."""

    def __init__(self, width: int, height: int) -> None:
        self.width = width
        self.height = height
        self.pixels = bytearray(b"\xff" * (width * height * 3))

    def set(self, x: int, y: int, color: RGB) -> None:
        if 0 <= x < self.width and 0 <= y < self.height:
            i = (y * self.width + x) * 3
            self.pixels[i : i + 3] = bytes(color)

    def rect(self, x0: int, y0: int, x1: int, y1: int, color: RGB) -> None:
        for y in range(max(0, y0), min(self.height, y1 + 1)):
            for x in range(max(0, x0), min(self.width, x1 + 1)):
                self.set(x, y, color)

    def line(
        self, x0: int, y0: int, x1: int, y1: int, color: RGB, width: int = 1, dash: int = 0
    ) -> None:
        """Bresenham; ``dash`` > 0 draws ``dash`` pixels on, ``dash`` off."""
        dx, dy = abs(x1 - x0), -abs(y1 - y0)
        sx, sy = (1 if x0 < x1 else -1), (1 if y0 < y1 else -1)
        err = dx + dy
        step = 0
        half = width // 2
        while True:
            if not dash or (step // dash) % 2 == 0:
                self.rect(x0 - half, y0 - half, x0 - half + width - 1, y0 - half + width - 1, color)
            step += 1
            if x0 == x1 and y0 == y1:
                break
            e2 = 2 * err
            if e2 >= dy:
                err += dy
                x0 += sx
            if e2 <= dx:
                err += dx
                y0 += sy

    def text(self, x: int, y: int, text: str, color: RGB = (0, 0, 0), scale: int = 2) -> int:
        """Draw upper-cased ``text`` with the 3x5 font; returns the x after the last glyph."""
        for char in text.upper():
            rows = _FONT_ROWS.get(char, _FONT_ROWS["?"])
            for index, bit in enumerate(rows):
                if bit == "1":
                    gx, gy = x + (index % 3) * scale, y + (index // 3) * scale
                    self.rect(gx, gy, gx + scale - 1, gy + scale - 1, color)
            x += 4 * scale
        return x

    @staticmethod
    def text_width(text: str, scale: int = 2) -> int:
        return len(text) * 4 * scale - scale

    def png(self) -> bytes:
        return encode_png(self.width, self.height, bytes(self.pixels))


@dataclass
class ChartSeries:
    label: str
    points: list[tuple[float, float]]  # (N, ops/s)
    #: 0 = solid, else the length in pixels of the dashes
    dash: int = 0
    color: RGB | None = None


def _nice_step(span: float, ticks: int = 5) -> float:
    raw = span / max(1, ticks)
    magnitude = 10 ** math.floor(math.log10(raw)) if raw > 0 else 1.0
    for factor in (1, 2, 2.5, 5, 10):
        if raw <= factor * magnitude:
            return factor * magnitude
    return 10 * magnitude


def compact(value: float) -> str:
    """12 -> "12", 1500 -> "1.5K", 25000 -> "25K", 2500000 -> "2.5M"."""
    for limit, suffix in ((1e6, "M"), (1e3, "K")):
        if abs(value) >= limit:
            text = f"{value / limit:.1f}".rstrip("0").rstrip(".")
            return text + suffix
    return f"{value:g}"


def line_chart(
    series: Sequence[ChartSeries],
    *,
    title: str,
    x_label: str = "N (PLCS, LOG SCALE)",
    y_label: str = "OPS/S",
    width: int = 960,
    height: int = 560,
) -> bytes:
    """Render the chart and return PNG bytes. Points with N <= 0 or ops <= 0 are dropped."""
    canvas = Canvas(width, height)
    left, right, top, bottom = 80, 300, 44, 60
    plot_w, plot_h = width - left - right, height - top - bottom
    pts = [(n, v) for s in series for n, v in s.points if n > 0 and v > 0]
    xs = [math.log10(n) for n, _ in pts] or [0.0, 1.0]
    x_lo, x_hi = math.floor(min(xs)), math.ceil(max(xs))
    if x_hi == x_lo:
        x_hi = x_lo + 1
    y_hi_raw = max((v for _, v in pts), default=1.0)
    step = _nice_step(y_hi_raw)
    y_hi = step * math.ceil(y_hi_raw / step)

    def px(n: float) -> int:
        return left + round((math.log10(n) - x_lo) / (x_hi - x_lo) * plot_w)

    def py(v: float) -> int:
        return top + plot_h - round(v / y_hi * plot_h)

    grey, black = (220, 220, 220), (0, 0, 0)
    canvas.text(left, 14, title, black, 2)
    # grid and ticks
    y = 0.0
    while y <= y_hi + step / 2:
        yy = py(y)
        canvas.line(left, yy, left + plot_w, yy, grey)
        label = compact(y)
        canvas.text(left - 8 - Canvas.text_width(label), yy - 5, label, black, 2)
        y += step
    for exponent in range(x_lo, x_hi + 1):
        xx = px(10.0**exponent)
        canvas.line(xx, top, xx, top + plot_h, grey)
        label = compact(10.0**exponent)
        canvas.text(xx - Canvas.text_width(label) // 2, top + plot_h + 8, label, black, 2)
    canvas.line(left, top, left, top + plot_h, black)
    canvas.line(left, top + plot_h, left + plot_w, top + plot_h, black)
    canvas.text(left + plot_w // 2 - Canvas.text_width(x_label) // 2, height - 24, x_label)
    canvas.text(8, top - 18 if top > 30 else 2, y_label)
    # series and legend
    legend_y = top
    for index, s in enumerate(series):
        color = s.color or PALETTE[index % len(PALETTE)]
        points = sorted((n, v) for n, v in s.points if n > 0 and v > 0)
        coords = [(px(n), py(v)) for n, v in points]
        for (x0, y0), (x1, y1) in itertools.pairwise(coords):
            canvas.line(x0, y0, x1, y1, color, width=2, dash=s.dash)
        for x0, y0 in coords:
            canvas.rect(x0 - 3, y0 - 3, x0 + 3, y0 + 3, color)
        lx = left + plot_w + 16
        canvas.line(lx, legend_y + 5, lx + 24, legend_y + 5, color, width=2, dash=s.dash)
        canvas.text(lx + 32, legend_y, s.label[:30], black, 2)
        legend_y += 18
    return canvas.png()
