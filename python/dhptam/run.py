"""``dhptam run``: a sequence through the whole system, with every output written safely.

The work is a four-stage pipeline, so that on a multi-core machine no stage waits for the
others:

1. reading (:meth:`dhptam.frontend.Frontend.read`: decoding the frames, decompressing the event
   windows; the only stage touching the files, and HDF5 holds the GIL) runs on its own thread;
2. the front-end (:meth:`~dhptam.frontend.Frontend.prepare`/``finish``: rectification, E3CT,
   warp, β fusion, kernels that release the GIL) runs on a second thread, behind the reading;
3. feature extraction (torch or OpenCV, both release the GIL) runs on a third thread, one frame
   behind the front-end;
4. tracking runs on the calling thread, while the back-end's mapping and loop-closing threads
   run inside the Rust core.

Outputs (in ``out``): ``trajectory.tum`` (every tracked frame, left rectified frame camera,
seconds), ``keyframes.tum``, ``map.ply``, ``frames.csv`` (per frame: state, inliers, β, fusion
bias, flood and quiet flags, ``hot_pixels`` masked, ``stretched`` frames of the pair (exposure recovered),
bridge, depth ``warp_depth_m`` of the event→frame warp plane, stage times), ``timing.json``
(per stage statistics), ``config.toml`` (resolved) and
``run.log``. Each file is written to a temporary name and renamed, so a reader never sees half
a file; Ctrl-C or a failure mid-run still writes everything done so far.

With ``viz="rerun"`` each tracked frame is also handed to a :class:`dhptam.viz.RerunSink`,
which streams ``recording.rrd`` as the run goes (the no-op :class:`dhptam.viz.VizSink`
otherwise).
"""

from __future__ import annotations

import io
import json
import logging
import os
import signal
import tempfile
import threading
import time
from array import array
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from . import _core
from ._prefetch import prefetched
from .errors import InputError

log = logging.getLogger(__name__)

FORMATS = ("tum-vie", "vector", "vector-bag", "mvsec", "euroc")  # dhptam.datasets.FORMATS
MODES = ("fusion", "frames", "events")
FEATURES = ("orb", "sift", "r2d2", "superpoint")
STAGES = ("reading", "frontend", "extraction", "tracking")
_NS = 1_000_000_000


@dataclass
class RunResult:
    """What :func:`run` did; the files in ``out`` hold the details."""

    out: Path
    mode: str
    features: str
    frames: int
    states: dict[str, int]
    keyframes: int
    map_points: int
    loop_closures: int
    seconds: float
    interrupted: bool = False
    error: str | None = None
    files: dict[str, Path] = field(default_factory=dict)
    tracking: dict[str, int] = field(default_factory=dict)
    """Bridge keyframes at fusion-mode switches (``bridges``, ``bridges_refused``), new map
    ``segments``, ``relocalisations``, flood frames ``predicted`` instead of tracked, quiet
    frames ``held`` at rest and
    ``implausible`` tracked poses rejected for jumping away from the motion model
    (``dhptam.System.tracking_totals``)."""

    @property
    def tracked(self) -> int:
        """Frames whose pose came from tracking (not lost, not only predicted or held)."""
        return sum(n for s, n in self.states.items() if s not in ("lost", "predicted", "held"))

    @property
    def fps(self) -> float:
        """Frames per second over the whole run."""
        return self.frames / self.seconds if self.seconds > 0 else 0.0


def _stats(values: Sequence[float]) -> dict[str, float]:
    if not values:
        return {"count": 0}
    a = np.asarray(values) * 1e3
    return {
        "count": len(values),
        "mean_ms": float(a.mean()),
        "median_ms": float(np.median(a)),
        "p95_ms": float(np.percentile(a, 95)),
        "max_ms": float(a.max()),
        "total_s": float(a.sum() / 1e3),
    }


class _Forward(logging.Handler):
    """Hands records on to the root logger's handlers (what propagation would have done)."""

    def emit(self, record: logging.LogRecord) -> None:
        logging.getLogger().handle(record)


@contextmanager
def _run_log(path: Path) -> Iterator[Callable[[int], None]]:
    """Writes the dhptam loggers' records to ``path`` while leaving what reaches the console
    exactly as configured.

    The file takes INFO and above, or lower when asked for: by ``$DHPTAM_LOG`` from the start,
    and by the run's ``[log] level`` once the caller hands the resolved level to the function
    this yields.
    """
    from .logs import LOGGER_NAMES, resolve_level

    requested = resolve_level()
    handler = logging.FileHandler(path, mode="w", encoding="utf-8")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    saved: list[tuple[logging.Logger, int, bool, list[tuple[logging.Handler, int]]]] = []
    forwarders: list[tuple[logging.Logger, logging.Handler]] = []
    for name in LOGGER_NAMES:
        logger = logging.getLogger(name)
        effective = logger.getEffectiveLevel()
        saved.append((logger, logger.level, logger.propagate, [(h, h.level) for h in logger.handlers]))
        for h in logger.handlers:
            h.setLevel(max(h.level, effective))
        if logger.propagate:
            forward = _Forward(effective)
            logger.addHandler(forward)
            forwarders.append((logger, forward))
            logger.propagate = False
        logger.setLevel(min(effective, logging.INFO, requested))
        logger.addHandler(handler)
    _core._reset_log_cache()

    def set_file_level(level: int) -> None:
        # Lower the loggers only: the console's handlers keep the levels clamped above.
        for logger, *_ in saved:
            logger.setLevel(min(logger.level, level))
        _core._reset_log_cache()

    try:
        yield set_file_level
    finally:
        handler.close()
        for logger, level, propagate, handlers in saved:
            logger.removeHandler(handler)
            logger.setLevel(level)
            logger.propagate = propagate
            for h, h_level in handlers:
                h.setLevel(h_level)
        for logger, forward in forwarders:
            logger.removeHandler(forward)
        _core._reset_log_cache()
        handler.close()


def _resolve_config(config: str | Path | _core.Config | None) -> _core.Config:
    if config is None:
        return _core.Config()
    if isinstance(config, _core.Config):
        return config
    return _core.Config.from_file(Path(config))


def _load_sequence(sequence: str | Path, fmt: str, calibration: str | Path | None) -> Any:
    if fmt not in FORMATS:
        raise InputError(
            f"unknown sequence format {fmt!r}; choose one of {', '.join(FORMATS)}", field="format"
        )
    from .datasets import load

    return load(fmt, sequence, calibration=calibration)


def _progress(total: int, enabled: bool, desc: str) -> Any:
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="frame", dynamic_ncols=True, leave=True)


class _Outputs:
    """Collects per-frame records and writes every output file atomically."""

    def __init__(
        self, out: Path, tracked_from_rect: Any, rect_from_cam: Any, extra_formats: tuple[str, ...] = ()
    ) -> None:
        from .trajectory import TRAJECTORY_FORMATS

        for fmt in extra_formats:
            if fmt not in TRAJECTORY_FORMATS:
                raise InputError(
                    f"unknown trajectory format {fmt!r}; choose from {', '.join(TRAJECTORY_FORMATS)}",
                    field="trajectory_formats",
                )
        self.extra_formats = extra_formats
        self.out = out
        # The back-end's poses are of the tracked camera (Frontend.tracked_from_rect: the
        # rectified left frame camera, or in mode events the rectified left event camera).
        self.tracked_from_rect = tracked_from_rect
        self.rect_from_cam = rect_from_cam
        # Per-frame rows are spooled to an unnamed temporary file as they come, so that memory
        # stays bounded on long runs (a dict per frame costs ~1 kB: 50 MB for 30 minutes).
        self.count = 0
        self.header: list[str] = ["index"]
        self._spool = tempfile.TemporaryFile("w+", encoding="utf-8", dir=out)  # noqa: SIM115 - closed by close()
        self.times: dict[str, array[float]] = {s: array("d") for s in STAGES}
        self.meta: dict[str, Any] = {}
        self.recorder: Any = None  # a dhptam.datasets.mcap.McapRecorder with --record
        self.record_path: Path | None = None
        # Frames whose state changed after they were recorded (index → state), applied when
        # frames.csv is written: quiet frames before the first map, held at its pose.
        self._restated: dict[int, str] = {}

    def _rectified(self, t_ns: Any, poses: Any) -> tuple[Any, Any]:
        """The back-end's ``(t_ns, world_from_tracked)`` as the rectified left frame camera's."""
        return t_ns, (poses @ self.tracked_from_rect.matrix() if len(poses) else poses)

    def record(self, row: dict[str, Any]) -> None:
        if self.count == 0:
            self.header = list(row)
        self._spool.write(",".join(str(row[h]) for h in self.header) + "\n")
        self.count += 1
        for s in STAGES:
            self.times[s].append(row[f"{s}_s"])

    def restate(self, indices: list[int], state: str) -> None:
        """Frames ``indices``, already recorded, end up in ``state`` (in ``frames.csv``)."""
        self._restated.update(dict.fromkeys(indices, state))

    def _rows(self) -> str:
        """The spooled rows, with the states :meth:`restate` changed."""
        text = self._spool.read()
        if not self._restated:
            return text
        column = self.header.index("state")
        lines = text.splitlines(keepends=True)
        for k, line in enumerate(lines):
            index = int(line.split(",", 1)[0])
            if index in self._restated:
                cells = line.split(",")
                cells[column] = self._restated[index]
                lines[k] = ",".join(cells)
        return "".join(lines)

    def close(self) -> None:
        self._spool.close()

    def write(self, system: Any, config_toml: str, meta: dict[str, Any]) -> dict[str, Path]:
        from .depth import write_ply
        from .trajectory import atomic_write_text, write_tum

        files: dict[str, Path] = {}
        t_ns, poses = self._rectified(*system.trajectory())
        path = self.out / "trajectory.tum"
        write_tum(
            path,
            t_ns,
            poses,
            header="timestamp[s] tx ty tz qx qy qz qw (world_from_cam, left rectified frame camera)",
        )
        files["trajectory"] = path
        # The same poses for the unrectified left frame camera, which ground truth describes.
        frame_cam = poses @ self.rect_from_cam.matrix() if len(poses) else poses
        path = self.out / "trajectory_frame_left.tum"
        write_tum(
            path,
            t_ns,
            frame_cam,
            header="timestamp[s] tx ty tz qx qy qz qw (world_from_cam, left frame camera)",
        )
        files["trajectory_frame_left"] = path
        kt, kposes = self._rectified(*system.keyframe_trajectory())
        path = self.out / "keyframes.tum"
        write_tum(
            path,
            kt,
            kposes,
            header="timestamp[s] tx ty tz qx qy qz qw (keyframes, left rectified frame camera)",
        )
        files["keyframes"] = path
        # Other trajectory formats (issue 9): the same poses, for evo and other tools.
        from .trajectory import write_trajectory

        for fmt in self.extra_formats:
            if fmt == "tum":
                continue
            ext = "csv" if fmt == "euroc" else fmt
            for key, (times, rows) in (
                ("trajectory_frame_left", (t_ns, frame_cam)),
                ("keyframes", (kt, kposes)),
            ):
                path = self.out / f"{key}.{ext}"
                write_trajectory(path, fmt, times, rows)
                files[f"{key}_{fmt}"] = path
        path = self.out / "map.ply"
        write_ply(str(path), system.map_points())
        files["map"] = path
        if self.recorder is not None:
            t_ns_rec, frame_cam_rec = self._rectified(*system.trajectory())
            if len(frame_cam_rec):
                frame_cam_rec = frame_cam_rec @ self.rect_from_cam.matrix()
            # Finished once: a repeated write (Ctrl-C while finishing) keeps the log written.
            self.record_path = self.recorder.finish(
                (t_ns_rec, frame_cam_rec), (kt, kposes), system.map_points()
            )
            self.recorder = None
        if self.record_path is not None:
            files["record"] = self.record_path
        self._spool.flush()
        self._spool.seek(0)
        path = self.out / "frames.csv"
        atomic_write_text(path, ",".join(self.header) + "\n" + self._rows())
        self._spool.seek(0, io.SEEK_END)
        files["frames"] = path
        timing = {
            "stages": {s: _stats(v) for s, v in self.times.items()},
            "backend": system.timing(),
            **meta,
        }
        path = self.out / "timing.json"
        atomic_write_text(path, json.dumps(timing, indent=2, sort_keys=True) + "\n")
        files["timing"] = path
        path = self.out / "config.toml"
        atomic_write_text(path, config_toml)
        files["config"] = path
        return files


def run(
    sequence: str | Path,
    out: str | Path,
    *,
    fmt: str = "tum-vie",
    calibration: str | Path | None = None,
    mode: str = "fusion",
    features: str = "orb",
    weights: str | Path | None = None,
    config: str | Path | _core.Config | None = None,
    realtime: bool = False,
    progress: bool = True,
    max_frames: int | None = None,
    trajectory_formats: tuple[str, ...] = (),
    threaded: bool = True,
    viz: str = "none",
    extractor: Any = None,
    record: str | Path | None = None,
    record_frames: str = "raw",
) -> RunResult:
    """Runs dhptam on a sequence and writes the outputs into ``out`` (see the module docstring).

    Parameters
    ----------
    sequence
        The sequence folder (TUM-VIE layout, real or simulated).
    out
        Output folder; created if needed, files in it are replaced.
    fmt
        Sequence format: ``tum-vie``.
    calibration
        A calibration file overriding the one found beside the sequence.
    mode
        ``fusion`` (frames and events blended by the online β), ``frames`` or ``events``.
    features
        ``orb``, ``sift`` (no weights needed), ``r2d2`` or ``superpoint``; it replaces
        ``[features] extractor`` of ``config``, whose other ``[features]`` settings
        (``max_keypoints``, 0 by default: :func:`dhptam.features.keypoint_budget` of the
        rectified frame size; ``device``, ``threads``, ``weights``, ``precision``, ``scales``)
        the extractor is built with; ``precision``, ``scales`` and ``weights`` are dropped, with
        a log line, where they do not apply to ``features``.
    weights
        Weight file for the learned extractors (see ``dhptam.features`` for the search order);
        replaces ``[features] weights``.
    config
        A configuration file or :class:`dhptam.Config`; defaults otherwise.
    realtime
        Feed frames no faster than the sensor produced them.
    progress
        Show a progress bar on stderr.
    max_frames
        Stop after this many frames.
    threaded
        Run mapping and loop closing on their own threads (``False``: inline, deterministic).
    trajectory_formats
        Also write the left frame camera's and the keyframes' trajectories as ``kitti``
        (``*.kitti``) and/or ``euroc`` (``*.csv``) files next to the TUM ones.
    viz
        ``none`` (default), ``rerun`` (write ``OUT/recording.rrd``, see :mod:`dhptam.viz`) or
        ``rerun-spawn`` (also stream it to a rerun viewer started here).
    extractor
        A ready feature extractor (anything with ``extract(left, right)``) used instead of
        loading ``features``/``weights``, e.g. one with custom settings; ``features`` then only
        names it in the outputs.
    record
        Also record the run's inputs (frames, raw events, calibration, ground truth) and
        outputs (trajectories, keyframes, map) into this MCAP log (``dhptam.datasets.mcap``).
    record_frames
        How ``record`` stores the frames: ``raw`` (``foxglove.RawImage``) or ``png`` (lossless
        PNG in ``foxglove.CompressedImage``).

    Returns
    -------
    RunResult
        Counts, timing and the files written. A Ctrl-C stops the run cleanly
        (``interrupted``); any other failure is raised after everything done so far is written.
    """
    from ._config import with_setting
    from .features import from_config as features_from_config
    from .features import keypoint_budget
    from .frontend import Frontend
    from .logs import resolve_level
    from .system import StereoCalibration, System

    if mode not in MODES:
        raise InputError(f"unknown mode {mode!r}; choose one of {', '.join(MODES)}", field="mode")
    from .viz import VIZ_CHOICES

    if viz not in VIZ_CHOICES:
        raise InputError(f"unknown viz {viz!r}; choose one of {', '.join(VIZ_CHOICES)}", field="viz")
    if features not in FEATURES:
        raise InputError(
            f"unknown features {features!r}; choose one of {', '.join(FEATURES)}", field="features"
        )
    if max_frames is not None and int(max_frames) < 1:
        raise InputError(f"max_frames must be at least 1, got {max_frames}", field="max_frames")
    out_dir = Path(out)
    out_dir.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    with _run_log(out_dir / "run.log") as set_log_level, ExitStack() as resources:
        cfg = _resolve_config(config)
        set_log_level(resolve_level(config=cfg))
        seq = resources.enter_context(_load_sequence(sequence, fmt, calibration))
        if mode != "frames" and not seq.events:
            raise InputError(
                f"{sequence}: a {fmt} sequence has no events; run it with mode 'frames'", field="mode"
            )
        # The extractor the run uses is `features`; the [features] section gives its settings.
        cfg = with_setting(_without_settings_foreign_to(features, cfg), "features", "extractor", features)
        if weights is not None:
            cfg = with_setting(cfg, "features", "weights", os.fspath(weights))
        stop_at = None if max_frames is None else int(max_frames)
        frontend = Frontend(seq, mode, cfg, prefetch=0, stop=stop_at)
        if int(cfg.to_dict()["features"]["max_keypoints"]) == 0:
            # 0: the budget of the rectified frames' size; config.toml records the number.
            budget = keypoint_budget(int(frontend.frame_rect.width), int(frontend.frame_rect.height))
            frontend.config = with_setting(frontend.config, "features", "max_keypoints", budget)
        if extractor is None:
            extractor = features_from_config(frontend.config)
        system = System(StereoCalibration(*frontend.tracked_calibration), frontend.config, threaded=threaded)
        outputs = _Outputs(
            out_dir, frontend.tracked_from_rect, frontend.rect_from_cam, tuple(trajectory_formats)
        )
        outputs.meta["sequence"] = str(Path(sequence).resolve())
        sink = _viz_sink(viz, out_dir, frontend.tracked_calibration, resources)
        reference = None
        if seq.ground_truth is not None:
            reference = (seq.ground_truth.t_ns, seq.ground_truth.world_from_cam)
        # MCAP recording (--record): inputs per frame in _track_all, outputs in _finish.
        if record is not None:
            from .datasets.mcap import McapRecorder

            outputs.recorder = McapRecorder(record, seq, frame_format=record_frames)
        resources.callback(outputs.close)
        log.info(
            "run: %s, %d frames, mode %s, features %s, out %s",
            sequence,
            len(frontend),
            mode,
            features,
            out_dir,
        )
        result = RunResult(out_dir, mode, features, 0, {}, 0, 0, 0, 0.0)
        states: Counter[str] = Counter()
        try:
            _track_all(frontend, extractor, system, outputs, states, realtime, progress, sink)
        except KeyboardInterrupt:
            result.interrupted = True
            log.warning("interrupted by the user after %d frames; writing what was done", outputs.count)
        except BaseException as error:
            result.error = f"{type(error).__name__}: {error}"
            log.error("run failed after %d frames: %s", outputs.count, result.error)
            _finish(system, outputs, frontend, result, states, started, features, sink, reference)
            raise
        _finish(system, outputs, frontend, result, states, started, features, sink, reference)
        log.info(
            "done: %d frames in %.1f s (%.1f fps), states %s, %d keyframes, %d map points, %d loops, "
            "%d bridges (%d refused), %d new map segments",
            result.frames, result.seconds, result.fps, dict(states), result.keyframes, result.map_points,
            result.loop_closures, result.tracking.get("bridges", 0),
            result.tracking.get("bridges_refused", 0), result.tracking.get("segments", 0),
        )  # fmt: skip
        return result


def _viz_sink(viz: str, out_dir: Path, calibration: Any, resources: ExitStack) -> Any:
    """The run's visualisation sink: the no-op one unless ``viz`` asks for rerun."""
    from .viz import RECORDING, RerunSink, VizSink

    if viz == "none":
        return VizSink()
    sink = RerunSink(out_dir / RECORDING, calibration, spawn=viz == "rerun-spawn", name=out_dir.name)
    resources.callback(sink.close)
    return sink


def _without_settings_foreign_to(extractor: str, config: _core.Config) -> _core.Config:
    """``config`` without the ``[features]`` settings that do not apply to ``extractor``.

    ``precision`` other than float32 belongs to the learned extractors (int8 to R2D2 alone),
    ``scales`` to R2D2, and ``weights`` to the configuration's own ``extractor``, so one
    configuration serves the feature ablation (``--features orb`` next to ``--features
    r2d2``); what is dropped is logged.
    """
    from ._config import with_setting

    section = config.to_dict()["features"]
    if section["weights"] and extractor != section["extractor"]:
        log.info(
            "features: weights %s are for %s; %s runs with its own",
            section["weights"], section["extractor"], extractor,
        )  # fmt: skip
        config = with_setting(config, "features", "weights", "")
    precision = section["precision"]
    keeps = {"r2d2": True, "superpoint": precision != "int8"}.get(extractor, precision == "float32")
    if not keeps:
        log.info("features: precision %s does not apply to %s; it runs in float32", precision, extractor)
        config = with_setting(config, "features", "precision", "float32")
    if section["scales"] and extractor != "r2d2":
        log.info("features: scales %s are R2D2's; %s does not use them", section["scales"], extractor)
        config = with_setting(config, "features", "scales", [])
    return config


def _finish(
    system: Any,
    outputs: _Outputs,
    frontend: Any,
    result: RunResult,
    states: Counter[str],
    started: float,
    features: str,
    sink: Any,
    reference: Any,
) -> None:
    _uninterrupted(system.shutdown, result, "stopping the back-end")
    iterations = int(frontend.config.to_dict()["mapping"]["final_ba_iterations"])
    if iterations > 0 and result.error is None and not result.interrupted:
        # The whole-map bundle adjustment (`[mapping] final_ba_iterations`); the core logs it.
        # A Ctrl-C meanwhile (it lands once the adjustment returns) skips nothing else.
        try:
            system.refine_map(iterations)
        except KeyboardInterrupt:
            result.interrupted = True
            log.warning("interrupted during the whole-map bundle adjustment; writing what was done")
    _uninterrupted(frontend.close, result, "closing the front-end")
    result.frames = outputs.count
    result.states = dict(states)
    result.seconds = time.perf_counter() - started
    kt, _ = system.keyframe_trajectory()
    result.keyframes = len(kt)
    result.map_points = len(system.map_points())
    result.loop_closures = len(system.loop_closures())
    result.tracking = system.tracking_totals()
    meta = {
        "frames": result.frames,
        "seconds": result.seconds,
        "fps": result.fps,
        "mode": result.mode,
        "features": features,
        "states": result.states,
        "interrupted": result.interrupted,
        "error": result.error,
        "loops_s": [[a / _NS, b / _NS] for a, b in system.loop_closures()],
        "tracking": result.tracking,
        **outputs.meta,
    }
    config_toml = frontend.config.to_toml()
    result.files = _uninterrupted(
        lambda: outputs.write(system, config_toml, meta), result, "writing the outputs"
    )
    if result.interrupted and not meta["interrupted"]:
        # The Ctrl-C came while finishing: say so in timing.json too.
        meta["interrupted"] = True
        result.files = outputs.write(system, config_toml, meta)
    try:
        sink.finish(system, reference)
    finally:
        sink.close()
    recording = getattr(sink, "path", None)
    if recording is not None:
        result.files["recording"] = recording


def _uninterrupted(step: Callable[[], Any], result: RunResult, what: str, tries: int = 3) -> Any:
    """Runs an idempotent finishing step to its end even if Ctrl-C arrives meanwhile: the
    interrupt is remembered in ``result`` and the step is run again (every output is written
    atomically, so a repeated write replaces whole files), up to ``tries`` times."""
    for attempt in range(tries):
        try:
            return step()
        except KeyboardInterrupt:
            result.interrupted = True
            if attempt == tries - 1:
                raise
            log.warning("interrupted while %s; finishing it before stopping", what)
    return None


class _DepthFeed:
    """The warp depth of each frame from the tracking of the frame before it
    (``[fusion] warp_depth = "tracked"``).

    The tracking loop :meth:`publish`-es, after each frame, the median depth of the map points
    it was tracked with (``System.tracked_depth``; ``None`` when lost or not initialised); the
    extraction thread :meth:`wait`-s for frame k−1's value before warping frame k, so a run
    gives the same images whatever the threads' timing. :meth:`close` releases a waiting
    thread when the loop ends early. With ``tracked = False`` every frame gets ``None`` at
    once (the configured plane) and nothing waits.
    """

    def __init__(self, start: int, tracked: bool) -> None:
        self._cond = threading.Condition()
        self._start = start
        self._tracked = tracked
        #: Whether frames wait for their predecessor's depth (``warp_depth = "tracked"``).
        self.waits = tracked
        self._done = start - 1  # the last frame index published
        self._depth: float | None = None
        self._closed = False

    def publish(self, index: int, depth_m: float | None) -> None:
        with self._cond:
            self._done, self._depth = index, depth_m
            self._cond.notify_all()

    def wait(self, index: int) -> float | None:
        """The depth for frame ``index``: frame ``index − 1``'s, once published."""
        if not self._tracked or index <= self._start:
            return None
        with self._cond:
            self._cond.wait_for(lambda: self._closed or self._done >= index - 1)
            if self._closed and self._done < index - 1:
                raise RuntimeError("the tracking loop ended before this frame's warp depth was known")
            return self._depth

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()


def _track_all(
    frontend: Any,
    extractor: Any,
    system: Any,
    outputs: _Outputs,
    states: Counter[str],
    realtime: bool,
    progress: bool,
    sink: Any,
) -> None:
    # One frame of front-end state: at a fusion-mode switch the front-end renders the frame
    # with usable raw data also with the other mode's β (Frontend.bridge_images).
    previous: list[Any] = [None]
    # [fusion] warp_depth = "tracked": the event warp of frame k goes through a plane at the
    # depth of the map points frame k-1 was tracked with, so the events' parallax against the
    # frame cameras is removed where the scene is (the E3CT of frame k is computed ahead, its
    # warp, blend and features wait for frame k-1's tracking).
    feed = _DepthFeed(frontend.start, frontend.warps_events and frontend.warp_depth == "tracked")

    # The depth the last frame was warped through (the quantisation keeps it while the tracked
    # depth stays within one bin of it).
    warped_at: list[float | None] = [None]

    def render(prepared: Any) -> tuple[Any, Any]:
        """Frame k's warp, blend and bridge rendering, through frame k−1's tracked depth."""
        depth = frontend.quantised_depth(feed.wait(prepared.index), warped_at[0])
        warped_at[0] = depth
        frame = frontend.across_flood(previous[0], frontend.finish(prepared, depth))
        bridge = None if previous[0] is None else frontend.bridge_images(previous[0], frame)
        # A flood frame is predicted (or, leaving a DVS-biased segment, tracked on its frames
        # alone): a bridge spans it, from the last clean frame.
        if not (frame.flood and frontend.flood_predict):
            previous[0] = frame
        return frame, bridge

    # Without a tracked depth to wait for, the whole front-end runs on its own thread, ahead of
    # the extraction; with one, only the E3CT runs ahead and the rest waits for frame k−1.
    # Reading the files (HDF5 decompression, image decoding) runs on a thread of its own ahead
    # of both: it holds the GIL, which the front-end's kernels release.
    def read(index: int) -> tuple[Any, float]:
        t0 = time.perf_counter()
        return frontend.read(index), time.perf_counter() - t0

    def front(item: tuple[Any, float]) -> tuple[Any, Any, float, float]:
        raw, t_read = item
        t0 = time.perf_counter()
        prepared = frontend.prepare(raw)
        rendered = None if feed.waits else render(prepared)
        return prepared, rendered, time.perf_counter() - t0, t_read

    def extract(item: tuple[Any, Any, float, float]) -> tuple[Any, float, Any, Any, float, Any, float]:
        prepared, rendered, t_front, t_read = item
        t0 = time.perf_counter()
        frame, bridge = render(prepared) if rendered is None else rendered
        t1 = time.perf_counter()
        left, right = extractor.extract(frame.left, frame.right)
        if bridge is not None:
            bridge = (bridge, extractor.extract(bridge.left, bridge.right))
        return frame, t_front + t1 - t0, left, right, time.perf_counter() - t1, bridge, t_read

    indices = iter(range(frontend.start, frontend.stop))
    raw = prefetched(indices, read, "reader", 2)
    fused = prefetched(raw, front, "frontend", 2)
    extracted = prefetched(fused, extract, "extraction", 2)
    bar = _progress(frontend.stop - frontend.start, progress, f"dhptam {frontend.mode}")
    with _interrupts_between_frames() as interrupt_pending:
        try:
            _track_frames(
                extracted, system, outputs, states, realtime, bar, sink, interrupt_pending,
                frontend.predicts, feed,
                _image_models(frontend),
            )  # fmt: skip
        finally:
            feed.close()
            extracted.close()
            if bar is not None:
                bar.close()


class ImageModel(NamedTuple):
    """How the tracker reads one image pair's features: the factor on its keypoint σ
    (``System.track``'s ``sigma_scale``), its disparity correction (``disparity``) and its
    event-stereo reading (``event_stereo``, which replaces the disparity correction), the
    viewpoint its keypoints are modelled from (``viewpoint``) and whether it is the fusion's
    DVS-biased rendering (``dvs_biased``: the keyframe floor ``[tracking]
    dvs_keyframe_min_tracked``)."""

    sigma_scale: float = 1.0
    disparity: tuple[float, float] = (1.0, 0.0)
    event_stereo: Any = None
    viewpoint: tuple[float, float, float] = (0.0, 0.0, 0.0)
    dvs_biased: bool = False


def _image_models(frontend: Any) -> Callable[[str, float], ImageModel]:
    """The :class:`ImageModel` of an image from its fusion bias and warp depth: DVS-biased
    images get ``[tracking] dvs_sigma_scale`` and are flagged ``dvs_biased``, and
    event-dominated ones (``dvs``, ``events``) the event cameras' disparity correction
    (:meth:`Frontend.event_disparity`, the default), or with ``[fusion] event_stereo =
    "exact"`` the reading of their stereo matches through the event cameras' geometry
    (:meth:`Frontend.event_stereo`), and with ``[fusion] event_viewpoint`` the event cameras'
    centre as their viewpoint (:meth:`Frontend.event_viewpoint`)."""
    dvs_sigma_scale = float(frontend.config.to_dict()["tracking"]["dvs_sigma_scale"])

    def model(bias: str, warp_depth_m: float) -> ImageModel:
        scale = dvs_sigma_scale if bias == "dvs" else 1.0
        if bias not in ("dvs", "events"):
            return ImageModel(scale)
        dvs_biased = bias == "dvs"
        reading = frontend.event_stereo(warp_depth_m)
        if reading is not None:
            return ImageModel(scale, event_stereo=reading, dvs_biased=dvs_biased)
        return ImageModel(
            scale,
            frontend.event_disparity(warp_depth_m),
            viewpoint=frontend.event_viewpoint(warp_depth_m),
            dvs_biased=dvs_biased,
        )

    return model


def _plain_model(bias: str, warp_depth_m: float) -> ImageModel:
    return ImageModel()


def _track_frames(
    extracted: Any,
    system: Any,
    outputs: _Outputs,
    states: Counter[str],
    realtime: bool,
    bar: Any,
    sink: Any,
    interrupt_pending: Callable[[], bool],
    predicts: Callable[[Any, int], bool] | None = None,
    feed: _DepthFeed | None = None,
    model: Callable[[str, float], ImageModel] = _plain_model,
) -> None:
    """The tracking loop on the caller's thread: one frame tracked and recorded per step; a
    Ctrl-C takes effect between frames, so the trajectory and ``frames.csv`` hold the same
    frames. A frame for which ``predicts(frame, features)`` holds (``Frontend.predicts``: a
    flood frame, ``features`` the fewer keypoints of its two images) has its pose predicted by
    the motion model (``System.predict``) instead of tracked, and the last clean frame stays
    the one a bridge keyframe may start from. After each frame the median depth of the map
    points it was tracked with goes to ``feed`` (the next frame's warp depth). ``model`` gives
    each image's :class:`ImageModel` from its fusion bias and warp depth. Quiet frames of
    event images before the first map are lost when tracked; the back-end holds them at the
    first map's pose once it is made, and their rows say ``held``."""
    wall0 = time.perf_counter()
    t_first: int | None = None
    # (frame index, (left, right) features it was tracked with, their image model)
    last: tuple[int, Any, ImageModel] | None = None
    # Before the first map: the last run of quiet frames lost, which the map may hold.
    mapped, rest = False, list[int]()

    for frame, t_front, left, right, t_extract, bridge, t_read in extracted:
        if interrupt_pending():
            raise KeyboardInterrupt
        if realtime:
            t_first = frame.t_ns if t_first is None else t_first
            wait = (frame.t_ns - t_first) / _NS - (time.perf_counter() - wall0)
            if wait > 0:
                time.sleep(wait)
        if outputs.recorder is not None:
            outputs.recorder.add_frame(frame.index)
        held_before = 0 if mapped else system.tracking_totals()["held"]
        t0 = time.perf_counter()
        if predicts is not None and predicts(frame, min(len(left.keypoints), len(right.keypoints))):
            r, bridged = system.predict(frame.t_ns), "none"
        else:
            r, bridged = _track_bridged(system, frame, (left, right), bridge, last, model)
            last = (frame.index, (left, right), model(frame.bias, frame.warp_depth_m))
        t_track = time.perf_counter() - t0
        if feed is not None:
            feed.publish(frame.index, system.tracked_depth())
        states[r.state] += 1
        if not mapped:
            if r.state == "initialised":
                mapped = True
                held = system.tracking_totals()["held"] - held_before
                if held:
                    outputs.restate(rest[-held:], "held")
                    states["lost"] -= held
                    states["held"] += held
                    if not states["lost"]:
                        del states["lost"]
            elif r.state == "lost" and frame.quiet:
                rest.append(frame.index)
            else:
                rest.clear()
        sink.frame(frame, left, right, r)
        outputs.record(
            {
                "index": frame.index,
                "t_s": f"{frame.t_ns / _NS:.9f}",
                "state": r.state,
                "inliers": r.inliers,
                "keyframe": int(r.keyframe),
                "keypoints_left": len(left.keypoints),
                "keypoints_right": len(right.keypoints),
                "beta_left": f"{frame.beta_left:.4f}",
                "bias": frame.bias,
                "flood": int(frame.flood),
                "quiet": int(frame.quiet),
                "hot_pixels": 0 if (st := frame.e3ct_stats) is None else st.hot_left + st.hot_right,
                "stretched": sum(frame.stretched),
                "warp_depth_m": f"{frame.warp_depth_m:.4f}",
                "bridge": bridged,
                "reading_s": round(t_read, 6),
                "frontend_s": round(t_front, 6),
                "extraction_s": round(t_extract, 6),
                "tracking_s": round(t_track, 6),
            }
        )
        if bar is not None:
            bar.update(1)
            bar.set_postfix_str(f"{r.state} {r.inliers} inl", refresh=False)
    if interrupt_pending():
        raise KeyboardInterrupt


@contextmanager
def _interrupts_between_frames() -> Iterator[Callable[[], bool]]:
    """Defers Ctrl-C in the tracking loop to the next frame boundary.

    The first SIGINT only sets a flag, which the loop checks before each frame (and once after
    the last), so a frame is either tracked and recorded or not started: the trajectory and
    ``frames.csv`` always hold the same frames (the handler does nothing else: no logging
    from inside a signal handler). A second SIGINT interrupts at once. One that comes after
    the loop's last check, while the loop's threads are closed, is raised when the block
    ends. Off the main thread, or when the caller installed its own SIGINT handler, nothing
    changes.
    """
    pending = [False]
    if (
        threading.current_thread() is not threading.main_thread()
        or signal.getsignal(signal.SIGINT) is not signal.default_int_handler
    ):
        yield lambda: False
        return

    def on_sigint(signum: int, frame: Any) -> None:
        if pending[0]:
            raise KeyboardInterrupt
        pending[0] = True

    previous = signal.signal(signal.SIGINT, on_sigint)
    try:
        yield lambda: pending[0]
    finally:
        signal.signal(signal.SIGINT, previous)
    if pending[0]:
        # A Ctrl-C after the loop's last check (while its threads were being closed) is not
        # lost: it takes effect here, as one between two frames would.
        raise KeyboardInterrupt


def _track_bridged(
    system: Any,
    frame: Any,
    features: tuple[Any, Any],
    bridge: Any,
    last: tuple[int, Any, ImageModel] | None,
    model: Callable[[str, float], ImageModel] = _plain_model,
) -> tuple[Any, str]:
    """Tracks one frame, inserting a bridge keyframe at a fusion-mode switch.

    ``bridge`` is ``(BridgeImages, (left, right) features)`` or ``None``. Entering a
    dark/saturated segment the bridge renders the previous frame (already tracked with
    ``last``'s features): the bridge keyframe goes in at that frame's pose before this frame
    is tracked. Leaving one it renders this frame in the previous frames' mode: the frame is
    tracked with that rendering (it matches the map) and the bridge keyframe adds its own
    image. ``model`` gives an image's :class:`ImageModel` from its fusion bias and warp
    depth. Returns the track result and ``none``, ``inserted`` or ``refused``.
    """
    here = model(frame.bias, frame.warp_depth_m)

    def track(feats: tuple[Any, Any], m: ImageModel) -> Any:
        return system.track(
            frame.t_ns,
            *feats,
            sigma_scale=m.sigma_scale,
            disparity=m.disparity,
            event_stereo=m.event_stereo,
            viewpoint=m.viewpoint,
            dvs_biased=m.dvs_biased,
            quiet=frame.quiet,
        )

    def bridge_at(t_ns: int, primary: Any, a: ImageModel, secondary: Any, b: ImageModel) -> Any:
        return system.bridge(
            t_ns,
            primary,
            secondary,
            sigma_scales=(a.sigma_scale, b.sigma_scale),
            disparities=(a.disparity, b.disparity),
            event_stereo=(a.event_stereo, b.event_stereo),
            viewpoints=(a.viewpoint, b.viewpoint),
        )

    if bridge is None:
        return track(features, here), "none"
    images, other = bridge
    there = model(images.bias, images.warp_depth_m)
    if images.index < frame.index and last is not None and last[0] == images.index:
        b = bridge_at(images.t_ns, last[1], last[2], other, there)
        return track(features, here), "refused" if b is None else "inserted"
    if images.index == frame.index:
        r = track(other, there)
        if r.state == "lost":
            return r, "refused"
        b = bridge_at(frame.t_ns, other, there, features, here)
        return r, "refused" if b is None else "inserted"
    return track(features, here), "none"
