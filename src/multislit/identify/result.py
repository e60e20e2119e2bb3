"""The result of identifying the slits of one image, with where each label came from."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from multislit.stripes import SlitExtraction

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: Where a piece's label came from (:attr:`PieceLabels.source`): left out, its own dots (the
#: labelling agrees with them and they alone are confident), or its neighbours (the labelling
#: of the frame gave it; its own dots were not confident alone).
SOURCES = ("left out", "its dots", "its neighbours")


@dataclass(frozen=True, eq=False)
class DotMatches:
    """Observed dots identified as rays of the dot projector.

    Attributes
    ----------
    u, v : (M,) float64, px, the observed dots' centres (as found:
        :func:`~multislit.stripes.find_dots`)
    dot : (M,) int64, the ray (index into the DotProjector's dots) of each
    window : (M,) int64, the window whose slit and slope predicted it
    slit : (M,) int64, that window's slit
    confidence : (M,) float64, that window's confidence
    angle : (M,) float64, rad, that window's stripe direction (from the image's vertical)
    """

    u: F64
    v: F64
    dot: NDArray[np.int64]
    window: NDArray[np.int64]
    slit: NDArray[np.int64]
    confidence: F64
    angle: F64

    def __len__(self) -> int:
        return len(self.u)


@dataclass(frozen=True, eq=False)
class PieceLabels:
    """Per stripe piece (a segment, or a part of one cut where its slit changes): its label
    and what gave it.

    Attributes
    ----------
    slit : (S,) int64, the piece's slit (-1: left out)
    confidence : (S,) float64, 0..1, the labelling's confidence in its best label
    own_slit : (S,) int64, the slit its own dots prefer (-1: none in the measuring volume)
    own_margin : (S,) float64, nats, how much more its own dots say for ``own_slit`` than for
        the next slit
    source : (S,) int8, index into :data:`SOURCES`
    """

    slit: I64
    confidence: F64
    own_slit: I64
    own_margin: F64
    source: NDArray[np.int8]

    def counts(self) -> dict[str, int]:
        """Pieces per source."""
        return {name: int(np.count_nonzero(self.source == i)) for i, name in enumerate(SOURCES)}


@dataclass(frozen=True, eq=False)
class Identification:
    """Result of identifying the slits of one image. Arrays are per stripe-centre point.

    Attributes
    ----------
    u, v : (K,) float64, px, stripe centres
    slit : (K,) int64, slit number 0..N-1, -1 where not identified
    confidence : (K,) float64, 0..1 (0 where not identified)
    segment : (K,) int64, piece id: the extraction's segment, cut where its slit changes (-1
        for unlinked points)
    peak, width : (K,) float64, stripe peak height (DN above background) and width (px)
    num_segments : number of pieces
    num_identified : number of pieces given a slit
    dropped : number of pieces left unidentified, by reason
    message : why nothing was identified (e.g. no slits in the image), else ""
    extraction : the :class:`~multislit.stripes.SlitExtraction` the points come from
    pieces : per piece (indexed by ``segment``), its label and where it came from (None for the
        template method)
    method : "geometry" (the dots' geometry) or "template" (the paper's template matching)
    dots : the observed dots identified as rays of the dot projector by the labelled pieces
        (geometry only; None for the template method and where not asked for:
        ``identify(..., match_dots=False)``)
    """

    u: F64
    v: F64
    slit: I64
    confidence: F64
    segment: I64
    peak: F64
    width: F64
    num_segments: int
    num_identified: int
    dropped: dict[str, int] = field(default_factory=dict)
    message: str = ""
    extraction: SlitExtraction | None = None
    pieces: PieceLabels | None = None
    method: str = "template"
    dots: DotMatches | None = None

    @property
    def identified(self) -> NDArray[np.bool_]:
        """(K,) bool, the points with a slit number."""
        return self.slit >= 0

    @property
    def num_dropped(self) -> int:
        """Number of pieces left unidentified."""
        return int(sum(self.dropped.values()))
