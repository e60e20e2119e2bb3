"""The capture folder, format ``multislit-capture/1`` (see ``docs/capture-format.md``).

::

    <capture>/
      rig.json                {"format": "multislit-capture/1", "image_size": [W, H], "num_slits": N}
      target.json             markers, faces, optional slit_points (world = target frame, mm)
      calibration/markers.png target, lasers off
      calibration/slits.png   same pose, lasers on
      reference/*.png         >= 2 flat-board images at different distances, lasers on
      scans/*.png             measurement images, lasers on

Readers ignore keys and files they do not know and raise :class:`CaptureError` naming the file
and the problem for anything missing or malformed.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from multislit.errors import CaptureError
from multislit.io.jsonio import read_json, write_bytes_atomic, write_json
from multislit.io.paths import as_path, is_regular_file
from multislit.stripes.channels import resolve_channel
from multislit.stripes.validation import AUTO, CHANNEL_CHOICES, as_image

FORMAT = "multislit-capture/1"
MIN_REFERENCES = 2

#: Largest magnitude of a coordinate in target.json (mm for points, px for image positions):
#: a rig measures within metres, so anything beyond is a typing error.
_MAX_COORD = 1e6

#: Largest image side in rig.json, px.
_MAX_IMAGE_SIDE = 100_000


# --------------------------------------------------------------------------- images
def laser_plane(frame: NDArray, channel: str, *, name: str = "frame") -> NDArray:
    """The laser's plane of an image as OpenCV gives it: grayscale, BGR or BGRA, 8 or 16 bit.

    Parameters
    ----------
    frame : (H, W), (H, W, 1), (H, W, 3) BGR or (H, W, 4) BGRA array, uint8 or uint16
    channel : the plane of a colour image: ``"auto"`` (the plane in which the stripes stand
        out most, clipped planes avoided: :func:`~multislit.stripes.channels.choose_channel`),
        ``"red"``, ``"green"``, ``"blue"`` or ``"luma"`` (Rec. 601); a grayscale image is
        returned as it is
    name : what the image is, for messages (e.g. ``"image scans/a.png"``); default "frame"

    Returns
    -------
    (H, W) uint8 or uint16, C-contiguous

    Raises
    ------
    CaptureError
        (a ``ValueError``) for another shape or pixel type, or an unknown ``channel``.
    """
    img = np.asarray(frame)
    if img.dtype not in (np.uint8, np.uint16):
        raise CaptureError(f"{name} has pixel type {img.dtype}; expected 8- or 16-bit")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 3:
        if img.shape[2] not in (3, 4):
            raise CaptureError(f"{name} has {img.shape[2]} channels; expected 1, 3 or 4")
        try:  # the package's one image check picks the plane of OpenCV's BGR(A) order
            plane = resolve_channel(img[:, :, :3], channel, order="bgr")
            img = np.ascontiguousarray(as_image(img, name=name, channel=plane, order="bgr"))
        except ValueError as exc:
            raise CaptureError(str(exc)) from None
    if img.ndim != 2:
        raise CaptureError(f"{name} has shape {img.shape}; expected (H, W) or (H, W, 3) pixels")
    return img


@contextmanager
def quiet_opencv() -> Iterator[None]:
    """OpenCV's own log lines off (its failure is reported as one line of ours)."""
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        yield
    finally:
        cv2.utils.logging.setLogLevel(level)


def _jpeg_complete(data: bytes) -> bool:
    """Whether JPEG ``data`` holds its image's end: an end-of-image marker (FF D9) after the
    last start-of-scan (FF DA). The coded data escapes every FF byte, so the marker cannot
    occur inside it; a thumbnail's end comes before the main image's scan."""
    sos = data.rfind(b"\xff\xda")
    return sos >= 0 and data.find(b"\xff\xd9", sos + 2) >= 0


def decode_image_file(path: Path) -> NDArray:
    """The pixels of an image file as OpenCV decodes them (grayscale, BGR or BGRA; any depth).

    A JPEG whose data ends before its image does (a file cut short while copied or
    written) is refused, not decoded into a frame whose lower part is grey.

    Raises
    ------
    CaptureError
        Not a regular file, unreadable, a truncated JPEG, or data OpenCV cannot decode.
    """
    if not is_regular_file(path):
        raise CaptureError(f"image {path} is not a file (a folder, device or pipe)")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise CaptureError(f"cannot read image {path}: {exc.strerror or exc}") from None
    if data[:3] == b"\xff\xd8\xff" and not _jpeg_complete(data):
        raise CaptureError(f"image {path} is a truncated JPEG (its data ends before the image)")
    with quiet_opencv():
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise CaptureError(
            f"cannot read image {path}: not a valid PNG, TIFF or JPEG (OpenCV cannot decode it)"
        )
    return img


def read_image(
    path: str | Path, expected_size: tuple[int, int] | None = None, *, channel: str = AUTO
) -> NDArray:
    """Read an 8- or 16-bit image (PNG, or any format OpenCV reads) as one plane.

    Parameters
    ----------
    path : path of the image
    expected_size : (W, H) px, optional; a different size is an error
    channel : the plane of a colour image: ``"auto"`` (default: the plane in which the
        stripes stand out most, clipped planes avoided), ``"red"``, ``"green"``, ``"blue"`` or
        ``"luma"`` (Rec. 601); a grayscale image is returned as it is

    Returns
    -------
    image : (H, W) uint8 or uint16

    Raises
    ------
    CaptureError
        A missing, unreadable or truncated file, another pixel type, or another size.
    """
    p = as_path(path, "image path", error=CaptureError)
    if not p.is_file():
        raise CaptureError(f"image not found: {p}")
    if channel not in CHANNEL_CHOICES:
        raise CaptureError(f"channel must be one of {CHANNEL_CHOICES}, got {channel!r}")
    img = laser_plane(decode_image_file(p), channel, name=f"image {p}")
    if expected_size is not None:
        w, h = expected_size
        if img.shape != (h, w):
            raise CaptureError(
                f"image {p} is {img.shape[1]}x{img.shape[0]} px but rig.json says image_size "
                f"{w}x{h}; all images of a capture must have the rig's size"
            )
    return img


def write_image(path: str | Path, image: NDArray) -> None:
    """Write a (H, W) uint8 or uint16 image as PNG, creating folders as needed.

    The file is written whole or not at all (a temporary file, then a rename).
    """
    img = np.asarray(image)
    if img.ndim != 2 or img.dtype not in (np.uint8, np.uint16):
        raise CaptureError(
            f"write_image needs a (H, W) uint8/uint16 array, got {img.dtype} {img.shape}"
        )
    p = Path(path)
    try:
        ok, buf = cv2.imencode(p.suffix or ".png", img)
    except cv2.error:
        ok = False
    if not ok:
        raise CaptureError(f"cannot write image {p}: OpenCV cannot encode {p.suffix!r} images")
    try:
        write_bytes_atomic(p, buf.tobytes())
    except OSError as exc:
        raise CaptureError(f"cannot write image {p}: {exc.strerror or exc}") from None


# --------------------------------------------------------------------------- target
def _vec(v: Any, n: int, where: str) -> tuple[float, ...]:
    if not isinstance(v, list | tuple) or any(isinstance(x, bool | str) for x in v):
        raise CaptureError(f"{where} must be a list of {n} numbers, got {_short(v)}")
    try:
        out = tuple(float(x) for x in v)
    except (TypeError, ValueError, OverflowError):
        raise CaptureError(f"{where} must be a list of {n} numbers, got {_short(v)}") from None
    if len(out) != n or not all(math.isfinite(x) for x in out):
        raise CaptureError(f"{where} must be a list of {n} finite numbers, got {_short(v)}")
    if any(abs(x) > _MAX_COORD for x in out):
        raise CaptureError(
            f"{where} = {_short(v)} is out of range: coordinates (mm, px) must lie within "
            f"+-{_MAX_COORD:g}"
        )
    return out


def _short(v: Any, limit: int = 80) -> str:
    """``repr(v)`` cut to ``limit`` characters, for messages."""
    r = repr(v)
    return r if len(r) <= limit else r[: limit - 3] + "..."


@dataclass(frozen=True)
class Marker:
    """A 2x2 checker marker: ``xyz`` (mm, target frame) is its centre corner."""

    id: str
    xyz: tuple[float, float, float]
    uv_hint: tuple[float, float]


@dataclass(frozen=True)
class Face:
    """A flat face of the target: unit normal plane n.X + d = 0 and its convex outline (mm)."""

    id: str
    plane: tuple[float, float, float, float]
    polygon: tuple[tuple[float, float, float], ...]


@dataclass(frozen=True)
class SlitPoint:
    """A hand reading: a point on slit ``slit`` at world ``xyz`` (mm) seen at ``uv`` (px)."""

    slit: int
    xyz: tuple[float, float, float]
    uv: tuple[float, float]


@dataclass(frozen=True)
class Target:
    """The standard object of ``target.json``."""

    markers: tuple[Marker, ...]
    faces: tuple[Face, ...]
    slit_points: tuple[SlitPoint, ...] = ()

    @property
    def marker_xyz(self) -> NDArray[np.float64]:
        """(M, 3) float64, mm, target frame."""
        return np.array([m.xyz for m in self.markers], dtype=float).reshape(-1, 3)

    @property
    def marker_hints(self) -> NDArray[np.float64]:
        """(M, 2) float64, px."""
        return np.array([m.uv_hint for m in self.markers], dtype=float).reshape(-1, 2)

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "markers": [
                {"id": m.id, "xyz": list(m.xyz), "uv_hint": list(m.uv_hint)} for m in self.markers
            ],
            "faces": [
                {"id": f.id, "plane": list(f.plane), "polygon": [list(p) for p in f.polygon]}
                for f in self.faces
            ],
        }
        if self.slit_points:
            d["slit_points"] = [
                {"slit": s.slit, "xyz": list(s.xyz), "uv": list(s.uv)} for s in self.slit_points
            ]
        return d

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=1)

    @classmethod
    def from_dict(cls, d: Any, num_slits: int | None = None, where: str = "target.json") -> Target:
        if not isinstance(d, dict):
            raise CaptureError(f"{where}: expected a JSON object")
        for key in ("markers", "faces", "slit_points"):
            if d.get(key) is not None and not isinstance(d[key], list):
                raise CaptureError(f"{where}: '{key}' must be a list, got {_short(d[key])}")
        markers = []
        seen: set[str] = set()
        for i, m in enumerate(d.get("markers") or []):
            w = f"{where}: markers[{i}]"
            if not isinstance(m, dict) or "id" not in m or "xyz" not in m or "uv_hint" not in m:
                raise CaptureError(f"{w} needs 'id', 'xyz' and 'uv_hint'")
            if isinstance(m["id"], bool) or not isinstance(m["id"], str | int):
                raise CaptureError(f"{w}.id must be a string, got {_short(m['id'])}")
            mid = str(m["id"])
            if mid in seen:
                raise CaptureError(f"{w}: duplicate marker id {_short(mid)}")
            seen.add(mid)
            markers.append(
                Marker(mid, _vec(m["xyz"], 3, f"{w}.xyz"), _vec(m["uv_hint"], 2, f"{w}.uv_hint"))
            )
        if "markers" not in d:
            raise CaptureError(
                f"{where}: missing 'markers' (the checker markers for camera calibration)"
            )
        faces = []
        for i, f in enumerate(d.get("faces") or []):
            w = f"{where}: faces[{i}]"
            if not isinstance(f, dict) or "plane" not in f or "polygon" not in f:
                raise CaptureError(f"{w} needs 'plane' and 'polygon'")
            plane = np.array(_vec(f["plane"], 4, f"{w}.plane"))
            nn = np.linalg.norm(plane[:3])
            if nn < 1e-9:
                raise CaptureError(f"{w}.plane has a zero normal")
            plane = plane / nn
            poly = f["polygon"]
            if not isinstance(poly, list) or len(poly) < 3:
                raise CaptureError(f"{w}.polygon needs >= 3 vertices")
            verts = tuple(_vec(p, 3, f"{w}.polygon[{j}]") for j, p in enumerate(poly))
            off = np.abs(np.array(verts) @ plane[:3] + plane[3]).max()
            if off > 1.0:
                raise CaptureError(
                    f"{w}: polygon vertices lie up to {off:.2f} mm off the face's plane"
                )
            faces.append(Face(str(f.get("id", f"F{i + 1}")), tuple(plane.tolist()), verts))
        slit_points = []
        for i, s in enumerate(d.get("slit_points") or []):
            w = f"{where}: slit_points[{i}]"
            if not isinstance(s, dict) or not {"slit", "xyz", "uv"} <= set(s):
                raise CaptureError(f"{w} needs 'slit', 'xyz' and 'uv'")
            k = s["slit"]
            if not isinstance(k, int) or isinstance(k, bool):
                raise CaptureError(f"{w}.slit must be an integer slit number, got {_short(k)}")
            if num_slits is not None and not 0 <= k < num_slits:
                raise CaptureError(
                    f"{w}.slit is {k}, but the rig has slits 0..{num_slits - 1}; fix the reading"
                )
            slit_points.append(
                SlitPoint(k, _vec(s["xyz"], 3, f"{w}.xyz"), _vec(s["uv"], 2, f"{w}.uv"))
            )
        return cls(tuple(markers), tuple(faces), tuple(slit_points))


# --------------------------------------------------------------------------- capture
@dataclass(frozen=True)
class Capture:
    """An opened, validated capture folder. Images are read on demand with :meth:`image`."""

    root: Path
    image_size: tuple[int, int]
    num_slits: int
    rig: dict[str, Any]
    target: Target | None
    references: tuple[Path, ...]
    scans: tuple[Path, ...]
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def markers_image(self) -> Path:
        return self.root / "calibration" / "markers.png"

    @property
    def slits_image(self) -> Path:
        return self.root / "calibration" / "slits.png"

    @property
    def laser_channel(self) -> str:
        """The plane read from colour images: rig.json's ``"laser_channel"`` (``"red"``,
        ``"green"``, ``"blue"``, ``"luma"`` or ``"auto"``); without one, ``"auto"``: in each
        image the plane in which the stripes stand out most, clipped planes avoided."""
        ch = self.rig.get("laser_channel", AUTO)
        if ch not in CHANNEL_CHOICES:
            raise CaptureError(
                f"{self.root / 'rig.json'}: 'laser_channel' must be one of "
                f"{list(CHANNEL_CHOICES)}, got {ch!r}"
            )
        return ch

    def image(self, path: str | Path, *, channel: str | None = None) -> NDArray:
        """Read one of this capture's images (any path), checking its size against rig.json.

        A colour image is read as ``channel`` if given, else as its :attr:`laser_channel`
        (by default the plane in which the laser's line stands out most); grayscale images
        are read as they are.
        """
        plane = channel if channel is not None else self.laser_channel
        return read_image(path, self.image_size, channel=plane)

    @classmethod
    def open(cls, root: str | Path, require_target: bool = True) -> Capture:
        """Open and validate a capture folder.

        Parameters
        ----------
        root : path of the capture folder
        require_target : bool
            When False a missing target.json is allowed (scanning with an existing calibration).
        """
        root = as_path(root, "capture folder", error=CaptureError)
        if not root.is_dir():
            raise CaptureError(f"capture folder not found: {root}")
        rig = _read_json(root / "rig.json")
        if not isinstance(rig, dict):
            raise CaptureError(f"{root / 'rig.json'}: expected a JSON object")
        where = root / "rig.json"
        fmt = rig.get("format")
        if fmt != FORMAT:
            raise CaptureError(
                f"{where}: 'format' is {_short(fmt)}; this reader understands {FORMAT!r}"
            )
        size = rig.get("image_size")
        if (
            not isinstance(size, list)
            or len(size) != 2
            or not all(
                isinstance(x, int) and not isinstance(x, bool) and 0 < x <= _MAX_IMAGE_SIDE
                for x in size
            )
        ):
            raise CaptureError(
                f"{where}: 'image_size' must be [W, H] in px (each 1..{_MAX_IMAGE_SIDE}), "
                f"got {_short(size)}"
            )
        n = rig.get("num_slits")
        if not isinstance(n, int) or isinstance(n, bool) or not 1 <= n <= max(size):
            raise CaptureError(
                f"{where}: 'num_slits' must be a positive integer (at most {max(size)}, the "
                f"image's larger side in px), got {_short(n)}"
            )
        target = None
        tpath = root / "target.json"
        if tpath.exists() or require_target:
            target = Target.from_dict(_read_json(tpath), num_slits=n, where=str(tpath))
        refs = tuple(sorted((root / "reference").glob("*.png")))
        if len(refs) < MIN_REFERENCES:
            raise CaptureError(
                f"{root / 'reference'}: found {len(refs)} reference image(s); the method needs >= "
                f"{MIN_REFERENCES} images of a flat board at different distances"
            )
        scans = tuple(sorted((root / "scans").glob("*.png")))
        return cls(root, (size[0], size[1]), n, rig, target, refs, scans)


def _read_json(path: Path) -> Any:
    if not path.exists():
        raise CaptureError(f"missing file: {path}")
    return read_json(path, what="capture file", error=CaptureError)


def write_rig_json(
    root: str | Path, image_size: tuple[int, int], num_slits: int, **extra: Any
) -> Path:
    """Write ``rig.json`` of format version 1 (extra keys are kept)."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    d = {
        "format": FORMAT,
        "image_size": [int(image_size[0]), int(image_size[1])],
        "num_slits": int(num_slits),
    }
    d.update(extra)
    return write_json(root / "rig.json", d)
