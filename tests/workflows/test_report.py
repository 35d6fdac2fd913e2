"""The HTML report: content, embedded plots, PNG files, escaping, missing plot data."""

import base64
import io
import re
from html.parser import HTMLParser

import matplotlib.colors
import matplotlib.image
import numpy as np
import pytest
from PIL import Image

from pipeline.errors import InputError
from pipeline.metrics import classification_scores
from workflows.report import (
    CLASS_COLOURS,
    PLOT_NAMES,
    class_colour,
    f1_per_stage_figure,
    format_score,
    importance_figure,
    topdown_figure,
    write_report,
)
from workflows.report.figures import draw_points

NAMES = ["terrain", "tree", "dead_wood", "misc"]
IMG = re.compile(r'<img src="data:image/png;base64,([A-Za-z0-9+/=]+)"')


def fake_run(names=NAMES, exclude=("misc",), n=3000, n_stages=3, seed=0):
    """Metrics of a cascade that improves stage by stage, and the report's plot data."""
    rng = np.random.default_rng(seed)
    truth = rng.integers(0, len(names), n)
    x, y = rng.uniform(0, 40, n), rng.uniform(0, 20, n)
    stages = []
    for stage in range(n_stages):
        logits = rng.normal(size=(n, len(names)))
        logits[np.arange(n), truth] += 0.5 + stage
        proba = np.exp(logits) / np.exp(logits).sum(axis=1, keepdims=True)
        pred = proba.argmax(axis=1)
        stages.append(classification_scores(truth, pred, names, exclude=exclude))
    metrics = {**stages[-1], "stages": stages}
    pr_data = {"y_true": truth, "proba": proba, "class_names": names, "exclude": list(exclude)}
    topdown = {"x": x, "y": y, "label": pred, "class_names": names}
    return metrics, pr_data, topdown


def fake_terrain(seed=0):
    """One scene's terrain model (a tilted, wavy surface) and canopy samples above it."""
    from pipeline.grid import Raster

    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:20, 0:40]
    dtm = Raster(100 + 0.1 * cols + np.sin(rows / 3.0), 0.0, 0.0, 1.0)
    x, y = rng.uniform(0, 40, 500), rng.uniform(0, 20, 500)
    return {"plot": {"dtm": dtm, "x": x, "y": y, "height": rng.uniform(2, 25, 500)}}


FEATURES = ["I2_22", "I2_222", "I3_33", "I3_11", "I23_3_2", "I23_31_2", "I23_1_2", "I3_3333",
            "I3_3131", "I3_3331", "I3_3111"]


def fake_importances(names=NAMES, n_stages=3, seed=0):
    """One {column: importance} dict per stage, as model.json records them (sum 1); the
    first stage's context columns are constant, so their importance is 0."""
    rng = np.random.default_rng(seed)
    columns = FEATURES + [f"context_{r}_{n}" for r in ("r1", "r2") for n in names]
    stages = []
    for stage in range(n_stages):
        values = rng.uniform(0.0, 1.0, len(columns))
        if stage == 0:
            values[len(FEATURES):] = 0.0
        values /= values.sum()
        stages.append({c: round(float(v), 6) for c, v in zip(columns, values)})
    return stages


class TagBalance(HTMLParser):
    """Checks that every non-void element is closed in order."""

    VOID = {"meta", "img", "br", "hr", "link", "input"}

    def __init__(self):
        super().__init__()
        self.stack, self.errors = [], []

    def handle_starttag(self, tag, attrs):
        if tag not in self.VOID:
            self.stack.append(tag)

    def handle_endtag(self, tag):
        if not self.stack or self.stack.pop() != tag:
            self.errors.append(tag)


@pytest.fixture(scope="module")
def full_report(tmp_path_factory):
    out = tmp_path_factory.mktemp("report")
    metrics, pr_data, topdown = fake_run()
    path = write_report(
        out, metrics, pr_data=pr_data, topdown=topdown, title="Forest plot 7",
        run_info={"command": "silva run forest.yaml", "input points": 1234567},
        config_text="features:\n  r1: 0.5\n", importances=fake_importances(),
        no_features={"points": 1234, "total": 1234567}, terrain=fake_terrain(),
    )
    return out, path, metrics


def test_report_and_png_files_are_written(full_report):
    out, path, _ = full_report
    assert path == out / "report.html"
    for name in PLOT_NAMES:
        png = out / "plots" / f"{name}.png"
        with Image.open(png) as image:
            image.verify()
        pixels = matplotlib.image.imread(png)
        assert pixels.ndim == 3 and pixels.shape[0] > 300 and pixels.shape[1] > 300
        assert pixels[..., :3].std() > 0.05  # a picture, not a blank canvas
    assert not list(out.rglob(".*"))  # no temporary file is left beside the outputs


def test_html_embeds_every_plot_as_its_png(full_report):
    out, path, _ = full_report
    page = path.read_text(encoding="utf-8")
    embedded = [base64.b64decode(data) for data in IMG.findall(page)]
    assert len(embedded) == len(PLOT_NAMES)
    assert embedded == [(out / "plots" / f"{n}.png").read_bytes() for n in PLOT_NAMES]
    for png in embedded:
        Image.open(io.BytesIO(png)).verify()
    parser = TagBalance()
    parser.feed(page)
    assert parser.errors == [] and parser.stack == []


def test_html_shows_the_numbers(full_report):
    _, path, metrics = full_report
    page = path.read_text(encoding="utf-8")
    assert "<title>Forest plot 7</title>" in page
    for name in NAMES:
        assert name in page
    macro_f1 = format_score(metrics["macro"]["f1"])
    assert re.search(rf"Macro average</td>(<td>[0-9.]+</td>){{2}}<td>{macro_f1}</td>", page)
    assert f"<td>{metrics['n_test_points']:,}</td>" in page
    assert "1,234,567" in page and "silva run forest.yaml" in page
    assert "<pre>features:\n  r1: 0.5\n</pre>" in page
    # Per-class row: precision, recall, F1, IoU in that order, then the support.
    tree = metrics["per_class"]["tree"]
    cells = "".join(f"<td>{format_score(tree[k])}</td>" for k in ("precision", "recall", "f1",
                                                                    "iou"))
    assert f"tree</td>{cells}<td>{tree['support']:,}</td>" in page


def stage_rows(page: str) -> list[tuple[str, str, str, str]]:
    """(stage number, macro F1, class of the change cell, change) of each stage table row."""
    table = page[page.index('<table class="stages">'):]
    table = table[: table.index("</table>")]
    return re.findall(r'<tr[^>]*><td>(\d+)</td><td><b>([0-9.]+)</b></td>'
                      r'<td(?: class="(\w*)")?>([^<]+)</td>', table)


def test_stage_table_gives_each_stage_and_its_change(full_report):
    _, path, metrics = full_report
    rows = stage_rows(path.read_text(encoding="utf-8"))
    f1 = [s["macro"]["f1"] for s in metrics["stages"]]
    assert [r[0] for r in rows] == ["1", "2", "3"]
    assert [r[1] for r in rows] == [format_score(v) for v in f1]
    assert rows[0][3] == "–"
    assert rows[1][3] == f"{f1[1] - f1[0]:+.3f}" and rows[2][3] == f"{f1[2] - f1[1]:+.3f}"


def test_stage_changes_are_marked_up_or_down(tmp_path):
    metrics, _, _ = fake_run(n=1000)
    first, second, third = metrics["stages"]
    # macro F1 rises from the first stage to the third, then falls back to the second's
    stages = [first, third, second]
    f1 = [s["macro"]["f1"] for s in stages]
    page = write_report(tmp_path, {**second, "stages": stages}).read_text(encoding="utf-8")
    assert [(r[2], r[3]) for r in stage_rows(page)] == [
        ("", "–"), ("up", f"{f1[1] - f1[0]:+.3f}"), ("down", f"{f1[2] - f1[1]:+.3f}")]


def test_report_without_plot_data_notes_the_missing_plots(tmp_path):
    metrics, pr_data, topdown = fake_run(n=500)
    write_report(tmp_path, metrics, pr_data=pr_data, topdown=topdown)
    assert (tmp_path / "plots" / "topdown.png").exists()
    page = write_report(tmp_path, metrics).read_text(encoding="utf-8")
    assert len(IMG.findall(page)) == 2
    assert "No precision-recall data" in page and "No point positions" in page
    assert "No feature importances were recorded" in page
    assert 'id="no-features"' not in page  # not counted: not claimed either
    # Stale pictures of an earlier report are removed so plots/ matches the report.
    assert sorted(p.name for p in (tmp_path / "plots").iterdir()) == [
        "confusion.png", "f1_per_stage.png"]
    assert "No configuration was recorded" in page


def test_metrics_without_stages_show_one_stage(tmp_path):
    metrics, _, _ = fake_run(n=300, n_stages=1)
    del metrics["stages"]
    page = write_report(tmp_path, metrics).read_text(encoding="utf-8")
    assert re.search(r"<tr class=\"final\"><td>1</td>", page)


def test_text_is_escaped(tmp_path):
    names = ["<script>alert(1)</script>", "a&b", "cost $5", "_hidden"]
    metrics, pr_data, topdown = fake_run(names=names, exclude=("a&b",), n=400)
    page = write_report(
        tmp_path, metrics, pr_data=pr_data, topdown=topdown, title="<b>t</b>",
        run_info={"<i>key</i>": "<script>x</script>"},
        config_text="note: </pre><script>evil()</script>",
        importances=fake_importances(names=names), terrain=fake_terrain(),
    ).read_text(encoding="utf-8")
    assert "<script" not in page
    assert "&lt;script&gt;alert(1)&lt;/script&gt;" in page
    assert "&lt;/pre&gt;&lt;script&gt;evil()&lt;/script&gt;" in page
    assert "<b>t</b>" not in page and "&lt;b&gt;t&lt;/b&gt;" in page
    assert "a&amp;b" in page and "a&b" not in page
    assert len(IMG.findall(page)) == len(PLOT_NAMES)


def test_bad_metrics_are_refused(tmp_path):
    metrics, _, _ = fake_run(n=100)
    del metrics["stages"][1]["confusion"]
    with pytest.raises(InputError, match=r"stages'\]\[1\] lacks \['confusion'\]"):
        write_report(tmp_path, metrics)
    assert not (tmp_path / "report.html").exists()


def test_class_colours_are_stable_and_used_on_the_map():
    assert [class_colour(i) for i in range(len(CLASS_COLOURS))] == list(CLASS_COLOURS)
    assert class_colour(len(CLASS_COLOURS) + 2) == class_colour(2)
    assert len(set(CLASS_COLOURS)) == len(CLASS_COLOURS)
    # Every point predicted as class 2: the map shows class 2's colour and no other class's.
    rng = np.random.default_rng(1)
    figure = topdown_figure({"x": rng.uniform(0, 10, 2000), "y": rng.uniform(0, 10, 2000),
                             "label": np.full(2000, 2), "class_names": ["a", "b", "c"]})
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=60)
    pixels = np.asarray(Image.open(buffer).convert("RGB")).reshape(-1, 3).astype(int)

    def share_of(colour):
        rgb = np.array([int(colour[k:k + 2], 16) for k in (1, 3, 5)])
        return (np.abs(pixels - rgb).max(axis=1) <= 3).mean()

    assert share_of(class_colour(2)) > 0.08
    assert share_of(class_colour(2)) > 20 * max(share_of(class_colour(0)),
                                                share_of(class_colour(1)))


def test_points_drawn_as_an_image_show_the_last_point_of_each_cell():
    from matplotlib.figure import Figure

    ax = Figure().add_subplot()
    red, blue = matplotlib.colors.to_rgba("red"), matplotlib.colors.to_rgba("blue")
    # two points share the cell at the origin (blue drawn last); one is alone at (2, 1)
    draw_points(ax, [0.0, 0.1, 2.0], [0.0, 0.2, 1.0], [red, blue, red], 0.5)
    image = ax.get_images()[0]
    pixels = np.asarray(image.get_array())
    assert pixels.shape == (3, 5, 4)  # cells of 0.5 from (-0.25, -0.25) to (2.25, 1.25)
    np.testing.assert_allclose(pixels[0, 0], blue)
    np.testing.assert_allclose(pixels[2, 4], red)
    assert np.count_nonzero(pixels[..., 3]) == 2  # transparent where no point is
    np.testing.assert_allclose(image.get_extent(), (-0.25, 2.25, -0.25, 1.25))
    x0, x1 = ax.get_xlim()
    assert x0 < -0.25 and x1 > 2.25  # a scatter's margins around the points


def test_topdown_rejects_labels_outside_the_classes():
    with pytest.raises(InputError, match="outside"):
        topdown_figure({"x": np.zeros(2), "y": np.zeros(2), "label": np.array([0, 3]),
                        "class_names": ["a", "b"]})


def test_f1_legend_names_every_evaluated_class():
    names = ["_ground", "tree", "misc"]
    metrics, _, _ = fake_run(names=names, exclude=("misc",), n=300, n_stages=2)
    figure = f1_per_stage_figure(metrics["stages"])
    legend = figure.axes[0].get_legend()
    assert [t.get_text() for t in legend.get_texts()] == ["_ground", "tree", "macro F1"]
    plotted = [list(line.get_ydata()) for line in figure.axes[0].get_lines()]
    assert [s["macro"]["f1"] for s in metrics["stages"]] in plotted
    assert [s["per_class"]["_ground"]["f1"] for s in metrics["stages"]] in plotted


# -- feature importances and points without features ----------------------------------------
def importance_rows(page: str) -> list[list[tuple[str, str]]]:
    """The (column, importance) cells of each rank row of the top-features table."""
    table = page[page.index('<table class="importances">'):]
    table = table[: table.index("</table>")]
    rows = re.findall(r"<tr><td>\d+</td>(.*?)</tr>", table)
    return [re.findall(r"<td>([^<]*)</td><td>([^<]*)</td>", row) for row in rows]


def test_importance_table_ranks_each_stages_top_columns(full_report):
    _, path, _ = full_report
    page = path.read_text(encoding="utf-8")
    stages = fake_importances()
    rows = importance_rows(page)
    assert len(rows) == 10
    for number, stage in enumerate(stages):
        shown = [row[number] for row in rows]
        expected = sorted(stage.items(), key=lambda kv: -kv[1])[:10]
        assert shown == [(name, format_score(value)) for name, value in expected]
    # the first stage's context columns are constant: none of them ranks there
    assert not any(row[0][0].startswith("context_") for row in rows)
    # every column of every stage is in the full table
    details = page[page.index("Every feature column"):]
    for column, value in stages[1].items():
        assert f"<tr><td>{column}</td><td>{format_score(stages[0][column])}</td>" \
               f"<td>{format_score(value)}</td>" in details


def test_importance_figure_has_a_panel_per_stage_with_the_top_columns():
    stages = fake_importances(n_stages=2)
    figure = importance_figure([stages[0], None, stages[1]], NAMES, top=5)
    assert [ax.get_title() for ax in figure.axes] == ["stage 1", "stage 3"]
    for ax, stage in zip(figure.axes, stages):
        top = [k for k, _ in sorted(stage.items(), key=lambda kv: -kv[1])[:5]]
        assert [t.get_text() for t in ax.get_yticklabels()] == top
        widths = [bar.get_width() for bar in ax.patches]
        assert widths == sorted(widths, reverse=True) and widths[0] == max(stage.values())
        for name, bar in zip(top, ax.patches):  # a context column has its class's colour
            if name.startswith("context_"):
                cls = NAMES.index(name.split("_", 2)[2])
                assert matplotlib.colors.to_hex(bar.get_facecolor()) == \
                    class_colour(cls).lower()
    with pytest.raises(InputError, match="no stage with feature importances"):
        importance_figure([None, {}], NAMES)


def test_points_without_features_are_counted_in_the_report(full_report, tmp_path):
    _, path, _ = full_report
    page = path.read_text(encoding="utf-8")
    assert re.search(r'Points without features</div><div class="value">1,234</div>', page)
    assert "1,234 of the 1,234,567 points written (0.10%) have a feature column undefined" in page
    assert "NoFeatures = 1" in page
    assert "scored test points" not in page  # the metrics do not count them
    metrics, _, _ = fake_run(n=200)
    page = write_report(tmp_path, {**metrics, "points_without_features": 3},
                        no_features={"points": 7, "total": 500}).read_text(encoding="utf-8")
    assert f"Of the {metrics['n_test_points']:,} scored test points, 3 (" in page
    page = write_report(tmp_path, metrics, no_features={"points": 0, "total": 500}
                        ).read_text(encoding="utf-8")
    assert "Every one of the 500 points written has its features." in page
    for bad in ({"points": 3}, {"points": 9, "total": 5}, {"points": -1, "total": 5}):
        with pytest.raises(InputError, match="no_features"):
            write_report(tmp_path, metrics, no_features=bad)
