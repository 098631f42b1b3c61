"""2D overlays on RGB pictures: landmarks, captions and the weight-bar strip.

The only module of the renderer that imports Pillow (for resizing and text). Pictures
are ``(height, width, 3) uint8`` arrays in and out.
"""

from __future__ import annotations

from functools import cache, lru_cache

import numpy as np

from ..exceptions import MissingDependencyError

__all__ = ["REGION_COLOURS", "OTHER_COLOUR", "region_palette", "landmark_colours", "resize_to_height",
           "draw_landmarks", "draw_crosses", "caption", "WeightStrip", "short_label", "HIDDEN_COLOUR"]

# Okabe–Ito colours (distinguishable with colour-blindness), one per region in order.
REGION_COLOURS = ((230, 159, 0), (86, 180, 233), (0, 158, 115), (240, 228, 66), (0, 114, 178),
                  (213, 94, 0), (204, 121, 167))
OTHER_COLOUR = (170, 170, 170)
HIDDEN_COLOUR = (128, 128, 128)  # a landmark the face does not show (a hand over it): a grey cross
STRIP_BACKGROUND = (24, 25, 28)


def _pil():
    try:
        from PIL import Image, ImageDraw, ImageFont
    except ImportError:
        raise MissingDependencyError("pillow") from None
    return Image, ImageDraw, ImageFont


@cache
def _font(size: int):
    _, _, image_font = _pil()
    try:
        return image_font.load_default(size=size)
    except (TypeError, OSError, ImportError):  # Pillow without FreeType: fixed bitmap font
        return image_font.load_default()


def region_palette(regions) -> dict[str, tuple[int, int, int]]:
    """Colour ``(r, g, b)`` of each region name, in order (cycling through :data:`REGION_COLOURS`)."""
    return {name: REGION_COLOURS[i % len(REGION_COLOURS)] for i, name in enumerate(regions)}


def landmark_colours(regions: dict[str, np.ndarray], n_landmarks: int) -> np.ndarray:
    """(n_landmarks, 3) uint8: each landmark in its region's colour, grey outside every region."""
    out = np.tile(np.array(OTHER_COLOUR, np.uint8), (n_landmarks, 1))
    for name, colour in region_palette(regions).items():
        out[np.asarray(regions[name], dtype=int)] = colour
    return out


def resize_to_height(image: np.ndarray, height: int) -> np.ndarray:
    """``image (h, w, 3) uint8`` scaled (bilinear) to ``height`` rows, aspect kept, even width."""
    image_mod, _, _ = _pil()
    h, w = image.shape[:2]
    width = max(2, int(round(w * height / h / 2)) * 2)
    if (h, w) == (height, width):
        return image
    return np.asarray(image_mod.fromarray(image).resize((width, height), image_mod.BILINEAR))


def draw_landmarks(image: np.ndarray, points: np.ndarray, colours: np.ndarray, *,
                   edges: np.ndarray | None = None, radius: float = 1.6) -> np.ndarray:
    """Landmarks (and contour lines) drawn onto a copy of ``image``.

    Parameters
    ----------
    image : (height, width, 3) uint8
    points : (n_landmarks, 2) float, pixels of ``image``; a NaN frame draws nothing
    colours : (n_landmarks, 3) uint8
    edges : (n_edges, 2) int, optional, keyword-only
        Contour segments, drawn one pixel wide in the colour of their first landmark.
    radius : float or (n_landmarks,) float, keyword-only
        Dot radius in pixels.

    Examples
    --------
    >>> out = draw_landmarks(np.zeros((5, 9, 3), np.uint8), np.array([[1.0, 2], [7, 2]]),
    ...                      np.full((2, 3), 255, np.uint8), edges=np.array([[0, 1]]), radius=0)
    >>> out[2, :, 0]
    array([  0, 255, 255, 255, 255, 255, 255, 255,   0], dtype=uint8)
    """
    out = np.array(image, dtype=np.uint8, copy=True)
    if not np.isfinite(points).all():
        return out
    if edges is not None and len(edges):
        _segments(out, points[edges[:, 0]], points[edges[:, 1]], colours[edges[:, 0]])
    radii = np.broadcast_to(np.asarray(radius, dtype=float), (len(points),))
    for r in np.unique(radii):
        _dots(out, points[radii == r], colours[radii == r], float(r))
    return out


def draw_crosses(image: np.ndarray, points: np.ndarray, colour, *, arm: float = 2.0) -> np.ndarray:
    """A small ``x`` (one-pixel lines, ``arm`` pixels from the centre) at each of ``points (n, 2)``,
    drawn onto a copy of ``image`` in ``colour`` (r, g, b).

    Examples
    --------
    >>> out = draw_crosses(np.zeros((5, 5, 3), np.uint8), np.array([[2.0, 2.0]]), (9, 9, 9), arm=1)
    >>> out[..., 0]
    array([[0, 0, 0, 0, 0],
           [0, 9, 0, 9, 0],
           [0, 0, 9, 0, 0],
           [0, 9, 0, 9, 0],
           [0, 0, 0, 0, 0]], dtype=uint8)
    """
    out = np.array(image, dtype=np.uint8, copy=True)
    points = np.asarray(points, dtype=float).reshape(-1, 2)
    points = points[np.isfinite(points).all(axis=1)]
    colours = np.tile(np.asarray(colour, np.uint8), (len(points), 1))
    for diagonal in ((1.0, 1.0), (1.0, -1.0)):
        offset = arm * np.array(diagonal)
        _segments(out, points - offset, points + offset, colours)
    return out


def _stamp(image: np.ndarray, xy: np.ndarray, colours: np.ndarray) -> None:
    """Set the pixels ``xy (n, 2) int`` (x, y) that fall inside ``image`` to ``colours (n, 3)``."""
    inside = ((xy >= 0) & (xy < (image.shape[1], image.shape[0]))).all(axis=1)
    image[xy[inside, 1], xy[inside, 0]] = colours[inside]


def _segments(image: np.ndarray, starts: np.ndarray, ends: np.ndarray, colours: np.ndarray) -> None:
    """One-pixel lines ``starts[i] → ends[i]`` (in place), sampled once per pixel of length."""
    steps = int(min(np.ceil(np.abs(ends - starts).max(initial=0.0)), 4096)) + 1
    t = np.linspace(0.0, 1.0, steps)[None, :, None]
    xy = np.round(starts[:, None] + t * (ends - starts)[:, None]).astype(np.int64)  # (n, steps, 2)
    _stamp(image, xy.reshape(-1, 2), np.repeat(colours, steps, axis=0))


def _dots(image: np.ndarray, points: np.ndarray, colours: np.ndarray, radius: float) -> None:
    """Filled discs stamped at ``points`` (in place)."""
    offsets = _disc(radius)  # (n_offsets, 2) as (dx, dy)
    xy = np.round(points).astype(np.int64)[:, None, :] + offsets[None]  # (n_points, n_offsets, 2)
    _stamp(image, xy.reshape(-1, 2), np.repeat(colours, len(offsets), axis=0))


@cache
def _disc(radius: float) -> np.ndarray:
    r = int(np.ceil(radius))
    dy, dx = np.mgrid[-r:r + 1, -r:r + 1]
    keep = dx**2 + dy**2 <= radius**2 + 0.25
    return np.stack([dx[keep], dy[keep]], axis=1)


def caption(image: np.ndarray, text: str, *, xy=(8, 6), size: int = 14) -> np.ndarray:
    """``text`` written (white on a black box) at ``xy`` on a copy of ``image``."""
    out = np.array(image, dtype=np.uint8, copy=True)
    patch = _text_patch(text, size)
    x, y = xy[0] - 4, xy[1] - 3
    h, w = min(patch.shape[0], out.shape[0] - y), min(patch.shape[1], out.shape[1] - x)
    if h > 0 and w > 0:
        out[y:y + h, x:x + w] = patch[:h, :w]
    return out


@lru_cache(maxsize=64)
def _text_patch(text: str, size: int) -> np.ndarray:
    """(h, w, 3) uint8: ``text`` in white on black with a 4 × 3 pixel margin."""
    image_mod, image_draw, _ = _pil()
    font = _font(size)
    _, _, right, bottom = image_draw.Draw(image_mod.new("RGB", (1, 1))).textbbox((0, 0), text, font=font)
    canvas = image_mod.new("RGB", (right + 8, bottom + 6), (0, 0, 0))
    image_draw.Draw(canvas).text((4, 3), text, fill=(255, 255, 255), font=font)
    return np.asarray(canvas)


MIRROR_MARK = "m"  # a mirrored key's short label: "03m" is region_03_mirror


def short_label(name: str, region: str | None) -> str:
    """A key's label under its bar when its region is named below the bars: ``upper_03_mirror`` of
    region ``upper`` is ``03m``; a name that does not start with its region's is kept whole.

    >>> short_label("upper_03_mirror", "upper"), short_label("lower_00", "lower"), short_label("jawOpen", None)
    ('03m', '00', 'jawOpen')
    """
    if not region or not name.startswith(f"{region}_"):
        return name
    rest = name[len(region) + 1:]
    return f"{rest[:-len('_mirror')]}{MIRROR_MARK}" if rest.endswith("_mirror") else rest


class WeightStrip:
    """A strip of vertical bars, one per weight, labelled and coloured by region.

    Under the bars, a row of labels (one per bar, each inside its bar's cell: a key of a region
    by its number, ``03``, a mirrored key ``03m``) and a row of region names, each centred under its
    keys' span (with "(m: mirrored)" when it has mirrored keys). Labels never run into each other:
    where the cells are too narrow even at the smallest font, only every k-th bar is labelled.
    The labels and frame are drawn once; :meth:`draw` only fills the bars.

    Parameters
    ----------
    names : tuple of n_channels str
    colours : (n_channels, 3) uint8
    width, height : int
    regions : tuple of n_channels (str or None), optional
        Each channel's region (None: not a key); default none, every name labelled whole.

    Attributes
    ----------
    labels : list of (str, (x0, y0, x1, y1))
        Every label drawn (per bar, then the region names) and its box in the strip's pixels.
    """

    MIN_FONT, MAX_FONT = 7, 13

    def __init__(self, names, colours: np.ndarray, width: int, height: int, regions=None):
        self.names = tuple(names)
        self.colours = np.asarray(colours, np.uint8)
        self.width, self.height = int(width), int(height)
        self.regions = tuple(regions) if regions is not None else (None,) * len(self.names)
        self.cell = self.width / max(len(self.names), 1)
        self.short = [short_label(n, r) for n, r in zip(self.names, self.regions)]
        self.groups = self._groups()
        self.font_size, self.stride = self._fit()
        rows = 2 if self.groups else 1
        self.bar_top, self.bar_bottom = 8, self.height - rows * (self.font_size + 4) - 6
        self.labels: list = []
        self.background = self._background()

    def _groups(self) -> list:
        """``[(region, first, stop)]``: runs of consecutive channels of one region (none without regions)."""
        runs, first = [], 0
        for i in range(1, len(self.names) + 1):
            if i == len(self.names) or self.regions[i] != self.regions[first]:
                if self.regions[first] is not None:
                    runs.append((self.regions[first], first, i))
                first = i
        return runs

    def _text_width(self, text: str, size: int) -> int:
        image_mod, image_draw, _ = _pil()
        left, _, right, _ = image_draw.Draw(image_mod.new("RGB", (1, 1))).textbbox((0, 0), text, font=_font(size))
        return right - left

    def _fit(self) -> tuple[int, int]:
        """``(font size, k)``: the largest font whose labels fit their cells, labelling every k-th bar."""
        longest = max(self.short, key=len, default="")
        for stride in range(1, max(len(self.names), 1) + 1):
            room = stride * self.cell - 4
            for size in range(self.MAX_FONT, self.MIN_FONT - 1, -1):
                if self._text_width(longest, size) <= room and max(
                        (self._text_width(t, size) for t in self.short), default=0) <= room:
                    return size, stride
        return self.MIN_FONT, max(len(self.names), 1)

    def _background(self) -> np.ndarray:
        image_mod, image_draw, _ = _pil()
        canvas = image_mod.new("RGB", (self.width, self.height), STRIP_BACKGROUND)
        pen = image_draw.Draw(canvas)
        font = _font(self.font_size)
        label_base = self.bar_bottom + self.font_size + 4
        for i in range(len(self.names)):
            x0, x1 = self._bar_span(i)
            pen.rectangle([x0, self.bar_top, x1 - 1, self.bar_bottom - 1], outline=(60, 62, 68))
            if i % self.stride or i + self.stride > len(self.names):  # labelled bars' labels end in the strip
                continue
            colour = tuple(int(c) for c in self.colours[i])
            if self.stride == 1:  # centred under its bar
                self._text(pen, ((x0 + x1) / 2, label_base), self.short[i], colour, font)
            else:  # from its bar's left edge over the k unlabelled cells beside it
                self._text(pen, (i * self.cell + 2, label_base), self.short[i], colour, font, anchor="ls")
        for region, first, stop in self.groups:
            left, right = int(first * self.cell) + 2, int(stop * self.cell) - 2
            mirrored = any(self.names[i].endswith("_mirror") for i in range(first, stop))
            text = f"{region}  ({MIRROR_MARK}: mirrored)" if mirrored else region
            if self._text_width(text, self.font_size) > right - left:
                text = region
            if self._text_width(text, self.font_size) > right - left:
                continue
            y = self.height - 4
            pen.line([left, y - self.font_size // 2 - 1, right, y - self.font_size // 2 - 1], fill=(60, 62, 68))
            width = self._text_width(text, self.font_size)
            pen.rectangle([(left + right - width) / 2 - 3, y - self.font_size - 2, (left + right + width) / 2 + 3, y],
                          fill=STRIP_BACKGROUND)
            self._text(pen, ((left + right) / 2, y), text, tuple(int(c) for c in self.colours[first]), font)
        return np.asarray(canvas).copy()

    def _text(self, pen, anchor_at, text: str, colour, font, anchor: str = "ms") -> None:
        pen.text(anchor_at, text, fill=colour, font=font, anchor=anchor)
        box = pen.textbbox(anchor_at, text, font=font, anchor=anchor)
        x0, y0, x1, y1 = box
        self.labels.append((text, (int(np.floor(x0)), int(np.floor(y0)), int(np.ceil(x1)), int(np.ceil(y1)))))

    def _bar_span(self, i: int) -> tuple[int, int]:
        pad = max(2, int(self.cell * 0.18))
        return int(i * self.cell) + pad, int((i + 1) * self.cell) - pad

    def draw(self, values: np.ndarray) -> np.ndarray:
        """The strip ``(height, width, 3) uint8`` for ``values (n_channels,)`` in [0, 1].

        NaN draws an empty bar; values above 1 fill the bar and are marked white at the top.
        """
        out = self.background.copy()
        full = self.bar_bottom - self.bar_top - 2
        for i, value in enumerate(np.asarray(values, dtype=float)):
            if not np.isfinite(value) or value <= 0:
                continue
            x0, x1 = self._bar_span(i)
            top = self.bar_bottom - 1 - int(round(min(value, 1.0) * full))
            out[top:self.bar_bottom - 1, x0 + 1:x1 - 1] = self.colours[i]
            if value > 1.0:
                out[self.bar_top + 1:self.bar_top + 3, x0 + 1:x1 - 1] = 255
        return out
