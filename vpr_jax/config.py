"""Every knob of a sweep, one frozen dataclass per concern, defaults in one place.

``parse_config(argv)`` layers: these defaults <- ``experiments/configs/<preset>.yaml`` <-
``key=value`` arguments. Unknown keys, wrong types and invalid values raise ``UserError``
with one line that names the key and the fix.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from vpr_jax import method_table, presets
from vpr_jax.compute_config import ClusterConfig, MatchingConfig, MeshConfig
from vpr_jax.compute_config import check as _check
from vpr_jax.shapes import IMAGE_SHAPE, MAX_PIXELS

# The names the config accepts, each list written once here and read by the code that acts
# on it (the Nordland readers, the benchmarks, the optimizers, the PR conventions).
NORDLAND_SOURCES = ("nordland_images", "nordland_videos", "folders")
ROUTE_SOURCES = ("synthetic", *NORDLAND_SOURCES)  # frame-aligned seasons
# Benchmarks whose database and queries are not frame-aligned (ground truth as sets), with
# the names of their one pair: (database, queries).
BENCHMARK_PAIRS = {
    "vpr_bench": ("ref", "query"),
    "positions": ("database", "queries"),
    "nordland_star": ("winter", "summer"),
}
BENCHMARK_SOURCES = tuple(BENCHMARK_PAIRS)
SOURCES = (*ROUTE_SOURCES, *BENCHMARK_SOURCES)
OPTIMIZERS = ("adam", "adamw", "sgd")  # optax's functions of these names
PREPROCESSES = ("none", "patchnorm")
GRADIENT_NORMS = ("L1", "L1-sqrt", "L2", "L2-Hys")  # vpr_jax.encoders.gradients.NORMS
# How PR recall counts (docs/metrics.md, "PR conventions"; vpr_jax.evaluation.metrics).
PR_CONVENTIONS = ("vpr_bench", "has_match", "vpr_tutorial")
# matching.precision: the matcher's products at float32, or the platform's fastest (TF32 on
# recent NVIDIA GPUs; vpr_jax.precision).
# train.* keys that say where and how often models are saved, not what is trained.
TRAIN_BOOKKEEPING = ("checkpoint_dir", "checkpoint_every_s")


@dataclass(frozen=True)
class DataConfig:
    """Where images come from: an aligned route (frame-aligned (N, 32, 64) seasons) or a
    benchmark (database, queries and ground-truth sets)."""

    # aligned routes: synthetic | nordland_images | nordland_videos | folders;
    # benchmarks: vpr_bench | positions | nordland_star (docs/guide.md, "Any benchmark")
    source: str = "synthetic"
    root: str | None = None  # data folder (not used by synthetic)
    radius_m: float = 25.0  # positions: a database image within this distance is correct
    # Benchmarks fit their encoders on their database images, or on the training places of
    # this aligned route (a route source: synthetic, nordland_images, ...) read from
    # train_root with data.seasons (two seasons: the pair to learn from).
    train_source: str | None = None
    train_root: str | None = None
    frame_range: tuple[int, ...] | None = None  # [first, last] frame ids kept (Nordland)
    seasons: tuple[str, ...] = ("spring", "summer", "fall")
    n_frames: int = 3600  # synthetic only: route length in frames per season
    frame_step: int = 1  # keep every step-th frame (10 on the full route gives ~3,577)
    # Nordland sources: file of frame names / ranges to keep, or a built-in list's name
    # (nordland_clean: the published clean list, vpr_jax/data/lists/)
    frame_list: str | None = None
    cache_dir: str = "~/.cache/vpr_jax"  # decoded videos are cached here as .npz
    # Places where a season shows a constant frame (tunnel, over-exposure) are always
    # counted in the run log; true drops them from every season before the split.
    drop_constant_frames: bool = False
    constant_std: float = 0.01  # a frame whose pixel std (grey in [0, 1]) is <= this is constant
    max_pixels: int = MAX_PIXELS  # larger images (read from their headers) are refused

    def __post_init__(self):
        _check(
            self.source in SOURCES,
            f"data.source={self.source} is unknown: use one of {', '.join(SOURCES)}",
        )
        _check(
            len(self.seasons) >= 2,
            "data.seasons needs at least two seasons, e.g. data.seasons=[summer,fall]",
        )
        _check(
            len(set(self.seasons)) == len(self.seasons),
            f"data.seasons={list(self.seasons)} repeats a season: name each once",
        )
        _check(self.n_frames >= 2, f"data.n_frames={self.n_frames} is too small: use >= 2")
        _check(self.frame_step >= 1, f"data.frame_step={self.frame_step} must be >= 1")
        _check(self.max_pixels >= 1, f"data.max_pixels={self.max_pixels} must be >= 1")
        _check(
            0 <= self.constant_std < 0.5,
            f"data.constant_std={self.constant_std} is not "
            "a pixel standard deviation in [0, 0.5): use e.g. 0.01",
        )
        _check(
            self.source == "synthetic" or self.root is not None,
            f"data.source={self.source} needs data.root=PATH (the folder with the seasons)",
        )
        _check(
            self.radius_m > 0,
            f"data.radius_m={self.radius_m} must be positive: a "
            "database image within that many metres of a query is correct, e.g. 25",
        )
        self._check_frames()
        if self.train_source is not None:
            self._check_train_source()

    def _check_frames(self) -> None:
        """frame_range and frame_list: Nordland sources only, a range is [first, last]."""
        if self.frame_range is not None:
            _check(
                len(self.frame_range) == 2 and self.frame_range[0] <= self.frame_range[1],
                f"data.frame_range={list(self.frame_range)} is not [first, last]: e.g. "
                "data.frame_range=[202,35582]",
            )
        framed = (*NORDLAND_SOURCES, "nordland_star")
        for key in ("frame_list", "frame_range"):
            _check(
                self.source in framed or getattr(self, key) is None,
                f"data.{key} applies to Nordland sources only: drop it for "
                f"data.source={self.source}",
            )

    def _check_train_source(self) -> None:
        """A benchmark's aligned training route: a route source, its root, two seasons."""
        _check(
            self.source in BENCHMARK_SOURCES,
            f"data.train_source applies to "
            f"benchmarks ({', '.join(BENCHMARK_SOURCES)}): data.source={self.source} "
            "trains on its own route; drop data.train_source",
        )
        _check(
            self.train_source in ROUTE_SOURCES,
            f"data.train_source={self.train_source} "
            f"is not an aligned route: use one of {', '.join(ROUTE_SOURCES)}",
        )
        _check(
            self.train_source == "synthetic" or self.train_root is not None,
            f"data.train_source={self.train_source} needs data.train_root=PATH",
        )
        _check(
            len(self.seasons) == 2,
            f"data.train_source reads the two seasons to learn "
            f"from, data.seasons={list(self.seasons)}: name two, e.g. "
            "data.seasons=[summer,winter]",
        )

    @property
    def aligned_training(self) -> bool:
        """Whether the encoders fit on aligned places of two seasons."""
        return self.source in ROUTE_SOURCES or self.train_source is not None


@dataclass(frozen=True)
class SplitConfig:
    """Training and test places: disjoint stretches of the route, ``gap`` frames apart.

    Counts (the paper's protocol): the first ``n_train`` frames train, the next ``n_test``
    after the gap test. Setting ``train_fraction`` switches to fractions: that share of the
    route trains and everything after the gap tests. Setting ``test_sections`` switches to
    Olid et al.'s partition of the whole route: that many test sections of ``n_test``
    frames, evenly spread, and every frame more than ``gap`` frames from all of them trains.
    """

    n_train: int = 2500  # training images per season (the pair contributes 2 x n_train)
    n_test: int = 450  # test images per season (with test_sections: per section)
    train_fraction: float | None = None  # e.g. 0.5; overrides n_train/n_test when set
    gap: int = 100  # original frame indices between training and test frames
    test_sections: int = 0  # > 0: Olid-style sections (n_train and train_fraction unused)
    database: str = "test"  # test: the database is the test places; all: every frame loaded
    val_fraction: float = 0.1  # end of the training stretch that validates (after a gap)
    # Fit every method on this many of the training stretch's places, spread evenly over
    # it (validation and test places unchanged); a list: a learning curve, each value its
    # own rows, never chosen among. None: every training place.
    train_places: tuple[int, ...] | None = None

    def __post_init__(self):
        _check(self.n_train >= 1, f"split.n_train={self.n_train} must be >= 1")
        places = list(self.train_places or ())
        _check(
            self.train_places is None or (places and min(places) >= 2),
            f"split.train_places={places} needs counts of at least 2 places, e.g. "
            "split.train_places=[100,200,400]",
        )
        _check(self.n_test >= 1, f"split.n_test={self.n_test} must be >= 1")
        _check(self.gap >= 0, f"split.gap={self.gap} must be >= 0")
        _check(
            self.train_fraction is None or 0 < self.train_fraction < 1,
            f"split.train_fraction={self.train_fraction} must lie strictly between 0 and 1",
        )
        _check(self.test_sections >= 0, f"split.test_sections={self.test_sections} must be >= 0")
        _check(
            0 < self.val_fraction < 0.5,
            f"split.val_fraction={self.val_fraction} must lie strictly between 0 and 0.5",
        )
        _check(
            self.database in ("test", "all"),
            f"split.database={self.database} is unknown: use test or all",
        )


@dataclass(frozen=True)
class TrainConfig:
    """Auto-encoder training (FAE and CAE), per season pair on its training images."""

    epochs: int = 30  # at most; early stopping may end sooner
    batch_size: int = 64
    learning_rate: float = 1e-3
    optimizer: str = "adam"  # adam | adamw | sgd (optax)
    patience: int = 3  # epochs without a better validation recall@1 before stopping
    # true: the paper's Table 2 (horizontal flip, width/height shift 0.2); false: none; auto:
    # train both and keep the better on the validation places' recall@1; place: no flip,
    # shifts of 0.05 (augmentation that keeps the place: vpr_jax.data.augment.PLACE).
    augment: Any = True
    temperature: float = 0.1  # the contrastive objective's: cosine similarities / this
    # The contrastive objective's: training places within this many positions of a batch's
    # place along the route are not its wrong places (they look alike; 0: every other is).
    contrastive_radius: int = 0
    # Pulls the trained weights towards their starting values (L2-SP): the loss gains
    # start_decay / 2 x the squared distance of every trainable weight from its start, so a
    # model started at a linear solution (fae.init, cae.init) moves from it only where the objective
    # gains more than the distance costs (0: no pull).
    start_decay: float = 0.0
    checkpoint_dir: str = "checkpoints"  # models go to <this>/<logdir name>/<pair>/<method>/
    # An epoch's checkpoint is written once this many seconds passed since the last one (and
    # always for the last epoch): a killed run loses at most about this much training, and
    # fast models (the FAE's epochs take half a second) do not spend their time saving.
    checkpoint_every_s: float = 20.0

    def __post_init__(self):
        _check(self.epochs >= 1, f"train.epochs={self.epochs} must be >= 1")
        _check(self.batch_size >= 1, f"train.batch_size={self.batch_size} must be >= 1")
        _check(self.learning_rate > 0, f"train.learning_rate={self.learning_rate} must be > 0")
        _check(
            self.optimizer in OPTIMIZERS,
            f"train.optimizer={self.optimizer} is unknown: use {', '.join(OPTIMIZERS)}",
        )
        _check(self.patience >= 1, f"train.patience={self.patience} must be >= 1")
        _check(
            any(self.augment is a for a in (True, False)) or self.augment in ("auto", "place"),
            f"train.augment={self.augment} is not true, false, auto or place",
        )
        _check(self.temperature > 0, f"train.temperature={self.temperature} must be > 0")
        _check(
            self.contrastive_radius >= 0,
            f"train.contrastive_radius={self.contrastive_radius} must be >= 0 (0: no mask)",
        )
        _check(self.start_decay >= 0, f"train.start_decay={self.start_decay} must be >= 0")
        _check(
            self.checkpoint_every_s >= 0,
            f"train.checkpoint_every_s={self.checkpoint_every_s} must be >= 0 (0: every epoch)",
        )


@dataclass(frozen=True)
class PatchNormConfig:
    """Patch normalisation: each image's non-overlapping size x size patches are z-scored
    (openSeqSLAM's), then mapped into [0, 1] (see ``vpr_jax.data.preprocess``): with
    ``preprocess=patchnorm`` for every method's training, database and query images, and
    for a method whose ``input`` has the part ``patchnorm``."""

    size: int = 8  # patch side in pixels; must divide the 32x64 images
    rounded: bool = False  # openSeqSLAM's integer variant: grey level 127 + round(z)

    def __post_init__(self):
        h, w = IMAGE_SHAPE
        sizes = [s for s in range(2, h + 1) if h % s == 0 and w % s == 0]
        _check(
            self.size in sizes,
            f"patchnorm.size={self.size} does not tile the {h}x{w} "
            f"images: use one of {', '.join(map(str, sizes))}",
        )


@dataclass(frozen=True)
class GradientsConfig:
    """The ``gradients`` input's histograms of gradient orientations (``<method>.input``;
    ``vpr_jax.encoders.gradients``), for every method that sees them."""

    cell: int = 4  # pixels per cell side
    bins: int = 9  # unsigned orientation bins over 0-180 degrees
    # cells per block side; blocks overlap by all but one cell. 3 and L2: chosen on the
    # Nordland dev frames' tuning half by validation recall@1 (docs/methods.md, inputs)
    block: int = 3
    norm: str = "L2"  # each block's normalisation: L1 | L1-sqrt | L2 | L2-Hys

    def __post_init__(self):
        h, w = IMAGE_SHAPE
        _check(
            self.cell >= 1 and h // self.cell >= max(self.block, 1),
            f"gradients.cell={self.cell} leaves fewer than gradients.block={self.block} cells "
            f"across the {h}x{w} images: use a cell of at most {h // max(self.block, 1)} pixels",
        )
        _check(self.bins >= 2, f"gradients.bins={self.bins} must be at least 2")
        _check(self.block >= 1, f"gradients.block={self.block} must be at least 1")
        _check(
            self.norm in GRADIENT_NORMS,
            f"gradients.norm={self.norm} is unknown: use one of {', '.join(GRADIENT_NORMS)}",
        )


@dataclass(frozen=True)
class BootstrapConfig:
    """95% intervals of each cell's recall@1 and AUC-PR (``vpr_jax.evaluation.bootstrap``)."""

    resamples: int = 1000  # block-bootstrap resamples of the queries (seeded by ``seed``)
    block_length: int = 10  # consecutive queries per block (at least ds for sequences)

    def __post_init__(self):
        _check(self.resamples >= 10, f"bootstrap.resamples={self.resamples} must be >= 10")
        _check(self.block_length >= 1, f"bootstrap.block_length={self.block_length} must be >= 1")


@dataclass(frozen=True)
class SequenceConfig:
    """Sequence matching (``vpr_jax.evaluation.sequence``, SeqSLAM) on top of every method's
    descriptors; ``ds`` is a sweep axis, ds = 1 being single-image matching."""

    enabled: bool = False
    ds: tuple[int, ...] = (1, 10)  # sequence lengths in frames
    contrast_window: int = 10  # R: database frames per local contrast window; 0: none
    v_min: float = 0.8  # trajectory velocities: database frames per query frame
    v_max: float = 1.2
    v_step: float = 0.1
    uniqueness_window: int = 10  # the runner-up is the best match beyond +-window/2 frames

    def __post_init__(self):
        _check(len(self.ds) > 0, "sequence.ds is empty: e.g. sequence.ds=[1,10]")
        _check(
            min(self.ds) >= 1,
            f"sequence.ds={list(self.ds)} has lengths below 1: a "
            "sequence holds at least one image (ds=1 is single-image matching)",
        )
        _check(
            self.contrast_window >= 0,
            f"sequence.contrast_window={self.contrast_window} "
            "must be >= 0 (0: no contrast enhancement)",
        )
        _check(
            self.uniqueness_window >= 0,
            f"sequence.uniqueness_window={self.uniqueness_window} must be >= 0",
        )
        _check(
            0 < self.v_min <= self.v_max and self.v_step > 0,
            f"sequence velocities v_min={self.v_min}, v_max={self.v_max}, "
            f"v_step={self.v_step} need 0 < v_min <= v_max and v_step > 0, e.g. 0.8, "
            "1.2, 0.1",
        )
        n = (self.v_max - self.v_min) / self.v_step + 1
        _check(
            n <= 101,
            f"sequence velocities from {self.v_min} to {self.v_max} in steps "
            f"of {self.v_step} are {int(n)} trajectories per frame: use a larger v_step",
        )


@dataclass(frozen=True)
class TensorBoardConfig:
    n_match_examples: int = 6  # query | best match | true match rows per run
    n_basis_images: int = 8  # removed PCs / independent components shown as 32x64 images
    pr_thresholds: int = 201  # points of the TensorBoard PR curve

    def __post_init__(self):
        _check(self.pr_thresholds >= 2, "tb.pr_thresholds must be >= 2")


@dataclass(frozen=True)
class SweepKnobs:
    """The sweep's own knobs; ``SweepConfig`` adds each built-in method's settings."""

    preset: str = "quick"  # quick | paper | ...: a file under experiments/configs/
    season_pairs: str = "all"  # all, or db-query pairs: summer-fall,spring-fall
    # built-in names (vpr_jax.method_table) and your own as module:name
    methods: tuple[str, ...] = method_table.NAMES
    # Handed to every method with a setting of this name (pca, ica, diff_pca) as a list.
    removed_pcs: tuple[int, ...] = (0, 5, 10, 20, 50, 100)
    # results.md's paired differences are to this method's selected rows (any entry of
    # methods or an outside set; without it in the sweep: the first outside set, or none).
    baseline: str = "pca"
    tolerance: int = 2  # a match is correct when |query frame - db frame| <= tolerance
    pr_convention: str = "vpr_bench"  # vpr_bench | has_match | vpr_tutorial: PR recall
    preprocess: str = "none"  # none | patchnorm: applied to every image before any method
    seed: int = 0  # the built-in route, the split, the bootstrap, and the fits' seed
    # Fits of the methods that draw random numbers (ica, fae, cae, a user's), once per seed;
    # the data never change with them. None: one fit, of ``seed``.
    seeds: tuple[int, ...] | None = None
    logdir: str | None = None  # default runs/<preset> (preset=real: runs/real_<data.source>)
    # XLA's compiled programs are kept here between runs (vpr_jax.compile_cache); None: off
    compile_cache: str | None = "~/.cache/vpr_jax/xla"
    data: DataConfig = field(default_factory=DataConfig)
    split: SplitConfig = field(default_factory=SplitConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    matching: MatchingConfig = field(default_factory=MatchingConfig)
    patchnorm: PatchNormConfig = field(default_factory=PatchNormConfig)
    gradients: GradientsConfig = field(default_factory=GradientsConfig)
    sequence: SequenceConfig = field(default_factory=SequenceConfig)
    bootstrap: BootstrapConfig = field(default_factory=BootstrapConfig)
    mesh: MeshConfig = field(default_factory=MeshConfig)
    cluster: ClusterConfig = field(default_factory=ClusterConfig)
    tb: TensorBoardConfig = field(default_factory=TensorBoardConfig)
    # Settings of your own methods: plugin.<name>.<key>=<value> reaches its fit as key=value.
    plugin: dict[str, dict[str, Any]] = field(default_factory=dict)
    # Descriptors computed elsewhere, per set: precomputed.<name>.database=PATH and
    # .queries=PATH (or precomputed.database / .queries / .name for one set); benchmarks only.
    precomputed: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        problem = method_table.check_methods(self.methods)
        _check(problem is None, problem or "")
        plugins = [method_table.plugin_name(m) for m in self.methods if method_table.is_plugin(m)]
        for name in self.plugin:
            _check(
                name in plugins,
                f"plugin.{name}.* is set but methods names no method {name} (as "
                f"module:{name}): add it to methods=[...] or drop the setting",
            )
        self._check_precomputed()
        negative = [k for k in self.removed_pcs if k < 0]
        _check(
            not negative,
            f"removed_pcs={list(self.removed_pcs)} has negative counts {negative}: use counts >= 0",
        )
        _check(len(self.removed_pcs) > 0, "removed_pcs is empty: e.g. removed_pcs=[0,50]")
        _check(self.tolerance >= 0, f"tolerance={self.tolerance} must be >= 0")
        _check(
            self.pr_convention in PR_CONVENTIONS,
            f"pr_convention={self.pr_convention} is "
            f"unknown: use one of {', '.join(PR_CONVENTIONS)}",
        )
        _check(
            self.preprocess in PREPROCESSES,
            f"preprocess={self.preprocess} is unknown: use one of {', '.join(PREPROCESSES)}",
        )
        seeds = self.seeds or ()
        _check(
            self.seeds is None or (len(seeds) > 0 and len(set(seeds)) == len(seeds)),
            f"seeds={list(seeds)} is empty or repeats a seed: name each once, e.g. seeds=[0,1,2]",
        )
        _check(
            self.cluster.address is None or not self.mesh.distributed,
            "cluster.address and mesh.distributed=true are two ways to use several machines: "
            "fits over a Ray cluster (cluster.address) or one cell over every host "
            "(mesh.distributed), not both; drop one (docs/scaling.md)",
        )

    def _check_precomputed(self) -> None:
        """``precomputed.*`` names sets only on a benchmark; ``methods=[precomputed]`` (the
        entry that stands for them) needs a set."""
        sets = precomputed_sets(self.precomputed)
        asked = method_table.PRECOMPUTED in self.methods
        _check(
            bool(sets) or not asked,
            "methods names precomputed but no descriptors are given: set "
            "precomputed.database=PATH and precomputed.queries=PATH (.npy files)",
        )
        methods = tuple(m for m in self.methods if m != method_table.PRECOMPUTED)
        _check(bool(methods) or bool(sets), "methods is empty: e.g. methods=[raw,pca]")
        problem = method_table.check_precomputed(tuple(sets), methods)
        _check(problem is None, problem or "")
        _check(
            not sets or self.data.source in BENCHMARK_SOURCES,
            f"precomputed descriptors are scored on benchmark sources "
            f"({', '.join(BENCHMARK_SOURCES)}), data.source={self.data.source} is an aligned "
            "route: arrange its frames as a vpr_bench folder (ref/, query/, "
            "ground_truth_new.npy) to score outside descriptors on them",
        )

    @property
    def sequence_lengths(self) -> tuple[int, ...]:
        """The ds axis of the sweep: (1,) unless sequence matching is enabled."""
        return self.sequence.ds if self.sequence.enabled else (1,)

    @property
    def fit_seeds(self) -> tuple[int, ...]:
        """The seeds a method that draws random numbers is fitted with."""
        return self.seeds or (self.seed,)


# Each built-in method's settings, ``<name>.<key>=<value>``: checked by the method's own
# ``Settings`` (``experiments.resolve``); a list given for one is a sweep axis.
SweepConfig = dataclasses.make_dataclass(
    "SweepConfig",
    [(m.name, dict[str, Any], field(default_factory=dict)) for m in method_table.BUILTIN],
    bases=(SweepKnobs,),
    frozen=True,
)
SweepConfig.__doc__ = """``python -m experiments.sweep [key=value ...]``: the sweep's own
knobs (``SweepKnobs``) and, under each built-in method's name, its settings as given
(docs/config.md lists every key)."""


def precomputed_sets(value: dict) -> dict[str, dict[str, str]]:
    """``precomputed.*`` settings as {set name: {"database": path, "queries": path}}, the
    paths absolute. One set may be written flat (``precomputed.database``, ``.queries``,
    ``.name``; named ``precomputed`` by default), several as ``precomputed.<name>.*``."""
    value = dict(value or {})
    flat = {k: value.pop(k) for k in ("database", "queries", "name") if k in value}
    _check(
        not (flat and value),
        f"precomputed.{next(iter(flat), '')} and precomputed.{next(iter(value), '')}.* "
        "cannot be mixed: write every set as precomputed.<name>.database=PATH and "
        "precomputed.<name>.queries=PATH",
    )
    if flat:
        value = {str(flat.pop("name", "precomputed")): flat}
    sets = {}
    for name, paths in value.items():
        form = f"write precomputed.{name}.database=PATH and precomputed.{name}.queries=PATH"
        _check(isinstance(paths, dict), f"precomputed.{name}={paths!r} is not a set: {form}")
        missing = [s for s in ("database", "queries") if not paths.get(s)]
        extra = sorted(set(paths) - {"database", "queries"})
        _check(not missing, f"precomputed set {name!r} has no {' or '.join(missing)}: {form}")
        _check(not extra, f"precomputed.{name}.{extra[0] if extra else ''} is unknown: {form}")
        sets[str(name)] = {s: str(Path(str(paths[s])).expanduser().resolve()) for s in paths}
    return sets


def normalised(cfg: SweepConfig) -> SweepConfig:
    """The config as the sweep reads it, made where OmegaConf hands it over: counts sorted
    and each once, outside sets by name with absolute paths, ``methods`` without the
    ``precomputed`` entry (it stands for the sets), the default logdir named: the preset's
    name, then the data source where it is not the preset's own (a preset that names none:
    the built-in route), so runs of one preset on two sources do not meet in one folder."""
    own = None if cfg.preset in presets.SOURCE_FREE else presets.source(cfg.preset) or "synthetic"
    source = "" if cfg.data.source == own else f"_{cfg.data.source}"
    return dataclasses.replace(
        cfg,
        removed_pcs=tuple(sorted(set(cfg.removed_pcs))),
        sequence=dataclasses.replace(cfg.sequence, ds=tuple(sorted(set(cfg.sequence.ds)))),
        precomputed=precomputed_sets(cfg.precomputed),
        methods=tuple(m for m in cfg.methods if m != method_table.PRECOMPUTED),
        logdir=cfg.logdir or f"runs/{cfg.preset}{source}",
    )


def training_identity(settings: TrainConfig) -> dict:
    """The training settings that determine a trained model's weights (not where or how often
    it is saved)."""
    return {
        k: v for k, v in plain(dataclasses.asdict(settings)).items() if k not in TRAIN_BOOKKEEPING
    }


def to_dict(cfg: SweepConfig) -> dict:
    """The config as plain YAML data (tuples become lists, as after a YAML round trip)."""
    return plain(dataclasses.asdict(cfg))


def plain(value: Any) -> Any:
    """Tuples to lists, recursively: the form a value takes after a YAML or JSON round trip,
    so a saved config or checkpoint metadata compares equal to the one in memory."""
    if isinstance(value, dict):
        return {k: plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [plain(v) for v in value]
    return value
