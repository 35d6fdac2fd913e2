"""The report's trees section (``output.trees``): tops over the canopy height, histograms of
height, crown diameter and DBH, trees per hectare, and the instance scores of a labelled run.
"""

import matplotlib
import numpy as np
from matplotlib.figure import Figure

from workflows.report.figures import DPI, STYLE, _mpl_text, png_bytes
from workflows.report.html import _escape, _format_value, figure_html

HECTARE = 10_000.0  # square metres


def trees_images(found: dict) -> dict[str, bytes]:
    """PNG figures of the trees of every scene: ``trees_map`` (tops over the canopy height)
    and ``trees_histograms``."""
    scenes = {s: f for s, f in found.items() if f.get("chm")}  # no canopy: nothing to draw
    images = {}
    if scenes:
        images["trees_map"] = png_bytes(tops_figure(scenes))
    if any(len(f["table"]) for f in found.values()):
        images["trees_histograms"] = png_bytes(histograms_figure(found))
    return images


def tops_figure(scenes: dict) -> Figure:
    """Per scene, the canopy height model (a list of Rasters, e.g. one per block, drawn
    coarser on a large survey) with the tree tops (or, trees found by their stems, the
    stems) on it."""
    with matplotlib.rc_context(STYLE):
        fig = Figure(figsize=(7.5, 6.2 * len(scenes)), dpi=DPI)
        for row, (scene, entry) in enumerate(scenes.items()):
            pieces, table = entry["chm"], entry["table"]  # the canopy height, by block
            low = min(np.nanmin(p.values) if np.isfinite(p.values).any() else np.inf
                      for p in pieces)
            high = max(np.nanmax(p.values) if np.isfinite(p.values).any() else -np.inf
                       for p in pieces)
            limits = (low, high) if np.isfinite(low) else (0.0, 1.0)
            ax = fig.add_subplot(len(scenes), 1, row + 1)
            for piece in pieces:
                ny, nx = piece.values.shape
                extent = (piece.x0, piece.x0 + nx * piece.cell, piece.y0,
                          piece.y0 + ny * piece.cell)
                shown = ax.imshow(piece.values, origin="lower", extent=extent, cmap="viridis",
                                  interpolation="nearest", vmin=limits[0], vmax=limits[1])
            ax.autoscale()
            ax.plot(table["x"], table["y"], "+", color="#d62728", markersize=5, mew=1.0)
            ax.set_title(f"{_mpl_text(scene)}: {len(table):,} trees ({entry['method']}) over "
                         f"the canopy height ({pieces[0].cell:g} m cells)")
            ax.set_aspect("equal")
            ax.ticklabel_format(useOffset=False, style="plain")
            fig.colorbar(shown, ax=ax, label="m above ground", shrink=0.8)
        fig.tight_layout()
    return fig


def fitted_dbh(found: dict) -> np.ndarray:
    """The DBH (m) of every tree of ``found`` whose stem was fitted."""
    table = np.concatenate([f["table"] for f in found.values()])
    return table["dbh"][np.isfinite(table["dbh"])]


def map_caption(found: dict) -> str:
    """The caption of ``trees_map``: its marks are the tops of trees found by their crowns
    and the stems of trees found by their stems."""
    methods = {f["method"] for f in found.values() if f.get("chm")}
    if methods == {"stems"}:
        return "Stems (+, where each tree's stem stands) over the canopy height model."
    if "stems" in methods:
        return ("Tree tops (+), or stems where a scene's trees were found by their stems "
                "(see each title), over the canopy height model.")
    return "Tree tops (+) over the canopy height model."


def histograms_caption(found: dict) -> str:
    """The caption of ``trees_histograms``: DBH only where its histogram is drawn."""
    if len(fitted_dbh(found)):
        return "Heights, crown diameters and DBH (of the fitted stems) of the trees found."
    return "Heights and crown diameters of the trees found (no stem was fitted: no DBH)."


def histograms_figure(found: dict) -> Figure:
    """Histograms of the trees' heights, crown diameters and (where fitted) DBH."""
    table = np.concatenate([f["table"] for f in found.values()])
    dbh = fitted_dbh(found)
    panels = [("height", table["height"], "m"), ("crown diameter", table["crown_diameter"], "m")]
    if len(dbh):
        panels.append(("DBH", dbh * 100, "cm"))
    with matplotlib.rc_context(STYLE):
        fig = Figure(figsize=(4.0 * len(panels), 3.4), dpi=DPI)
        for i, (name, values, unit) in enumerate(panels):
            ax = fig.add_subplot(1, len(panels), i + 1)
            finite = values[np.isfinite(values)]
            ax.hist(finite, bins=min(30, max(len(finite) // 3, 1)), color="#2ca02c")
            ax.set_xlabel(f"{name} ({unit})")
            ax.set_ylabel("trees")
            ax.set_title(f"{name}: median {np.median(finite):.2f} {unit}" if len(finite)
                         else name)
        fig.tight_layout()
    return fig


def trees_html(found: dict, images: dict, scores: dict | None = None) -> str:
    """The section of the page: a table per scene, the scores, the figures."""
    e = _escape
    parts = ["<h2>Trees</h2>", '<table class="info"><tr><th>scene</th><th>method</th>'
             "<th>trees</th><th>trees per hectare</th><th>median height (m)</th>"
             "<th>stems with a DBH</th></tr>"]
    for scene, entry in found.items():
        table = entry["table"]
        per_ha = len(table) / (entry["area"] / HECTARE) if entry["area"] > 0 else float("nan")
        height = float(np.median(table["height"])) if len(table) else float("nan")
        fitted = int(np.count_nonzero(np.isfinite(table["dbh"])))
        parts.append(f"<tr><td>{e(scene)}</td><td>{e(entry['method'])}</td>"
                     f"<td>{len(table):,}</td><td>{per_ha:.0f}</td><td>{height:.1f}</td>"
                     f"<td>{fitted:,}</td></tr>")
    parts.append("</table>")
    if scores:
        parts.append("<h3>Tree instances against the reference (TreeID)</h3>")
        parts.append('<table class="info">' + "".join(
            f"<tr><td>{e(k)}</td><td>{e(_format_value(v))}</td></tr>"
            for k, v in scores.items() if not isinstance(v, (dict, list))) + "</table>")
    for name, caption in (("trees_map", map_caption(found)),
                          ("trees_histograms", histograms_caption(found))):
        if name in images:
            parts.append(figure_html(images[name], name, caption))
    return "\n".join(parts)
