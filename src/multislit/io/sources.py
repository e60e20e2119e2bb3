"""Frame sources: image sequences, video files and live cameras, one grayscale frame at a time.

:func:`open_source` understands these SOURCE strings:

- a folder (its ``*.png *.tif *.tiff *.jpg *.jpeg`` files in name order) or a glob pattern
  (``scans/*.tif``) of images, 8 or 16 bit;
- a video file, anything OpenCV's ``cv2.VideoCapture`` reads (e.g. FFV1 or MJPG in AVI/MKV);
- ``camera:N``, OpenCV camera number N (live);
- ``basler:`` (the first Basler camera) or ``basler:SERIAL``, through pypylon (live; the
  optional extra ``pip install 'multislit[basler]'``). pylon's camera emulation
  (``PYLON_CAMEMU=1``) replays image files as such a camera when its ``ImageFilename`` and
  ``ImageFileMode`` features are set (see ``features``).

Colour frames become the laser's channel (``channel``), not luminance: a red laser on dark
texture is far clearer in the red channel than in a grey mix. By default (``"auto"``) each
frame's plane is the one in which the stripes stand out most, clipped planes avoided: red
for a red laser, green or blue where the red plane is clipped over an over-exposed line.

A live source never makes the camera wait: a background thread takes every frame the camera
delivers and keeps only the newest; frames replaced before the reader took them are counted in
:attr:`FrameSource.dropped`.
"""

from __future__ import annotations

import glob
import os
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from multislit.errors import CaptureError
from multislit.io.capture import decode_image_file, laser_plane, quiet_opencv
from multislit.io.paths import as_path
from multislit.stripes.validation import AUTO, CHANNEL_CHOICES

__all__ = ["Frame", "FrameSource", "open_source", "IMAGE_SUFFIXES", "CHANNEL_CHOICES"]

#: File name endings read as images from a folder (case-insensitive).
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg")
#: Channel names for colour frames (``luma``: luminance, 0.299 R + 0.587 G + 0.114 B).

_GLOB_CHARS = set("*?[")
_OPEN_TIMEOUT_S = 5.0  # a live camera that gives no first frame in this time is absent
_FRAME_TIMEOUT_S = 10.0  # a live camera silent this long has stopped
_MAX_READ_FAILURES = 50  # consecutive failed reads before a live camera counts as stopped
_MAX_CAMERA_INDEX = 9999  # OpenCV camera numbers (with a capture API's offset, e.g. 1200 + N)


@dataclass(frozen=True)
class Frame:
    """One frame of a source.

    Attributes
    ----------
    index : int
        The frame's number in the source (0-based): files in name order, video frames, or a
        live camera's frames in the order they were taken (frames dropped in between are not
        numbered).
    source : str
        Where it came from: the image file name, ``VIDEO#N`` for a video's frame N, or the
        capture time (ISO 8601, UTC) for a live camera.
    image : (H, W) uint8 or uint16, or None
        The frame (the laser's channel of a colour frame); None when it could not be read.
    error : str
        Why ``image`` is None; '' otherwise.
    """

    index: int
    source: str
    image: NDArray | None
    error: str = ""


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="microseconds").replace("+00:00", "Z")


class FrameSource:
    """Frames from one SOURCE; iterate with :meth:`frames`, then :meth:`close` (or use ``with``).

    Attributes
    ----------
    name : str
        The SOURCE string as given.
    live : bool
        True for cameras: frames arrive at the camera's rate and may be dropped.
    """

    name: str = ""
    live: bool = False

    def __init__(self, name: str, channel: str) -> None:
        self.name = name
        self.channel = channel

    @property
    def dropped(self) -> int:
        """Frames the camera delivered that were replaced by a newer one before being read."""
        return 0

    def frames(self) -> Iterator[Frame]:  # pragma: no cover - abstract
        raise NotImplementedError

    def close(self) -> None:
        """Release the file, video or camera."""

    def __enter__(self) -> FrameSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _frame(self, index: int, source: str, image: NDArray | None) -> Frame:
        if image is None:
            return Frame(index, source, None, "cannot read the frame")
        try:
            return Frame(index, source, laser_plane(image, self.channel))
        except ValueError as exc:
            return Frame(index, source, None, str(exc))


# --------------------------------------------------------------------------- files
class ImageFiles(FrameSource):
    """Image files (PNG, TIFF, JPEG; 8 or 16 bit) in name order."""

    def __init__(self, name: str, paths: Sequence[Path], channel: str) -> None:
        super().__init__(name, channel)
        self.paths = tuple(paths)

    def frames(self) -> Iterator[Frame]:
        for i, p in enumerate(self.paths):
            try:
                img = decode_image_file(p)
            except CaptureError as exc:
                yield Frame(i, p.name, None, str(exc))
                continue
            fr = self._frame(i, p.name, img)
            if fr.error:
                fr = Frame(i, p.name, None, f"{p}: {fr.error}")
            yield fr


def _image_files(spec: str) -> list[Path]:
    p = Path(spec)
    if p.is_dir():
        paths = [q for q in p.iterdir() if q.is_file() and q.suffix.lower() in IMAGE_SUFFIXES]
        if not paths:
            raise CaptureError(
                f"SOURCE {spec}: the folder has no {'/'.join(s[1:] for s in IMAGE_SUFFIXES)} images"
            )
        return sorted(paths)
    paths = [Path(q) for q in glob.glob(spec) if Path(q).is_file()]
    if not paths:
        raise CaptureError(f"SOURCE {spec}: the pattern matches no files")
    return sorted(paths)


# --------------------------------------------------------------------------- video
class VideoFile(FrameSource):
    """The frames of a video file, read with ``cv2.VideoCapture``."""

    def __init__(self, name: str, channel: str) -> None:
        super().__init__(name, channel)
        path = Path(name)
        with quiet_opencv():
            self._cap = cv2.VideoCapture(str(path))
            ok = self._cap.isOpened()
            first = self._cap.read() if ok else (False, None)
        if not first[0]:
            self._cap.release()
            raise CaptureError(
                f"SOURCE {name}: not an image folder, pattern or video that OpenCV can read"
            )
        self._first = first[1]
        self._label = path.name

    def frames(self) -> Iterator[Frame]:
        i = 0
        img = self._first
        while img is not None:
            yield self._frame(i, f"{self._label}#{i}", img)
            ok, img = self._cap.read()
            if not ok:
                break
            i += 1

    def close(self) -> None:
        self._cap.release()


# --------------------------------------------------------------------------- live
class _Newest:
    """A thread that keeps reading ``read()`` and holds only the newest frame.

    ``read`` returns ``(image or None, skipped)``: None is a failed read, ``skipped`` frames
    the device itself skipped (counted as dropped).
    """

    def __init__(self, read: Callable[[], tuple[NDArray | None, int]], what: str) -> None:
        self._read = read
        self._what = what
        self._cond = threading.Condition()
        self._item: tuple[NDArray, str] | None = None
        self._stop = False
        self.error = ""
        self.delivered = 0
        self.dropped = 0
        self._counting = False  # drops count from the first frame taken on
        self._thread = threading.Thread(target=self._run, name=f"grab {what}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        failures = 0
        while not self._stop:
            try:
                img, skipped = self._read()
            except Exception as exc:  # the device's own error ends the stream with its text
                img, skipped = None, 0
                failures = _MAX_READ_FAILURES
                self.error = str(exc)
            if img is None:
                failures += 1
                if failures >= _MAX_READ_FAILURES:
                    with self._cond:
                        self.error = self.error or "the camera stopped delivering frames"
                        self._stop = True
                        self._cond.notify_all()
                    return
                time.sleep(0.001)
                continue
            failures = 0
            stamp = _now()
            with self._cond:
                self.delivered += 1 + skipped
                if self._counting:
                    self.dropped += skipped + (self._item is not None)
                self._item = (img, stamp)
                self._cond.notify_all()

    def take(self, timeout: float) -> tuple[NDArray, str] | None:
        """The newest frame not yet taken (waits up to ``timeout`` s); None if none came."""
        with self._cond:
            self._cond.wait_for(lambda: self._item is not None or self._stop, timeout)
            item, self._item = self._item, None
            self._counting = self._counting or item is not None
            return item

    def request_stop(self) -> None:
        """Ask the thread to end after its current read."""
        with self._cond:
            self._stop = True
            self._cond.notify_all()

    def stop(self) -> None:
        """End the thread (waits for its current read)."""
        self.request_stop()
        self._thread.join(timeout=_FRAME_TIMEOUT_S)


class _LiveSource(FrameSource):
    live = True
    _newest: _Newest

    @property
    def dropped(self) -> int:
        return self._newest.dropped

    def _first(self) -> tuple[NDArray, str]:
        item = self._newest.take(_OPEN_TIMEOUT_S)
        if item is None:
            self.close()
            raise CaptureError(
                f"SOURCE {self.name}: the camera gave no frame in {_OPEN_TIMEOUT_S:.0f} s"
                + (f" ({self._newest.error})" if self._newest.error else "")
                + "; check that it is connected and not in use by another program"
            )
        return item

    def frames(self) -> Iterator[Frame]:
        item: tuple[NDArray, str] | None = self._first()
        i = 0
        while item is not None:
            yield self._frame(i, item[1], item[0])
            i += 1
            item = self._newest.take(_FRAME_TIMEOUT_S)
        raise CaptureError(
            f"SOURCE {self.name}: "
            + (self._newest.error or f"no frame for {_FRAME_TIMEOUT_S:.0f} s")
        )


class OpenCVCamera(_LiveSource):
    """OpenCV camera number N (``camera:N``)."""

    def __init__(self, name: str, index: int, channel: str) -> None:
        super().__init__(name, channel)
        with quiet_opencv():
            self._cap = cv2.VideoCapture(index)
        if not self._cap.isOpened():
            self._cap.release()
            raise CaptureError(
                f"SOURCE {name}: no camera {index} (OpenCV cannot open it); check the camera "
                "is connected, or try another number"
            )

        def read() -> tuple[NDArray | None, int]:
            ok, img = self._cap.read()
            return (img if ok else None), 0

        self._newest = _Newest(read, name)

    def close(self) -> None:
        self._newest.stop()
        self._cap.release()


class BaslerCamera(_LiveSource):
    """A Basler camera through pypylon (``basler:`` or ``basler:SERIAL``)."""

    def __init__(
        self,
        name: str,
        serial: str,
        channel: str,
        *,
        image_size: tuple[int, int] | None,
        features: Sequence[tuple[str, str]],
    ) -> None:
        super().__init__(name, channel)
        try:
            from pypylon import genicam, pylon
        except ImportError:
            raise CaptureError(
                f"SOURCE {name}: Basler cameras need pypylon: pip install 'multislit[basler]'"
            ) from None
        self._pylon = pylon
        tl = pylon.TlFactory.GetInstance()
        devices = list(tl.EnumerateDevices())
        if serial:
            devices = [d for d in devices if d.GetSerialNumber() == serial]
        if not devices:
            raise CaptureError(
                f"SOURCE {name}: no Basler camera"
                + (f" with serial number {serial}" if serial else "")
                + " found; check the cable and that pylon sees it"
            )
        try:
            self._cam = pylon.InstantCamera(tl.CreateDevice(devices[0]))
            self._cam.Open()
            if image_size is not None:
                w, h = image_size
                if self._cam.Width.Value != w or self._cam.Height.Value != h:
                    self._cam.Width.Value, self._cam.Height.Value = w, h
            for key, value in features:
                _set_feature(self._cam, key, value)
            self._converter = None
            if not str(self._cam.PixelFormat.Value).startswith("Mono"):
                conv = pylon.ImageFormatConverter()
                conv.OutputPixelFormat = pylon.PixelType_BGR8packed
                self._converter = conv
            self._cam.StartGrabbing(pylon.GrabStrategy_LatestImageOnly)
        except (genicam.GenericException, ValueError) as exc:
            self.close()
            raise CaptureError(f"SOURCE {name} {str(exc).split(' : ')[0]}") from None

        def read() -> tuple[NDArray | None, int]:
            res = self._cam.RetrieveResult(
                int(_FRAME_TIMEOUT_S * 1000), pylon.TimeoutHandling_Return
            )
            try:
                if not res.IsValid() or not res.GrabSucceeded():
                    return None, 0
                if self._converter is not None:
                    img = self._converter.Convert(res).GetArray()
                else:
                    img = res.GetArray()
                return np.array(img, copy=True), int(res.GetNumberOfSkippedImages())
            finally:
                if res.IsValid():
                    res.Release()

        self._newest = _Newest(read, name)

    def close(self) -> None:
        newest = getattr(self, "_newest", None)
        cam = getattr(self, "_cam", None)
        if newest is not None:
            newest.request_stop()
        if cam is not None and cam.IsGrabbing():
            cam.StopGrabbing()  # ends a wait for the next frame at once
        if newest is not None:
            newest.stop()
        if cam is not None:
            cam.Close()


def _set_feature(cam: Any, key: str, value: str) -> None:
    """Set the camera's GenICam feature ``key`` from the text ``value`` (its own type)."""
    from pypylon import genicam

    node = cam.GetNodeMap().GetNode(key)
    if not node.IsValid() or not hasattr(node, "FromString"):
        raise ValueError(f"the camera has no feature {key!r} (check the name in pylon Viewer)")
    try:
        node.FromString(value)
    except genicam.GenericException as exc:
        msg = str(exc).split(" : ")[0]
        raise ValueError(f"cannot set {key}={value}: {msg}") from None


# --------------------------------------------------------------------------- opening
class _Every(FrameSource):
    """Every k-th frame of another source."""

    def __init__(self, inner: FrameSource, every: int) -> None:
        super().__init__(inner.name, inner.channel)
        self.inner, self.every, self.live = inner, every, inner.live

    @property
    def dropped(self) -> int:
        return self.inner.dropped

    def frames(self) -> Iterator[Frame]:
        for fr in self.inner.frames():
            if fr.index % self.every == 0:
                yield fr

    def close(self) -> None:
        self.inner.close()


def open_source(
    source: str | os.PathLike[str],
    *,
    channel: str = AUTO,
    every: int = 1,
    image_size: tuple[int, int] | None = None,
    features: Sequence[tuple[str, str]] = (),
) -> FrameSource:
    """Open a SOURCE of frames (see the module's text for the forms).

    Parameters
    ----------
    source : str or path-like
        A folder or glob of images, a video file, ``camera:N``, ``basler:`` or
        ``basler:SERIAL``.
    channel : {'auto', 'red', 'green', 'blue', 'luma'}
        The channel of colour frames that shows the laser; ``luma``: luminance; ``auto``
        (default): in each frame the plane in which the stripes stand out most, clipped
        planes avoided (:func:`~multislit.stripes.channels.choose_channel`).
    every : int
        Keep every ``every``-th frame of the source (its frames 0, k, 2k, ...). Default 1.
    image_size : (W, H) px, optional
        For a Basler camera: the image size to set (the calibration's). Default: as it is.
    features : sequence of (name, value) str pairs
        For a Basler camera: GenICam features to set after opening, in order (e.g.
        ``("ExposureTime", "2000")``, or ``("ImageFilename", DIR)`` and ``("ImageFileMode",
        "On")`` for pylon's emulation to replay the images in DIR). Default none.

    Returns
    -------
    FrameSource
        Iterate its :meth:`~FrameSource.frames`; close it when done.

    Raises
    ------
    CaptureError
        A SOURCE that does not exist or cannot be read, a camera that is absent, a bad option.
    """
    as_path(source, "SOURCE", error=CaptureError)
    spec = os.fsdecode(os.fspath(source))
    if channel not in CHANNEL_CHOICES:
        raise CaptureError(f"channel must be one of {', '.join(CHANNEL_CHOICES)}, got {channel!r}")
    if isinstance(every, bool) or not isinstance(every, int) or every < 1:
        raise CaptureError(f"every must be an integer >= 1, got {every!r}")
    if features and not spec.startswith("basler:"):
        raise CaptureError("camera features can be set only for a Basler camera (basler:...)")
    src: FrameSource
    if spec.startswith("camera:"):
        num = spec[len("camera:") :]
        if not (num.isascii() and num.isdigit()) or int(num) > _MAX_CAMERA_INDEX:
            raise CaptureError(
                f"SOURCE {spec}: give the camera number (0 to {_MAX_CAMERA_INDEX}), e.g. camera:0"
            )
        src = OpenCVCamera(spec, int(num), channel)
    elif spec.startswith("basler:"):
        src = BaslerCamera(
            spec,
            spec[len("basler:") :],
            channel,
            image_size=image_size,
            features=features,
        )
    elif Path(spec).is_dir() or (_GLOB_CHARS & set(spec) and not Path(spec).exists()):
        try:
            src = ImageFiles(spec, _image_files(spec), channel)
        except OSError as exc:
            raise CaptureError(f"SOURCE {spec}: cannot list the images ({exc.strerror})") from None
    elif Path(spec).is_file():
        if Path(spec).suffix.lower() in IMAGE_SUFFIXES:
            src = ImageFiles(spec, [Path(spec)], channel)
        elif not os.access(spec, os.R_OK):
            raise CaptureError(f"SOURCE {spec}: the file is not readable (permissions)")
        else:
            src = VideoFile(spec, channel)
    else:
        raise CaptureError(
            f"SOURCE {spec}: no such file or folder (give an image folder or pattern, a video "
            "file, camera:N or basler:[SERIAL])"
        )
    return _Every(src, every) if every > 1 else src
