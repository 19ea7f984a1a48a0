"""One colour per agent, the same in every picture swarmpc makes (PNG, GIF, MP4, HTML).

Plain hex strings, no plotting library: the figures (matplotlib) and the viewer (plotly) both
take them as they are.
"""

from __future__ import annotations

import colorsys

TAB10 = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd",
         "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf")
"""matplotlib's ``tab10``: distinct, colour-blind friendlier than a hue wheel, for up to 10."""

GOLDEN = 0.618033988749895


def agent_colors(m: int) -> list[str]:
    """``m`` hex colours: ``tab10`` up to 10 agents; beyond, hues spaced by the golden ratio (so
    neighbours in index order differ) at two alternating lightnesses."""
    if m <= len(TAB10):
        return list(TAB10[: max(m, 0)])
    colors = []
    for i in range(m):
        hue = (i * GOLDEN) % 1.0
        lightness = 0.42 if i % 2 else 0.55
        r, g, b = colorsys.hls_to_rgb(hue, lightness, 0.75)
        colors.append(f"#{round(r * 255):02x}{round(g * 255):02x}{round(b * 255):02x}")
    return colors
