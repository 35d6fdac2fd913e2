"""The report of a run without labels (:mod:`workflows.steps.survey`): class shares of the
points and of the area, per tile; the class map, a side view and where the uncertain points
are, per scene; confidence and entropy histograms; the terrain model and canopy height."""

from pathlib import Path

import matplotlib
import matplotlib.colors
import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from pipeline.atomic import atomic_path, atomic_write_bytes
from workflows.report.figures import (
    DPI, STYLE, _mpl_text, class_colour, class_colours, draw_points, marker_side, png_bytes,
    span, terrain_figure, topdown_figure,
)
from workflows.report.html import CSS, _escape, _format_value, figure_html

CAPTIONS = {
    "topdown": "The predicted class of a sample of the points seen from above: in each cell "
               "the highest of them, as a map is read.",
    "profile": "A side view through the middle of each scene: height above the terrain model "
               "of a sample of the points in a band across it, by predicted class.",
    "uncertain": "Where the model hesitates: the sampled points whose predicted class has a "
                 "probability below {low} (red) among all sampled points (grey).",
    "histograms": "Confidence (probability of the predicted class) and entropy of the class "
                  "probabilities of every classified point.",
    "terrain": "Left: the hillshade of each scene's terrain model, every block of points far "
               "from the others at its place and outlined. Right: the height above it of the "
               "sampled points predicted as a canopy class (output.canopy_classes).",
}
TITLES = {"topdown": "Class map", "profile": "Side view", "uncertain": "Low confidence",
          "histograms": "Confidence and entropy", "terrain": "Terrain model and canopy height"}


def profile_figure(survey: dict) -> Figure:
    names = survey["classes"]
    scenes = survey["scenes"]
    with matplotlib.rc_context(STYLE):
        fig = Figure(figsize=(10.0, 2.8 * len(scenes) + 0.6), dpi=DPI)
        for row, (scene, data) in enumerate(scenes.items()):
            ax = fig.add_subplot(len(scenes), 1, row + 1)
            along, height, label = data["profile"]
            order = np.random.default_rng(0).permutation(len(label))
            draw_points(ax, along[order], height[order], class_colours(label[order], len(names)),
                        (marker_side(1.5, span(along) / 9.0), marker_side(1.5, span(height) / 2.2)),
                        aspect="auto")
            ax.ticklabel_format(useOffset=False, style="plain")
            ax.set_xlabel(f"{data['profile_axis']} (map units)")
            ax.set_ylabel("m above ground")
            ax.set_title(f"{_mpl_text(scene)}: side view ({len(label):,} points)")
        handles = [Patch(color=class_colour(i)) for i in range(len(names))]
        fig.legend(handles, [_mpl_text(n) for n in names], loc="upper right", ncols=len(names))
        fig.tight_layout(rect=(0, 0, 1, 0.95))
    return fig


def uncertain_figure(survey: dict) -> Figure:
    scenes = survey["scenes"]
    low = survey["low_confidence"]
    with matplotlib.rc_context(STYLE):
        fig = Figure(figsize=(7.0, 6.0 * len(scenes)), dpi=DPI)
        for row, (scene, data) in enumerate(scenes.items()):
            ax = fig.add_subplot(len(scenes), 1, row + 1)
            x, y, _, _, confidence = data["map"]
            uncertain = confidence < low
            per_inch = max(span(x), span(y) * 7.0 / 6.0) / 6.5
            for chosen, colour, size in ((~uncertain, "#D0D4D8", 0.6),
                                         (uncertain, "#CF222E", 1.2)):  # uncertain on top
                draw_points(ax, x[chosen], y[chosen],
                            np.tile(matplotlib.colors.to_rgba(colour), (chosen.sum(), 1)),
                            marker_side(size, per_inch))
            ax.set_aspect("equal")
            ax.ticklabel_format(useOffset=False, style="plain")
            share = uncertain.mean() if len(x) else 0.0
            ax.set_title(f"{_mpl_text(scene)}: {share:.1%} of the sampled points below "
                         f"confidence {low:g}")
        fig.tight_layout()
    return fig


def histograms_figure(survey: dict) -> Figure:
    n_classes = len(survey["classes"])
    with matplotlib.rc_context(STYLE):
        fig = Figure(figsize=(9.0, 3.0), dpi=DPI)
        for i, (key, top, label) in enumerate((
                ("confidence", 1.0, "confidence"),
                ("entropy", max(np.log(n_classes), 1e-9), "entropy (nats)"))):
            ax = fig.add_subplot(1, 2, i + 1)
            counts = np.asarray(survey[key], dtype=np.float64)
            edges = np.linspace(0.0, top, len(counts) + 1)
            ax.bar(edges[:-1], counts / max(counts.sum(), 1), width=np.diff(edges),
                   align="edge", color="#0072B2", edgecolor="white", linewidth=0.5)
            ax.set_xlabel(label)
            ax.set_ylabel("share of the points")
        fig.tight_layout()
    return fig


def survey_images(survey: dict, terrain: dict | None) -> dict:
    """name -> PNG bytes of the survey's figures."""
    names = survey["classes"]
    maps = [d["map"] for d in survey["scenes"].values()]
    figures = {
        "topdown": topdown_figure({"x": np.concatenate([m[0] for m in maps]),
                                   "y": np.concatenate([m[1] for m in maps]),
                                   "label": np.concatenate([m[2] for m in maps]),
                                   "height": np.concatenate([m[3] for m in maps]),
                                   "class_names": names}),
        "profile": profile_figure(survey),
        "uncertain": uncertain_figure(survey),
        "histograms": histograms_figure(survey),
    }
    if terrain:
        figures["terrain"] = terrain_figure(terrain)
    return {name: png_bytes(fig) for name, fig in figures.items()}


def survey_html(survey: dict, images: dict) -> str:
    """The survey's sections: the class table, the per-tile table and the figures."""
    e = _escape
    names, codes = survey["classes"], survey["codes"]
    counts = np.sum([t["counts"] for t in survey["tiles"]], axis=0)
    area = np.sum([d["area_cells"] for d in survey["scenes"].values()], axis=0)
    total, cells = max(int(counts.sum()), 1), max(int(area.sum()), 1)
    parts = ["<h2>Predicted classes</h2>",
             "<table><tr><th>class</th><th>code</th><th>points</th><th>share of the points</th>"
             "<th>share of the area</th></tr>"]
    for i, name in enumerate(names):
        swatch = f'<span class="swatch" style="background:{class_colour(i)}"></span>'
        parts.append(f"<tr><td>{swatch}{e(name)}</td><td>{codes[i]}</td>"
                     f"<td>{int(counts[i]):,}</td><td>{counts[i] / total:.1%}</td>"
                     f"<td>{area[i] / cells:.1%}</td></tr>")
    parts.append(f'<tr class="total"><td>all</td><td></td><td>{int(counts.sum()):,}</td>'
                 "<td>100%</td><td>100%</td></tr></table>")
    parts.append(f'<p class="note">The share of the area is that of the {survey["cell"]:g} m '
                 "cells whose highest point is of the class (the class seen from above), over "
                 f"{int(area.sum()):,} cells with points.</p>")
    parts.append("<h2>Per tile</h2><table><tr><th>tile</th><th>scene</th><th>points</th>"
                 + "".join(f"<th>{e(n)}</th>" for n in names) + "</tr>")
    for tile in survey["tiles"]:
        n = int(np.sum(tile["counts"]))
        shares = "".join(f"<td>{c / max(n, 1):.1%}</td>" for c in tile["counts"])
        parts.append(f"<tr><td>{e(tile['name'])}</td><td>{e(tile['scene'])}</td>"
                     f"<td>{n:,}</td>{shares}</tr>")
    parts.append("</table>")
    for name, png in images.items():
        caption = CAPTIONS[name].format(low=survey["low_confidence"])
        parts.append(figure_html(png, TITLES[name], caption, TITLES[name]))
    return "\n".join(parts)


def render_survey_page(survey: dict, images: dict, title: str, run_info: dict | None,
                       config_text: str | None, sections=()) -> str:
    """The whole page of an unlabelled run."""
    e = _escape
    n_points = sum(int(np.sum(t["counts"])) for t in survey["tiles"])
    subtitle = (f"Classified without labels · {len(survey['classes'])} classes · "
                f"{len(survey['tiles'])} tiles · {n_points:,} classified points · no scores: "
                "give labelled tiles (data.test or data.split) to measure the model")
    parts = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
             '<meta name="viewport" content="width=device-width, initial-scale=1">',
             f"<title>{e(title)}</title><style>{CSS}</style></head><body><main>",
             f"<h1>{e(title)}</h1>", f'<p class="sub">{e(subtitle)}</p>']
    if run_info:
        parts.append('<table class="info">')
        parts += [f"<tr><td>{e(k)}</td><td>{e(_format_value(v))}</td></tr>"
                  for k, v in run_info.items()]
        parts.append("</table>")
    parts.append(survey_html(survey, images))
    parts += list(sections)  # more of the run's results (its trees), as HTML
    if config_text:
        parts.append("<h2>Configuration</h2><details><summary>The resolved configuration"
                     f"</summary><pre>{e(config_text)}</pre></details>")
    parts.append("</main></body></html>")
    return "\n".join(parts)


def write_survey_report(out_dir, survey: dict, images: dict, *, title: str = "Silva report",
                        run_info: dict | None = None, config_text: str | None = None,
                        sections: tuple = ()) -> Path:
    """Write ``out_dir/report.html`` of an unlabelled run and its figures ``images``
    (:func:`survey_images`) as ``out_dir/plots/*.png`` (atomically, as
    :func:`workflows.report.write_report`)."""
    out_dir = Path(out_dir)
    plot_dir = out_dir / "plots"
    plot_dir.mkdir(parents=True, exist_ok=True)
    written = {**images, **{name: png for _, pngs in sections for name, png in pngs.items()}}
    for old in plot_dir.glob("*.png"):
        if old.stem not in written:
            old.unlink(missing_ok=True)  # the plots of an earlier, labelled report
    for name, png in written.items():
        atomic_write_bytes(plot_dir / f"{name}.png", png)
    target = out_dir / "report.html"
    with atomic_path(target) as tmp:
        tmp.write_text(render_survey_page(survey, images, title, run_info, config_text,
                                          [html for html, _ in sections]),
                       encoding="utf-8")
    return target
