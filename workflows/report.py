"""The HTML report of a run: headline scores, per-class and per-stage tables, plots, config.

``report.html`` is self-contained (every plot is embedded as a base64 PNG), so it opens
offline on any machine; the same plots are also written as PNG files in ``plots/``. Plots
are drawn with matplotlib's Agg renderer on ``Figure`` objects, never through pyplot, so no
display is needed and no global state is touched.

Each class has one colour everywhere, chosen by its index from :data:`CLASS_COLOURS`
(Okabe & Ito's colour-blind-safe palette, then a few more distinct colours);
:func:`class_colour` is the function other pictures (previews, exports) should use.
"""

import base64
import html
import io
import os
from pathlib import Path

import matplotlib
import matplotlib.ticker
import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Patch

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

PLOT_NAMES = ("confusion", "precision_recall", "f1_per_stage", "topdown")
REQUIRED_KEYS = ("classes", "per_class", "macro", "overall_accuracy", "confusion",
                 "n_test_points")
SCORES = ("precision", "recall", "f1", "iou")
SCORE_LABELS = {"precision": "Precision", "recall": "Recall", "f1": "F1", "iou": "IoU"}
DPI = 150

_STYLE = {
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


def format_score(value: float) -> str:
    """A score as the report's tables show it (three decimals, as in the paper)."""
    return f"{float(value):.3f}"


def write_report(
    out_dir,
    metrics: dict,
    *,
    pr_data: dict | None = None,
    topdown: dict | None = None,
    title: str = "Silva report",
    run_info: dict | None = None,
    config_text: str | None = None,
) -> Path:
    """Write ``out_dir/report.html`` and its plots as ``out_dir/plots/*.png``.

    Parameters
    ----------
    out_dir : path
        Created if needed.
    metrics : dict
        A metrics.json dict (see :func:`pipeline.metrics.scores_from_confusion`) for the
        final stage, plus ``"stages"``: one such dict per cascade stage, in order. Without
        ``"stages"`` the metrics are shown as a single stage.
    pr_data : dict, optional
        ``{"y_true": int (n,), "proba": float (n, C), "class_names": [C], "exclude": [...]}``,
        final-stage probabilities of (a sample of) the test points, for the precision-recall
        curves. Without it the report says the plot is missing.
    topdown : dict, optional
        ``{"x": float (m,), "y": float (m,), "label": int (m,) class indices,
        "class_names": [C]}``, predicted classes of (a sample of) the points in map
        coordinates, for the top-down map.
    title : str
    run_info : dict, optional
        Shown as a two-column table (command, date, software version, durations, ...).
    config_text : str, optional
        The resolved configuration, shown verbatim.

    Returns
    -------
    Path of report.html. It is written atomically: a partial report never exists under that
    name. PNGs of plots that could not be drawn are removed from ``plots/``, so the folder
    always matches the report.
    """
    metrics = _check_metrics(metrics)
    stages = metrics.get("stages") or [metrics]
    out_dir = Path(out_dir)
    plot_dir = out_dir / "plots"
    plot_dir.mkdir(parents=True, exist_ok=True)

    figures = {
        "confusion": (confusion_figure(metrics), None),
        "precision_recall": _optional_figure(
            pr_data, lambda: precision_recall_figure(pr_data, metrics),
            "No precision-recall data was passed to the report, so this plot is omitted.",
        ),
        "f1_per_stage": (f1_per_stage_figure(stages), None),
        "topdown": _optional_figure(
            topdown, lambda: topdown_figure(topdown),
            "No point positions were passed to the report, so the map is omitted.",
        ),
    }
    images = {}
    for name, (figure, note) in figures.items():
        path = plot_dir / f"{name}.png"
        if figure is None:
            path.unlink(missing_ok=True)
            images[name] = (None, note)
            continue
        png = _png_bytes(figure)
        path.write_bytes(png)
        images[name] = (png, None)

    page = _render_page(metrics, stages, images, title, run_info, config_text)
    target = out_dir / "report.html"
    partial = out_dir / ".report.html.partial"
    partial.write_text(page, encoding="utf-8")
    os.replace(partial, target)
    return target


# -- figures -----------------------------------------------------------------------------


def confusion_figure(metrics: dict) -> Figure:
    """Confusion matrix: colours are shares of each true class (rows), cells give counts."""
    names = list(metrics["classes"])
    excluded = set(metrics.get("excluded", ()))
    counts = np.asarray(metrics["confusion"], dtype=np.int64)
    n = len(names)
    rows = counts.sum(axis=1, keepdims=True)
    share = np.divide(counts, rows, out=np.zeros(counts.shape), where=rows > 0)

    size = max(4.2, 0.85 * n + 2.2)
    with matplotlib.rc_context(_STYLE):
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
    with matplotlib.rc_context(_STYLE):
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
    with matplotlib.rc_context(_STYLE):
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
    """Predicted class of every given point seen from above, in map coordinates."""
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
    # A fixed shuffle, so that no class is systematically drawn over another.
    order = np.random.default_rng(0).permutation(x.size)
    x, y, label = x[order], y[order], label[order].astype(np.int64)

    span_x = float(np.ptp(x)) if x.size else 1.0
    span_y = float(np.ptp(y)) if y.size else 1.0
    span_x, span_y = max(span_x, 1e-9), max(span_y, 1e-9)
    width = 7.0
    height = float(np.clip(width * span_y / span_x, 2.5, 9.0))
    with matplotlib.rc_context(_STYLE):
        fig = Figure(figsize=(width + 2.0, height + 0.8), dpi=DPI)
        ax = fig.add_subplot()
        # Marker area (pt^2) about the map area per point, so the cover looks continuous.
        per_point = width * height * 72 * 72 / max(x.size, 1)
        size = float(np.clip(2.5 * per_point, 0.05, 30.0))
        palette = np.array([class_colour(i) for i in range(len(names))])
        ax.scatter(x, y, c=palette[label] if x.size else [], s=size, marker="s",
                   linewidths=0, rasterized=True)
        ax.set_aspect("equal")
        ax.ticklabel_format(useOffset=False, style="plain")
        ax.set_xlabel("x (map units)")
        ax.set_ylabel("y (map units)")
        ax.set_title(f"Predicted classes seen from above ({x.size:,} points)")
        shares = np.bincount(label, minlength=len(names)) / max(x.size, 1)
        handles = [Patch(color=class_colour(i)) for i in range(len(names))]
        labels = [f"{_mpl_text(n)}  {shares[i]:.1%}" for i, n in enumerate(names)]
        ax.legend(handles, labels, loc="upper left", bbox_to_anchor=(1.02, 1.0),
                  title="predicted class")
    return fig


# -- page --------------------------------------------------------------------------------

_CSS = """
:root { --ink:#1f2328; --muted:#656d76; --line:#d8dee4; --soft:#f6f8fa; --accent:#0072B2; }
* { box-sizing: border-box; }
body { margin:0; background:#eef1f4; color:var(--ink);
  font:14px/1.5 -apple-system,"Segoe UI",Roboto,"Helvetica Neue",Arial,sans-serif; }
main { max-width:1120px; margin:24px auto; background:#fff; padding:28px 40px 36px;
  border-radius:10px; box-shadow:0 1px 3px rgba(0,0,0,.08); }
h1 { margin:0 0 4px; font-size:26px; }
h2 { margin:34px 0 12px; font-size:18px; padding-bottom:6px; border-bottom:1px solid var(--line); }
.sub { color:var(--muted); margin:0 0 18px; }
.cards { display:grid; grid-template-columns:repeat(auto-fit,minmax(150px,1fr)); gap:12px; }
.card { background:var(--soft); border:1px solid var(--line); border-radius:8px;
  padding:12px 14px; }
.card .label { color:var(--muted); font-size:12px; text-transform:uppercase; letter-spacing:.04em; }
.card .value { font-size:26px; font-weight:600; font-variant-numeric:tabular-nums; }
.card.main { background:#e7f1f8; border-color:#b6d4ea; }
.card.main .value { color:var(--accent); }
table { border-collapse:collapse; font-variant-numeric:tabular-nums; margin:4px 0; }
th, td { padding:5px 12px; border-bottom:1px solid var(--line); text-align:right; }
th { background:var(--soft); font-weight:600; font-size:13px; }
td:first-child, th:first-child { text-align:left; }
tr.total td { font-weight:600; border-top:2px solid #aab3bc; }
tr.excluded td { color:#8c959f; }
td.diag { font-weight:600; background:#eef5fb; }
tr.final td { background:#f2f8fc; }
table.info td:first-child { color:var(--muted); padding-right:24px; }
table.info td { text-align:left; }
.tag { font-size:11px; border:1px solid #c5ccd3; border-radius:9px; padding:0 6px;
  margin-left:6px; color:var(--muted); }
.swatch { display:inline-block; width:11px; height:11px; border-radius:2px; margin-right:7px;
  vertical-align:-1px; }
.up { color:#1a7f37; } .down { color:#cf222e; }
.note { color:var(--muted); font-size:13px; }
.missing { background:var(--soft); border:1px dashed var(--line); padding:14px; border-radius:8px;
  color:var(--muted); }
figure { margin:18px 0 26px; }
figure img { max-width:100%; height:auto; display:block; }
figcaption { color:var(--muted); font-size:13px; margin-top:6px; max-width:860px; }
pre { background:var(--soft); border:1px solid var(--line); border-radius:8px; padding:12px;
  overflow:auto; font-size:12px; line-height:1.45; }
details summary { cursor:pointer; color:var(--accent); margin:8px 0; }
footer { margin-top:32px; color:var(--muted); font-size:12px; border-top:1px solid var(--line);
  padding-top:10px; }
"""

_CAPTIONS = {
    "confusion": (
        "Confusion matrix of the final stage on the test points. Colours and percentages are "
        "shares of each true class (rows sum to 100%, the diagonal is the recall); the smaller "
        "number is the point count."
    ),
    "precision_recall": (
        "Precision-recall curves of each evaluated class against the rest, from the "
        "final-stage class probabilities of a sample of the test points. AP = average "
        "precision; dots mark the precision and recall of the predicted classes."
    ),
    "f1_per_stage": (
        "F1 after each stage of the cascade: every stage adds the class frequencies around "
        "each point (the context) predicted by the previous stage."
    ),
    "topdown": "Final predicted class of a sample of the points, seen from above.",
}
_TITLES = {
    "confusion": "Confusion matrix",
    "precision_recall": "Precision-recall curves",
    "f1_per_stage": "F1 per stage",
    "topdown": "Map of predicted classes",
}


def _render_page(metrics, stages, images, title, run_info, config_text) -> str:
    e = _escape
    names = list(metrics["classes"])
    excluded = list(metrics.get("excluded", ()))
    n_eval = len(names) - len(excluded)
    subtitle = (f"Test-set evaluation · {len(names)} classes · {len(stages)} cascade "
                f"stage{'s' if len(stages) != 1 else ''} · "
                f"{metrics['n_test_points']:,} evaluated test points")
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>{e(title)}</title><style>{_CSS}</style></head><body><main>",
        f"<h1>{e(title)}</h1>",
        f'<p class="sub">{e(subtitle)}</p>',
    ]
    if run_info:
        parts.append('<table class="info">')
        parts += [f"<tr><td>{e(k)}</td><td>{e(_format_value(v))}</td></tr>"
                  for k, v in run_info.items()]
        parts.append("</table>")

    parts.append("<h2>Summary</h2>")
    parts.append(_cards(metrics))
    excluded_text = (f"; excluded as background: {', '.join(excluded)}" if excluded else "")
    note = (f"Macro scores are unweighted means over the {n_eval} evaluated classes"
            f"{excluded_text}. Overall accuracy and the point count cover the test points of "
            "evaluated classes.")
    parts.append(f'<p class="note">{e(note)}</p>')

    parts.append("<h2>Per class (final stage)</h2>")
    parts.append(_class_table(metrics))

    parts.append("<h2>Cascade stages</h2>")
    parts.append(_stage_table(stages))

    parts.append("<h2>Plots</h2>")
    for name in PLOT_NAMES:
        png, note = images[name]
        parts.append(f"<figure><h3>{e(_TITLES[name])}</h3>")
        if png is None:
            parts.append(f'<p class="missing">{e(note)}</p></figure>')
            continue
        data = base64.b64encode(png).decode("ascii")
        parts.append(f'<img src="data:image/png;base64,{data}" alt="{e(_TITLES[name])}">')
        parts.append(f"<figcaption>{e(_CAPTIONS[name])}</figcaption></figure>")

    parts.append("<h2>Confusion counts</h2>")
    parts.append("<details><summary>Exact point counts (rows: true class, columns: "
                 "predicted class)</summary>")
    parts.append(_confusion_table(metrics))
    parts.append("</details>")

    parts.append("<h2>Configuration</h2>")
    if config_text:
        parts.append(f"<pre>{e(config_text)}</pre>")
    else:
        parts.append('<p class="note">No configuration was recorded with this report.</p>')
    parts.append(
        "<footer>Precision = TP / (TP + FP), recall = TP / (TP + FN), F1 = their harmonic "
        "mean, IoU = TP / (TP + FP + FN), one class against the rest; a division by zero "
        "counts as 0. Points whose true class is excluded are left out of every score of "
        "the evaluated classes; predictions into an excluded class count as misses. Excluded "
        "classes are scored on all test points, for information only.</footer>"
    )
    parts.append("</main></body></html>")
    return "\n".join(parts) + "\n"


def _cards(metrics) -> str:
    macro = metrics["macro"]
    cards = [("Macro F1", format_score(macro["f1"]), True)]
    cards += [(f"Macro {SCORE_LABELS[k].lower() if k != 'iou' else 'IoU'}",
               format_score(macro[k]), False) for k in ("precision", "recall", "iou")]
    cards += [("Overall accuracy", format_score(metrics["overall_accuracy"]), False),
              ("Test points", f"{metrics['n_test_points']:,}", False)]
    return '<div class="cards">' + "".join(
        f'<div class="card{" main" if main else ""}"><div class="label">{_escape(label)}</div>'
        f'<div class="value">{_escape(value)}</div></div>'
        for label, value, main in cards
    ) + "</div>"


def _class_table(metrics) -> str:
    e = _escape
    excluded = set(metrics.get("excluded", ()))
    head = "".join(f"<th>{SCORE_LABELS[k]}</th>" for k in SCORES)
    rows = [f"<table><tr><th>Class</th>{head}<th>Test points</th></tr>"]
    for i, name in enumerate(metrics["classes"]):
        scores = metrics["per_class"][name]
        tag = '<span class="tag">excluded</span>' if name in excluded else ""
        cells = "".join(f"<td>{format_score(scores[k])}</td>" for k in SCORES)
        row_class = ' class="excluded"' if name in excluded else ""
        rows.append(
            f"<tr{row_class}><td>"
            f'<span class="swatch" style="background:{class_colour(i)}"></span>{e(name)}{tag}'
            f"</td>{cells}<td>{int(scores['support']):,}</td></tr>"
        )
    cells = "".join(f"<td>{format_score(metrics['macro'][k])}</td>" for k in SCORES)
    rows.append(f'<tr class="total"><td>Macro average</td>{cells}'
                f"<td>{metrics['n_test_points']:,}</td></tr></table>")
    return "\n".join(rows)


def _stage_table(stages) -> str:
    e = _escape
    names = [n for n in stages[-1]["classes"] if n not in set(stages[-1].get("excluded", ()))]
    head = ("<tr><th>Stage</th><th>Macro F1</th><th>Change</th><th>Macro precision</th>"
            "<th>Macro recall</th><th>Macro IoU</th><th>Overall accuracy</th>"
            + "".join(f"<th>F1 {e(n)}</th>" for n in names) + "</tr>")
    rows = ['<table class="stages">', head]
    previous = None
    for number, stage in enumerate(stages, start=1):
        f1 = stage["macro"]["f1"]
        if previous is None:
            change = "<td>–</td>"
        else:
            delta = f1 - previous
            shown = f"{delta:+.3f}"
            css = "up" if float(shown) > 0 else "down" if float(shown) < 0 else ""
            change = f'<td class="{css}">{shown}</td>'
        previous = f1
        per_class = "".join(
            f"<td>{format_score(stage['per_class'][n]['f1'])}</td>" for n in names
        )
        final = ' class="final"' if number == len(stages) else ""
        rows.append(
            f"<tr{final}><td>{number}</td><td><b>{format_score(f1)}</b></td>{change}"
            f"<td>{format_score(stage['macro']['precision'])}</td>"
            f"<td>{format_score(stage['macro']['recall'])}</td>"
            f"<td>{format_score(stage['macro']['iou'])}</td>"
            f"<td>{format_score(stage['overall_accuracy'])}</td>{per_class}</tr>"
        )
    rows.append("</table>")
    rows.append('<p class="note">Change: macro F1 minus that of the previous stage.</p>')
    return "\n".join(rows)


def _confusion_table(metrics) -> str:
    e = _escape
    diag = ' class="diag"'
    names = list(metrics["classes"])
    rows = ["<table><tr><th>true \\ predicted</th>"
            + "".join(f"<th>{e(n)}</th>" for n in names) + "<th>Total</th></tr>"]
    for i, (name, counts) in enumerate(zip(names, metrics["confusion"])):
        cells = "".join(f"<td{diag if i == j else ''}>{int(c):,}</td>"
                        for j, c in enumerate(counts))
        rows.append(f"<tr><td>{e(name)}</td>{cells}<td>{int(sum(counts)):,}</td></tr>")
    rows.append("</table>")
    return "\n".join(rows)


# -- small utilities ---------------------------------------------------------------------


def _check_metrics(metrics: dict) -> dict:
    if not isinstance(metrics, dict):
        raise InputError(f"metrics must be a metrics.json dict, got {type(metrics).__name__}")
    for where, m in [("metrics", metrics)] + [
        (f"metrics['stages'][{i}]", s) for i, s in enumerate(metrics.get("stages") or [])
    ]:
        missing = [k for k in REQUIRED_KEYS if k not in m]
        if missing:
            raise InputError(f"{where} lacks {missing}: pass the dict of "
                             "pipeline.metrics.scores_from_confusion")
    return metrics


def _optional_figure(data, draw, note):
    return (None, note) if data is None else (draw(), None)


def _png_bytes(figure: Figure) -> bytes:
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=DPI, bbox_inches="tight", pad_inches=0.12,
                   facecolor="white")
    return buffer.getvalue()


def _escape(value) -> str:
    return html.escape(str(value), quote=True)


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


def _format_value(value) -> str:
    if isinstance(value, bool):
        return str(value)
    if isinstance(value, (int, np.integer)):
        return f"{int(value):,}"
    if isinstance(value, (list, tuple)):
        return ", ".join(str(v) for v in value)
    return str(value)
