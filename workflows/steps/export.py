"""Export: one classified LAS/LAZ per input tile, every point in its original order.

Each task streams its input tile, finds each point's chunk from its coordinates (the same grid
as ingest) and its row there by global id, and writes the original dimensions plus the
predicted class, one probability per class, a confidence, an entropy, ``NoFeatures`` (1
where the point's features could not be computed: too few neighbours, or collinear ones; its
prediction then rests on what the forests make of missing values) and ``HeightAboveGround``
(metres above the scene's terrain model). Files are written atomically. With
``output.rasters`` the same pass writes the tile's DTM, DSM and canopy height as GeoTIFF
(the highest point of each cell, unless it is a stray point far above everything near it).

When ingest leaves points out (``data.exclude_codes``, ``data.exclude_withheld``,
``data.drop_unlisted``) a dimension ``Excluded`` is added: 1 for those points, which were in
no neighbourhood and were never classified. They keep every input value (their
classification too, even with ``output.write_classification``), and get
PredictedClassification 0, Confidence, Entropy and probabilities 0 and NaN feature columns.
``output.feature_dims`` adds chosen feature columns (float32, NaN where undefined), read from
the features stored per chunk.
"""

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from pipeline.atomic import remove_parts, remove_stale
from pipeline.errors import ConfigError, StoreError
from pipeline.features.sets import feature_set
from pipeline.io import ExtraDim, export_with_extra_dims
from pipeline.io.catalogue import Tile
from pipeline.io.las import extra_dimension_types
from pipeline.grid import MAX_CELLS, Raster, cell_index, tile_grid
from pipeline.io.raster import write_geotiff
from pipeline.store import open_store, rows_of
from pipeline.surface import despike, top_two
from pipeline.terrain import SceneTerrain, ground_elevation
from pipeline.tiling import BalancedLayout, Grid, global_ids
from workflows.config.point_filter import PointFilter
from workflows.config.schema import feature_dim_name
from workflows.exec.engine import Task
from workflows.run.directory import Run, rerun_command
from workflows.run.progress import counted, say
from workflows.steps.trees import REFERENCE_TREE_ID, TileTrees, TreeTask
from workflows.store.layout import chunk_path, proba_array
from workflows.store.marks import is_done, mark_done, read_array
from workflows.store.scenes import RunLayout
from workflows.store.terrain import stored_terrain

PREDICTED = "PredictedClassification"
HEIGHT_ABOVE_GROUND = "HeightAboveGround"
CONFIDENCE = "Confidence"
ENTROPY = "Entropy"
NO_FEATURES = "NoFeatures"
EXCLUDED = "Excluded"
TREE_ID = "PredictedTreeID"
#: Largest classification code of LAS point formats 0-5 (a 5-bit field); 6-10 hold 0..255.
LEGACY_MAX_CLASS = 31


def probability_dim(name: str) -> str:
    return f"Probability_{name}"


def entropy(proba: np.ndarray) -> np.ndarray:
    """float32 Shannon entropy (nats) of each row of probabilities (Myria3D's convention):
    0 for a certain prediction, log C when every class is equally likely."""
    p = np.asarray(proba, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        terms = np.where(p > 0, p * np.log(p), 0.0)
    return (-terms.sum(axis=1)).astype(np.float32)


def extra_dims(classes: list[str], codes: list[int], probabilities: bool,
               excluded: bool = False, features: tuple[str, ...] = (),
               trees: bool = False) -> list[ExtraDim]:
    """The dimensions Silva adds to every exported point: ``Excluded`` when ``excluded``
    (ingest filters points out), ``PredictedTreeID`` with ``trees``, one float32 dimension
    per feature column of ``features``."""
    dtype = "uint8" if max(codes) <= 255 else "uint16"
    dims = [
        ExtraDim(PREDICTED, dtype, "Predicted class code"),
        ExtraDim(CONFIDENCE, "float32", "Probability of predicted class"),
        ExtraDim(ENTROPY, "float32", "Entropy of class probabilities"),
        ExtraDim(NO_FEATURES, "uint8", "1: a feature column undefined"),
        ExtraDim(HEIGHT_ABOVE_GROUND, "float32", "Height above terrain model (m)"),
    ]
    if excluded:
        dims.append(ExtraDim(EXCLUDED, "uint8", "1: left out, not classified"))
    if trees:
        dims.append(ExtraDim(TREE_ID, "uint32", "Tree ID (0: in no tree)"))
    if probabilities:
        dims += [ExtraDim(probability_dim(n), "float32", f"Probability of {n}"[:32])
                 for n in classes]
    dims += [ExtraDim(feature_dim_name(c), "float32", f"Feature {c}"[:32]) for c in features]
    return dims


@dataclass(frozen=True)
class RasterRequest:
    """The rasters export writes per tile: ``names`` of :data:`RASTERS` into ``directory``,
    cells of ``resolution`` metres, the canopy from the points predicted as the classes
    ``canopy`` (indices)."""

    names: tuple[str, ...]
    resolution: float
    canopy: tuple[int, ...]
    directory: str

    def path(self, tile_name: str, name: str) -> Path:
        return Path(self.directory) / f"{tile_name}_{name}.tif"


class _TileRasters:
    """DSM and canopy height of one tile, accumulated batch by batch (the two highest values
    per cell), without the spikes of stray points (:func:`pipeline.surface.despike`)."""

    def __init__(self, tile: Tile, request: RasterRequest, dtm: SceneTerrain):
        self.tile, self.request, self.dtm = tile, request, dtm
        cell = request.resolution
        self.x0, self.y0, nx, ny = tile_grid(tile.mins, tile.maxs, cell)
        self.dsm = (np.full((ny, nx), np.nan), np.full((ny, nx), np.nan))  # top, second
        self.chm = (np.full((ny, nx), np.nan), np.full((ny, nx), np.nan))

    def add(self, xyz, height, kept, canopy) -> None:
        """``kept``: the points classified (not excluded); ``canopy``: those of them
        predicted as a canopy class; ``height`` their heights above ground."""
        flat = cell_index(xyz[kept, :2], self.x0, self.y0, self.request.resolution,
                          self.dsm[0].shape)
        top_two(flat, xyz[kept, 2], *self.dsm)
        top_two(flat[canopy[kept]], height[kept][canopy[kept]], *self.chm)

    def write(self) -> list[str]:
        cell, (ny, nx) = self.request.resolution, self.dsm[0].shape
        centres = np.stack(np.meshgrid(self.x0 + (np.arange(nx) + 0.5) * cell,
                                       self.y0 + (np.arange(ny) + 0.5) * cell), axis=-1)
        dsm = despike(*self.dsm, cell)
        chm = despike(*self.chm, cell, floor=0.0)  # an empty cell: no canopy
        rasters = {
            "dtm": ground_elevation(self.dtm, centres.reshape(-1, 2)).reshape(ny, nx),
            "dsm": dsm,
            # 0 where points but no canopy; heights below the terrain model are 0
            "chm": np.where(np.isnan(dsm), np.nan, np.maximum(np.nan_to_num(chm, nan=0.0), 0.0)),
        }
        written = []
        for name in self.request.names:
            path = self.request.path(self.tile.name, name)
            write_geotiff(path, Raster(rasters[name], self.x0, self.y0, cell),
                          self.tile.crs_wkt)
            written.append(str(path))
        return written


def prefixed(dims: list[ExtraDim], prefix: str) -> list[ExtraDim]:
    """``dims`` with ``prefix`` before each name (output.dim_prefix)."""
    return [replace(d, name=prefix + d.name) for d in dims]


def run_dims(run: Run) -> list[ExtraDim]:
    """Every dimension the export of ``run`` may add, under its written name."""
    dims = extra_dims(run.classes, run.class_codes, run.cfg.output.probabilities,
                      excluded=True, features=tuple(run.cfg.feature_dim_columns),
                      trees=run.cfg.output.trees)
    return prefixed(dims, run.cfg.output.dim_prefix)


def check_output_names(run: Run, tiles: list[Tile]) -> None:
    """Refuse, before any work, an input tile that already has a dimension of a name Silva
    adds with another type (it could not be written); the same type is replaced, as a rerun
    on Silva's own output does."""
    wanted = {d.name: d.numpy_dtype.name for d in run_dims(run)}
    for tile in tiles:
        if tile.format not in ("las", "laz"):
            continue
        for name, dtype in extra_dimension_types(tile.path).items():
            if name in wanted and dtype != wanted[name]:
                raise ConfigError(
                    f"config error: {tile.path} already has a dimension '{name}' of type "
                    f"{dtype}, and Silva writes one of that name as {wanted[name]}; set "
                    f"output.dim_prefix (e.g. --set output.dim_prefix=silva_, which writes "
                    f"silva_{name[len(run.cfg.output.dim_prefix):]}) or remove the dimension "
                    "from the input")


#: Cells a tile's raster may hold: the largest raster shared by the four float64 arrays a
#: tile's rasters hold at once (the two highest values of the DSM's and the canopy's cells),
#: where a resolution written in the wrong unit asks for billions.
MAX_RASTER_CELLS = MAX_CELLS // 4


def check_raster_size(run: Run, tiles: list[Tile]) -> None:
    """Refuse an ``output.raster_resolution`` that gives a tile's raster (of its XY box:
    its header's before any work, that of its points as read once ingested, before the
    features) more than :data:`MAX_RASTER_CELLS` cells."""
    out = run.cfg.output
    if not out.rasters:
        return
    for tile in tiles:
        _, _, nx, ny = tile_grid(np.asarray(tile.mins), np.asarray(tile.maxs),
                                 out.raster_resolution)
        if nx * ny > MAX_RASTER_CELLS:
            raise ConfigError(
                f"config error: output.raster_resolution={out.raster_resolution} gives the "
                f"rasters of {tile.path} {nx} x {ny} cells, more than {MAX_RASTER_CELLS:,}; "
                "set a coarser resolution in map units (e.g. --set output.raster_resolution=1)")


class _ChunkPredictions:
    """Final probabilities (and chosen feature columns) of the chunks a tile touches,
    loaded once each."""

    def __init__(self, root, scene, grid, stage, allow_missing, feature_index=()):
        self.root, self.scene, self.grid, self.stage = root, scene, grid, stage
        self.allow_missing = allow_missing  # points left out at ingest (data.drop_unlisted)
        self.feature_index = list(feature_index)  # columns of 'features' to return
        self.cache = {}

    def _load(self, chunk, n_classes):
        """(sorted global ids, probabilities, undefined features, feature columns) of one
        chunk; empty for a chunk never stored."""
        name = self.grid.chunk_name(chunk)
        try:
            group = self.root[chunk_path(self.scene, name)]
        except KeyError:
            # ingest stores only chunks with points: every point here was left out
            if not self.allow_missing:
                raise StoreError(f"chunk {name} of scene '{self.scene}' is missing from the "
                                 "store; rerun with --overwrite") from None
            return (np.empty(0, np.int64), np.empty((0, n_classes), np.float32),
                    np.empty(0, bool), np.empty((0, len(self.feature_index)), np.float32))
        gid = read_array(group, "gid")
        columns = (read_array(group, "features")[:, self.feature_index] if self.feature_index
                   else np.empty((len(gid), 0), np.float32))  # kept features: see one_pass
        return (gid, read_array(group, proba_array(self.stage)), read_array(group, "undefined"),
                columns)

    def lookup(self, xyz, gid, n_classes):
        """float32 (n, C) probabilities, a bool mask of the points the store holds, one of
        the points whose features are undefined, and float32 (n, F) feature columns (NaN for
        a point the store does not hold)."""
        chunks = self.grid.chunk_of(xyz)
        proba = np.zeros((len(gid), n_classes), dtype=np.float32)
        found = np.ones(len(gid), dtype=bool)
        undefined = np.zeros(len(gid), dtype=bool)
        columns = np.full((len(gid), len(self.feature_index)), np.nan, dtype=np.float32)
        for chunk in np.unique(chunks):
            rows = np.flatnonzero(chunks == chunk)
            if chunk not in self.cache:
                if len(self.cache) >= 8:  # bounded memory on tiles spanning many chunks
                    self.cache.clear()
                self.cache[chunk] = self._load(int(chunk), n_classes)
            ids, chunk_proba, chunk_undefined, chunk_columns = self.cache[chunk]
            pos, hit = rows_of(ids, gid[rows])
            if not hit.all() and not self.allow_missing:
                raise StoreError(f"points of scene '{self.scene}' missing from chunk "
                                 f"{self.grid.chunk_name(int(chunk))}; rerun with --overwrite")
            proba[rows[hit]] = chunk_proba[pos[hit]]
            undefined[rows[hit]] = chunk_undefined[pos[hit]]
            columns[rows[hit]] = chunk_columns[pos[hit]]
            found[rows[~hit]] = False
        return proba, found, undefined, columns


@dataclass(frozen=True)
class ExportSpec:
    """What every exported tile of a run gets, resolved once from the run (:meth:`of`)."""

    stage: int  # the final stage, whose probabilities are written
    classes: tuple[str, ...]
    codes: tuple[int, ...]
    probabilities: bool
    write_classification: bool
    read_batch: int
    points_filter: PointFilter = PointFilter()  # ingest's: the points it left out
    feature_columns: tuple[str, ...] = ()  # written from the stored features' columns
    feature_index: tuple[int, ...] = ()  # ... at these indices
    keep_point_format: bool = False  # the input's LAS version and point format
    rasters: RasterRequest | None = None  # also the tile's rasters
    prefix: str = ""  # starts the name of every dimension Silva adds
    trees: TreeTask | None = None  # PredictedTreeID from the scene's tree model

    @classmethod
    def of(cls, run: Run, final_stage: int, stage_fp: str) -> "ExportSpec":
        out = run.cfg.output
        feature_columns = tuple(run.cfg.feature_dim_columns)
        all_columns = list(feature_set(run.features).columns)
        rasters = (RasterRequest(tuple(out.rasters), out.raster_resolution,
                                 tuple(run.cfg.canopy_classes), str(run.out / "rasters"))
                   if out.rasters else None)
        trees = TreeTask.of(run, final_stage, stage_fp) if out.trees else None
        return cls(final_stage, tuple(run.classes), tuple(run.class_codes), out.probabilities,
                   out.write_classification, run.cfg.tiling.read_batch,
                   run.cfg.data.points_filter, feature_columns,
                   tuple(all_columns.index(c) for c in feature_columns),
                   out.point_format == "keep", rasters, out.dim_prefix, trees)

    def dims(self) -> list:
        """The extra dimensions of an exported tile, under their prefixed names."""
        return prefixed(extra_dims(self.classes, self.codes, self.probabilities,
                                   self.points_filter.excludes, self.feature_columns,
                                   self.trees is not None), self.prefix)


@dataclass(frozen=True)
class ExportTask:
    """What the export of one input tile needs (see :func:`export_tile`)."""

    store_path: str
    tile: Tile
    grid: Grid | BalancedLayout
    dst: str
    fingerprint: str
    spec: ExportSpec
    score_trees: bool = False  # count the points per (reference TreeID, predicted tree)


class _TileExport:
    """The values of the dimensions export adds to one tile, batch by batch (``values``),
    and its counts of points without features and excluded at ingest."""

    def __init__(self, root, store_path: str, tile: Tile, grid, spec: ExportSpec,
                 score_trees: bool):
        self.tile, self.spec = tile, spec
        # a labelled scene's unlisted codes were left out at ingest: their points are missing
        allow_missing = spec.points_filter.keep_codes is not None and tile.scene != "predict"
        self.predictions = _ChunkPredictions(root, tile.scene, grid,
                                             spec.stage, allow_missing, spec.feature_index)
        self.dtm = stored_terrain(root, store_path, tile.scene)  # once per worker process
        rasters = spec.rasters
        self.rasters = _TileRasters(tile, rasters, self.dtm) if rasters is not None else None
        self.canopy = np.zeros(len(spec.classes), dtype=bool)
        if rasters is not None:
            self.canopy[list(rasters.canopy)] = True
        self.trees = TileTrees(spec.trees, store_path, tile.scene, len(spec.classes),
                               score_trees)
        self.n_undefined = self.n_excluded = 0

    def _lookup(self, batch, gid):
        """Probabilities, found, undefined and feature columns of a batch's points; the
        points ingest left out by code or flag are not looked up."""
        spec, n = self.spec, len(batch.xyz)
        filtered = spec.points_filter.excluded(batch.fields)
        if filtered is None:
            filtered = np.zeros(n, dtype=bool)
        look = np.flatnonzero(~filtered)  # the points ingest stored (or dropped if unlisted)
        proba = np.zeros((n, len(spec.classes)), dtype=np.float32)
        found = np.zeros(n, dtype=bool)
        undefined = np.zeros(n, dtype=bool)
        columns = np.full((n, len(spec.feature_columns)), np.nan, dtype=np.float32)
        proba[look], found[look], undefined[look], columns[look] = self.predictions.lookup(
            batch.xyz[look], gid[look], len(spec.classes))
        self.n_undefined += int(np.count_nonzero(undefined))
        self.n_excluded += int(np.count_nonzero(filtered))
        return proba, found, undefined, columns

    def values(self, batch) -> dict:
        """The added dimensions of a read batch, by their unprefixed names."""
        spec = self.spec
        gid = global_ids(self.tile.index, batch.start, len(batch.xyz))
        proba, found, undefined, columns = self._lookup(batch, gid)
        best = np.argmax(proba, axis=1)
        predicted = np.where(found, np.asarray(spec.codes)[best], 0)  # 0: never classified
        height = batch.xyz[:, 2] - ground_elevation(self.dtm, batch.xyz[:, :2])
        if self.rasters is not None:
            self.rasters.add(batch.xyz, height, found, self.canopy[best])
        values = {
            PREDICTED: predicted,
            CONFIDENCE: proba[np.arange(len(best)), best],
            ENTROPY: entropy(proba),
            NO_FEATURES: undefined.astype(np.uint8),
            HEIGHT_ABOVE_GROUND: height.astype(np.float32),
        }
        if spec.points_filter.excludes:
            values[EXCLUDED] = (~found).astype(np.uint8)
        if spec.trees is not None:
            values[TREE_ID] = self.trees.assign(batch, height, best, found)
        if spec.probabilities:
            for index, name in enumerate(spec.classes):
                values[probability_dim(name)] = proba[:, index]
        for index, column in enumerate(spec.feature_columns):
            values[feature_dim_name(column)] = columns[:, index]
        if spec.write_classification:
            original = batch.fields.get("classification")  # None for Oakland text
            values["classification"] = (predicted if original is None
                                        else np.where(found, predicted, original))
        return values

    def named(self, batch) -> dict:
        """:meth:`values` under the prefixed names of the dimensions."""
        return {(name if name == "classification" else self.spec.prefix + name): values
                for name, values in self.values(batch).items()}


def export_tile(task: ExportTask):
    """Worker task: write the classified copy of one input tile; return its path and the
    number of its points without features and of its points excluded at ingest. Every point
    gets its height above the terrain model of its scene."""
    tile, spec, dst = task.tile, task.spec, task.dst
    root = open_store(task.store_path)
    marker = root.require_group(f"exports/{tile.index}")
    raster_paths = ([spec.rasters.path(tile.name, name) for name in spec.rasters.names]
                    if spec.rasters is not None else [])
    if (is_done(marker, "export", task.fingerprint) and Path(dst).is_file()
            and all(p.is_file() for p in raster_paths)):
        return {"path": dst, "no_features": marker.attrs.get("no_features", 0),
                "excluded": marker.attrs.get("excluded", 0),
                "rasters": [str(p) for p in raster_paths]}
    tile_export = _TileExport(root, task.store_path, tile, task.grid, spec, task.score_trees)
    export_with_extra_dims(
        tile.path, dst, spec.dims(), tile_export.named, batch_size=spec.read_batch,
        set_classification=spec.write_classification,
        keep_point_format=spec.keep_point_format,
        source_fields=(REFERENCE_TREE_ID,) if task.score_trees else (),
    )
    written = tile_export.rasters.write() if tile_export.rasters is not None else []
    tile_export.trees.store_pairs(marker)
    mark_done(marker, "export", task.fingerprint, no_features=tile_export.n_undefined,
              excluded=tile_export.n_excluded)
    return {"path": dst, "no_features": tile_export.n_undefined,
            "excluded": tile_export.n_excluded, "rasters": written}


def check_point_formats(run: Run, tiles: list[Tile]) -> None:
    """Refuse, before any work, ``output.point_format: keep`` with write_classification when
    a LAS tile's point format (0-5: codes 0..31) cannot hold the class codes."""
    out = run.cfg.output
    if out.point_format != "keep" or not out.write_classification:
        return
    largest = max(run.class_codes, default=0)
    if largest <= LEGACY_MAX_CLASS:
        return
    for tile in tiles:
        if tile.format not in ("las", "laz"):
            continue
        point_format = tile.point_format
        if point_format is not None and point_format < 6:
            raise ConfigError(
                f"config error: output.point_format keep cannot write class code {largest} "
                f"into the classification of {tile.path}: its point format {point_format} "
                f"holds codes 0..{LEGACY_MAX_CLASS}; set output.point_format: auto (LAS 1.4, "
                "codes 0..255) or output.write_classification: false (the prediction stays "
                f"in {PREDICTED})")


def export_command(out: Path) -> str:
    """The command that reruns the export of the run in ``out``: with the configuration the
    run saved there, which a 'silva predict' without a configuration has too."""
    return rerun_command(out, "export", "--in-process")


def export(run: Run, engine, layout: RunLayout, final_stage: int, stage_fp: str
           ) -> list[str]:
    """Write predictions/<tile>.laz (or .las) for every input tile; remove every other
    file of predictions/ (tiles no longer in the run, the other format, parts of files a
    killed export left)."""
    fingerprint = f"{run.fingerprint('export')}-{stage_fp}"
    out_dir = run.predictions_path
    out_dir.mkdir(parents=True, exist_ok=True)
    remove_parts(out_dir)
    suffix = "." + run.cfg.output.format
    spec = ExportSpec.of(run, final_stage, stage_fp)
    raster_dir = run.out / "rasters"
    if spec.rasters is not None:
        raster_dir.mkdir(parents=True, exist_ok=True)
        remove_parts(raster_dir)
    tasks = []
    for tile in layout.tiles:
        dst = out_dir / f"{tile.name}{suffix}"
        tasks.append(Task(
            key=f"export-{tile.index}-{fingerprint[:8]}",
            fn=export_tile,
            kwargs={"task": ExportTask(
                str(run.store_path), tile, layout.scenes[tile.scene].grid, str(dst),
                fingerprint, spec,
                score_trees=spec.trees is not None and tile.scene == "test")},
            where=f"export of tile {tile.path}",
            reproduce=export_command(run.out),
        ))
    results = list(engine.map("export", tasks).values())
    written = [r["path"] for r in results]
    remove_stale(out_dir, written)
    if raster_dir.is_dir():  # rasters of tiles no longer in the run, or no longer asked for
        remove_stale(raster_dir, [p for r in results for p in r.get("rasters", ())],
                     suffixes=(".tif",))
    undefined = sum(r["no_features"] for r in results)
    if undefined:
        share = undefined / max(layout.n_points, 1)
        say(f"export: {counted(undefined, 'point')} ({share:.2%}) have a feature column "
            "undefined (no surface within features.r1, fewer than 3 neighbours in a "
            "covariance sphere, or collinear ones), classified with it missing; marked "
            f"{NO_FEATURES}=1",
            quiet=run.quiet)  # -q keeps one line per step; the log has it
    return written
