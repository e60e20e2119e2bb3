"""Archives on a Dask cluster (``multislit batch``): the frames of a SOURCE scanned by Dask
workers, written to the same OUT folder as ``multislit stream`` writes.

The reference set and the calibration are scattered to every worker once; each frame's image
goes to a worker with its task, and the points come back to this process, which writes the
frames in the source's order (:func:`multislit.app.stream.run_frames`). Without a scheduler
address a local cluster of worker processes is started for the run.

Needs the optional extra ``pip install 'multislit[dask]'`` (``dask.distributed``). Workers of
a cluster of your own scan about twice as fast when started without Dask's default
``MALLOC_TRIM_THRESHOLD_=65536`` (Dask setting ``distributed.nanny.pre-spawn-environ``).
"""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import Any

import numba
from numpy.typing import NDArray

from multislit import compile_kernels, set_threads
from multislit.app.stream import (
    FrameResult,
    FrameWriter,
    StreamSummary,
    check_frame_options,
    laser_channel,
    precompute_reference,
    run_frames,
    run_record,
    scan_frame,
)
from multislit.errors import CaptureError, MeasurementError
from multislit.identify import capture_reference
from multislit.io import Capture
from multislit.io.paths import as_path
from multislit.io.sources import open_source
from multislit.reconstruct import ScanOptions, load_capture_calibration
from multislit.reconstruct.options import as_scan_options

__all__ = ["DaskRunner", "batch"]

_INFLIGHT_PER_WORKER = 3  # frames queued per Dask worker
_CONNECT_TIMEOUT_S = 10
_TRIM_KEY = "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_"


def _dask():
    try:
        from dask import distributed
    except ImportError:
        raise MeasurementError(
            "multislit batch needs dask.distributed: pip install 'multislit[dask]'"
        ) from None
    return distributed


#: Address schemes of Dask's communication layer.
_SCHEMES = ("tcp", "tls", "ws", "wss", "ucx", "inproc")


def check_address(address: object) -> str:
    """``address`` if it is a Dask scheduler address (``[SCHEME://]HOST:PORT``); else a
    :class:`~multislit.errors.MeasurementError` naming ``--dask`` and the problem."""
    example = "e.g. tcp://192.168.1.10:8786"
    if not isinstance(address, str) or not address.strip():
        raise MeasurementError(f"--dask {address!r}: give the scheduler's address, {example}")
    scheme, sep, location = address.partition("://")
    if not sep:
        scheme, location = "tcp", address
    if scheme not in _SCHEMES:
        raise MeasurementError(
            f"--dask {address}: unknown scheme {scheme!r} (one of {', '.join(_SCHEMES)}); {example}"
        )
    if scheme == "inproc":
        return address
    host, colon, port = location.rpartition(":")
    host = host.strip("[]")  # an IPv6 address: [::1]:8786
    if (
        not colon
        or not host
        or not (port.isascii() and port.isdigit())
        or not 0 < int(port) < 65536
    ):
        raise MeasurementError(
            f"--dask {address}: give the host and a port number 1-65535 as HOST:PORT; {example}"
        )
    return address


async def _identity(address: str, timeout: float) -> Any:
    """The scheduler's answer to an 'identity' message, within ``timeout`` s in all."""
    from distributed.comm import connect

    async def ask() -> Any:
        comm = await connect(address, timeout=timeout)
        try:
            await comm.write({"op": "identity", "reply": True})
            return await comm.read()
        finally:
            comm.abort()

    return await asyncio.wait_for(ask(), timeout)


def _probe(address: str, timeout: float) -> None:
    """Raise a one-line MeasurementError unless a Dask scheduler answers at ``address`` within
    ``timeout`` s (a Dask client alone waits for ever on a server that accepts the connection
    and never answers)."""
    with ThreadPoolExecutor(1) as pool:  # its own event loop, whatever runs in this thread
        try:
            reply = pool.submit(asyncio.run, _identity(address, timeout)).result()
        except TimeoutError:
            reply = f"no answer in {timeout:g} s"
        except Exception as exc:  # noqa: BLE001 - any failure to talk is the one message
            reply = str(exc) or type(exc).__name__
    if isinstance(reply, dict) and reply.get("type") == "Scheduler":
        return
    why = reply if isinstance(reply, str) else "the server there is not a Dask scheduler"
    raise MeasurementError(f"--dask {address}: cannot reach the Dask scheduler ({why})")


@contextmanager
def _loop_errors_quiet() -> Iterator[None]:
    """The Dask client's event loop does not print its callbacks' errors while the command
    runs: a Ctrl-C in the middle of one of the client's calls makes Dask log one with a
    traceback (its call's cancellation), and the command then says "interrupted" itself. The
    frames' own errors come back through their futures."""
    log = logging.getLogger("tornado.application")
    old = log.level
    log.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        log.setLevel(old)


@contextmanager
def _sigint_ignored() -> Iterator[None]:
    """Ctrl-C ignored while the local cluster's processes start: they inherit it, so a Ctrl-C
    reaches only this process, which then closes the cluster (no worker tracebacks)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


def _one_thread() -> None:
    """A local worker process on one core: OpenCV's threads, which are the process's (Numba
    keeps its setting per thread: :func:`_scan_on_one_thread` sets it in each task's)."""
    set_threads(1)


def _scan_on_one_thread(*args: Any, **kwargs: Any) -> FrameResult:
    """:func:`scan_frame` with Numba's threads set to one in the task's thread (Numba keeps
    the setting per thread, and a Dask worker runs its tasks on threads of its own)."""
    numba.set_num_threads(1)
    return scan_frame(*args, **kwargs)


class DaskRunner:
    """Scans frames on a Dask cluster; the reference and calibration are on every worker once.

    Parameters
    ----------
    client : a connected ``dask.distributed.Client``
    reference, calibration : the capture's prepared reference set and calibration
    pictures, options : as :func:`batch`'s
    one_thread : each frame on one of Numba's threads (a local cluster: its workers are the
        parallelism); False: the workers' own setting
    """

    def __init__(
        self,
        client: Any,
        reference: Any,
        calibration: Any,
        *,
        pictures: bool = False,
        options: ScanOptions | None = None,
        one_thread: bool = False,
    ) -> None:
        self.client = client
        self._scan = _scan_on_one_thread if one_thread else scan_frame
        self.pictures, self.options = bool(pictures), options
        workers = max(1, len(client.scheduler_info().get("workers", {})))
        self.capacity = _INFLIGHT_PER_WORKER * workers
        self._ref = client.scatter(precompute_reference(reference), broadcast=True)
        self._cal = client.scatter(calibration, broadcast=True)

    def submit(self, image: NDArray, name: str) -> Any:
        # hash=False: frames alike (a static or dark scene) get keys of their own; with content
        # keys one finished frame releases the data that a later, equal one still needs
        img = self.client.scatter(image, hash=False)
        return self.client.submit(
            self._scan,
            img,
            self._ref,
            self._cal,
            name=name,
            picture=self.pictures,
            options=self.options,
            pure=False,
        )

    def done(self, handle: Any) -> bool:
        return handle.done()

    def result(self, handle: Any) -> FrameResult:
        return handle.result()

    def close(self) -> None:
        pass


def batch(
    capture: str | os.PathLike[str] | Capture,
    source: str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    address: str | None = None,
    workers: int = 2,
    processes: bool = True,
    max_frames: int | None = None,
    every: int = 1,
    on_bad_frame: str = "skip",
    options: ScanOptions | None = None,
    calibration: str | os.PathLike[str] | None = None,
    overwrite: bool = False,
    pictures: bool = False,
    progress: Callable[..., None] | None = None,
) -> StreamSummary:
    """Scan the frames of ``source`` on a Dask cluster and write ``out`` like ``stream``.

    Parameters
    ----------
    capture, source, out, max_frames, every, on_bad_frame, options, calibration, overwrite,
    pictures, progress :
        As :func:`multislit.app.stream.stream`.
    address : str, optional
        The Dask scheduler (``tcp://host:8786``). Default: a local cluster for this run.
    workers : int
        Workers of the local cluster (one thread each). Default 2; ignored with ``address``.
    processes : bool
        Local cluster workers in processes (True, default) or threads of this process.

    Raises
    ------
    MultislitError
        As :func:`~multislit.app.stream.stream`; a scheduler that cannot be reached; no Dask.
    """
    check_frame_options(workers, every, max_frames, on_bad_frame)
    opts = as_scan_options(options)
    if address is not None:
        check_address(address)
    as_path(source, "SOURCE", error=CaptureError)
    writer = FrameWriter(out, overwrite=overwrite)
    distributed = _dask()
    cap = capture if isinstance(capture, Capture) else Capture.open(capture, require_target=False)
    cal = load_capture_calibration(cap, calibration)
    channel = laser_channel(cap, opts.extraction.channel)
    src = open_source(source, channel=channel, every=every)
    settings = {"channel": channel, "every": every, "dask": address, "workers": workers}
    writer.run = run_record("batch", cap, calibration, source, settings, opts)
    cluster = client = None
    with _loop_errors_quiet():
        try:
            if address is not None:
                _probe(address, _CONNECT_TIMEOUT_S)
                try:
                    client = distributed.Client(address, timeout=_CONNECT_TIMEOUT_S)
                except (OSError, TimeoutError, ValueError) as exc:
                    raise MeasurementError(
                        f"--dask {address}: cannot reach the Dask scheduler ({exc})"
                    ) from None
            else:
                import dask

                # Dask sets MALLOC_TRIM_THRESHOLD_=65536 in its worker processes by default: glibc
                # then returns every large array's memory at once and scans run about twice as
                # slowly; the workers of this cluster keep glibc's own setting.
                with dask.config.set({_TRIM_KEY: None}), _sigint_ignored():
                    cluster = distributed.LocalCluster(
                        n_workers=workers,
                        threads_per_worker=1,
                        processes=processes,
                        dashboard_address=None,
                        # the workers' own log stays quiet: a frame's error comes back through
                        # its future, and at the end (Ctrl-C) a worker whose scheduler has just
                        # closed logs its failed heartbeat with a traceback
                        silence_logs=logging.CRITICAL,
                    )
                client = distributed.Client(cluster)
                if processes:
                    client.run(_one_thread)  # a core per worker process
            client.run(compile_kernels)  # each worker's compiled kernels before its first frame
            ref = capture_reference(cap)
            return run_frames(
                src,
                writer,
                DaskRunner(
                    client,
                    ref,
                    cal,
                    pictures=pictures,
                    options=opts,
                    one_thread=cluster is not None,
                ),
                image_size=cap.image_size,
                max_frames=max_frames,
                on_bad_frame=on_bad_frame,
                progress=progress,
            )
        finally:
            src.close()
            writer.close()
            if client is not None:
                client.close()
            if cluster is not None:
                cluster.close()
