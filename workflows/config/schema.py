"""The configuration's sections and :class:`SilvaConfig`, the whole validated configuration.

One module (the cluster section apart) because the sections validate against each other:
the halo against the features, the output names against the classes.

Every key has a default and a description; validators resolve derived values (``features.r2``,
``tiling.halo``) and raise one-line errors naming the dotted key.
"""

import fnmatch
import re
from typing import Annotated, Any, Literal, Union

import laspy
from pydantic import BeforeValidator, Field, field_validator, model_validator

from pipeline.cascade import CascadeParams, ForestParams, one_pass_halo
from pipeline.features.sets import (
    AUTO_NEIGHBORS, FEATURE_SETS, FeatureParams, feature_set,
)
from pipeline.io.base import LAS_NAME_BYTES
from pipeline.terrain import BlockGrid, TerrainParams
from pipeline.trees import TreeParams
from pipeline.trees.blocks import tree_grid
from workflows.config.fields import (
    AutoBool,
    AutoLength,
    ChunkSize,
    Integer,
    MaxFeatures,
    Number,
    PathList,
    Section,
)
from workflows.config.cluster import ClusterConfig
from workflows.config.messages import fail, field_error, show
from workflows.config.point_filter import PointFilter

_FEATURES, _CASCADE, _FOREST = FeatureParams(), CascadeParams(), ForestParams()
_TERRAIN = TerrainParams()
_TREES = TreeParams()
#: Export writes one extra dimension ``Probability_<class>`` per class; LAS names hold 32 bytes.
PROBABILITY_PREFIX = "Probability_"
MAX_CLASS_NAME_BYTES = LAS_NAME_BYTES - len(PROBABILITY_PREFIX)


# -- data ------------------------------------------------------------------------------------
class SplitConfig(Section):
    """One labelled cloud cut by a plane: coordinate < ``at`` trains, >= ``at`` tests."""

    axis: Literal["x", "y", "z"] = Field(description="The coordinate that splits the cloud.")
    at: Number = Field(description="Points with coordinate < at train, >= at test (metres).")


class DataConfig(Section):
    """Inputs, labels and classes.

    ``classes`` maps a class name to its source label codes; the order of the mapping is
    the class index and the first code of a class is its output code.
    """

    train: PathList = Field(
        default_factory=list,
        description="Paths or globs (LAS, LAZ, Oakland text) of the labelled training tiles; "
        "the files of one list are tiles of one scene.",
    )
    test: PathList = Field(
        default_factory=list, description="Labelled tiles that are classified and evaluated."
    )
    predict: PathList = Field(
        default_factory=list, description="Unlabelled tiles that are only classified."
    )
    label_field: str = Field(
        "classification", min_length=1,
        description="The point dimension that holds the source labels.",
    )
    classes: dict[str, list[Integer]] = Field(
        default_factory=dict,
        description="Class name -> source label codes; order = class index; the output code "
        "of a class is its first code. Required whenever train or test is given.",
    )
    ignore: list[Union[str, int]] = Field(
        default_factory=list,
        description="Class names or raw codes dropped from training and evaluation.",
    )
    background: list[str] = Field(
        default_factory=list,
        description="Class names trained on but left out of the metric averages.",
    )
    split: SplitConfig | None = Field(
        None, description="Cut the labelled training cloud into a training and a test part.",
    )
    exclude_codes: list[Integer] = Field(
        default_factory=list,
        description="LAS classification codes whose points are left out of every "
        "neighbourhood, of training and of the metrics, e.g. [7, 18] (low and high noise); "
        "they are exported unchanged with Excluded 1 and PredictedClassification 0.",
    )
    exclude_withheld: bool = Field(
        False,
        description="Leave out the points whose LAS withheld flag is set, as exclude_codes "
        "does.",
    )
    drop_unlisted: bool = Field(
        False,
        description="Remove labelled points whose code is in no class and not in ignore "
        "before anything is computed (the Oakland benchmark protocol); they are exported "
        "with PredictedClassification 0. By default they stay as unlabelled neighbours.",
    )
    allow_overlap: bool = Field(
        False,
        description="Accept a tile that is both in data.train and in data.test (the same "
        "file); its test scores are then scores on training points. Refused by default.",
    )
    densities: list[Number] = Field(
        default_factory=list,
        description="Point densities (points per m²) to train at, e.g. [5, 2]: besides "
        "itself, the training scene (data.train) gets one thinned copy per density below "
        "its own (points per occupied 2 m cell), of the points a hash of their id keeps "
        "(seeded by cascade.seed: the same points every run, whatever the chunking), with "
        "its own terrain model and features; copies are trained on, never exported nor "
        "scored. A density at or above the scene's makes no copy (silva plan says so); a "
        "run applying a saved model makes none.",
    )

    @field_validator("classes", mode="before")
    @classmethod
    def _classes_shape(cls, value: Any) -> Any:
        if not isinstance(value, dict):
            return value
        result = {}
        for name, codes in value.items():
            if not isinstance(name, str) or not name:
                raise fail(f"data.classes: class names must be non-empty text, got "
                           f"{show(name)}; quote it ('{name}')")
            if len(name.encode()) > MAX_CLASS_NAME_BYTES:
                raise fail(f"data.classes: class name '{name}' is {len(name.encode())} bytes; "
                           f"its output dimension {PROBABILITY_PREFIX}{name} must fit the "
                           f"{LAS_NAME_BYTES}-byte LAS extra-dimension name, so use at most "
                           f"{MAX_CLASS_NAME_BYTES} bytes")
            # "tree: 5" is a class with one code
            result[name] = [codes] if isinstance(codes, int) and not isinstance(codes, bool) \
                else codes
        return result

    @field_validator("densities")
    @classmethod
    def _densities_positive(cls, value: list[float]) -> list[float]:
        names = set()
        for i, density in enumerate(value):
            if not density > 0:
                raise fail(f"data.densities[{i}] must be a number of points per m² > 0, got "
                           f"{show(density)}")
            if f"{density:g}" in names:
                raise fail(f"data.densities lists {density:g} points/m² twice; list each "
                           "density once")
            names.add(f"{density:g}")
        return value

    @field_validator("ignore", mode="before")
    @classmethod
    def _ignore_items(cls, value: Any) -> Any:
        if isinstance(value, (list, tuple)):
            for i, item in enumerate(value):
                if isinstance(item, bool) or not isinstance(item, (str, int)):
                    raise fail(f"data.ignore[{i}] must be a class name or an integer label "
                               f"code, got {show(item)}")
        return value

    @model_validator(mode="after")
    def _check_classes(self) -> "DataConfig":
        owner: dict[int, str] = {}
        for name, codes in self.classes.items():
            if not codes:
                raise fail(f"data.classes.{name} has no label codes; give at least one, "
                           f"e.g. {name}: [2]")
            for code in codes:
                if code in owner:
                    where = ("twice under" if owner[code] == name
                             else f"under both '{owner[code]}' and")
                    raise fail(f"data.classes: label code {code} is listed {where} "
                               f"'{name}'; each source code belongs to one class")
                owner[code] = name
        labelled = [scene for scene in ("train", "test") if getattr(self, scene)]
        if labelled and not self.classes:
            raise fail(f"data.classes is empty but data.{labelled[0]} is given; list the "
                       "classes, e.g. classes: {ground: [2], vegetation: [3, 4, 5]}")
        known = ", ".join(self.classes) or "none"
        for i, item in enumerate(self.ignore):
            if isinstance(item, str) and item not in self.classes:
                raise fail(f"data.ignore[{i}] '{item}' is not a class in data.classes "
                           f"(classes: {known}); use a class name or an integer code")
        for i, name in enumerate(self.background):
            if name not in self.classes:
                raise fail(f"data.background[{i}] '{name}' is not a class in data.classes "
                           f"(classes: {known})")
            if name in self.ignore:
                raise fail(f"data.background '{name}' is also in data.ignore; a class is "
                           "either trained on (background) or dropped (ignore), not both")
        ignored_codes = {c for c in self.ignore if isinstance(c, int)}
        for name, codes in self.classes.items():
            if name not in self.ignore and codes and set(codes) <= ignored_codes:
                raise fail(f"data.ignore drops every code of class '{name}' "
                           f"({show(codes)}); ignore the class by name instead")
        if self.classes and not self.class_names:
            raise fail("data.ignore drops every class in data.classes; keep at least one")
        for i, code in enumerate(self.exclude_codes):
            if not 0 <= code <= 255:
                raise fail(f"data.exclude_codes[{i}] must be a LAS classification code "
                           f"0..255, got {show(code)}")
            owner = next((name for name, codes in self.classes.items() if code in codes), None)
            if owner is not None and self.label_field == "classification":
                raise fail(f"data.exclude_codes leaves out code {code}, which is a code of "
                           f"class '{owner}'; remove it from one of them")
        if self.split is not None and not self.train:
            raise fail("data.split cuts the data.train cloud, but data.train is empty; "
                       "give data.train or remove data.split")
        return self

    @property
    def points_filter(self) -> PointFilter:
        """The points ingest leaves out (exclude_codes, exclude_withheld, drop_unlisted)."""
        return PointFilter(tuple(self.exclude_codes), self.exclude_withheld,
                           tuple(self.listed_codes) if self.drop_unlisted else None)

    @property
    def excludes(self) -> bool:
        """Whether ingest leaves points out: the export then marks them (``Excluded``)."""
        return self.points_filter.excludes

    # -- class helpers ----------------------------------------------------------------------
    @property
    def class_names(self) -> list[str]:
        """Names of the classes the model learns and predicts (ignored ones removed), in order."""
        return [name for name in self.classes if name not in self.ignore]

    @property
    def class_codes(self) -> list[int]:
        """The output code of each class of :attr:`class_names`: its first source code."""
        return [self.classes[name][0] for name in self.class_names]

    @property
    def code_to_class(self) -> dict[int, int]:
        """Source label code -> index in :attr:`class_names`; ignored codes are absent."""
        ignored_codes = {c for c in self.ignore if isinstance(c, int)}
        return {
            code: index
            for index, name in enumerate(self.class_names)
            for code in self.classes[name]
            if code not in ignored_codes
        }

    @property
    def listed_codes(self) -> list[int]:
        """Every source code named by a class or by ignore (kept by drop_unlisted)."""
        codes = {code for codes in self.classes.values() for code in codes}
        return sorted(codes | {c for c in self.ignore if isinstance(c, int)})

    @property
    def background_indices(self) -> list[int]:
        """Indices in :attr:`class_names` of the background classes."""
        names = self.class_names
        return [names.index(name) for name in self.background]


# -- tiling and features ---------------------------------------------------------------------
class FeaturesConfig(Section):
    """The per-point features: moment invariants in S1 and context in S1 and S2."""

    set: str = Field(
        _FEATURES.set,
        description="The feature set; 'paper' = the 11 moment invariants and the context "
        "features as published.",
    )
    r1: AutoLength = Field(
        _FEATURES.r1,
        description="Radius of the sphere S1 in metres, or 'auto': from the training tiles' "
        "point density, the paper's 0.5 m unless S1 would then hold fewer than about "
        f"{AUTO_NEIGHBORS} points (sparse airborne tiles get a larger radius).",
    )
    r2: Number | None = Field(
        None, description="Radius of the inner context sphere S2 in metres; default r1 / 2."
    )
    max_neighbors: Integer = Field(
        _FEATURES.max_neighbors, ge=3,
        description="At most this many nearest points of S1 form the local surface.",
    )
    context_max_neighbors: Integer | None = Field(
        _FEATURES.context_max_neighbors, ge=1,
        description="Unset: every point within r1 counts in the context (the "
        "paper; exact and fast at any density). A number: only that many nearest points, "
        "which on dense scans shrinks the context sphere well below r1.",
    )

    plane: Literal["pca", "xy"] = Field(
        _FEATURES.plane,
        description="Where S1 is triangulated: 'pca', the plane of its two principal axes, "
        "or 'xy', the horizontal plane (the paper does not say which).",
    )
    scales: list[Number] = Field(
        list(_FEATURES.scales), min_length=1,
        description="Sets 'covariance' and 'default': the radii of the covariance features, "
        "as multiples of r1.",
    )
    column: Number = Field(
        _FEATURES.column, gt=0,
        description="Sets 'covariance' and 'default': radius in metres of the column of "
        "the height features (the terrain under a point is a matter of metres at any density).",
    )
    cell: Number = Field(
        _FEATURES.cell, gt=0,
        description="Sets 'covariance' and 'default': side in metres of the cells of the height "
        "column; the lowest points of its cells are the terrain reference.",
    )
    voxel: AutoLength | None = Field(
        _FEATURES.voxel,
        description="Unset: the surface features of every point. A side in metres: they are "
        "computed on one point per voxel (the smallest id) and shared by its points; "
        "dense scans then see all of S1, not a patch of its 64 nearest points. 'auto': the "
        "side at which S1 holds about max_neighbors voxels of a surface.",
    )
    echoes: AutoBool = Field(
        _FEATURES.echoes,
        description="Sets 'covariance' and 'default': add, in the sphere of each covariance "
        "radius, the share of points of multi-return pulses, the share of last returns and "
        "the spread of return numbers, from each point's return number and number of "
        "returns (LAS tiles whose points record them; a tile without them is refused). On "
        "airborne surveys they tell crowns from roofs. 'auto': on for those sets when the "
        "header of every tile of the run counts points of second or later returns "
        "(multi-return airborne surveys), off otherwise (text files, single-return scans, "
        "headers that count no returns).",
    )
    version: Integer = Field(
        _FEATURES.version,
        description="Which feature values: 2 (the default) takes the heights of sets "
        "'covariance' and 'default' above the column's ground level, which does not follow "
        "the point density, and keeps the points far under the terrain model out of every "
        "neighbourhood; 1, the values before, for models trained with them. A run applying a "
        "model takes the model's.",
    )

    @field_validator("set")
    @classmethod
    def _known_set(cls, value: str) -> str:
        if value not in FEATURE_SETS:
            raise field_error("must be one of the feature sets "
                              + ", ".join(f"'{s}'" for s in FEATURE_SETS))
        return value

    @property
    def resolved(self) -> bool:
        """False while r1, voxel or echoes is 'auto' (resolved from the data when a run
        starts)."""
        return all(value != "auto" for value in (self.r1, self.voxel, self.echoes))

    @model_validator(mode="after")
    def _check_params(self) -> "FeaturesConfig":
        # FeatureParams checks the values; while r1, voxel or echoes waits for the data
        # ('auto'), it checks the others at the paper's radius, and everything once the run
        # resolves
        try:
            params = (self.params if self.resolved else
                      FeatureParams(self.set, plane=self.plane, scales=tuple(self.scales),
                                    column=self.column, cell=self.cell,
                                    echoes=self.echoes is True, version=self.version))
        except ValueError as err:
            raise fail(str(err)) from None
        if self.resolved and self.r2 is None:
            object.__setattr__(self, "r2", params.r2)  # FeatureParams' default, r1 / 2
        return self

    @property
    def params(self) -> FeatureParams:
        """The resolved parameters the feature and context steps receive."""
        return FeatureParams(self.set, self.r1, self.r2, self.max_neighbors,
                             self.context_max_neighbors, self.plane, tuple(self.scales),
                             self.column, self.cell, self.voxel, echoes=self.echoes,
                             version=self.version)

    @property
    def radius2(self) -> float:
        """The inner context radius, resolved (r1 / 2 unless set)."""
        return self.params.r2

    @property
    def largest_radius(self) -> float:
        """The largest distance any step looks at: the halo must be at least this."""
        return self.params.halo


class TilingConfig(Section):
    """The chunk grid the tiles are cut into, and how they are streamed."""

    chunk_size: ChunkSize = Field(
        "auto",
        description="Side of a square chunk of a regular grid in metres, or 'auto': chunks "
        "that hold about tiling.target_points points each with their halo, cut as "
        "tiling.layout says.",
    )
    layout: Literal["balanced", "grid"] = Field(
        "balanced",
        description="With chunk_size 'auto': 'balanced', rectangles cut where a quick first "
        "pass over the points shares them out evenly (dense parts get small chunks, empty "
        "space none); 'grid', squares sized from the tiles' headers at the scene's mean "
        "density. Ignored when chunk_size is a number (a regular grid).",
    )
    target_points: Integer = Field(
        1_000_000, ge=1,
        description="With chunk_size 'auto': points wanted in a chunk with its halo; a "
        "worker holds one chunk at a time, so this bounds its memory. Ignored when "
        "chunk_size is a number.",
    )
    halo: Number | None = Field(
        None, gt=0,
        description="Width in metres of the copies of neighbouring points around a chunk; "
        "minimum: the features' reach (their largest radius or height column); default: "
        "that plus one context reach (features.r1 and a tenth more for the voxels that bound a "
        "pile-up of points) and a centimetre per cascade stage after the first, with which a chunk that is only classified computes all its "
        "stages in one pass and stores no features. The scenes that go stage by stage "
        "(those trained on, and those output.keep_features keeps) take only the features' "
        "reach.",
    )
    read_batch: Integer = Field(
        1_000_000, ge=1, description="Points per read batch when streaming tiles."
    )



# -- terrain ---------------------------------------------------------------------------------
class TerrainConfig(Section):
    """The ground model of each scene: a progressive morphological filter with slope
    tolerance (SMRF, Pingel et al. 2013, as PDAL's filters.smrf) on the raster of the
    lowest point of each cell; the heights above it are features and an output dimension."""

    cell: Number = Field(_TERRAIN.cell, gt=0,
                         description="Side in metres of the cells of the terrain model.")
    slope: Number = Field(_TERRAIN.slope, gt=0,
                          description="Slope tolerance (rise over run) of the ground.")
    window: Number = Field(
        _TERRAIN.window, gt=0,
        description="Largest opening radius in metres: objects (roofs) up to twice as wide "
        "are taken off the ground.")
    threshold: Number = Field(
        _TERRAIN.threshold, gt=0,
        description="Height in metres above the terrain model below which a cell's lowest "
        "point is ground.")
    scalar: Number = Field(
        _TERRAIN.scalar, ge=0,
        description="How much the threshold grows with the local slope (metres per unit slope).")
    block: AutoLength = Field(
        "auto",
        description="Side in metres of the square blocks the terrain is modelled in, each on "
        "a worker from its points and a buffer around it, anchored at multiples of it in map "
        "coordinates: the memory of a block's model follows it, not the survey's area. "
        "'auto': 1,000 cells (1 km at 1 m cells). The results depend on it (a little, at the "
        "blocks' edges), never on the chunking or the workers.")
    ground_tolerance: Number | None = Field(
        None, gt=0,
        description="Where the terrain model is confident, its answer is the class: a point "
        "over a cell whose own lowest point the filter kept as ground (seen, not filled) and "
        "within this many metres of the DTM is ground (the class of code 2), certainly, at "
        "every cascade stage and whatever the forests say; a model records it. Unset: off "
        "(the forests decide; models saved before the key). 0.1 m, the installed "
        "terrestrial model's, calls 99 % of a 40-degree synthetic hillside's terrain terrain "
        "where forests trained on gentle ground alone call 55 %, and costs their dead wood "
        "on gentle ground 0.01 F1 (docs/BENCHMARKS.md, 'Steep slopes').")

    @model_validator(mode="after")
    def _check_params(self) -> "TerrainConfig":
        self.grid  # noqa: B018 -- the filter's own checks (window >= cell), at load time
        return self

    @property
    def grid(self) -> BlockGrid:
        """The fixed blocks the terrain is modelled in."""
        try:
            return BlockGrid.of(self.params, None if self.block == "auto" else self.block)
        except ValueError as err:
            raise fail(str(err)) from None

    @property
    def params(self) -> TerrainParams:
        """The resolved parameters of the ground filter."""
        try:
            return TerrainParams(self.cell, self.slope, self.window, self.threshold, self.scalar)
        except ValueError as err:
            raise fail(str(err)) from None


# -- trees -----------------------------------------------------------------------------------
class TreesConfig(Section):
    """Every tree of a scene (with ``output.trees: true``): crowns segmented on the canopy
    height of the points predicted as ``output.canopy_classes`` (airborne), or stems fitted
    at breast height among the points of ``trees.stem_classes`` (terrestrial). The values
    are checked by :class:`pipeline.trees.TreeParams`."""

    method: Literal["auto", "crowns", "stems"] = Field(
        _TREES.method,
        description="crowns: tops and crowns from the canopy height (airborne scans); "
        "stems: stems and DBH from circles fitted at breast height, crowns grown from them "
        "(terrestrial scans); auto: stems where the scan sees them, crowns otherwise.")
    min_height: Number = Field(_TREES.min_height,
                               description="Lowest tree height in metres above ground.")
    resolution: AutoLength = Field(
        "auto",
        description="Side in metres of the canopy height cells. 'auto': 0.5 m, or on a scan "
        "sparser than about 2 points/m² the finest cell its points resolve (three quarters "
        "of their mean spacing in the sparsest scene's headers: 0.75 m at 1 point/m²).")
    smoothing: Number = Field(
        _TREES.smoothing,
        description="Gaussian smoothing of the canopy height (sigma in cells; 0: none).")
    window: list[Number] = Field(
        list(_TREES.window),
        description="[a, b]: the local-maximum window that finds tree tops is a + b * height "
        "metres wide (taller trees, wider crowns).")
    crown_radius: list[Number] = Field(
        list(_TREES.crown_radius),
        description="[a, b]: a crown reaches at most a + b * height metres from its top.")
    breast_height: Number = Field(_TREES.breast_height,
                                  description="Height in metres of the DBH measurement.")
    slice_half_width: Number = Field(
        _TREES.slice_half_width,
        description="Half the thickness in metres of the section a stem's circle is fitted to.")
    fallback_offsets: list[Number] = Field(
        list(_TREES.fallback_offsets),
        description="Offsets in metres from breast height of the sections tried, in order, "
        "when the circle at breast height fails.")
    stem_cluster_eps: Number = Field(
        _TREES.stem_cluster_eps,
        description="Largest gap in metres between points of one stem's section.")
    stem_min_points: Integer = Field(_TREES.stem_min_points,
                                     description="Fewest points of a stem's section.")
    stem_voxel: Number = Field(
        _TREES.stem_voxel,
        description="Side in metres of the voxels the stem slice is thinned to.")
    max_dbh: Number = Field(_TREES.max_dbh, description="Largest plausible DBH in metres.")
    stem_classes: list[str] | None = Field(
        None,
        description="The classes whose points make stems; default: every class that may "
        "be a tree (all but those of ASPRS codes 2 ground, 6 building, 7 and 18 noise, 9 "
        "water, 17 bridge deck), so that a stem the classifier calls dead wood is found.")

    block: AutoLength = Field(
        "auto",
        description="Side in metres of the square blocks crowns are found in, each on a "
        "worker from its canopy and a buffer around it, anchored at multiples of it in map "
        "coordinates: the memory of a block follows it, not the survey's area. 'auto': "
        "1,000 canopy cells (500 m at 0.5 m cells). The trees depend on it only where a "
        "crown's top sits near a block's edge, never on the chunking or the workers.")

    @model_validator(mode="after")
    def _check_params(self) -> "TreesConfig":
        self.params  # noqa: B018 -- TreeParams checks the values, at load time (the blocks
        return self  # once the scan is known: check_tree_settings)

    @property
    def params(self) -> TreeParams:
        """The tree step's parameters (validated by TreeParams)."""
        values = self.model_dump(exclude={"stem_classes", "block"})
        if values["resolution"] == "auto":  # resolved from the tiles as a run starts
            values["resolution"] = _TREES.resolution
        values = {k: tuple(v) if isinstance(v, list) else v for k, v in values.items()}
        try:
            return TreeParams(**values)
        except ValueError as err:
            raise fail(str(err)) from None

    @property
    def grid(self) -> BlockGrid:
        """The fixed blocks crowns are found in (ConfigError: blocks beyond a raster's
        size, refused with the scan's other reasons by the tree step's checks)."""
        return tree_grid(self.params, None if self.block == "auto" else self.block)


# -- cascade ---------------------------------------------------------------------------------
class CascadeConfig(Section):
    """The cascade of random forests (auto-context)."""

    stages: Integer = Field(_CASCADE.stages, ge=1,
                            description="Number of cascade stages (forests).")
    n_estimators: Integer = Field(_FOREST.n_estimators, ge=1, description="Trees per forest.")
    min_samples_leaf: Integer = Field(_FOREST.min_samples_leaf, ge=1,
                                      description="Minimum samples in a leaf.")
    max_features: MaxFeatures = Field(
        _FOREST.max_features,
        description="Features tried per split, as scikit-learn takes it: 'sqrt', 'log2', "
        "an integer or a fraction in (0, 1].",
    )
    context: Literal["hard", "soft"] = Field(
        _CASCADE.context,
        description="Context from predicted classes (hard) or averaged probabilities (soft).",
    )
    out_of_fold: bool = Field(
        _CASCADE.out_of_fold,
        description="Compute the training points' context from out-of-fold predictions.",
    )
    folds: Integer = Field(_CASCADE.folds, ge=2, description="Folds used with out_of_fold.")
    max_train_points: Integer = Field(
        _CASCADE.max_train_points, ge=1,
        description="At most this many training points per stage.",
    )
    balanced: bool = Field(
        _CASCADE.balanced,
        description="Balance the classes: equal quotas per class when the training points "
        "exceed max_train_points, and class weights in every forest.",
    )
    seed: Integer = Field(_CASCADE.seed, ge=0, le=2**32 - 1,
                          description="Seed of sampling and forests.")

    def params(self, n_jobs: int = 1) -> CascadeParams:
        """The resolved parameters of the cascade; ``n_jobs`` threads per forest fit."""
        forest = ForestParams(self.n_estimators, self.min_samples_leaf, self.max_features,
                              n_jobs)
        return CascadeParams(self.stages, self.context, self.out_of_fold, self.folds,
                             self.max_train_points, self.balanced, self.seed, forest)


# -- output ----------------------------------------------------------------------------------
#: The dimensions export adds besides the probabilities and the feature columns.
SILVA_DIMS = ("PredictedClassification", "Confidence", "Entropy", "NoFeatures", "Excluded",
              "HeightAboveGround")
#: ASPRS classification codes: ground, and low, medium and high vegetation.
GROUND_CODE, VEGETATION_CODES = 2, (3, 4, 5)
#: ASPRS codes of what is surely not a tree: ground, building, low noise, water, bridge
#: deck, high noise.
NOT_TREE_CODES = (GROUND_CODE, 6, 7, 9, 17, 18)
#: The rasters output.rasters may ask for.
RASTERS = ("dtm", "dsm", "chm")


def feature_dim_name(column: str) -> str:
    """The extra-dimension name of a feature column: each character other than an ASCII
    letter, digit or underscore becomes '_' (PDAL's dimension names allow no dots)."""
    return re.sub(r"[^A-Za-z0-9_]", "_", column)


def _feature_dims(value: Any) -> Any:
    if isinstance(value, str) and value != "all":
        value = [value]  # one column or pattern
    if isinstance(value, (list, tuple)):
        for item in value:
            if not isinstance(item, str) or not item:
                raise field_error("must be 'all' or a list of feature column names or patterns")
    return value


FeatureDims = Annotated[Union[Literal["all"], list[str]], BeforeValidator(_feature_dims)]


class OutputConfig(Section):
    """The classified tiles written back."""

    format: Literal["laz", "las"] = Field("laz", description="laz | las.")
    write_classification: bool = Field(
        False,
        description="Also overwrite the classification field with the prediction (the "
        "original is otherwise kept untouched).",
    )
    probabilities: bool = Field(True, description="One extra dimension per class.")
    keep_store: bool = Field(
        True,
        description="false: once a run has completed (predictions, metrics and report "
        "written), remove the chunks of store.zarr, the bulk of the output directory; a "
        "rerun of the same configuration then says the results are complete, any other "
        "recomputes from the input tiles.",
    )
    keep_features: AutoBool = Field(
        "auto",
        description="false: the scenes no forest trains on (data.test, data.predict, every "
        "scene of silva predict) are classified in one pass per chunk and store no "
        "features: a store a few times the input instead of some forty. true: keep the "
        "features of every scene in store.zarr, so that a rerun with other cascade "
        "settings, or another model applied to the same output, reuses them (silva sweep "
        "sets it). auto: false, except for a scene whose chunks are so small that the one "
        "pass would compute more than an eighth of its points twice (their borders). "
        "Exported feature columns (output.feature_dims) keep them too. Changing it in an "
        "output directory ingests again: each scene's halo follows it.",
    )
    feature_dims: FeatureDims = Field(
        default_factory=list,
        description="Feature columns also written as float32 extra dimensions: 'all', or "
        "a list of column names or patterns of the feature set (e.g. [linearity_*, "
        "I2_22]); a dimension's name is the column's with each character other than a "
        "letter, digit or _ replaced by _ (linearity_r0.5 -> linearity_r0_5).",
    )
    point_format: Literal["auto", "keep"] = Field(
        "auto",
        description="auto: LAS 1.4, the point format 6-10 that holds every input value; "
        "keep: the input's LAS version and point format (formats 0-5 hold classification "
        "codes 0..31 only, so write_classification then needs class codes <= 31).",
    )

    dim_prefix: str = Field(
        "",
        description="Prefix of the names of the dimensions Silva adds (e.g. silva_ gives "
        "silva_PredictedClassification, silva_Probability_tree, ...): for inputs that "
        "already carry dimensions of those names with other types.",
    )
    rasters: list[Literal[RASTERS]] = Field(
        default_factory=list,
        description="GeoTIFF rasters written per input tile as rasters/<tile>_<name>.tif "
        "(float32, the tile's CRS): dtm, the terrain model; dsm, the highest point of each "
        "cell; chm, the canopy height, the highest height above ground of the points "
        "predicted as output.canopy_classes (0 in cells with points but no canopy). A "
        "stray point 15 m or more above every point near it (a bird) sets no cell.",
    )
    raster_resolution: Number = Field(
        1.0, gt=0, description="Side in metres of the cells of output.rasters.")
    trees: bool = Field(
        False,
        description="Find every tree (see the trees section): PredictedTreeID per point, "
        "and per input tile trees/<tile>.csv and trees/<tile>.gpkg (tops and crowns).")
    canopy_classes: list[str] | None = Field(
        None,
        description="The classes whose points make the canopy height (chm) and the crowns "
        "of output.trees; default: the "
        "classes whose first code is an ASPRS vegetation code (3, 4, 5), or else every "
        "class but the ground's (code 2).",
    )

    def feature_columns(self, columns, set_name: str) -> list[str]:
        """The columns of ``columns`` (feature set ``set_name``'s, in its order) that
        feature_dims names; a one-line error for a name or pattern that matches none."""
        if self.feature_dims == "all":
            return list(columns)
        chosen = set()
        for i, pattern in enumerate(self.feature_dims):
            matched = fnmatch.filter(columns, pattern)
            if not matched:
                raise fail(f"output.feature_dims[{i}] '{pattern}' is not a column of "
                           f"feature set '{set_name}'; valid: {', '.join(columns)}, or 'all'")
            chosen.update(matched)
        return [c for c in columns if c in chosen]


# -- the whole configuration -----------------------------------------------------------------
class SilvaConfig(Section):
    """A complete, validated Silva configuration."""

    data: DataConfig = Field(default_factory=DataConfig)
    tiling: TilingConfig = Field(default_factory=TilingConfig)
    features: FeaturesConfig = Field(default_factory=FeaturesConfig)
    terrain: TerrainConfig = Field(default_factory=TerrainConfig)
    cascade: CascadeConfig = Field(default_factory=CascadeConfig)
    trees: TreesConfig = Field(default_factory=TreesConfig)
    cluster: ClusterConfig = Field(default_factory=ClusterConfig)
    output: OutputConfig = Field(default_factory=OutputConfig)

    @model_validator(mode="after")
    def _resolve_halo(self) -> "SilvaConfig":
        if not self.features.resolved:
            return self  # the run resolves r1 or voxel from the data, then validates again
        largest = self.features.largest_radius
        halo = self.tiling.halo
        size = self.tiling.chunk_size
        reach = float(halo) if halo is not None else self.halo
        if size != "auto" and size < reach / 2:
            # every point is copied into the halos of ((2 halo / size) + 1)^2 chunks: a
            # chunk far narrower than its halo makes ingest and the store grow without bound
            raise fail(f"tiling.chunk_size {show(size)} m is less than half the halo of "
                       f"{show(reach)} m, so each point would be copied into the halos of "
                       f"about {int((2 * reach / size + 1) ** 2):,} chunks; use a chunk_size "
                       f"of at least {show(reach)} m (better ten times that) or auto")
        if halo is None:
            object.__setattr__(self, "tiling", self.tiling.model_copy(update={"halo": self.halo}))
        elif halo < largest:
            raise fail(f"tiling.halo {show(halo)} is smaller than the features' reach "
                       f"{show(largest)}; use a halo >= {show(largest)} or leave it unset")
        return self

    @model_validator(mode="after")
    def _check_feature_dims(self) -> "SilvaConfig":
        if not self.output.feature_dims or not self.features.resolved:
            return self  # checked again once the run has resolved r1 and voxel
        taken = {PROBABILITY_PREFIX + name for name in self.data.class_names}
        taken |= set(SILVA_DIMS) | set(laspy.PointFormat(10).standard_dimension_names)
        seen: dict[str, str] = {}
        for column in self.feature_dim_columns:
            name = feature_dim_name(column)
            if len(name.encode()) > LAS_NAME_BYTES or name in taken or name in seen:
                why = (f"is longer than the {LAS_NAME_BYTES}-byte LAS limit"
                       if len(name.encode()) > LAS_NAME_BYTES else
                       f"is also the dimension of column '{seen[name]}'" if name in seen
                       else "is already an output dimension")
                raise fail(f"output.feature_dims: the dimension '{name}' of feature column "
                           f"'{column}' {why}; leave the column out of output.feature_dims")
            seen[name] = column
        return self

    @field_validator("output")
    @classmethod
    def _check_dim_prefix(cls, output):
        if output.dim_prefix and not re.fullmatch(r"[A-Za-z0-9_]+", output.dim_prefix):
            raise field_error("dim_prefix may hold letters, digits and _ only, got "
                              f"{output.dim_prefix!r}")
        return output

    @model_validator(mode="after")
    def _check_prefixed_names(self) -> "SilvaConfig":
        prefix = self.output.dim_prefix
        names = [*SILVA_DIMS, *(PROBABILITY_PREFIX + n for n in self.data.class_names)]
        for name in names:
            if len((prefix + name).encode()) > LAS_NAME_BYTES:
                raise fail(f"output.dim_prefix '{prefix}' makes the dimension "
                           f"'{prefix + name}' longer than the {LAS_NAME_BYTES}-byte LAS "
                           "limit; use a shorter prefix")
        return self

    @model_validator(mode="after")
    def _check_class_lists(self) -> "SilvaConfig":
        for key, names in (("output.canopy_classes", self.output.canopy_classes),
                           ("trees.stem_classes", self.trees.stem_classes)):
            for name in names or ():
                if name not in self.data.class_names:
                    raise fail(f"{key}: '{name}' is not a class; classes: "
                               + ", ".join(self.data.class_names))
        return self

    @model_validator(mode="after")
    def _check_ground_class(self) -> "SilvaConfig":
        if self.terrain.ground_tolerance is not None and self.data.class_names \
                and self.ground_class is None:
            raise fail("terrain.ground_tolerance makes points on seen ground ground, but no "
                       f"class of data.classes has the code {GROUND_CODE} (ground); give the "
                       "ground class that code or remove terrain.ground_tolerance")
        return self

    @property
    def ground_class(self) -> int | None:
        """Index of the class whose first code is :data:`GROUND_CODE` (None: none is)."""
        codes = self.data.class_codes
        return codes.index(GROUND_CODE) if GROUND_CODE in codes else None

    @property
    def canopy_classes(self) -> list[int]:
        """Indices of the classes whose points make the canopy height model (see
        :attr:`OutputConfig.canopy_classes`)."""
        names, codes = self.data.class_names, self.data.class_codes
        if self.output.canopy_classes is not None:
            return [names.index(name) for name in self.output.canopy_classes]
        vegetation = [i for i, code in enumerate(codes) if code in VEGETATION_CODES]
        return vegetation or [i for i, code in enumerate(codes) if code != GROUND_CODE]

    @property
    def tree_point_classes(self) -> list[int]:
        """Indices of the classes whose points a tree may hold (grown from its stem, a tree
        goes through them): every class whose first code is not one of
        :data:`NOT_TREE_CODES` (ground, buildings, noise, water), and always the classes
        that ``output.canopy_classes`` and ``trees.stem_classes`` name. A stem section the
        classifier calls dead wood or misc then does not cut its tree in two."""
        names = self.data.class_names
        chosen = {i for i, code in enumerate(self.data.class_codes)
                  if code not in NOT_TREE_CODES}
        for given in (self.output.canopy_classes, self.trees.stem_classes):
            chosen |= {names.index(name) for name in given or ()}
        return sorted(chosen)

    @property
    def stem_classes(self) -> list[int]:
        """Indices of the classes whose points make stems (see
        :attr:`TreesConfig.stem_classes`; default: :attr:`tree_point_classes`)."""
        if self.trees.stem_classes is None:
            return self.tree_point_classes
        return [self.data.class_names.index(name) for name in self.trees.stem_classes]

    @property
    def feature_dim_columns(self) -> list[str]:
        """The feature columns written as extra dimensions (output.feature_dims resolved)."""
        if not self.output.feature_dims:
            return []
        params = self.features.params
        return self.output.feature_columns(list(feature_set(params).columns), params.set)

    @property
    def halo(self) -> float:
        """The halo in metres (resolved: see :attr:`TilingConfig.halo`)."""
        if self.tiling.halo is not None:
            return self.tiling.halo
        return one_pass_halo(self.features.largest_radius, self.features.params.r1,
                             self.cascade.stages)

    @property
    def class_names(self) -> list[str]:
        """See :attr:`DataConfig.class_names`."""
        return self.data.class_names
