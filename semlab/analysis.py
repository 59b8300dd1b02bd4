"""One analysis of one experiment: every step computed once, cached, its result files written.

:class:`Analysis` is what ``semlab run`` executes and what the notebooks call::

    experiment.toml ─► Analysis(experiment, out_dir, config)
        .stereo()    ─► points3d.csv, calibration.json
        .heightmap() ─► heightmap.tif/_sigma.tif/.x3p/.gsf/.ply, surface_parameters.csv,
                        bands.csv                       (seeded by .stereo();
                                                         .map_metrology() has the CSVs' numbers)
        .tracking()  ─► tracks.csv, displacements.csv   (seeded by .stereo())
        .strain()    ─► strain.npz                      (from .tracking())

Each step is a function of the experiment's input files, of the fields of the frozen
:class:`AnalysisConfig` it depends on and of semlab's own code. Its result is kept in
``out_dir/.semlab/cache`` under a key made of exactly these, so a step runs once per
experiment and configuration: ``semlab run`` computes, the notebooks it then executes load the
cached results, and an interactive re-run after a change recomputes only the steps whose
inputs changed. Result files are written once, when the step is computed, through a temporary
name, so a step that fails leaves no partial file. A failed step is cached too (its message),
so every notebook reports the same error without computing it again.

Without ``out_dir`` no result file is written and the cache lives in the user's cache folder
(``$XDG_CACHE_HOME/semlab`` or ``~/.cache/semlab``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import pickle
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

from ._api import check_keywords
from .errors import SemlabError

__all__ = ["AnalysisConfig", "Analysis", "StepFailed", "STEPS"]

#: The steps of an analysis, in the order :meth:`Analysis.run` executes them.
STEPS = ("stereo", "heightmap", "tracking", "strain")
STEP_FILES = {"stereo": ("points3d.csv", "calibration.json"),
              "heightmap": ("heightmap.tif", "heightmap_sigma.tif", "heightmap.x3p",
                            "heightmap.gsf", "heightmap.ply", "surface_parameters.csv",
                            "bands.csv"),
              "tracking": ("tracks.csv", "displacements.csv"),
              "strain": ("strain.npz",)}
STEREO_METHODS = (None, "raw", "refined", "auto", "merged")
TRACK_METHODS = ("lk", "subset")
MAP_PRIORS = ("isotropic", "band")
DENSE_STRAIN_METHODS = ("variational", "subsets")


class StepFailed(SemlabError):
    """A step of the analysis could not produce its result (the message says why)."""


@dataclass(frozen=True)
class AnalysisConfig:
    """Every setting of an analysis, recorded with its results (``calibration.json`` and
    ``.semlab/config.json``).

    Attributes
    ----------
    stereo_method : {None, "raw", "refined", "auto", "merged"}
        Correspondences for the heights; None: ``merged`` when the experiment has clicked
        correspondences, else ``auto``.
    n_boot : int
        Bootstrap resamples of the height error bars (0: matching σ only).
    seed : int
        Seed of the bootstrap.
    stereo_target_sigma_px : float or None
        The predicted 1σ (pixels) that each refined click's subset is sized to reach
        (``refine_correspondences(target_sigma_px=...)``, :func:`semlab.adaptive.adaptive_icgn`;
        default 0.05, issue #13); None (``--set stereo_target_sigma_px=none``): fixed 21×21
        subsets. Until 2026-12-04 it sized the automatic grid too.
    stereo_grid_target_sigma_px : float or None
        The same for the automatic grid and the tilt matches (``auto_match``); default None:
        fixed 21×21 subsets, whose matches stage 9 averages with the variational map (see
        :class:`semlab.matching.AutoMatchParams`, ``target_sigma_px``, for why); e.g.
        ``--set stereo_grid_target_sigma_px=0.05`` sizes them as from 2026-12-03 to 12-04.
    track_method : {"subset", "lk"}
        IC-GN subsets (default) or pyramidal Lucas–Kanade for the tracking steps. On the
        8-frame polished / real:fei / real:quartz series of
        ``benchmarks/tracking_series.py`` LK (the default before 2026-12-02) lost every
        track of the polished one at the first step and gave no strain on quartz (21 % of
        52 corner tracks valid one step back); the sized subsets keep 55 / 63 / 88 % there,
        with strain from frames 4 / 0 / 0.
    track_target_sigma_px : float, None or "auto"
        With ``track_method="subset"``: size each step's subset by its information and the
        displacement's curvature (``track_reverse(target_sigma_px=...)``, pixels; the
        tracking then also seeds a grid where the texture allows valid steps, see
        :func:`semlab.series.run_tracking`); None: fixed 21×21 subsets, corner seeds.
        ``"auto"`` (default): 0.02 with subsets, None with LK (``"none"``, e.g. from
        ``--set track_target_sigma_px=none``, is None).
    gauge_length_px : float or None
        Gauge length of the sparse strain (None: from the track density).
    heightmap : bool
        Compute the dense height map (every pixel of view 0: minutes on megapixel views);
        False leaves the height-map files out.
    heightmap_roi : (x0, y0, x1, y1) or None
        Map only this half-open window of view-0 pixels (None: the whole view). Maps of
        more than ``semlab.tiled_stereo.DEFAULT_TILING.map_min_pixels`` pixels (or of views
        of more than its ``min_pixels``) are mapped in tiles either way.
    heightmap_method : {"variational", "subset"}
        The dense map's parallax: the variational refinement (:mod:`semlab.variational`,
        default since 2026-12-05) or an IC-GN subset at every pixel (the default before).
        Why (``benchmarks/dense_map.py``, 2026-12-05, README "Dense height map"): on weakly
        textured surfaces the subset map measures 25–72 % of the pixels, at 1.3–1.9×
        DeepFlow's height error on them, where the variational map measures every pixel at
        0.77–0.86×; on speckle the two are alike (0.60–0.79× against 0.54–0.79×).
    map_prior : {"band", "isotropic"}
        The prior of every variational parallax map (the height map's and those stage 9 of
        the automatic matching averages with its subset matches): ``"band"`` (default since
        2026-12-06) pools the data along the local direction of straight slip bands
        (``VariationalParams()``, :class:`semlab.variational.VariationalParams`:
        0.33–0.66× DeepFlow's height error on the 16 textured two-view cells of the accuracy
        matrix where the isotropic prior gives 0.69–1.00×, at ~2.5× the map's time; README,
        "Accuracy and speed"); ``"isotropic"`` smooths alike in every direction (the
        default before; ``VariationalParams(**semlab.variational.ISOTROPIC)``).
    dense_strain_method : {"variational", "subsets"}
        The dense strain's displacement (``strain_from_tracks(dense_method=...)``): the
        variational map of :func:`semlab.flow.variational_flow` (default; every pixel, with the
        strain's 1σ ``E_sigma``, solved in tiles on large frames) or a grid of IC-GN subsets
        (faster on large frames, no ``E_sigma``; 1.4–2.8× less accurate on the four slip-band
        series of ``benchmarks/dense_strain_bands.py``).
    """

    stereo_method: str | None = None
    n_boot: int = 200
    seed: int = 0
    stereo_target_sigma_px: float | str | None = 0.05
    stereo_grid_target_sigma_px: float | str | None = None
    track_method: str = "subset"
    track_target_sigma_px: float | str | None = "auto"
    gauge_length_px: float | None = None
    heightmap: bool = True
    heightmap_roi: tuple | None = None
    heightmap_method: str = "variational"
    map_prior: str = "band"
    dense_strain_method: str = "variational"

    def __post_init__(self):
        if self.heightmap_roi is not None:
            r = self.heightmap_roi
            try:
                ok = (len(r) == 4 and all(int(v) == v for v in r) and r[0] < r[2]
                      and r[1] < r[3] and min(r) >= 0)
            except (TypeError, ValueError):
                ok = False
            if not ok:
                raise SemlabError(f"heightmap_roi = {r!r}: give [x0, y0, x1, y1], whole view-0 "
                                  "pixels with x0 < x1 and y0 < y1 (half-open), or None")
            object.__setattr__(self, "heightmap_roi", tuple(int(v) for v in r))
        if self.stereo_method not in STEREO_METHODS:
            raise SemlabError(f"stereo_method = {self.stereo_method!r}: use one of "
                              "raw, refined, auto, merged (or None)")
        if self.track_method not in TRACK_METHODS:
            raise SemlabError(f"track_method = {self.track_method!r}: use 'lk' or 'subset'")
        for key, t in (("stereo_target_sigma_px", self.stereo_target),
                       ("stereo_grid_target_sigma_px", self.stereo_grid_target)):
            if t is not None and not (isinstance(t, (int, float)) and not isinstance(t, bool)
                                      and math.isfinite(t) and t > 0):
                raise SemlabError(f"{key} = {t!r}: give a target > 0 pixels, "
                                  "or None (fixed 21×21 subsets)")
        t = self.track_target
        if t is not None and not (self.track_method == "subset" and isinstance(t, (int, float))
                                  and not isinstance(t, bool) and t > 0):
            raise SemlabError(f"track_target_sigma_px = {t!r}: give a target > 0 pixels with "
                              "track_method = 'subset', or None")
        if int(self.n_boot) != self.n_boot or self.n_boot < 0:
            raise SemlabError(f"n_boot = {self.n_boot!r}: give a whole number >= 0")
        if self.heightmap_method not in ("subset", "variational"):
            raise SemlabError(f"heightmap_method = {self.heightmap_method!r}: use 'subset' or "
                              "'variational'")
        if self.map_prior not in MAP_PRIORS:
            raise SemlabError(f"map_prior = {self.map_prior!r}: use 'isotropic' or 'band'")
        if self.dense_strain_method not in DENSE_STRAIN_METHODS:
            raise SemlabError(f"dense_strain_method = {self.dense_strain_method!r}: use "
                              "'variational' or 'subsets'")
        if not isinstance(self.heightmap, bool):
            raise SemlabError(f"heightmap = {self.heightmap!r}: give true or false")
        if self.gauge_length_px is not None and not self.gauge_length_px > 0:
            raise SemlabError(f"gauge_length_px = {self.gauge_length_px!r}: give a length > 0 "
                              "in pixels, or None")

    def variational_params(self):
        """The :class:`semlab.variational.VariationalParams` of ``map_prior``."""
        from .variational import ISOTROPIC, VariationalParams

        if self.map_prior == "isotropic":
            return VariationalParams(**ISOTROPIC)
        return VariationalParams()

    @property
    def stereo_target(self):
        """``stereo_target_sigma_px`` with ``"none"`` (from ``--set``) as None."""
        return _none_word(self.stereo_target_sigma_px)

    @property
    def stereo_grid_target(self):
        """``stereo_grid_target_sigma_px`` with ``"none"`` as None."""
        return _none_word(self.stereo_grid_target_sigma_px)

    @property
    def track_target(self):
        """``track_target_sigma_px`` with ``"auto"`` resolved (0.02 px with subsets, None
        with LK)."""
        t = _none_word(self.track_target_sigma_px)   # `--set ...=none`: fixed subsets
        if isinstance(t, str):
            if t != "auto":
                raise SemlabError(f"track_target_sigma_px = {t!r}: give a target > 0 pixels, "
                                  "'auto' or None")
            return 0.02 if self.track_method == "subset" else None
        return t

    @classmethod
    def fields(cls):
        """Names of the settings."""
        return [f.name for f in dataclasses.fields(cls)]

    @classmethod
    def from_dict(cls, d):
        """A configuration from a dict; unknown keys raise ``TypeError`` naming the nearest."""
        d = dict(d or {})
        check_keywords(cls.__name__, d, cls.fields())
        return cls(**d)

    def replace(self, **changes):
        """A copy with ``changes``; unknown names raise ``TypeError`` naming the nearest."""
        check_keywords(f"{type(self).__name__}.replace", changes, self.fields())
        return dataclasses.replace(self, **changes)

    def as_dict(self):
        d = dataclasses.asdict(self)
        if d["heightmap_roi"] is not None:       # JSON / notebook parameters: a list
            d["heightmap_roi"] = list(d["heightmap_roi"])
        return d

    def for_step(self, step):
        """The settings ``step`` depends on (with those of the steps it uses)."""
        own = {"stereo": ("stereo_method", "n_boot", "seed", "stereo_target",
                           "stereo_grid_target", "map_prior"),
               "heightmap": ("heightmap_roi", "heightmap_method"),
               "tracking": ("track_method", "track_target"),
               "strain": ("gauge_length_px", "dense_strain_method")}
        needs = {"stereo": ("stereo",), "heightmap": ("stereo", "heightmap"),
                 "tracking": ("stereo", "tracking"),
                 "strain": ("stereo", "tracking", "strain")}
        return {k: getattr(self, k) for s in needs[step] for k in own[s]}


def _none_word(value):
    """None for the word "none" (any case: a `--set KEY=none` value, not TOML), else ``value``."""
    return None if isinstance(value, str) and value.lower() == "none" else value


# ------------------------------------------------------------------------------ fingerprints
def _file_sha256(path, memo):
    """SHA-256 of a file's bytes; ``memo`` maps its path, size and mtime to a hash computed
    before, so that the notebooks of a run do not read every frame again."""
    st = os.stat(path)
    tag = f"{Path(path).resolve()}|{st.st_size}|{st.st_mtime_ns}"
    if tag not in memo:
        h = hashlib.sha256()
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
        memo[tag] = h.hexdigest()
    return memo[tag]


def experiment_fingerprint(exp):
    """SHA-256 of the experiment's TOML and every input file it names (views, frames,
    correspondences, lines), in order; the ``truth/`` folder is not an input. File hashes
    are remembered by path, size and mtime in the user's cache folder (``file_hashes.json``)."""
    paths = [exp.toml_path]
    if exp.stereo is not None:
        paths += list(exp.stereo.view_paths)
        paths += [p for p in (exp.stereo.correspondences_path, exp.stereo.lines_path) if p]
        if isinstance(exp.stereo.reference_region, Path):
            paths.append(exp.stereo.reference_region)
    paths += [p for p in exp.metrology_regions.values() if isinstance(p, Path)]
    if exp.series is not None:
        paths += list(exp.series.frame_paths)
    memo_path = _user_cache_dir() / "file_hashes.json"
    try:
        memo = json.loads(memo_path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        memo = {}
    known = len(memo)
    h = hashlib.sha256()
    for p in paths:
        h.update(str(Path(p).name).encode())
        h.update(_file_sha256(p, memo).encode())
    if len(memo) != known:
        memo = prune_hash_memo(memo)
        try:  # a cache that cannot be written only costs the hashing next time
            memo_path.parent.mkdir(parents=True, exist_ok=True)
            tmp = memo_path.with_name(f"{memo_path.name}.{os.getpid()}.tmp")
            tmp.write_text(json.dumps(memo), encoding="utf-8")
            os.replace(tmp, memo_path)
        except OSError:
            pass
    return h.hexdigest()


#: At most this many file hashes are remembered (newest kept).
MAX_HASH_MEMO = 20000


def prune_hash_memo(memo, max_entries=MAX_HASH_MEMO):
    """Drop the remembered hashes of files that are gone or changed, keep the newest.

    Parameters
    ----------
    memo : dict
        ``"path|size|mtime_ns" -> sha256`` in insertion order (oldest first), as kept in
        ``file_hashes.json``.
    max_entries : int
        How many entries to keep at most.

    Returns
    -------
    dict
        The entries whose file still exists with that size and mtime, the newest
        ``max_entries`` of them.
    """
    kept = {}
    for tag, digest in memo.items():
        path, _, rest = tag.rpartition("|")
        path, _, size = path.rpartition("|")
        try:
            st = os.stat(path)
        except OSError:
            continue
        if f"{st.st_size}|{st.st_mtime_ns}" == f"{size}|{rest}":
            kept[tag] = digest
    return dict(list(kept.items())[-max_entries:]) if max_entries > 0 else {}


def code_fingerprint():
    """SHA-256 of semlab's own source files (a change of the code invalidates the cache)."""
    h = hashlib.sha256()
    for p in sorted(Path(__file__).resolve().parent.glob("*.py")):
        h.update(p.name.encode())
        h.update(p.read_bytes())
    return h.hexdigest()


def _peak_rss_gb():
    """This process's peak resident set so far, GB (``getrusage``), or None where the
    system does not give it."""
    try:
        import resource
    except ImportError:          # Windows
        return None
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    scale = 1.0 if sys.platform == "darwin" else 1024.0      # bytes on macOS, kB elsewhere
    return round(peak * scale / 1e9, 3)


def _user_cache_dir():
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "semlab"


# ------------------------------------------------------------------------------ the analysis
class Analysis:
    """Run an experiment's analysis steps once each, cache them and write the result files.

    Parameters
    ----------
    experiment : str, Path or semlab.experiment.Experiment
        The experiment folder, its ``experiment.toml``, or a loaded experiment.
    out_dir : str or Path, optional
        Folder of the result files and of the step cache (``out_dir/.semlab``). None: no
        result files; the cache is kept in the user's cache folder.
    config : AnalysisConfig or dict, optional
        The settings (default: :class:`AnalysisConfig` defaults).
    progress : bool
        Progress bars on long steps.
    cache_dir : str or Path, optional
        Where the step cache lives (default: ``out_dir/.semlab/cache``, or the user's cache
        folder without ``out_dir``). ``semlab run`` writes its result files into a staging
        folder and keeps the cache in the output folder itself.
    scheduler : str, optional
        ``tcp://HOST:PORT`` of a running dask.distributed scheduler: the tiled steps (dense
        IC-GN, tracking) run on that cluster (see :mod:`semlab.parallel`); None: a local
        cluster, or the one ``semlab run --scheduler`` named. Checked when given; it applies to this analysis only (not to
        other analyses in the same kernel).
    **changes
        Settings that replace those of ``config`` (unknown names raise ``TypeError``).

    Attributes
    ----------
    experiment : semlab.experiment.Experiment
    config : AnalysisConfig
    computed : list of str
        Steps computed (not loaded from the cache) by this object, in order.
    warnings : dict
        Step name → the warnings its computation gave (kept in the cache with the result).

    Examples
    --------
    >>> import tempfile, semlab
    >>> from semlab.synth import make_experiment
    >>> tmp = tempfile.mkdtemp()
    >>> exp = make_experiment(tmp + "/exp", seed=3, size=(96, 128), n_frames=3, n_clicks=12,
    ...                       progress=False)
    >>> an = semlab.Analysis(exp, tmp + "/out", n_boot=0, progress=False)
    >>> res = an.stereo()
    >>> sorted(p.name for p in (an.out_dir).glob("*.csv"))
    ['points3d.csv']
    >>> again = semlab.Analysis(exp, tmp + "/out", n_boot=0, progress=False)
    >>> bool((again.stereo().z_um == res.z_um).all()), again.computed
    (True, [])
    """

    def __init__(self, experiment, out_dir=None, config=None, progress=True, cache_dir=None,
                 scheduler=None, **changes):
        from .experiment import Experiment, load

        if scheduler:
            from .parallel import check_scheduler

            check_scheduler(scheduler)  # a wrong address fails here, not mid-run
        self.scheduler = scheduler or None
        self.experiment = experiment if isinstance(experiment, Experiment) else load(experiment)
        if config is None:
            config = AnalysisConfig()
        elif isinstance(config, dict):
            config = AnalysisConfig.from_dict(config)
        self.config = config.replace(**changes) if changes else config
        self.progress = bool(progress)
        self.out_dir = None if out_dir is None else Path(out_dir)
        self._fingerprint = experiment_fingerprint(self.experiment)
        self._code = code_fingerprint()
        if cache_dir is not None:
            self.cache_dir = Path(cache_dir)
        elif self.out_dir is None:
            self.cache_dir = _user_cache_dir() / self._fingerprint[:16]
        else:
            self.cache_dir = self.out_dir / ".semlab" / "cache"
        self._memo = {}
        self.computed = []
        self.warnings = {}

    # -------------------------------------------------------------------------- caching
    def _key(self, step, params):
        blob = json.dumps({"step": step, "experiment": self._fingerprint, "code": self._code,
                           "params": params}, sort_keys=True, default=str)
        return hashlib.sha256(blob.encode()).hexdigest()[:20]

    def _log(self, step, key, event, seconds=0.0):
        if self.out_dir is None:
            return
        log = self.cache_dir.parent / "steps.jsonl"
        log.parent.mkdir(parents=True, exist_ok=True)
        with open(log, "a", encoding="utf-8") as fh:
            fh.write(json.dumps({"step": step, "key": key, "event": event,
                                 "seconds": round(seconds, 3), "pid": os.getpid(),
                                 "peak_rss_gb": _peak_rss_gb()}) + "\n")

    def _cached(self, step, params, compute, write=None):
        """The result of ``step`` for ``params``: from memory, the cache, or ``compute()``;
        ``write(result, folder)`` writes its result files when it is computed."""
        key = self._key(step, params)
        if key in self._memo:
            return self._unwrap(step, self._memo[key])
        path = self.cache_dir / f"{step}-{key}.pkl"
        if path.is_file():
            try:
                with open(path, "rb") as fh:
                    entry = pickle.load(fh)
            except Exception:  # a truncated or foreign cache file: compute again
                entry = None
            if entry is not None:
                self._memo[key] = entry
                self._log(step, key, "cached")
                missing = [f for f in STEP_FILES.get(step, ())
                           if self.out_dir is not None and not (self.out_dir / f).exists()]
                if entry[0] == "ok" and write is not None and missing:
                    self._write_files(step, entry[1], write)  # e.g. deleted by hand
                return self._unwrap(step, entry)
        t0 = time.perf_counter()
        # warnings of a step (e.g. frames where no track is valid) are part of its result:
        # kept with it, shown once by `semlab run` and in the notebooks (Analysis.warnings)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                from .parallel import scheduler_scope

                with scheduler_scope(self.scheduler):  # this analysis' cluster, not the process'
                    entry = ("ok", compute())
            except SemlabError as exc:
                entry = ("failed", str(exc))
        said = list(dict.fromkeys(str(w.message) for w in caught))
        entry = entry + (said,)
        if entry[0] == "ok" and write is not None and self.out_dir is not None:
            self._write_files(step, entry[1], write)
        self.computed.append(step)
        self._log(step, key, "computed" if entry[0] == "ok" else "failed",
                  time.perf_counter() - t0)
        self._store(path, entry)
        self._memo[key] = entry
        return self._unwrap(step, entry)

    def _unwrap(self, step, entry):
        status, value = entry[:2]
        if len(entry) > 2 and entry[2]:
            self.warnings[step] = entry[2]
        if status == "failed":
            raise StepFailed(f"step {step!r} failed: {value}")
        return value

    def _store(self, path, entry):
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + f".{os.getpid()}.tmp")
        with open(tmp, "wb") as fh:
            pickle.dump(entry, fh, protocol=pickle.HIGHEST_PROTOCOL)
        os.replace(tmp, path)

    def _write_files(self, step, result, write):
        """Write the step's files into a staging folder, then move them into ``out_dir``:
        a writer that fails half-way leaves nothing that looks like a result."""
        import shutil
        import tempfile

        self.out_dir.mkdir(parents=True, exist_ok=True)
        stage = Path(tempfile.mkdtemp(prefix=f".{step}-", dir=self.out_dir))
        try:
            written = write(result, stage)
            for p in written:
                os.replace(p, self.out_dir / Path(p).name)
        finally:
            shutil.rmtree(stage, ignore_errors=True)

    # -------------------------------------------------------------------------- the steps
    @property
    def has_stereo(self):
        return self.experiment.stereo is not None

    @property
    def has_series(self):
        return self.experiment.series is not None

    def stereo(self, method=None):
        """Heights of the end-state surface (:class:`semlab.pipeline.StereoResult`).

        Parameters
        ----------
        method : {None, "raw", "refined", "auto", "merged"}
            None: the configured ``stereo_method``. Another method is computed and cached
            as a variant (for comparisons, e.g. notebook 08) and writes no result file.
        """
        from . import pipeline

        exp, cfg = self.experiment, self.config
        if not self.has_stereo:
            raise StepFailed(f"{exp.toml_path}: no [stereo] table, so no heights to compute")
        main = method is None or method == cfg.stereo_method
        m = cfg.stereo_method if main else method
        n_boot = cfg.n_boot if main else 0
        params = dict(cfg.for_step("stereo"), stereo_method=m, n_boot=n_boot)

        def compute():
            res = pipeline.run_stereo(exp, method=m, n_boot=n_boot, seed=cfg.seed,
                                      progress=self.progress, tilt_matches=self.tilt_matches(),
                                      refine_kw={"target_sigma_px": cfg.stereo_target},
                                      auto_kw=self._auto_kw())
            res.calibration["analysis_config"] = cfg.as_dict()
            return res

        return self._cached("stereo" if main else f"stereo_{m}", params, compute,
                            pipeline.write_stereo_results if main else None)

    def tilt_matches(self):
        """Matches for the tilt estimation (3+ views without given tilts), computed once for
        every stereo method; None where the tilts are given or there are two views."""
        from . import pipeline

        st = self.experiment.stereo
        if st is None or st.tilt_deg is not None or len(st.view_paths) < 3:
            return None
        cfg = self.config
        return self._cached("tilt_matches", {"stereo_grid_target": cfg.stereo_grid_target,
                                             "map_prior": cfg.map_prior},
                            lambda: pipeline.match_for_tilts(
                                self.experiment, progress=self.progress,
                                auto_kw=self._auto_kw()))

    def _auto_kw(self):
        """The keywords of ``auto_match`` that the configuration sets."""
        cfg = self.config
        return {"target_sigma_px": cfg.stereo_grid_target,
                "variational_params": cfg.variational_params()}

    def heightmap(self):
        """The dense height map of views 0 and 1 and the bands measured on it.

        Returns
        -------
        (semlab.heightmap.HeightMap, list of semlab.metrology.Band)
            The bands are the clicked cracks (``crack_id``) and the straight traces found in
            the map (:func:`semlab.metrology.map_bands`).
        """
        hm, measured = self._heightmap_step()
        return hm, measured["bands"]

    def map_metrology(self):
        """The metrology of the dense height map, computed once with it (the numbers of
        ``surface_parameters.csv`` and ``bands.csv``; ``[metrology] regions`` included).

        Returns
        -------
        dict
            ``surface_parameters`` (list of dict, one row per region, ``"map"`` first),
            ``bands`` and ``band_profiles`` (:func:`semlab.heightmap.measure_map`).
        """
        return self._heightmap_step()[1]

    def _heightmap_step(self):
        import numpy as np

        from . import heightmap, metrology

        exp = self.experiment
        if not self.has_stereo:
            raise StepFailed(f"{exp.toml_path}: no [stereo] table, so no height map")
        if not self.config.heightmap:
            raise StepFailed("the dense height map is switched off (heightmap = false)")

        def compute():
            res = self._needs("stereo")
            try:
                params = None
                if self.config.heightmap_method == "variational":
                    params = self.config.variational_params()
                hm = heightmap.heightmap_from_stereo(exp, res, params=params,
                                                     progress=self.progress,
                                                     roi=self.config.heightmap_roi)
            except SemlabError as exc:
                if "roi must be" not in str(exc):
                    raise
                raise StepFailed(f"heightmap_roi = {list(self.config.heightmap_roi)}: "
                                 f"outside the views ({exc})") from None
            bands = metrology.map_bands(hm.z_um, exp.pixel_size_um, sigma_um=hm.sigma_um,
                                        pts_px=res.pts[:, 0] - np.asarray(hm.roi[:2], float),
                                        crack_id=res.crack_id)
            regions = metrology.regions_on_map(exp.metrology_regions, hm.roi)
            return hm, heightmap.measure_map(hm, regions=regions, bands=bands)

        def write(result, folder):
            return list(heightmap.write_heightmap_results(result[0], folder,
                                                          measured=result[1]).values())

        return self._cached("heightmap", self.config.for_step("heightmap"), compute, write)

    def tracking(self):
        """Tracks and displacements (:class:`semlab.series.TrackingResult`), seeded by
        Shi–Tomasi corners and by the stereo points when the stereo step succeeds."""
        from . import series

        exp, cfg = self.experiment, self.config
        if not self.has_series:
            raise StepFailed(f"{exp.toml_path}: no [series] table, so nothing to track")

        def compute():
            stereo = None
            if self.has_stereo:
                try:
                    s = self.stereo()
                    stereo = (s.pts[:, 0], s.z_um)
                except StepFailed:
                    stereo = None  # tracking goes on with corner seeds; the stereo step reports
            kw = None if cfg.track_target is None else {
                "target_sigma_px": float(cfg.track_target)}
            return series.run_tracking(exp, stereo=stereo, method=cfg.track_method,
                                         track_kw=kw, progress=self.progress)

        return self._cached("tracking", cfg.for_step("tracking"), compute,
                            series.write_tracking_results)

    def strain(self):
        """Sparse and dense strain (dict, see :func:`semlab.series.run_strain`)."""
        from . import series

        exp, cfg = self.experiment, self.config

        def compute():
            return series.run_strain(exp, self._needs("tracking"),
                                     gauge_length_px=cfg.gauge_length_px,
                                     dense_method=cfg.dense_strain_method, progress=self.progress)

        if not self.has_series:
            raise StepFailed(f"{exp.toml_path}: no [series] table, so no strain")
        return self._cached("strain", cfg.for_step("strain"), compute,
                            series.write_strain_results)

    # -------------------------------------------------------------------------- all of it
    def applicable_steps(self):
        """The steps this experiment has input for."""
        stereo_steps = ("stereo", "heightmap")
        return [s for s in STEPS if ((s in stereo_steps and self.has_stereo)
                                     or (s not in stereo_steps and self.has_series))
                and (s != "heightmap" or self.config.heightmap)]

    def comparison_methods(self):
        """Stereo methods the reports compare with the configured one: the reference method
        (raw clicks) and the refined clicks when the experiment has clicks (notebooks 03, 04,
        08), automatic matching when it has a ``truth/`` folder (notebook 08)."""
        if not self.has_stereo:
            return []
        corr = self.experiment.correspondences()
        methods = ["raw", "refined"] if corr is not None and len(corr.pts) else []
        if self.experiment.truth_dir is not None:
            methods.append("auto")
        return [m for m in methods if m != self.config.stereo_method]

    def _needs(self, step):
        """The result of the step another one builds on; its failure, already named on its
        own, becomes a one-line reason of the dependent step instead of a repeat of it."""
        try:
            return getattr(self, step)()
        except StepFailed:
            raise StepFailed(f"it needs the {step} step, which failed") from None

    def optional(self, step, **kwargs):
        """The result of ``step`` (``"stereo"``, ``"heightmap"``, ``"tracking"``,
        ``"strain"``), or None when the step failed, its error printed.

        For the notebooks: a step that cannot produce its result (every track lost in a
        featureless series, no frame with enough tracks for strain) is one error of that
        step, named by ``semlab run`` in its message and exit status; the other steps' results
        and reports are still written. ``kwargs`` go to the step (e.g. ``method="raw"``).
        """
        check_keywords("Analysis.optional", [step], STEPS)
        try:
            return getattr(self, step)(**kwargs)
        except StepFailed as exc:
            print(exc)
            return None

    def run(self, steps=None):
        """Run ``steps`` (default: every applicable step) and record their status.

        With the stereo step, the comparison methods of :meth:`comparison_methods` run too
        (as ``stereo_<method>``), so the notebooks compute nothing.

        Returns
        -------
        dict
            step name → ``"ok"`` or the error message of a failed step. Also written to
            ``status.json`` with the configuration (``config.json``) beside the cache
            (``out_dir/.semlab/``).
        """
        from tqdm.auto import tqdm

        steps = self.applicable_steps() if steps is None else list(steps)
        check_keywords("Analysis.run", steps, STEPS)
        todo = [(s, None) for s in steps]
        if "stereo" in steps:
            todo += [("stereo", m) for m in self.comparison_methods()]
        status = {}
        for step, method in tqdm(todo, desc="analysis", disable=not self.progress):
            name = step if method is None else f"{step}_{method}"
            try:
                self.stereo(method) if method else getattr(self, step)()
                status[name] = "ok"
            except StepFailed as exc:
                status[name] = str(exc)
        if self.out_dir is not None:
            meta = self.cache_dir.parent
            meta.mkdir(parents=True, exist_ok=True)
            (meta / "config.json").write_text(json.dumps(self.config.as_dict(), indent=1))
            (meta / "status.json").write_text(json.dumps(
                {"status": status, "warnings": self.warnings}, indent=1))
        return status

    def __repr__(self):
        return (f"Analysis({self.experiment.name!r}, out_dir={str(self.out_dir)!r}, "
                f"config={self.config})")
