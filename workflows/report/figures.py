"""The report's plots as matplotlib figures, and the one colour of each class.

Plots are drawn with matplotlib's Agg renderer on ``Figure`` objects, never through pyplot, so
no display is needed and no global state is touched. Each class has one colour everywhere,
chosen by its index from :data:`CLASS_COLOURS` (Okabe & Ito's colour-blind-safe palette, then
a few more distinct colours); :func:`class_colour` is the function other pictures (previews,
exports) should use.
"""

import io
import math

import matplotlib
import matplotlib.cm
import matplotlib.colors
import matplotlib.ticker
import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Patch, Rectangle

from pipeline.errors import InputError
from pipeline.metrics import precision_recall_curve_data

# Okabe-Ito (colour-blind safe), ordered so that typical first classes read naturally
# (terrain ochre, vegetation green), followed by extra colours for larger class tables.
CLASS_COLOURS = (
    "#E69F00",  # orange
    "#009E73",  # bluish green
    "#D55E00",  # vermillion
    "#56B4E9",  # sky blue
    "#0072B2",  # blue
    "#CC79A7",  # reddish purple
    "#F0E442",  # yellow
    "#882255",  # wine (instead of Okabe-Ito's black, which the macro F1 line uses)
    "#8C564B",  # brown
    "#7F7F7F",  # grey
    "#BCBD22",  # olive
    "#17BECF",  # cyan
)

DPI = 150

STYLE = {
    "font.size": 9,
    "axes.titlesize": 10,
    "axes.titleweight": "bold",
    "axes.labelsize": 9,
    "axes.spines.top": False,
    "axes.spines.right": False,
    "axes.edgecolor": "#555555",
    "axes.grid": False,
    "grid.color": "#DDDDDD",
    "grid.linewidth": 0.6,
    "legend.frameon": False,
    "legend.fontsize": 8,
    "savefig.bbox": "tight",
    "savefig.pad_inches": 0.12,
    "savefig.facecolor": "white",
}


def class_colour(i: int) -> str:
    """The colour ('#RRGGBB') of class index ``i``; the palette repeats after 12 classes."""
    return CLASS_COLOURS[int(i) % len(CLASS_COLOURS)]


def class_colours(labels: np.ndarray, n_classes: int) -> np.ndarray:
    """float (N, 4) RGBA of class indices ``labels``: a scatter of many points parses
    colours given as numbers at once, and '#RRGGBB' strings one by one."""
    palette = matplotlib.colors.to_rgba_array([class_colour(i) for i in range(n_classes)])
    return palette[np.asarray(labels, dtype=np.int64)]


def marker_side(size: float, data_per_inch: float) -> float:
    """The side in data units of a square marker of ``size`` pt² (as a scatter's ``s``),
    at least one pixel, on axes showing ``data_per_inch`` data units per inch."""
    return max(math.sqrt(size) / 72.0, 1.0 / DPI) * data_per_inch


def span(values) -> float:
    """The spread (max - min) of ``values``, or 1 (one data unit) when they have none: no
    value, one, or all equal (a flat tile, a single point), so a scale taken from it is
    never 0."""
    values = np.asarray(values, dtype=np.float64)
    spread = float(np.ptp(values)) if values.size else 0.0
    return spread if spread > 0.0 else 1.0


def draw_points(ax, x, y, rgba, side, **imshow) -> None:
    """Draw points as square markers of ``side`` data units (or (side x, side y)), each
    cell of that side in the colour of the last point in it, as one image: the same
    picture as a scatter of square markers, which Agg draws in a good part of a second
    for 10^5 points, and an image in milliseconds. ``imshow``: more imshow arguments
    (e.g. aspect="auto")."""
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if x.size == 0:
        return
    sx, sy = np.broadcast_to(np.asarray(side, dtype=np.float64), (2,))
    if not (np.isfinite([sx, sy]).all() and sx > 0 and sy > 0):
        raise InputError(f"marker sides must be positive, got ({sx}, {sy}): take them from "
                         "spans(), which never gives 0")
    x0, y0 = x.min() - sx / 2, y.min() - sy / 2
    i = ((x - x0) / sx).astype(np.int64)
    j = ((y - y0) / sy).astype(np.int64)
    nx, ny = int(i.max()) + 1, int(j.max()) + 1
    cell = j * nx + i
    _, from_end = np.unique(cell[::-1], return_index=True)
    last = x.size - 1 - from_end  # the last point of each occupied cell is drawn on top
    image = np.zeros((ny * nx, 4), dtype=np.float32)  # transparent where no point is
    image[cell[last]] = np.asarray(rgba, dtype=np.float32)[last]
    drawn = ax.imshow(image.reshape(ny, nx, 4), origin="lower", interpolation="nearest",
                      extent=(x0, x0 + nx * sx, y0, y0 + ny * sy), **imshow)
    drawn.sticky_edges.x.clear()  # the axes keep a scatter's margins around the points
    drawn.sticky_edges.y.clear()
    ax.autoscale_view()


def format_score(value: float) -> str:
    """A score as the report's tables show it (three decimals, as in the paper)."""
    return f"{float(value):.3f}"


def confusion_figure(metrics: dict) -> Figure:
    """Confusion matrix: colours are shares of each true class (rows), cells give counts."""
    names = list(metrics["classes"])
    excluded = set(metrics.get("excluded", ()))
    counts = np.asarray(metrics["confusion"], dtype=np.int64)
    n = len(names)
    rows = counts.sum(axis=1, keepdims=True)
    share = np.divide(counts, rows, out=np.zeros(counts.shape), where=rows > 0)

    size = max(4.2, 0.85 * n + 2.2)
    with matplotlib.rc_context(STYLE):
        fig = Figure(figsize=(size + 0.9, size), dpi=DPI)
        ax = fig.add_subplot()
        image = ax.imshow(share, cmap="Blues", vmin=0.0, vmax=1.0)
        for i in range(n):
            for j in range(n):
                dark = share[i, j] > 0.55
                ax.text(j, i - 0.12, f"{share[i, j]:.1%}" if rows[i, 0] else "–",
                        ha="center", va="center", fontsize=9 if n <= 8 else 7,
                        fontweight="bold" if i == j else "normal",
                        color="white" if dark else "#222222")
                ax.text(j, i + 0.2, _compact_count(counts[i, j]), ha="center", va="center",
                        fontsize=7 if n <= 8 else 6, color="#E8EEF6" if dark else "#666666")
        labels = [_mpl_text(name) + (" *" if name in excluded else "") for name in names]
        ax.set_xticks(range(n), labels, rotation=30, ha="right", rotation_mode="anchor")
        ax.set_yticks(range(n), [
            f"{label}\n({_compact_count(rows[i, 0])})" for i, label in enumerate(labels)
        ])
        for tick_labels in (ax.get_xticklabels(), ax.get_yticklabels()):
            for name, label in zip(names, tick_labels):
                label.set_color(_class_text_colour(name, excluded))
        ax.set_xlabel("predicted class")
        ax.set_ylabel("true class (test points)")
        ax.set_title("Confusion matrix, final stage")
        ax.tick_params(length=0)
        for spine in ax.spines.values():
            spine.set_visible(False)
        bar = fig.colorbar(image, ax=ax, fraction=0.046, pad=0.04)
        bar.set_label("share of the true class")
        bar.ax.yaxis.set_major_formatter(matplotlib.ticker.PercentFormatter(1.0))
        bar.outline.set_visible(False)
        if excluded:
            fig.text(0.01, 0.005, "* excluded from the averages", fontsize=7, color="#777777")
    return fig


def precision_recall_figure(pr_data: dict, metrics: dict | None = None) -> Figure:
    """One-vs-rest precision-recall curve per evaluated class, average precision in the
    legend; dots mark the precision and recall of the final predictions (``metrics``)."""
    missing = [k for k in ("y_true", "proba", "class_names") if k not in pr_data]
    if missing:
        raise InputError(f"pr_data lacks {missing}: pass y_true, proba, class_names, exclude")
    names = [str(n) for n in pr_data["class_names"]]
    curves = precision_recall_curve_data(
        pr_data["y_true"], pr_data["proba"], names, exclude=pr_data.get("exclude", ())
    )
    per_class = (metrics or {}).get("per_class", {})
    with matplotlib.rc_context(STYLE):
        fig = Figure(figsize=(6.4, 5.0), dpi=DPI)
        ax = fig.add_subplot()
        handles, labels, dots = [], [], False
        for name, curve in curves.items():
            colour = class_colour(names.index(name))
            if curve["support"] == 0:
                handles.append(Patch(color=colour, alpha=0.3))
                labels.append(f"{_mpl_text(name)} (no test points in the sample)")
                continue
            (line,) = ax.plot(curve["recall"], curve["precision"], color=colour, lw=1.8,
                              drawstyle="steps-post")
            handles.append(line)
            labels.append(f"{_mpl_text(name)}  AP {curve['average_precision']:.3f}"
                          f"  (n = {_compact_count(curve['support'])})")
            if name in per_class:
                ax.plot(per_class[name]["recall"], per_class[name]["precision"], "o",
                        color=colour, markeredgecolor="white", markersize=7, zorder=5)
                dots = True
        if dots:
            handles.append(ax.plot([], [], "o", color="#555555", markeredgecolor="white")[0])
            labels.append("predicted class (argmax)")
        ax.set_xlim(0.0, 1.01)
        ax.set_ylim(0.0, 1.02)
        ax.set_aspect("equal")
        ax.grid(True)
        ax.set_xlabel("recall")
        ax.set_ylabel("precision")
        ax.set_title("Precision-recall, one class against the rest (final stage)")
        ax.legend(handles, labels, loc="center left", bbox_to_anchor=(1.02, 0.5))
    return fig


def f1_per_stage_figure(stages: list[dict]) -> Figure:
    """Macro F1 and the F1 of every evaluated class against the cascade stage."""
    names = list(stages[-1]["classes"])
    excluded = set(stages[-1].get("excluded", ()))
    x = np.arange(1, len(stages) + 1)
    macro = np.array([s["macro"]["f1"] for s in stages])
    with matplotlib.rc_context(STYLE):
        fig = Figure(figsize=(6.4, 4.2), dpi=DPI)
        ax = fig.add_subplot()
        values, handles, labels = [macro], [], []
        for i, name in enumerate(names):
            if name in excluded:
                continue
            f1 = np.array([s["per_class"][name]["f1"] for s in stages])
            values.append(f1)
            handles += ax.plot(x, f1, "-o", color=class_colour(i), lw=1.4, markersize=4.5)
            labels.append(_mpl_text(name))
        handles += ax.plot(x, macro, "-s", color="#222222", lw=2.6, markersize=6.5, zorder=5)
        labels.append("macro F1")
        for xi, value in zip(x, macro):
            ax.annotate(format_score(value), (xi, value), textcoords="offset points",
                        xytext=(0, 10), ha="center", fontsize=8, fontweight="bold",
                        color="#222222", zorder=6,
                        bbox=dict(boxstyle="round,pad=0.2", fc="white", ec="none", alpha=0.85))
        low, high = float(np.min(values)), float(np.max(values))
        pad = max(0.04, 0.12 * (high - low))
        ax.set_ylim(max(0.0, low - pad), min(1.0, high + pad) + 0.05)
        ax.set_xlim(0.7, len(stages) + 0.3)
        ax.set_xticks(x, [f"stage {i}" for i in x])
        ax.grid(True, axis="y")
        ax.set_ylabel("F1 (test points)")
        ax.set_title("F1 per cascade stage")
        # Explicit labels: matplotlib would drop names that start with "_".
        ax.legend(handles, labels, loc="center left", bbox_to_anchor=(1.02, 0.5))
    return fig


def topdown_figure(topdown: dict) -> Figure:
    """Predicted class of the given points seen from above, in map coordinates: with
    ``height`` (each point's height above the ground, or its elevation), the highest point
    of each drawn cell, as a map is read; without, a fixed shuffle of them."""
    missing = [k for k in ("x", "y", "label", "class_names") if k not in topdown]
    if missing:
        raise InputError(f"topdown lacks {missing}: pass x, y, label and class_names")
    names = [str(n) for n in topdown["class_names"]]
    x = np.asarray(topdown["x"], dtype=np.float64)
    y = np.asarray(topdown["y"], dtype=np.float64)
    label = np.asarray(topdown["label"])
    if not (x.shape == y.shape == label.shape) or x.ndim != 1:
        raise InputError(
            f"topdown x, y and label must be 1-D of one length, got shapes {x.shape}, "
            f"{y.shape}, {label.shape}"
        )
    if label.size and (label.min() < 0 or label.max() >= len(names)):
        raise InputError(
            f"topdown label holds class indices outside [0, {len(names)}): pass predicted "
            "class indices"
        )
    if topdown.get("height") is not None:
        height = np.asarray(topdown["height"], dtype=np.float64)
        if height.shape != x.shape:
            raise InputError(f"topdown height must be of the points' shape {x.shape}, got "
                             f"{height.shape}")
        # the highest drawn last: each cell shows its highest point (unknown heights lowest)
        order = np.argsort(np.nan_to_num(height, nan=-np.inf), kind="stable")
    else:  # a fixed shuffle, so that no class is systematically drawn over another
        order = np.random.default_rng(0).permutation(x.size)
    x, y, label = x[order], y[order], label[order].astype(np.int64)

    span_x, span_y = span(x), span(y)
    width = 7.0
    height = float(np.clip(width * span_y / span_x, 2.5, 9.0))
    with matplotlib.rc_context(STYLE):
        fig = Figure(figsize=(width + 2.0, height + 0.8), dpi=DPI)
        ax = fig.add_subplot()
        # Marker area (pt^2) about the map area per point, so the cover looks continuous.
        per_point = width * height * 72 * 72 / max(x.size, 1)
        size = float(np.clip(2.5 * per_point, 0.05, 30.0))
        side = marker_side(size, max(span_x / width, span_y / height))
        draw_points(ax, x, y, class_colours(label, len(names)), side)
        ax.set_aspect("equal")
        ax.ticklabel_format(useOffset=False, style="plain")
        ax.set_xlabel("x (map units)")
        ax.set_ylabel("y (map units)")
        ax.set_title(f"Predicted classes seen from above ({x.size:,} points"
                     + (", the highest of each cell drawn)" if "height" in topdown else ")"))
        shares = np.bincount(label, minlength=len(names)) / max(x.size, 1)
        handles = [Patch(color=class_colour(i)) for i in range(len(names))]
        labels = [f"{_mpl_text(n)}  {shares[i]:.1%}" for i, n in enumerate(names)]
        ax.legend(handles, labels, loc="upper left", bbox_to_anchor=(1.02, 1.0),
                  title="predicted class")
    return fig


def top_importances(importances: dict, top: int) -> list[tuple[str, float]]:
    """The ``top`` (column, importance) pairs of one stage, largest first (ties by name)."""
    pairs = sorted(((str(k), float(v)) for k, v in importances.items()),
                   key=lambda kv: (-kv[1], kv[0]))
    return pairs[:top]


def importance_figure(importances: list, class_names=(), top: int = 10) -> Figure:
    """The ``top`` feature columns by impurity importance, one bar panel per cascade stage.

    ``importances`` holds one ``{column: importance}`` dict per stage (None or empty for a
    stage without a record). Context columns (``context_r1_<class>``, ``context_r2_<class>``)
    take their class's colour; the other feature columns are grey.
    """
    stages = [(i + 1, s) for i, s in enumerate(importances) if s]
    if not stages:
        raise InputError("importances holds no stage with feature importances")
    names = [str(n) for n in class_names]
    colour_of = {f"context_{r}_{n}": class_colour(i)
                 for i, n in enumerate(names) for r in ("r1", "r2")}
    n_rows = max(len(top_importances(s, top)) for _, s in stages)
    largest = max(v for _, s in stages for _, v in top_importances(s, top))
    width = min(3.4 * len(stages), 13.0)
    with matplotlib.rc_context(STYLE):
        fig = Figure(figsize=(max(width, 4.6), 0.9 + 0.26 * n_rows), dpi=DPI)
        axes = fig.subplots(1, len(stages), squeeze=False)[0]
        for ax, (number, stage) in zip(axes, stages):
            pairs = top_importances(stage, top)
            y = np.arange(len(pairs))
            ax.barh(y, [v for _, v in pairs], height=0.72,
                    color=[colour_of.get(k, "#8C959F") for k, _ in pairs])
            ax.set_yticks(y, [_mpl_text(k) for k, _ in pairs], fontsize=7)
            ax.set_ylim(n_rows - 0.5, -0.5)  # largest on top
            ax.set_xlim(0.0, largest * 1.08)
            ax.grid(True, axis="x")
            ax.tick_params(axis="y", length=0)
            ax.set_title(f"stage {number}")
            ax.set_xlabel("importance")
        fig.suptitle(f"Top {top} feature columns by importance", fontweight="bold",
                     fontsize=10)
        fig.tight_layout()
    return fig


def png_bytes(figure: Figure) -> bytes:
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=DPI, bbox_inches="tight", pad_inches=0.12,
                   facecolor="white")
    return buffer.getvalue()


def _mpl_text(text) -> str:
    """Text shown literally by matplotlib ('$' would start mathtext)."""
    return str(text).replace("$", r"\$")


def _class_text_colour(name: str, excluded: set) -> str:
    return "#8C959F" if name in excluded else "#222222"


def _compact_count(count) -> str:
    count = int(count)
    if count < 10_000:
        return f"{count:,}"
    if count < 1_000_000:
        return f"{count / 1e3:.1f}k" if count < 100_000 else f"{count / 1e3:.0f}k"
    return f"{count / 1e6:.2f}M" if count < 100_000_000 else f"{count / 1e6:.0f}M"


def scene_rasters(dtm) -> tuple:
    """The rasters of a scene's terrain model: ``dtm`` itself (a
    :class:`pipeline.grid.Raster`), or every raster of a sequence of them."""
    if hasattr(dtm, "values"):
        return (dtm,)
    return tuple(dtm)


def raster_extent(raster) -> tuple[float, float, float, float]:
    """(x0, x1, y0, y1): the box a raster covers, as imshow's ``extent``."""
    ny, nx = raster.values.shape
    return (raster.x0, raster.x0 + nx * raster.cell, raster.y0, raster.y0 + ny * raster.cell)


def draw_hillshades(ax, rasters) -> tuple[float, float, float, float]:
    """Draw the hillshade of each raster at its place, each outlined (a block far from the
    others stays visible however small it is drawn); return the box of them all."""
    from pipeline.io.raster import hillshade

    boxes = np.array([raster_extent(r) for r in rasters])
    for raster, (x0, x1, y0, y1) in zip(rasters, boxes):
        ax.imshow(hillshade(raster.values, raster.cell), cmap="gray", origin="lower",
                  extent=(x0, x1, y0, y1), vmin=0, vmax=1, interpolation="nearest")
        if len(rasters) > 1:
            ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, linewidth=0.8,
                                   edgecolor="#CF222E"))
    extent = (boxes[:, 0].min(), boxes[:, 1].max(), boxes[:, 2].min(), boxes[:, 3].max())
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])
    return extent


def terrain_figure(terrain: dict) -> Figure:
    """Per scene, the terrain model's hillshade and the canopy height of the sampled points.

    ``terrain`` maps a scene name to ``{"dtm": ..., "x", "y", "height"}``: the scene's
    terrain model (a :class:`pipeline.grid.Raster`, or its blocks, see
    :func:`scene_rasters`: every block is drawn at its place, so plots far apart are all
    seen) and the map coordinates and heights above it of the sampled points predicted as a
    canopy class.
    """
    scenes = list(terrain)
    if not scenes:
        raise InputError("terrain holds no scene: pass {scene: {dtm, x, y, height}}")
    with matplotlib.rc_context(STYLE):
        fig = Figure(figsize=(11.0, 4.6 * len(scenes)), dpi=DPI)
        for row, scene in enumerate(scenes):
            entry = terrain[scene]
            rasters = scene_rasters(entry["dtm"])
            ax = fig.add_subplot(len(scenes), 2, 2 * row + 1)
            extent = draw_hillshades(ax, rasters)
            low = min(np.nanmin(r.values) for r in rasters)
            high = max(np.nanmax(r.values) for r in rasters)
            blocks = f", {len(rasters)} blocks" if len(rasters) > 1 else ""
            ax.set_title(f"{_mpl_text(scene)}: terrain model\n{low:.1f}-{high:.1f} m "
                         f"({rasters[0].cell:g} m cells{blocks})")
            ax.ticklabel_format(useOffset=False, style="plain")
            ax = fig.add_subplot(len(scenes), 2, 2 * row + 2)
            x, y = np.asarray(entry["x"]), np.asarray(entry["y"])
            height = np.asarray(entry["height"], dtype=np.float64)
            order = np.argsort(height, kind="stable")  # the tallest drawn last, on top
            colours = matplotlib.cm.ScalarMappable(
                matplotlib.colors.Normalize(vmin=0, vmax=max(height.max(initial=0), 1e-9)),
                "viridis")
            panel = 4.5  # inches: about the width of this axes
            side = marker_side(1.0, max(extent[1] - extent[0], extent[3] - extent[2]) / panel)
            draw_points(ax, x[order], y[order], colours.to_rgba(height[order]), side)
            ax.set_xlim(extent[0], extent[1])
            ax.set_ylim(extent[2], extent[3])
            ax.set_aspect("equal")
            ax.ticklabel_format(useOffset=False, style="plain")
            ax.set_title(f"canopy height above the terrain\n({x.size:,} sampled points)")
            fig.colorbar(colours, ax=ax, label="m above ground", shrink=0.8)
        fig.tight_layout()
    return fig
