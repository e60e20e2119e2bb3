"""The scan's hot path (extraction, identification, centre refinement, triangulation) makes no
array as large as a full-image float64 copy, even for a moment.

Every NumPy array buffer made during a scan is seen through a NumPy data allocator (NEP 49,
``PyDataMem_SetHandler``) installed for the duration of the scan: it hands the work to NumPy's
own allocator and notes each buffer of at least 8 bytes per image pixel (the size of an (H, W)
float64 array) with the Python stack that asked for it. Arrays that OpenCV's Python bindings
return are NumPy arrays and are seen too; the work arrays of compiled (Numba) kernels are not.
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import traceback
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

import multislit
from multislit.calibrate import Calibration, SlitPlanes
from multislit.geometry import MatrixCamera, PinholeCamera
from multislit.io import Capture
from multislit.reconstruct import scan_image
from multislit.sim import RigSpec, SimulatedRig, true_dot_projector
from multislit.stripes import extract_slits, refine_centres

try:
    from numpy._core import _multiarray_umath
except ImportError:  # NumPy 1.x
    from numpy.core import _multiarray_umath

# --------------------------------------------------------------------------- allocator
_MALLOC = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t)
_CALLOC = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t, ctypes.c_size_t)


class _Allocator(ctypes.Structure):  # PyDataMemAllocator (numpy/ndarraytypes.h)
    _fields_ = [(k, ctypes.c_void_p) for k in ("ctx", "malloc", "calloc", "realloc", "free")]


class _Handler(ctypes.Structure):  # PyDataMem_Handler, version 1
    _fields_ = [
        ("name", ctypes.c_char * 127),
        ("version", ctypes.c_uint8),
        ("allocator", _Allocator),
    ]


_py = ctypes.pythonapi
_py.PyCapsule_GetPointer.restype = ctypes.c_void_p
_py.PyCapsule_GetPointer.argtypes = [ctypes.py_object, ctypes.c_char_p]
_py.PyCapsule_New.restype = ctypes.py_object
_py.PyCapsule_New.argtypes = [ctypes.c_void_p, ctypes.c_char_p, ctypes.c_void_p]
_API = (ctypes.c_void_p * 306).from_address(
    _py.PyCapsule_GetPointer(_multiarray_umath._ARRAY_API, None)
)
_set_handler = ctypes.PYFUNCTYPE(ctypes.py_object, ctypes.py_object)(_API[304])
_get_handler = ctypes.PYFUNCTYPE(ctypes.py_object)(_API[305])

_seen: list[tuple[int, traceback.StackSummary]] = []
_threshold: list[int] = []  # empty: note nothing


def _note(size: int) -> None:
    if _threshold and size >= _threshold[0]:
        _seen.append((size, traceback.extract_stack()[:-2]))


def _make_handler() -> object:
    """A handler capsule that allocates with NumPy's default allocator and notes the large
    buffers. Freeing and resizing are NumPy's own C functions, so arrays made under it can
    outlive it; its parts are kept alive for the whole process."""
    default = _Handler.from_address(_py.PyCapsule_GetPointer(_get_handler(), b"mem_handler"))
    d = default.allocator
    # NumPy's functions release the GIL around the system call: called with the GIL held
    malloc = ctypes.PYFUNCTYPE(ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t)(d.malloc)
    calloc = ctypes.PYFUNCTYPE(ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t, ctypes.c_size_t)(
        d.calloc
    )

    def on_malloc(ctx: int | None, size: int) -> int | None:
        _note(size)
        return malloc(ctx, size)

    def on_calloc(ctx: int | None, n: int, size: int) -> int | None:
        _note(n * size)
        return calloc(ctx, n, size)

    hooks = (_MALLOC(on_malloc), _CALLOC(on_calloc))
    ours = _Handler(b"multislit_test_memory", 1)
    ours.allocator = _Allocator(
        d.ctx,
        ctypes.cast(hooks[0], ctypes.c_void_p),
        ctypes.cast(hooks[1], ctypes.c_void_p),
        d.realloc,
        d.free,
    )
    name = b"mem_handler"
    capsule = _py.PyCapsule_New(ctypes.addressof(ours), name, None)
    for obj in (ours, name, hooks, malloc, calloc, capsule):
        _py.Py_IncRef(ctypes.py_object(obj))  # never freed: arrays may point at them
    return capsule


_HANDLER = _make_handler()


@contextlib.contextmanager
def large_buffers(threshold: int) -> Iterator[list[tuple[int, traceback.StackSummary]]]:
    """The NumPy buffers of at least ``threshold`` bytes made inside the block: a list of
    (bytes, Python stack), filled as they are made."""
    _seen.clear()
    _threshold[:] = [int(threshold)]
    old = _set_handler(_HANDLER)
    try:
        yield _seen
    finally:
        _set_handler(old)
        _threshold.clear()


_PACKAGE = str(Path(multislit.__file__).resolve().parent)


def _ours(stack: traceback.StackSummary) -> list[traceback.FrameSummary]:
    """The package's frames of a stack, innermost first."""
    return [f for f in stack if str(Path(f.filename).resolve()).startswith(_PACKAGE)][::-1]


def _where(stack: traceback.StackSummary) -> str:
    """Where a buffer was made: 'folder/file:line' of the package's (else all) frames,
    innermost first, and the innermost line's code."""
    ours = _ours(stack) or list(stack)[::-1]
    return " <- ".join(
        f"{Path(f.filename).parent.name}/{Path(f.filename).name}:{f.lineno}" for f in ours[:4]
    ) + (f"  [{ours[0].line}]" if ours else "")


# --------------------------------------------------------------------------- tests
def test_large_buffers_sees_a_float64_copy_and_not_a_float32_one():
    """The check can fail: a full-image float64 copy is seen, a float32 one is not, and the
    usual allocator is back afterwards."""
    img = np.zeros((64, 80), np.uint8)
    with large_buffers(8 * img.size) as big:
        a = img.astype(np.float32) + 1
        b = np.zeros(img.shape)  # calloc
        c = (img + 0.5).sum()  # a transient float64 image
    assert (a.dtype, b.dtype, float(c)) == (np.float32, np.float64, 0.5 * img.size)
    assert [s for s, _ in big] == [8 * img.size] * 2
    assert "test_memory.py" in _where(big[0][1])
    with large_buffers(8 * img.size) as after:
        pass
    img.astype(np.float64)
    assert not after


def _truth_calibration(cap_dir: Path) -> Calibration:
    """The simulator's true camera, slit planes and dot projector as a calibration."""
    models = json.loads((cap_dir / "truth" / "models.json").read_text())
    cam = PinholeCamera.from_dict(models["camera"])
    planes = np.array(models["projector"]["planes"], np.float64)
    size = tuple(cam.image_size)
    sp = SlitPlanes(planes, np.zeros(len(planes)), np.full(len(planes), 10))
    rig = SimulatedRig.build(RigSpec.from_dict(Capture.open(cap_dir).rig["simulator"]["rig"]))
    return Calibration(
        size,
        MatrixCamera(cam.matrix, image_size=size),
        refined=cam,
        slit_planes=sp,
        dot_projector=true_dot_projector(rig),
    )


#: The identification's template work arrays: float32 stacks of one small patch per sample
#: point and candidate, so they grow with the number of points, not with the image, and on a
#: small frame they pass 8 bytes per pixel. Buffers made directly in these functions are not
#: counted; anything else of that size is.
_TEMPLATE_STACKS = frozenset(
    {
        ("patches.py", "_remap_patches"),
        ("patches.py", "normalise_patches"),
        ("patches.py", "bilinear_patch_moments"),
        ("matching.py", "_ncc_at"),
    }
)


def _image_sized(big: list, num_px: int) -> list[str]:
    """The buffers of ``big`` not made by a template stack, as lines for a message."""
    out = []
    for size, stack in big:
        inner = (_ours(stack) or [None])[0]
        if inner is None or (Path(inner.filename).name, inner.name) not in _TEMPLATE_STACKS:
            out.append(f"{size / num_px:.2f} bytes/px ({size} B): {_where(stack)}")
    return out


def test_scan_makes_no_full_image_float64_array(scenes_capture: Path, scenes_reference):
    """``scan_image`` on a half-size frame (after a first frame that builds the reference's
    caches and loads the compiled kernels) makes no buffer of 8 bytes per pixel or more -- no
    (H, W) float64 array nor anything as large -- apart from the template stacks."""
    cap = Capture.open(scenes_capture)
    cal = _truth_calibration(scenes_capture)
    img = cap.image(cap.scans[0])
    scan_image(img, scenes_reference, cal)
    with large_buffers(8 * img.size) as big:
        res = scan_image(img, scenes_reference, cal)
    assert res.num_points > 0.5 * res.num_centres  # the whole path ran
    found = _image_sized(big, img.size)
    assert not found, "full-image-sized buffers in the scan:\n" + "\n".join(found)


@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
def test_extraction_and_refinement_make_no_full_image_float64_array(
    scenes_capture: Path, scenes_reference, dtype
):
    """The same for extraction and centre refinement of a 16-bit and a float frame: no buffer
    of 8 bytes per pixel or more at all."""
    cap = Capture.open(scenes_capture)
    img8 = cap.image(cap.scans[0])
    img = img8.astype(dtype) * 257 if dtype == np.uint16 else img8.astype(dtype) / 255
    w, d = scenes_reference.stripe_width_px, scenes_reference.dot_size_px

    def run():
        ex = extract_slits(img, stripe_width_px=w, dot_size_px=d)
        return ex, *refine_centres(img, ex.u, ex.v, ex.segment, w, d)

    run()  # the kernels for this pixel type loaded
    with large_buffers(8 * img.size) as big:
        ex, _, ok = run()
    assert len(ex.u) > 1000 and ok.mean() > 0.5  # centres found and refined
    found = [f"{s / img.size:.2f} bytes/px ({s} B): {_where(st)}" for s, st in big]
    assert not found, "full-image-sized buffers:\n" + "\n".join(found)
