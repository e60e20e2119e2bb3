"""multislit.calibrate: camera and projector calibration from a capture folder.

:func:`calibrate_capture` turns a capture folder into a :class:`CalibrationResult`, whose
``calibration`` (:class:`Calibration`) the scans use; :func:`write_calibration` saves it with
its report. The building blocks live in the modules: ``camera`` (DLT and refinement),
``markers`` (checker corners), ``capture_camera`` (the camera of a capture), ``slit_points``
and ``slit_labels`` (points on the slits), ``slit_planes`` and ``projector`` (the projector
models and fits), ``boards`` (points on the slits from the reference boards), ``model`` (the
calibration file). :func:`compile_kernels` compiles the calibration's Numba kernels.
"""

import numpy as np

from multislit.calibrate.board_dots import board_catalogue, board_view, fit_rays_on_boards
from multislit.calibrate.camera import calibrate_dlt
from multislit.calibrate.model import Calibration
from multislit.calibrate.pipeline import (
    CalibrationResult,
    calibrate_capture,
    format_report,
    write_calibration,
)
from multislit.calibrate.projector import ProjectorMatrix
from multislit.calibrate.row_order import OrderParams, apply_run_offsets, row_runs, run_offsets
from multislit.calibrate.slit_planes import SlitPlanes, fit_slit_planes

__all__ = [
    "Calibration",
    "CalibrationResult",
    "ProjectorMatrix",
    "SlitPlanes",
    "calibrate_capture",
    "calibrate_dlt",
    "compile_kernels",
    "fit_slit_planes",
    "format_report",
    "write_calibration",
]


def compile_kernels() -> None:
    """Compile the calibration's Numba kernels now: a small synthetic reference board (five
    stripes, dots beside them) read for its dots (:func:`~.board_dots.board_view`,
    :func:`~.board_dots.board_catalogue`), its dots' rays fitted on it
    (:func:`~.board_dots.fit_rays_on_boards`), and its stripes labelled by their order in the
    rows (:mod:`~multislit.calibrate.row_order`).

    Numba compiles each kernel on first use and caches the machine code on disk beside the
    package; :func:`multislit.compile_kernels` calls this with the other stages' warm-ups.
    """
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:128, 0:128].astype(np.float64)
    img = 10.0 + sum(180.0 * np.exp(-0.5 * ((xx - c) / 1.5) ** 2) for c in (24, 44, 64, 84, 104))
    for cu, cv in rng.uniform(8.0, 120.0, size=(60, 2)):
        img += 90.0 * np.exp(-0.5 * ((xx - cu) ** 2 + (yy - cv) ** 2) / 1.1**2)
    img += rng.normal(0.0, 1.0, img.shape)
    view = board_view(np.clip(img, 0, 255).astype(np.uint8), 4.0, 2.6)
    dots, sharp = board_catalogue(view)
    view.z(dots.u, dots.v)
    n = len(dots)
    fit_rays_on_boards(
        [sharp],
        dots.uv[:, None, :].copy(),
        np.tile(np.eye(2), (n, 1, 1, 1)),
        dots.height[:, None].copy(),
        np.zeros((1, *sharp.response.shape)),
    )
    ex = view.extraction
    p = OrderParams()
    run, rank = row_runs(ex.u, ex.v, ex.segment >= 0, p)
    n_runs = int(run.max()) + 1
    offset = run_offsets(run, rank, rank.copy(), np.ones(len(run)), n_runs, p)
    apply_run_offsets(run, rank, offset, 5)
