"""Identify the slits of one frame: :func:`identify`, by the dots' geometry or by templates."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from multislit.errors import IdentificationError
from multislit.geometry import PinholeCamera
from multislit.geometry.dots import DotProjector, angles_of, dot_frame
from multislit.identify.geometric import identify_geometry
from multislit.identify.labelling import compile_kernels as compile_template_kernels
from multislit.identify.labelling import identify_template, synthetic_frame
from multislit.identify.options import IdentifyOptions
from multislit.identify.reference import ReferenceSet
from multislit.identify.result import Identification
from multislit.identify.rig import RigGeometry, rig_geometry
from multislit.stripes import SlitExtraction, as_image, extract_slits


def identify(
    image: ArrayLike,
    reference: ReferenceSet,
    rig: RigGeometry | None = None,
    *,
    options: IdentifyOptions | None = None,
    extraction: SlitExtraction | None = None,
    previous: Identification | None = None,
    match_dots: bool = True,
) -> Identification:
    """Find the slits in one image and give each stripe-centre point its slit number.

    Parameters
    ----------
    image : (H, W) uint8/uint16, a scan (lasers on); must have the reference's image size
    reference : the prepared :class:`~multislit.identify.ReferenceSet` (see
        :func:`~multislit.identify.prepare_reference`), reused for every scan
    rig : the calibrated rig (:func:`~multislit.identify.rig_geometry`; from a calibration:
        :func:`multislit.reconstruct.rig_of`), needed by ``method="geometry"``
    options : :class:`~multislit.identify.IdentifyOptions`; default ``IdentifyOptions()``
        (by the dots' geometry)
    extraction : an extraction of ``image`` already made (skips extracting again); default
        None: extract with the reference's stripe width and dot size
    previous : the Identification of the previous frame of a sequence: the template method
        checks its labels instead of searching every slit (see
        :func:`~multislit.identify.labelling.identify_template`); the geometry method takes
        none (it scores every slit of every frame) and raises if given one
    match_dots : the geometry method also pairs the observed dots beside the labelled pieces
        with the projector's rays (:attr:`Identification.dots`, what the dots are measured
        from as 3D points); False leaves ``dots`` None and saves that work (a scan that
        measures no dot points)

    Returns
    -------
    Identification with per-point u, v, slit (-1 = not identified) and confidence, and for
    the geometry method per piece where its label came from. An image with no slits gives
    empty arrays and a message, not an exception.

    Raises
    ------
    IdentificationError
        (a ``ValueError``) if ``image`` is not a grayscale image of the reference's size,
        ``options`` is not an IdentifyOptions, ``match_dots`` is not a bool, or the geometry
        method has no ``rig`` or is given a ``previous``.
    """
    if not isinstance(match_dots, bool | np.bool_):
        raise IdentificationError(f"match_dots must be True or False, got {match_dots!r}")
    opts = IdentifyOptions() if options is None else options
    if not isinstance(opts, IdentifyOptions):
        raise IdentificationError(
            f"options must be an IdentifyOptions, got {type(options).__name__}"
        )
    if opts.method == "template":
        return identify_template(
            image,
            reference,
            min_confidence=opts.confidence,
            extraction=extraction,
            previous=previous,
        )
    if previous is not None:
        raise IdentificationError(
            "previous: a prior from the previous frame is used by the template method only "
            "(options=IdentifyOptions(method='template')); by the dots' geometry every frame "
            "is identified on its own"
        )
    if not isinstance(rig, RigGeometry):
        raise IdentificationError(
            "identification by the dots' geometry needs the calibrated rig (rig=rig_geometry(...), "
            "or scan with a calibration that has a dot projector); for the paper's template "
            "matching pass options=IdentifyOptions(method='template')"
        )
    img = as_image(image)
    w, h = reference.image_size
    if img.shape != (h, w):
        raise IdentificationError(
            f"image is {img.shape[1]}x{img.shape[0]} px but the reference was prepared for {w}x{h} px"
        )
    ex = extraction or extract_slits(
        img, stripe_width_px=reference.stripe_width_px, dot_size_px=reference.dot_size_px
    )
    if opts.depth_range is not None:
        rig = rig.with_depth_range(opts.depth_range)
    return identify_geometry(ex, reference, rig, opts, match_dots=match_dots)


def synthetic_rig() -> tuple[ReferenceSet, list, RigGeometry]:
    """The frame of :func:`~multislit.identify.labelling.synthetic_frame` with a rig that puts
    its stripes and dots on a wall 1 m in front of the camera: slit k through the k-th stripe
    (planes through a vertical axis 200 mm left of the camera), one dot ray from a source 150
    mm left of the camera through each dot.

    Returns
    -------
    reference, images : those of :func:`~multislit.identify.labelling.synthetic_frame`
    rig : the RigGeometry
    """
    reference, images, dot_uv, stripe_u = synthetic_frame()
    w, h = reference.image_size
    f, depth = 400.0, 1000.0
    camera = PinholeCamera(f, f, w / 2, h / 2, image_size=(w, h))
    axis = np.array([-200.0, 0.0, 0.0])
    x = (stripe_u - w / 2) * depth / f
    normal = np.stack([np.full_like(x, depth), np.zeros_like(x), -(x - axis[0])], axis=1)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    planes = np.c_[normal, -normal @ axis]
    source = np.array([-150.0, 0.0, 0.0])
    wall = np.c_[(dot_uv - [w / 2, h / 2]) * depth / f, np.full(len(dot_uv), depth)]
    rays = wall - source
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    frame = dot_frame(rays, [0.0, 1.0, 0.0])
    phi, psi, _ = angles_of(rays, frame)
    dots = DotProjector(
        source,
        frame,
        phi,
        psi,
        seen=np.full(len(phi), 2),
        residual_px=np.zeros(len(phi)),
        reference_depths=np.array([0.9, 1.1]) * depth,
    )
    return reference, images, rig_geometry(camera, planes, dots)


def compile_kernels() -> None:
    """Compile the identification's Numba kernels now, both methods'.

    Numba compiles each kernel on first use (seconds) and caches the machine code on disk
    beside the package, so only the first run after an install pays it;
    :func:`multislit.compile_kernels` calls this with the other stages' warm-ups. The template matching's kernels
    (:func:`~multislit.identify.labelling.compile_kernels`), then the identification by the
    dots' geometry on the frames of :func:`synthetic_rig`.
    """
    compile_template_kernels()
    reference, images, rig = synthetic_rig()
    for image in images:
        identify(image, reference, rig)
