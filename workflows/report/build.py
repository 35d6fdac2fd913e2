"""Writing a run's report: ``report.html`` and the same plots as PNG files in ``plots/``."""

from pathlib import Path

from pipeline.atomic import atomic_path, atomic_write_bytes
from pipeline.errors import InputError
from workflows.report.figures import (
    confusion_figure,
    f1_per_stage_figure,
    importance_figure,
    png_bytes,
    precision_recall_figure,
    terrain_figure,
    topdown_figure,
)
from workflows.report.html import TOP_FEATURES, render_page

REQUIRED_KEYS = ("classes", "per_class", "macro", "overall_accuracy", "confusion",
                 "n_test_points")


def write_report(
    out_dir,
    metrics: dict,
    *,
    pr_data: dict | None = None,
    topdown: dict | None = None,
    title: str = "Silva report",
    run_info: dict | None = None,
    config_text: str | None = None,
    importances: list | None = None,
    no_features: dict | None = None,
    terrain: dict | None = None,
    sections: tuple = (),
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
        "class_names": [C]}`` and optionally ``"height": float (m,)`` (above the ground:
        each cell of the map then shows its highest point), predicted classes of (a sample
        of) the points in map coordinates, for the top-down map.
    title : str
    run_info : dict, optional
        Shown as a two-column table (command, date, software version, durations, ...).
    config_text : str, optional
        The resolved configuration, shown verbatim.
    importances : list, optional
        One ``{feature column: importance}`` dict per cascade stage (model.json's
        ``stages[i]["importances"]``; None for a stage without one): a table and a bar
        figure of each stage's top columns. Without it the report says they are missing.
    no_features : dict, optional
        ``{"points": int, "total": int}``: the points whose features could not be computed
        (marked ``NoFeatures`` = 1 in the output) among all the points written.
    terrain : dict, optional
        ``{scene: {"dtm": Raster or Rasters, "x", "y", "height"}}`` for the terrain
        figure (see :func:`workflows.report.figures.terrain_figure`).
    sections : tuple, optional
        More sections of the page, each ``(html, {name: png bytes})``: the HTML is placed
        before the configuration, the PNGs are written to ``plots/`` too.

    Returns
    -------
    Path of report.html. It is written atomically: a partial report never exists under that
    name. PNGs of plots that could not be drawn are removed from ``plots/``, so the folder
    always matches the report.
    """
    metrics = _check_metrics(metrics)
    no_features = _check_no_features(no_features)
    stages = metrics.get("stages") or [metrics]
    out_dir = Path(out_dir)
    plot_dir = out_dir / "plots"
    plot_dir.mkdir(parents=True, exist_ok=True)

    images = _write_figures(plot_dir, metrics, stages, pr_data, importances, topdown,
                            terrain)
    for _, pngs in sections:
        for name, png in pngs.items():
            atomic_write_bytes(plot_dir / f"{name}.png", png)

    page = render_page(metrics, stages, images, title, run_info, config_text,
                       importances=importances, no_features=no_features,
                       sections=[html for html, _ in sections])
    target = out_dir / "report.html"
    with atomic_path(target) as tmp:
        tmp.write_text(page, encoding="utf-8")
    return target


def _write_figures(plot_dir: Path, metrics, stages, pr_data, importances, topdown,
                   terrain) -> dict:
    """Draw the report's figures into ``plot_dir`` (a figure that cannot be drawn removes
    its PNG); name -> (png bytes or None, the note that replaces a missing figure)."""
    figures = {
        "confusion": (confusion_figure(metrics), None),
        "precision_recall": _optional_figure(
            pr_data, lambda: precision_recall_figure(pr_data, metrics),
            "No precision-recall data was passed to the report, so this plot is omitted.",
        ),
        "f1_per_stage": (f1_per_stage_figure(stages), None),
        "importances": _optional_figure(
            importances if importances and any(importances) else None,
            lambda: importance_figure(importances, metrics["classes"], TOP_FEATURES),
            "No feature importances were recorded with the model, so this plot is omitted.",
        ),
        "topdown": _optional_figure(
            topdown, lambda: topdown_figure(topdown),
            "No point positions were passed to the report, so the map is omitted.",
        ),
        "terrain": _optional_figure(
            terrain or None, lambda: terrain_figure(terrain),
            "No terrain model was passed to the report, so this plot is omitted.",
        ),
    }
    images = {}
    for name, (figure, note) in figures.items():
        path = plot_dir / f"{name}.png"
        if figure is None:
            path.unlink(missing_ok=True)
            images[name] = (None, note)
            continue
        png = png_bytes(figure)
        atomic_write_bytes(path, png)
        images[name] = (png, None)
    return images


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


def _check_no_features(no_features):
    if no_features is None:
        return None
    try:
        points, total = int(no_features["points"]), int(no_features["total"])
    except (KeyError, TypeError, ValueError):
        raise InputError(f"no_features must be {{'points': int, 'total': int}}, got "
                         f"{no_features!r}") from None
    if not 0 <= points <= total:
        raise InputError(f"no_features counts {points} of {total} points: pass 0 <= points "
                         "<= total")
    return {"points": points, "total": total}


def _optional_figure(data, draw, note):
    return (None, note) if data is None else (draw(), None)
