"""Streams of frames in, one point cloud per frame out (``multislit stream``).

The capture folder gives the calibration and the reference set, both prepared once; every frame
of a SOURCE (:func:`multislit.io.sources.open_source`) is scanned with
:func:`multislit.scan_image` and written to the OUT folder as it finishes::

    OUT/frame_000000.ply   binary PLY, the vertex properties of 'multislit scan'
    OUT/frame_000001.ply
    OUT/frames.jsonl       one line per frame: frame, source, points, slits, ms

Each PLY is written to a temporary name and renamed; its line in ``frames.jsonl`` is appended
(one write, flushed) after it, so a killed run leaves whole frames and an index of exactly
those. Frames are written in the source's order, also when several processes scan them.

:func:`run_frames` is the loop; it takes a *runner* that scans frames (in this process, in a
process pool, or on a Dask cluster, see :mod:`multislit.app.batch`).
"""

from __future__ import annotations

import json
import multiprocessing
import os
import re
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from multislit import __version__, compile_kernels, set_threads
from multislit.app.index import INDEX_FILE, RUN_FILE, RUN_FORMAT, frame_file, picture_file
from multislit.app.pictures import encode_png, scan_picture
from multislit.calibrate import Calibration
from multislit.errors import CaptureError, MeasurementError, MultislitError
from multislit.identify import ReferenceSet, capture_reference, prepare_scoring
from multislit.io import Capture, json_safe, write_bytes_atomic, write_json, write_ply
from multislit.io.paths import as_path, check_output_dir
from multislit.io.sources import FrameSource, open_source
from multislit.reconstruct import (
    CALIBRATION_FILE,
    ScanOptions,
    ScanResult,
    load_capture_calibration,
    scan_image,
)
from multislit.reconstruct.options import as_scan_options

__all__ = [
    "FrameResult",
    "FrameWriter",
    "StreamSummary",
    "ProgressLine",
    "scan_frame",
    "run_frames",
    "stream",
    "INDEX_FILE",
    "frame_file",
]

_PROGRESS_EVERY_S = 5.0  # progress lines when stderr is not a terminal
_INFLIGHT_PER_WORKER = 2  # frames queued per worker process for files and videos
_PARENT_POLL_S = 0.5  # a worker process checks this often that its parent still runs
#: Most worker processes per core: more only share the cores and multiply the memory.
_WORKERS_PER_CORE = 4
#: s without a usable frame after which a live camera run stops (every frame of the wrong
#: size or unreadable: a camera set to another size, another camera).
_LIVE_BAD_FRAMES_S = 10.0


@dataclass(frozen=True, eq=False)
class FrameResult:
    """The points of one frame, as written to its PLY.

    Attributes
    ----------
    points : (K, 3) float64, mm, target frame
    u, v : (K,) float64, px, image position of each point
    slit : (K,) int64, slit number of each point
    confidence : (K,) float64, 0..1
    slits : int, distinct slits among the points
    ms : float, ms, time to scan the frame
    message : str, why the frame gave no points or another note of the scan; '' if none
    picture : bytes, PNG of :func:`~multislit.app.pictures.scan_picture` (the points on the
        frame) when asked for; b'' otherwise
    dot : (K,) bool, True for the points of identified dots (``dot_points`` of the scan's
        options; after the stripes' points), or None without them
    """

    points: NDArray[np.float64]
    u: NDArray[np.float64]
    v: NDArray[np.float64]
    slit: NDArray[np.int64]
    confidence: NDArray[np.float64]
    slits: int
    ms: float
    message: str = ""
    picture: bytes = b""
    dot: NDArray[np.bool_] | None = None


def scan_frame(
    image: NDArray,
    reference: ReferenceSet,
    calibration: Calibration,
    *,
    name: str = "",
    picture: bool = False,
    options: ScanOptions | None = None,
) -> FrameResult:
    """Scan one frame with :func:`multislit.scan_image` (the settings of ``multislit scan``).

    Parameters
    ----------
    image : (H, W) uint8 or uint16, the calibrated size
    reference, calibration : the capture's prepared reference set and calibration
    name : str, a name for messages. Default ''.
    options : :class:`~multislit.reconstruct.ScanOptions`, optional; default the defaults
    picture : bool
        Draw the frame's picture (:func:`~multislit.app.pictures.scan_picture`) into the
        result. Default False.
    """
    res, ms = _timed_scan(image, reference, calibration, name, None, options)
    return _frame_result(res, ms, image if picture else None, reference.num_slits)


def _timed_scan(
    image: NDArray,
    reference: ReferenceSet,
    calibration: Calibration,
    name: str,
    previous: ScanResult | None,
    options: ScanOptions | None = None,
) -> tuple[ScanResult, float]:
    t0 = time.perf_counter()
    res = scan_image(image, reference, calibration, options, name=name, previous=previous)
    return res, (time.perf_counter() - t0) * 1000.0


def _frame_result(
    res: ScanResult, ms: float, image: NDArray | None = None, num_slits: int | None = None
) -> FrameResult:
    """The frame's result; with ``image``, its picture too (slit colours over ``num_slits``)."""
    picture = b""
    if image is not None:
        picture = encode_png(scan_picture(image, res, num_slits=num_slits))
    points, cols = res.ply_columns()
    return FrameResult(
        points,
        cols["u"],
        cols["v"],
        cols["slit"],
        cols["confidence"],
        res.num_slits_found,
        ms,
        res.message,
        picture,
        cols.get("dot"),
    )


# --------------------------------------------------------------------------- output
class FrameWriter:
    """Writes frames to an OUT folder: the PLY whole, then its line in ``frames.jsonl``.

    Nothing is written or removed before the first frame: a run that fails before it
    leaves the folder as it was (no empty index that would then need ``overwrite``).

    Parameters
    ----------
    out : folder (created at the first frame if needed)
    overwrite : bool
        Remove the frames and index already in ``out`` (``frame_NNNNNN.ply`` and ``.png``, the
        index, ``run.json`` and the temporary files of a killed run; no other file) when the
        first frame is written; without it, a folder that holds frames is refused. Default
        False.
    run : dict, optional
        How the run is made (capture, calibration, source, options), written to ``run.json``
        beside the index with the first frame. Default: no ``run.json``.

    Raises
    ------
    MeasurementError
        ``out`` is a file, cannot be created or written, or holds frames (without
        ``overwrite``).
    """

    def __init__(
        self,
        out: str | os.PathLike[str],
        *,
        overwrite: bool = False,
        run: dict[str, Any] | None = None,
    ) -> None:
        try:
            self.out = check_output_dir(out, "-o")
        except MultislitError as exc:
            raise MeasurementError(str(exc)) from None
        old = _frame_files(self.out)
        if old and not overwrite:
            raise MeasurementError(
                f"-o {self.out}: the folder already holds frames ({old[0].name}, ...); give an "
                "empty folder or --overwrite"
            )
        self._old = old
        self.run = run
        self._fd = -1
        self._closed = False
        self.frames = 0

    def _open(self) -> None:
        """Make the folder, remove the old frames (``overwrite``), start the index."""
        try:
            self.out.mkdir(parents=True, exist_ok=True)
            for p in [*self._old, *_frame_files(self.out, temporary=True)]:
                p.unlink(missing_ok=True)
            if self.run is not None:
                write_json(self.out / RUN_FILE, self.run)
            self._fd = os.open(
                self.out / INDEX_FILE, os.O_WRONLY | os.O_CREAT | os.O_APPEND | os.O_TRUNC, 0o644
            )
        except OSError as exc:
            raise MeasurementError(f"-o {self.out}: cannot write there ({exc})") from None
        self._old = []

    def write(self, source: str, result: FrameResult) -> Path:
        """Write the next frame; returns its PLY path."""
        if self._closed:
            raise MeasurementError(f"-o {self.out}: the writer is closed")
        if self._fd < 0:
            self._open()
        path = self.out / frame_file(self.frames)
        label = " ".join(str(source).split())
        if result.picture:
            write_bytes_atomic(self.out / picture_file(self.frames), result.picture)
        write_ply(
            path,
            result.points,
            u=result.u,
            v=result.v,
            slit=result.slit,
            confidence=result.confidence,
            **({} if result.dot is None else {"dot": result.dot}),
            comment=f"multislit frame {self.frames} of {label}",
        )
        line = {
            "frame": self.frames,
            "source": str(source),
            "points": int(len(result.points)),
            "slits": int(result.slits),
            "ms": round(float(result.ms), 1),
        }
        if result.message:
            line["message"] = result.message
        data = (json.dumps(json_safe(line)) + "\n").encode("utf-8")
        os.write(self._fd, data)  # one append: the line is whole or absent
        os.fsync(self._fd)
        self.frames += 1
        return path

    def close(self) -> None:
        self._closed = True
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1


#: The files of an OUT folder that a run writes: its frames, pictures, index and run record;
#: with ``temporary``, the temporary files of a killed write (``.frame_000000.ply.XXXX.tmp``).
_FRAME_NAME = re.compile(r"frame_\d{6,}\.(ply|png)")
_TEMPORARY_NAME = re.compile(r"\.(frame_\d{6,}\.(ply|png)|run\.json)\..+\.tmp")


def _frame_files(out: Path, *, temporary: bool = False) -> list[Path]:
    """The frame files (or their temporary files) and the index in ``out``, sorted."""
    if not out.is_dir():
        return []
    pattern = _TEMPORARY_NAME if temporary else _FRAME_NAME
    found = sorted(p for p in out.iterdir() if pattern.fullmatch(p.name))
    if not temporary:
        found += [out / name for name in (INDEX_FILE, RUN_FILE) if (out / name).exists()]
    return found


# --------------------------------------------------------------------------- runners
class Runner(Protocol):
    """Scans frames somewhere: ``submit`` returns a handle, ``result`` waits for it."""

    capacity: int

    def submit(self, image: NDArray, name: str) -> Any: ...

    def done(self, handle: Any) -> bool: ...

    def result(self, handle: Any) -> FrameResult: ...

    def close(self) -> None: ...


class InlineRunner:
    """Scans each frame at once in this process, in order; with ``prior``, each frame's slit
    labels are the prior for the next frame's identification (``scan_image(previous=)``)."""

    capacity = 1

    def __init__(
        self,
        reference: ReferenceSet,
        calibration: Calibration,
        *,
        prior: bool = False,
        pictures: bool = False,
        options: ScanOptions | None = None,
    ) -> None:
        self.reference, self.calibration, self.prior = reference, calibration, bool(prior)
        self.pictures, self.options = bool(pictures), options
        self._last: ScanResult | None = None
        compile_kernels()  # loaded before the first frame, which then costs what the others do

    def submit(self, image: NDArray, name: str) -> FrameResult:
        res, ms = _timed_scan(
            image, self.reference, self.calibration, name, self._last, self.options
        )
        if self.prior:
            self._last = res
        return _frame_result(res, ms, image if self.pictures else None, self.reference.num_slits)

    def done(self, handle: FrameResult) -> bool:
        return True

    def result(self, handle: FrameResult) -> FrameResult:
        return handle

    def close(self) -> None:
        pass


_WORKER: dict[str, Any] = {}


def precompute_reference(reference: ReferenceSet) -> ReferenceSet:
    """``reference`` with the data identification derives from it (window sums of the dot
    images, their padded copy) computed now, so that it travels with the set to worker
    processes instead of being computed again in each."""
    return prepare_scoring(reference)


def _watch_parent(parent: int) -> None:
    """End this worker process as soon as its parent ``parent`` (a pid) has ended (killed,
    even by SIGKILL, which leaves it no time to end its workers): polled every
    ``_PARENT_POLL_S``."""
    while os.getppid() == parent:
        time.sleep(_PARENT_POLL_S)
    os._exit(1)


def _init_worker(
    reference: ReferenceSet,
    calibration: Calibration,
    parent: int,
    pictures: bool,
    options: ScanOptions | None,
) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    threading.Thread(target=_watch_parent, args=(parent,), name="parent", daemon=True).start()
    set_threads(1)  # a core per worker process: the processes are the parallelism
    compile_kernels()  # loaded before the first frame, which then costs what the others do
    _WORKER["reference"], _WORKER["calibration"] = reference, calibration
    _WORKER["pictures"], _WORKER["options"] = pictures, options


def _scan_in_worker(image: NDArray, name: str) -> FrameResult:
    return scan_frame(
        image,
        _WORKER["reference"],
        _WORKER["calibration"],
        name=name,
        picture=_WORKER["pictures"],
        options=_WORKER["options"],
    )


class ProcessRunner:
    """Scans frames in ``workers`` processes; the reference and calibration go to each once."""

    def __init__(
        self,
        reference: ReferenceSet,
        calibration: Calibration,
        workers: int,
        *,
        live: bool,
        pictures: bool = False,
        options: ScanOptions | None = None,
    ) -> None:
        self.capacity = workers if live else _INFLIGHT_PER_WORKER * workers
        self._pool = ProcessPoolExecutor(
            max_workers=workers,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=_init_worker,
            initargs=(
                precompute_reference(reference),
                calibration,
                os.getpid(),
                bool(pictures),
                options,
            ),
        )

    def submit(self, image: NDArray, name: str) -> Future:
        return self._pool.submit(_scan_in_worker, image, name)

    def done(self, handle: Future) -> bool:
        return handle.done()

    def result(self, handle: Future) -> FrameResult:
        return handle.result()

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


# --------------------------------------------------------------------------- the loop
@dataclass(frozen=True)
class StreamSummary:
    """What a run did.

    Attributes
    ----------
    frames : frames written
    skipped : frames skipped (wrong size or unreadable)
    dropped : live frames the camera delivered while the pipeline was busy (not scanned)
    seconds : s, from the first frame read to the last written
    out : the OUT folder
    empty : frames written that gave no points
    """

    frames: int
    skipped: int
    dropped: int
    seconds: float
    out: Path
    empty: int = 0

    @property
    def fps(self) -> float:
        """Frames written per second."""
        return self.frames / self.seconds if self.seconds > 0 else 0.0

    def line(self, prefix: str = "") -> str:
        return (
            f"{prefix}{self.frames} frames, {self.fps:.2f} fps, {self.dropped} dropped, "
            f"{self.skipped} skipped" + (f", {self.empty} without points" if self.empty else "")
        )


class ProgressLine:
    """The progress line on stderr (frames, fps, dropped, skipped): rewritten in place on a
    terminal, a line every few seconds otherwise. Call it as ``progress`` of
    :func:`run_frames`.

    Parameters
    ----------
    prefix : str, the text before the counts, e.g. ``"stream: "``
    """

    def __init__(self, prefix: str) -> None:
        self.prefix = prefix
        self.tty = sys.stderr.isatty()
        self._last = 0.0

    def __call__(self, s: StreamSummary, final: bool = False) -> None:
        now = time.perf_counter()
        if self.tty:
            sys.stderr.write("\r" + s.line(self.prefix) + ("\n" if final else ""))
        elif final or now - self._last >= _PROGRESS_EVERY_S:
            sys.stderr.write(s.line(self.prefix) + "\n")
            self._last = now
        sys.stderr.flush()


def run_frames(
    source: FrameSource,
    writer: FrameWriter,
    runner: Runner,
    *,
    image_size: tuple[int, int],
    max_frames: int | None = None,
    on_bad_frame: str = "skip",
    progress: Callable[..., None] | None = None,
) -> StreamSummary:
    """Scan the frames of ``source`` with ``runner`` and write them in order with ``writer``.

    Parameters
    ----------
    source : an opened frame source (closed by the caller)
    writer : the OUT folder's writer (closed by the caller)
    runner : scans frames (:class:`InlineRunner`, :class:`ProcessRunner`, a Dask runner)
    image_size : (W, H) px, the calibrated size; other frames are bad frames
    max_frames : int, optional
        Stop after this many frames are written. Default: the whole source.
    on_bad_frame : {'skip', 'stop'}
        A frame of the wrong size or that cannot be read: skip it and count it, or stop with
        an error (after writing the frames before it). Default skip.
    progress : called as ``progress(summary)`` as frames finish or are skipped and
        ``progress(summary, final=True)`` at the end. Default none.

    Returns
    -------
    StreamSummary

    Raises
    ------
    MeasurementError
        A bad frame with ``on_bad_frame='stop'``; a live camera that gives no usable frame
        for ``_LIVE_BAD_FRAMES_S``; a run in which no frame gave points (every frame skipped
        or empty: the reason of the first is named, after the frames are written); errors of
        the source or of a frame's scan.
    """
    with _BetweenFrames() as check:
        return _run_frames(
            source, writer, runner, image_size, max_frames, on_bad_frame, progress, check
        )


class _BetweenFrames:
    """A context in which Ctrl-C (SIGINT) is noted and raised as ``KeyboardInterrupt`` where
    the run calls it (before each frame is read, after each is written), not at whatever line
    it arrives: there it may land in a finaliser (a Dask future's), which swallows it, and the
    run would go on. A second Ctrl-C raises at once. Off the main thread, or where SIGINT is
    ignored, nothing changes."""

    def __init__(self) -> None:
        self._seen = False
        self._installed = False
        self._old: Any = None

    def __enter__(self) -> Callable[[], None]:
        if threading.current_thread() is threading.main_thread():
            if signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:
                self._old = signal.signal(signal.SIGINT, self._note)
                self._installed = True
        return self._check

    def __exit__(self, *exc: object) -> None:
        if self._installed:
            # None: a handler not set from Python; the default one stands in for it
            signal.signal(signal.SIGINT, signal.SIG_DFL if self._old is None else self._old)

    def _note(self, signum: int, frame: object) -> None:
        if self._seen:
            raise KeyboardInterrupt
        self._seen = True

    def _check(self) -> None:
        if self._seen:
            raise KeyboardInterrupt


def _run_frames(
    source: FrameSource,
    writer: FrameWriter,
    runner: Runner,
    image_size: tuple[int, int],
    max_frames: int | None,
    on_bad_frame: str,
    progress: Callable[..., None] | None,
    check: Callable[[], None],
) -> StreamSummary:
    """:func:`run_frames`, calling ``check`` between frames (it raises on Ctrl-C)."""
    w, h = image_size
    pending: deque[tuple[str, Any]] = deque()
    skipped = empty = with_points = 0
    first_skip = first_empty = ""
    t0: float | None = None
    last_usable = time.perf_counter()
    frames = source.frames()

    def summary() -> StreamSummary:
        dt = time.perf_counter() - t0 if t0 is not None else 0.0
        return StreamSummary(writer.frames, skipped, source.dropped, dt, writer.out, empty)

    def write_head() -> None:
        nonlocal empty, with_points, first_empty
        name, handle = pending.popleft()
        result = runner.result(handle)
        writer.write(name, result)
        if len(result.points):
            with_points += 1
        else:
            empty += 1
            first_empty = first_empty or f"{name}: {result.message or 'no points'}"
        if progress:
            progress(summary())
        check()

    while True:
        check()
        while len(pending) >= runner.capacity:
            write_head()
        while pending and runner.done(pending[0][1]):
            write_head()
        if max_frames is not None and writer.frames + len(pending) >= max_frames:
            break
        fr = next(frames, None)
        if fr is None:
            break
        if t0 is None:
            t0 = time.perf_counter()
        problem = fr.error
        if not problem and fr.image is not None and fr.image.shape != (h, w):
            problem = (
                f"frame {fr.source} is {fr.image.shape[1]}x{fr.image.shape[0]} px but the "
                f"calibration is for {w}x{h} px"
            )
        if problem:
            if on_bad_frame == "stop":
                while pending:  # the frames before it are written
                    write_head()
                raise MeasurementError(f"{problem} (--on-bad-frame skip to skip such frames)")
            skipped += 1
            first_skip = first_skip or problem
            if progress:
                progress(summary())
            if source.live and time.perf_counter() - last_usable > _LIVE_BAD_FRAMES_S:
                while pending:
                    write_head()
                raise MeasurementError(
                    f"SOURCE {source.name}: no usable frame for {_LIVE_BAD_FRAMES_S:.0f} s "
                    f"({skipped} skipped; the last: {problem})"
                )
            continue
        last_usable = time.perf_counter()
        pending.append((fr.source, runner.submit(fr.image, fr.source)))
    while pending:
        write_head()
    out = summary()
    if progress:
        progress(out, final=True)
    if with_points == 0:
        raise MeasurementError(_nothing_usable(source.name, out, first_skip, first_empty))
    return out


def _nothing_usable(name: str, s: StreamSummary, first_skip: str, first_empty: str) -> str:
    """Why a run gave no points at all: its counts and the first reason of each kind."""
    if not s.frames and not s.skipped:
        return f"SOURCE {name}: no frames"
    parts = []
    if s.skipped:
        parts.append(f"{s.skipped} skipped (first: {first_skip})")
    if s.empty:
        parts.append(
            f"{s.empty} written without points (first: {first_empty}; is --channel the "
            "laser's colour, and the calibration this rig's?)"
        )
    return f"no frame of {name} gave points: " + "; ".join(parts)


# --------------------------------------------------------------------------- stream
def run_record(
    command: str,
    capture: Capture,
    calibration: str | os.PathLike[str] | None,
    source: str | os.PathLike[str],
    settings: dict[str, Any],
    options: ScanOptions,
) -> dict[str, Any]:
    """What ``run.json`` says of a run: the command, the package's version, when it started,
    the capture and calibration (absolute paths), the SOURCE, the run's settings and the
    scan's options."""
    cal = Path(calibration) if calibration is not None else capture.root / CALIBRATION_FILE
    return {
        "format": RUN_FORMAT,
        "command": command,
        "version": __version__,
        "started": datetime.now(UTC).isoformat(timespec="seconds").replace("+00:00", "Z"),
        "capture": os.fsdecode(capture.root.resolve()),
        "calibration": os.fsdecode(cal.resolve()),
        "source": os.fsdecode(os.fspath(source)),
        "settings": settings,
        "options": options.to_dict(),
    }


def laser_channel(capture: Capture, channel: str | None) -> str:
    """``channel`` if given, else the capture's (:attr:`~multislit.io.Capture.laser_channel`:
    rig.json's ``laser_channel``, else auto)."""
    return channel if channel is not None else capture.laser_channel


def _positive(x: int | None, name: str, allow_none: bool = False) -> None:
    if x is None and allow_none:
        return
    if isinstance(x, bool) or not isinstance(x, int) or x < 1:
        flag = "--" + name.replace("_", "-")
        raise MeasurementError(f"{name} ({flag}) must be an integer >= 1, got {x!r}")


def max_workers() -> int:
    """The most worker processes a run may start: ``_WORKERS_PER_CORE`` per core."""
    return _WORKERS_PER_CORE * (os.cpu_count() or 1)


def check_frame_options(
    workers: int, every: int, max_frames: int | None, on_bad_frame: str
) -> None:
    """The checks of the options :func:`stream` and ``batch`` share (one line naming the
    option, a :class:`~multislit.errors.MeasurementError`)."""
    _positive(workers, "workers")
    if workers > max_workers():
        raise MeasurementError(
            f"workers (--workers) must be at most {max_workers()} ({_WORKERS_PER_CORE} per core "
            f"of this machine's {os.cpu_count() or 1}), got {workers}"
        )
    _positive(every, "every")
    _positive(max_frames, "max_frames", allow_none=True)
    if on_bad_frame not in ("skip", "stop"):
        raise MeasurementError(f"on_bad_frame must be 'skip' or 'stop', got {on_bad_frame!r}")


def stream(
    capture: str | os.PathLike[str] | Capture,
    source: str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    workers: int = 1,
    max_frames: int | None = None,
    every: int = 1,
    on_bad_frame: str = "skip",
    options: ScanOptions | None = None,
    calibration: str | os.PathLike[str] | None = None,
    camera_features: Sequence[tuple[str, str]] = (),
    overwrite: bool = False,
    prior: bool = False,
    pictures: bool = False,
    progress: Callable[..., None] | None = None,
) -> StreamSummary:
    """Scan every frame of ``source`` and write ``out`` (see the module's text).

    Parameters
    ----------
    capture : the capture folder (rig.json, reference/, calibration.json) or an opened Capture
    source : a folder or glob of images, a video file, ``camera:N``, ``basler:[SERIAL]``
    out : the OUT folder
    workers : int
        Processes that scan frames; 1 (default) scans in this process.
    max_frames : int, optional
        Stop after this many frames. Default: all.
    every : int
        Scan every ``every``-th frame of the source. Default 1.
    on_bad_frame : {'skip', 'stop'}
        Frames of the wrong size or unreadable: skip and count, or stop. Default skip.
    options : :class:`~multislit.reconstruct.ScanOptions`, optional
        The scan's options (:func:`multislit.scan_image`), written to ``run.json``. Colour
        frames are read in the extraction's channel (``auto``: in each frame the plane in
        which the stripes stand out most, clipped planes avoided); without one, rig.json's
        ``laser_channel``, else auto. Default ``ScanOptions()``.
    calibration : calibration file. Default ``CAPTURE/calibration.json``.
    camera_features : (name, value) pairs set on a Basler camera. Default none.
    overwrite : bool
        Replace the frames already in ``out``. Default False.
    prior : bool
        Identify each frame with the previous frame's slits as a prior (``scan_image``'s
        ``previous``): a stripe where the last frame had slit k is checked against k-1..k+1
        and searched in full only when the check fails. Faster on a moving scene, the same
        slit numbers; confidences are measured against the neighbouring slits, so a few
        points can differ from a single-image scan. Needs ``workers`` 1 (frames in order).
        Default False.
    pictures : bool
        Write beside each frame's PLY its picture, ``frame_000000.png``: the frame with the
        stripe points coloured by slit and the stripe centres left out in magenta
        (:func:`~multislit.app.pictures.scan_picture`). Default False.
    progress : see :func:`run_frames`

    Raises
    ------
    MultislitError
        A bad capture, calibration, SOURCE, OUT, option or (with ``on_bad_frame='stop'``)
        frame; a run in which no frame gave points (see :func:`run_frames`).
    """
    check_frame_options(workers, every, max_frames, on_bad_frame)
    opts = as_scan_options(options)
    if prior and opts.identification.method != "template":
        raise MeasurementError(
            "prior: the previous frame's slits are a prior for the template identification "
            "only; add --method template, or leave out --prior"
        )
    if prior and workers != 1:
        raise MeasurementError(
            f"prior needs the frames in order in one process: use workers 1, not {workers}"
        )
    as_path(source, "SOURCE", error=CaptureError)
    writer = FrameWriter(out, overwrite=overwrite)
    cap = capture if isinstance(capture, Capture) else Capture.open(capture, require_target=False)
    cal = load_capture_calibration(cap, calibration)
    channel = laser_channel(cap, opts.extraction.channel)
    src = open_source(
        source, channel=channel, every=every, image_size=cap.image_size, features=camera_features
    )
    settings = {"channel": channel, "every": every, "prior": prior, "workers": workers}
    writer.run = run_record("stream", cap, calibration, source, settings, opts)
    runner = None
    try:
        ref = capture_reference(cap)
        if workers == 1:
            runner = InlineRunner(ref, cal, prior=prior, pictures=pictures, options=opts)
        else:
            runner = ProcessRunner(
                ref, cal, workers, live=src.live, pictures=pictures, options=opts
            )
        return run_frames(
            src,
            writer,
            runner,
            image_size=cap.image_size,
            max_frames=max_frames,
            on_bad_frame=on_bad_frame,
            progress=progress,
        )
    finally:
        src.close()
        if runner is not None:
            runner.close()
        writer.close()
