"""The report page: its CSS, section titles and captions, and the HTML of every table."""

import base64
import html

import numpy as np

from workflows.report.figures import class_colour, format_score, top_importances

PLOT_NAMES = ("confusion", "precision_recall", "f1_per_stage", "importances", "topdown",
              "terrain")
TOP_FEATURES = 10  # feature columns shown per stage
SCORES = ("precision", "recall", "f1", "iou")
SCORE_LABELS = {"precision": "Precision", "recall": "Recall", "f1": "F1", "iou": "IoU"}

CSS = """
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

CAPTIONS = {
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
    "importances": (
        "The feature columns each stage's forest relied on most: impurity importance (mean "
        "decrease of the Gini impurity, over all trees; a stage's columns sum to 1). Context "
        "columns take their class's colour, the point's own features are grey."
    ),
    "topdown": "Final predicted class of a sample of the points seen from above: in each "
               "cell the highest of them, as a map is read.",
    "terrain": (
        "Left: the hillshade of each scene's terrain model (SMRF ground filter on the lowest "
        "point of each cell), every block of points far from the others at its place and "
        "outlined. Right: the height above it of the sampled points predicted as a canopy "
        "class (output.canopy_classes)."
    ),
}
TITLES = {
    "confusion": "Confusion matrix",
    "precision_recall": "Precision-recall curves",
    "f1_per_stage": "F1 per stage",
    "importances": "Feature importances",
    "topdown": "Map of predicted classes",
    "terrain": "Terrain model and canopy height",
}


def figure_html(png: bytes, alt: str, caption: str, title: str | None = None) -> str:
    """A figure of the page: the PNG embedded, its caption, and a heading when ``title``."""
    data = base64.b64encode(png).decode("ascii")
    heading = f"<h3>{_escape(title)}</h3>" if title else ""
    return (f'<figure>{heading}<img src="data:image/png;base64,{data}" alt="{_escape(alt)}">'
            f"<figcaption>{_escape(caption)}</figcaption></figure>")


def render_page(metrics, stages, images, title, run_info, config_text, *, importances=None,
                no_features=None, sections=()) -> str:
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
        f"<title>{e(title)}</title><style>{CSS}</style></head><body><main>",
        f"<h1>{e(title)}</h1>",
        f'<p class="sub">{e(subtitle)}</p>',
    ]
    if run_info:
        parts.append('<table class="info">')
        parts += [f"<tr><td>{e(k)}</td><td>{e(_format_value(v))}</td></tr>"
                  for k, v in run_info.items()]
        parts.append("</table>")

    parts.append("<h2>Summary</h2>")
    parts.append(_cards(metrics, no_features))
    excluded_text = (f"; excluded as background: {', '.join(excluded)}" if excluded else "")
    note = (f"Macro scores are unweighted means over the {n_eval} evaluated classes"
            f"{excluded_text}. Overall accuracy and the point count cover the test points of "
            "evaluated classes.")
    parts.append(f'<p class="note">{e(note)}</p>')
    if no_features is not None:
        note = _no_features_note(no_features, metrics.get("points_without_features"),
                                 metrics["n_test_points"])
        parts.append(f'<p class="note" id="no-features">{e(note)}</p>')

    parts.append("<h2>Per class (final stage)</h2>")
    parts.append(_class_table(metrics))

    parts.append("<h2>Cascade stages</h2>")
    parts.append(_stage_table(stages))

    parts.append("<h2>Feature importances</h2>")
    parts.append(_importance_tables(importances))

    parts.append("<h2>Plots</h2>")
    for name in PLOT_NAMES:
        png, note = images[name]
        if png is None:
            parts.append(f"<figure><h3>{e(TITLES[name])}</h3>"
                         f'<p class="missing">{e(note)}</p></figure>')
            continue
        parts.append(figure_html(png, TITLES[name], CAPTIONS[name], TITLES[name]))

    parts.append("<h2>Confusion counts</h2>")
    parts.append("<details><summary>Exact point counts (rows: true class, columns: "
                 "predicted class)</summary>")
    parts.append(_confusion_table(metrics))
    parts.append("</details>")
    parts += list(sections)  # more of the run's results (its trees), as HTML

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


def _no_features_note(no_features, scored=None, n_test=0) -> str:
    """The points written without features; ``scored``: how many of the ``n_test`` scored
    test points are among them (metrics.json's points_without_features), when known."""
    points, total = no_features["points"], no_features["total"]
    if points == 0:
        return f"Every one of the {total:,} points written has its features."
    note = (f"{points:,} of the {total:,} points written ({points / max(total, 1):.2%}) have "
            "a feature column undefined (no surface within features.r1, fewer than 3 "
            "neighbours in one of the covariance spheres, or collinear ones): the forests "
            "classify them with those columns missing, as they learned such points in "
            "training; a point without a surface is the least reliable. They are marked "
            "NoFeatures = 1 in the output files.")
    if scored is not None:
        note += (f" Of the {n_test:,} scored test points, {int(scored):,} "
                 f"({int(scored) / max(n_test, 1):.2%}) are among them.")
    return note


def _importance_tables(importances) -> str:
    """The top columns of every stage side by side, and every column in a details block."""
    e = _escape
    stages = [(i + 1, s) for i, s in enumerate(importances or ()) if s]
    if not stages:
        return ('<p class="missing">No feature importances were recorded with the model '
                "(a model saved by an older Silva), so they are omitted.</p>")
    tops = {number: top_importances(s, TOP_FEATURES) for number, s in stages}
    head = "".join(f"<th>Stage {n}</th><th></th>" for n, _ in stages)
    rows = [f'<table class="importances"><tr><th>Rank</th>{head}</tr>']
    for rank in range(max(len(t) for t in tops.values())):
        cells = ""
        for number, _ in stages:
            pairs = tops[number]
            if rank < len(pairs):
                name, value = pairs[rank]
                cells += f"<td>{e(name)}</td><td>{format_score(value)}</td>"
            else:
                cells += "<td></td><td></td>"
        rows.append(f"<tr><td>{rank + 1}</td>{cells}</tr>")
    rows.append("</table>")
    columns = list(dict.fromkeys(k for _, s in stages for k in s))
    rows.append("<details><summary>Every feature column</summary><table><tr><th>Column</th>"
                + "".join(f"<th>Stage {n}</th>" for n, _ in stages) + "</tr>")
    for column in columns:
        cells = "".join(f"<td>{format_score(s[column])}</td>" if column in s else "<td>–</td>"
                        for _, s in stages)
        rows.append(f"<tr><td>{e(column)}</td>{cells}</tr>")
    rows.append("</table></details>")
    rows.append(
        '<p class="note">Impurity importance of each column in the forest of each stage '
        f"(the top {TOP_FEATURES}; a stage's columns sum to 1). context_r1_&lt;class&gt; and "
        "context_r2_&lt;class&gt; are the shares of the points around each point (within r1 "
        "and r2) that the previous stage gave that class; the first stage sees only 1/C "
        "there, so its context columns carry nothing.</p>")
    return "\n".join(rows)


def _cards(metrics, no_features=None) -> str:
    macro = metrics["macro"]
    cards = [("Macro F1", format_score(macro["f1"]), True)]
    cards += [(f"Macro {SCORE_LABELS[k].lower() if k != 'iou' else 'IoU'}",
               format_score(macro[k]), False) for k in ("precision", "recall", "iou")]
    cards += [("Overall accuracy", format_score(metrics["overall_accuracy"]), False),
              ("Test points", f"{metrics['n_test_points']:,}", False)]
    if no_features is not None:
        cards.append(("Points without features", f"{no_features['points']:,}", False))
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


def _escape(value) -> str:
    return html.escape(str(value), quote=True)


def _format_value(value) -> str:
    if isinstance(value, bool):
        return str(value)
    if isinstance(value, (int, np.integer)):
        return f"{int(value):,}"
    if isinstance(value, (list, tuple)):
        return ", ".join(str(v) for v in value)
    return str(value)
