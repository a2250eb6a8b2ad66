"""Deterministic qualitative colours for clusters and labels (no matplotlib import: ``kbs run``
does not pay for it). The one palette of the project: the result PLY's red/green/blue, the
``kbs render`` figures and the HTML report all take their colours from here.

The first 18 colours are matplotlib's ``tab20`` without its two greys, dark shades first then
light ones (so neighbouring indices differ strongly); from index 18 on, hues step by the golden
ratio at two saturation/value levels, which keeps any number of colours distinct and
reproducible. Index -1 (noise, not assigned) is grey, a colour the palette never uses.

>>> from kbs.report.colors import colors_for
>>> colors_for(np.array([0, 1, -1]))
array([[ 31, 119, 180],
       [255, 127,  14],
       [128, 128, 128]], dtype=uint8)
"""
from __future__ import annotations

import colorsys

import numpy as np

#: RGB (uint8) of noise / unassigned points (cluster or label -1).
NOISE_RGB = (128, 128, 128)

#: The cells of a drive's obstacle grid by class (unknown 0, ground 1, obstacle 2): the colours of
#: ``map.png`` (:mod:`kbs.maps.files`) and of the map view's grid (:mod:`kbs.report.mapview`).
GRID_HEX = ("#f0f0f0", "#9ccc65", "#b71c1c")

# matplotlib tab20, dark shades (even indices) first, then light ones; its greys (127,127,127)
# and (199,199,199) left out so that grey means noise only.
_TAB20_DARK = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
               (140, 86, 75), (227, 119, 194), (188, 189, 34), (23, 190, 207)]
_TAB20_LIGHT = [(174, 199, 232), (255, 187, 120), (152, 223, 138), (255, 152, 150), (197, 176, 213),
                (196, 156, 148), (247, 182, 210), (219, 219, 141), (158, 218, 229)]
_BASE = np.array(_TAB20_DARK + _TAB20_LIGHT, dtype=np.uint8)
_GOLDEN = 0.618033988749895


#: colours made from the golden-ratio hue sequence; past them (very large scenes), a bijective
#: scramble of the 24-bit colour space, so that any number of clusters costs O(n) and stays distinct
_GOLDEN_COUNT = 1000


def palette(n: int) -> np.ndarray:
    """The first ``n`` colours of the palette, as an (n, 3) uint8 array (deterministic, pairwise
    distinct, never grey)."""
    if n <= len(_BASE):
        return _BASE[:max(n, 0)].copy()
    extra = []
    for i in range(min(n, len(_BASE) + _GOLDEN_COUNT) - len(_BASE)):
        h = (0.11 + i * _GOLDEN) % 1.0
        s, v = (0.85, 0.80) if i % 2 == 0 else (0.55, 0.95)
        extra.append([round(255 * c) for c in colorsys.hsv_to_rgb(h, s, v)])
    out = np.vstack([_BASE, np.array(extra, dtype=np.uint8)])
    # a golden-ratio hue could, after rounding, land on an earlier colour: nudge it
    seen: set[tuple[int, int, int]] = {NOISE_RGB}
    for i in range(out.shape[0]):
        while tuple(int(c) for c in out[i]) in seen:
            out[i, 2] = (int(out[i, 2]) + 1) % 256
        seen.add((int(out[i, 0]), int(out[i, 1]), int(out[i, 2])))
    if n > out.shape[0]:
        rest: list[tuple[int, int, int]] = []
        j = 0
        while len(rest) < n - out.shape[0]:
            j += 1
            c = (j * 0x9E3779) & 0xFFFFFF  # an odd multiplier: a bijection of the 24-bit colours
            rgb = (c >> 16, (c >> 8) & 255, c & 255)
            if rgb[0] == rgb[1] == rgb[2] or rgb in seen:  # greys are for noise
                continue
            seen.add(rgb)
            rest.append(rgb)
        out = np.vstack([out, np.array(rest, dtype=np.uint8)])
    return out


def colors_for(index: np.ndarray) -> np.ndarray:
    """RGB colours (n, 3) uint8 for integer indices (n,) (cluster or label numbers): index i gets
    ``palette[i]``, any negative index (noise) gets :data:`NOISE_RGB`."""
    index = np.asarray(index)
    out = np.empty((index.size, 3), dtype=np.uint8)
    out[:] = NOISE_RGB
    ok = index >= 0
    if ok.any():
        pal = palette(int(index[ok].max()) + 1)
        out[ok] = pal[index[ok]]
    return out


def hex_colors(n: int) -> list[str]:
    """The first ``n`` colours of :func:`palette` as ``#rrggbb`` strings (the HTML report's)."""
    return [f"#{r:02x}{g:02x}{b:02x}" for r, g, b in palette(n).tolist()]


#: :data:`NOISE_RGB` as ``#rrggbb``.
NOISE_HEX = "#{:02x}{:02x}{:02x}".format(*NOISE_RGB)


def rgb_fields(index: np.ndarray) -> dict[str, np.ndarray]:
    """The PLY per-vertex properties ``red``, ``green``, ``blue`` (uint8) for indices (n,)."""
    rgb = colors_for(index)
    return {"red": rgb[:, 0].copy(), "green": rgb[:, 1].copy(), "blue": rgb[:, 2].copy()}
