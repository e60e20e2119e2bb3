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

import logging
import os
from collections.abc import Callable
from typing import Any

from numpy.typing import NDArray

from multislit.app.stream import (
    FrameResult,
    FrameWriter,
    StreamSummary,
    check_frame_options,
    laser_channel,
    precompute_reference,
    run_frames,
    scan_frame,
)
from multislit.errors import MeasurementError
from multislit.identify import capture_reference
from multislit.io import Capture
from multislit.io.sources import open_source
from multislit.reconstruct import load_capture_calibration

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


def _one_thread() -> None:
    import cv2

    cv2.setNumThreads(1)


class DaskRunner:
    """Scans frames on a Dask cluster; the reference and calibration are on every worker once.

    Parameters
    ----------
    client : a connected ``dask.distributed.Client``
    reference, calibration : the capture's prepared reference set and calibration
    """

    def __init__(self, client: Any, reference: Any, calibration: Any) -> None:
        self.client = client
        workers = max(1, len(client.scheduler_info().get("workers", {})))
        self.capacity = _INFLIGHT_PER_WORKER * workers
        self._ref = client.scatter(precompute_reference(reference), broadcast=True)
        self._cal = client.scatter(calibration, broadcast=True)

    def submit(self, image: NDArray, name: str) -> Any:
        # hash=False: frames alike (a static or dark scene) get keys of their own; with content
        # keys one finished frame releases the data that a later, equal one still needs
        img = self.client.scatter(image, hash=False)
        return self.client.submit(scan_frame, img, self._ref, self._cal, name=name, pure=False)

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
    channel: str | None = None,
    calibration: str | os.PathLike[str] | None = None,
    overwrite: bool = False,
    progress: Callable[..., None] | None = None,
) -> StreamSummary:
    """Scan the frames of ``source`` on a Dask cluster and write ``out`` like ``stream``.

    Parameters
    ----------
    capture, source, out, max_frames, every, on_bad_frame, channel, calibration, overwrite,
    progress :
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
    distributed = _dask()
    cap = capture if isinstance(capture, Capture) else Capture.open(capture, require_target=False)
    cal = load_capture_calibration(cap, calibration)
    src = open_source(source, channel=laser_channel(cap, channel), every=every)
    writer = cluster = client = None
    try:
        if address:
            try:
                client = distributed.Client(address, timeout=_CONNECT_TIMEOUT_S)
            except (OSError, TimeoutError) as exc:
                raise MeasurementError(
                    f"--dask {address}: cannot reach the Dask scheduler ({exc})"
                ) from None
        else:
            import dask

            # Dask sets MALLOC_TRIM_THRESHOLD_=65536 in its worker processes by default: glibc
            # then returns every large array's memory at once and scans run about twice as
            # slowly; the workers of this cluster keep glibc's own setting.
            with dask.config.set({_TRIM_KEY: None}):
                cluster = distributed.LocalCluster(
                    n_workers=workers,
                    threads_per_worker=1,
                    processes=processes,
                    dashboard_address=None,
                    silence_logs=logging.ERROR,
                )
            client = distributed.Client(cluster)
            if processes:
                client.run(_one_thread)  # a core per worker process
        writer = FrameWriter(out, overwrite=overwrite)
        ref = capture_reference(cap)
        return run_frames(
            src,
            writer,
            DaskRunner(client, ref, cal),
            image_size=cap.image_size,
            max_frames=max_frames,
            on_bad_frame=on_bad_frame,
            progress=progress,
        )
    finally:
        src.close()
        if writer is not None:
            writer.close()
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()
