"""The matcher's settings (:class:`SequenceConfig`), its constants, and its result (:class:`SequenceMatch`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from memlog.configfile import check_ints
from memlog.errors import ConfigError
from memlog.settings import Flag, nonneg_float, nonneg_int, positive_float, positive_int, setting, speed_range

__all__ = ["SequenceConfig", "SequenceMatch", "COORDINATES", "STAT_SAMPLE", "FALLBACK_REASONS",
           "F32", "F64", "I64", "BoolArray"]

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]



COORDINATES = ("auto", "frames", "time", "positions")
DEFAULT_SPEEDS = (1 / 3, 3.0)  # frames and time: a third to three times the map's speed (stops are left out)
POSITION_SPEEDS = (0.8, 1.25)  # positions: metres against metres; the range allows for odometry scale
VOTERS = 10  # candidates per query frame that vote (--sequence-k)
SPEED_PRIOR = 1.0  # a path's score loses this much per doubling or halving of its speed against the pace
STAT_SAMPLE = 256  # map frames the contrast normalisation's statistics are taken from
MAX_SPEEDS = 128  # at most this many speeds are searched (speed_step is raised to fit)
EXACT_PLACES = 3  # the best-voted places that compete for the best match (more: more false maxima)
TOP_VOTES = 64  # best-voted places per query looked at by the non-maximum suppression
CENTRE_STEPS = 2  # centres are tried every half reference frame (a map sparser than the query: between its frames)
RESCORE_SPEEDS = 3  # exact scores are taken at the voted speed and this many steps either side
VOTE_ELEMS = 1 << 21  # votes of one block of centres (memory bound whatever the window, candidates and speeds)
SCORE_ELEMS = 1 << 20  # elements of one [B, P, D, S, W] block of exact scores (memory bound whatever the sparsity)
PAIR_ELEMS = 1 << 21  # float32 elements per chunk of pair products (8 MiB)
GAP_FACTOR = 10.0  # default run boundary: a stamp gap above this many median frame intervals
MAX_LENGTH_SCALE = 2.0  # scale_length: a window grows at most 2x on a sparse map
#: why a query row was matched frame by frame (``SequenceMatch.fallback``; "" for sequence rows)
FALLBACK_REASONS = {
    "single": "single frames asked for (sequence length 0)",
    "small-map": "the map spans fewer reference frames than the window",
    "standing": "the query stood still: fewer moving frames in its run than the window needs",
    "short-run": "its run of ordered frames is shorter than the window (a single image, or frames whose stamps "
                 "do not increase)",
    "causal-start": "fewer frames of its run before it than the causal window needs",
    "no-path": "no place stood out of its window's single-frame candidates",
}


@dataclass(frozen=True)
class SequenceConfig:
    """How query frames are matched as sequences (``docs/method.md``, "Drives, not frames").

    ``length``: frames before (and, unless ``causal``, after) each query frame; 0 = single
    frames. ``speeds``: (min, max) relative speed, map coordinate per query coordinate (None:
    1/3..3 times the drives' pace for frames and time, 0.8..1.25 for positions); ``speed_step``
    (None: the step that moves the window's far end by one reference frame). ``candidates``: map
    frames per query frame from the single-frame search that vote. ``coordinate``: auto | frames | time |
    positions. ``max_gap_s``: a stamp gap above this cuts the query
    into runs (None: :data:`GAP_FACTOR` times the median frame interval). ``exclude``:
    half-width, in reference frames, of the window around the best place inside which no
    second-best place is taken (the margin's "different place"). ``block``: query frames per block of votes, at most (fewer when a block's votes would pass
    :data:`VOTE_ELEMS`; speed and
    memory only; never the result). ``scale_length``: on a sparse map (the kept frames' median
    spacing ``s`` reference frames, a half map ``s = 2``) the window is ``length * s`` frames
    (at most :data:`MAX_LENGTH_SCALE` times), so a sequence meets as many map frames as on the
    full map (measured on Nordland's half and quarter maps; windows of 4x were worse on drives
    that change speed; ``info["length_used"]``).
    ``stops``: in the ``frames`` coordinate, drives run along their moving index and a standing
    query frame takes its stop's match (``docs/method.md``, "Stops"). ``speed_prior``: a path's
    score loses this much per doubling (or halving) of its speed against 1, ``|log2 v|`` (0: every
    speed in the range alike). ``rerank``: re-rank each
    query's best places by patch features when both tables carry them under one PCA
    (:func:`rerank_by_patches`; ``--no-rerank`` turns it off). ``hmm``: after the re-rank, decide
    each frame's place with its neighbours', as the drive's most likely path through every
    frame's candidate places (:mod:`memlog.matching.drive_hmm`; ``--no-hmm`` turns it off).
    ``ensemble``: on a small whitened map, re-rank the drive in several whitened dimensions and
    let one HMM decide between all their places (:mod:`memlog.matching.ensemble`;
    ``--no-ensemble`` turns it off).
    """

    length: int = setting(10, Flag(
        ("--sequence",), "match each query frame together with the N frames before and after it (default 10); 0: "
        "single frames. A single image or unordered frames are matched frame by frame", "sequence matching",
        nonneg_int, metavar="N"))
    causal: bool = setting(False, Flag(
        ("--causal",), "use only past frames: the N frames before each query frame and the frame itself (a robot "
        "localizing live)", "sequence matching", action="store_true"))
    speeds: tuple[float, float] | None = setting(None, Flag(
        ("--speeds",), "relative speeds searched, map coordinate per query coordinate (default: 1/3 to 3 times the "
        "drives' pace, i.e. 1 at one frame rate, else the ratio of their frame intervals; positions: 0.8:1.25)",
        "sequence matching", speed_range, metavar="MIN:MAX"))
    speed_step: float | None = None
    candidates: int = setting(VOTERS, Flag(
        ("--sequence-k",), "candidates per query frame from the single-frame search that vote for places (default "
        f"{VOTERS})", "sequence matching", positive_int, metavar="K"))
    coordinate: str = setting("auto", Flag(
        ("--coordinate",), "what sequences follow: frame indices, stamps, or distance along both logs' positions "
        "(default auto: positions when both logs have them, else frames)", "sequence matching",
        choices=COORDINATES))
    max_gap_s: float | None = setting(None, Flag(
        ("--max-gap",), "a gap of more than S seconds between query stamps starts a new run (sequences never cross "
        "one; default: 10 x the median frame interval)", "sequence matching", positive_float, metavar="S"))
    exclude: float = 1.0
    block: int = 128
    scale_length: bool = True
    stops: bool = setting(True, Flag(
        ("--keep-stops",), "match along the frame index as recorded, every frame on its own (default: where the "
        "camera stood still (from the log's odometry, twist or GNSS when it knows every frame, else from the "
        "images), the stop counts as one place and its frames take the match of its first frame; the query's "
        "stops are found as the map recorded its own; frames coordinate only)", "sequence matching",
        action="store_true", value=lambda v: False))
    speed_prior: float = setting(SPEED_PRIOR, Flag(
        ("--speed-prior",), "a path's score loses P per doubling or halving of its speed against the map's (default "
        f"{SPEED_PRIOR:g}; 0: every speed of --speeds alike)", "sequence matching", nonneg_float, metavar="P"))
    rerank: bool = setting(True, Flag(
        ("--no-rerank",), "keep the order of the descriptor match (default: each query's best places are re-ranked "
        "by the map's stored patch features, and the confidence is the re-rank's margin)", "sequence matching",
        action="store_true", dest="no_rerank", value=lambda v: False))
    hmm: bool = setting(True, Flag(
        ("--no-hmm",), "decide each query frame's place from its own re-ranked places alone (default: the drive's "
        "most likely path through every frame's re-ranked places decides, an HMM over each run; the confidence is "
        "the place's probability minus the best other place's)", "sequence matching", action="store_true",
        dest="no_hmm", value=lambda v: False))
    ensemble: bool = setting(True, Flag(
        ("--no-ensemble",), "match the drive once, in the map's whole whitening (default: on a map whitened on fewer "
        "than 1024 frames, the drive is re-ranked in the whitening's leading 100, 80, 60 and 40 %% of dimensions and "
        "the drive HMM decides between all their places, which steadies a whitening fitted on few frames)", "sequence matching",
        action="store_true", dest="no_ensemble", value=lambda v: False))

    def __post_init__(self) -> None:
        check_ints(self, {"length": 0, "candidates": 1, "block": 1})
        if not isinstance(self.causal, bool):
            raise ConfigError("causal must be true or false")
        if self.coordinate not in COORDINATES:
            raise ConfigError(f"coordinate must be one of {', '.join(COORDINATES)}, got {self.coordinate!r}")
        if self.speeds is not None:
            sp = tuple(self.speeds)
            if len(sp) != 2 or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                                       for v in sp):
                raise ConfigError(f"speeds must be two finite numbers (min, max), got {self.speeds!r}")
            if sp[0] < 0 or sp[1] < sp[0]:
                raise ConfigError(f"speeds must satisfy 0 <= min <= max, got {sp[0]:g}:{sp[1]:g}")
            object.__setattr__(self, "speeds", (float(sp[0]), float(sp[1])))
        if isinstance(self.speed_prior, bool) or not isinstance(self.speed_prior, (int, float)) or not (
                math.isfinite(self.speed_prior) and self.speed_prior >= 0):
            raise ConfigError(f"speed_prior must be a number >= 0, got {self.speed_prior!r}")
        for name in ("speed_step", "max_gap_s"):
            v = getattr(self, name)
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v)
                                  or v <= 0):
                raise ConfigError(f"{name} must be a number > 0, got {v!r}")
        if isinstance(self.exclude, bool) or not isinstance(self.exclude, (int, float)) or not (
                math.isfinite(self.exclude) and self.exclude >= 0):
            raise ConfigError(f"exclude must be a number >= 0, got {self.exclude!r}")
        if not all(isinstance(v, bool) for v in (self.scale_length, self.stops, self.rerank, self.hmm, self.ensemble)):
            raise ConfigError("scale_length, stops, rerank, hmm and ensemble must be true or false")
        if self.length == 0 and self.causal:
            raise ConfigError("causal needs a sequence: length (--sequence) must be >= 1")

    @property
    def enabled(self) -> bool:
        """Sequences are matched (``length >= 1``)."""
        return self.length > 0

    def speed_range(self, coordinate: str) -> tuple[float, float]:
        """``speeds``, or the default for ``coordinate``."""
        if self.speeds is not None:
            return self.speeds
        return POSITION_SPEEDS if coordinate == "positions" else DEFAULT_SPEEDS

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict: every setting."""
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d["speeds"] = list(self.speeds) if self.speeds is not None else None
        return d


@dataclass
class SequenceMatch:
    """Best map places of every query frame.

    ``indices`` ``[Q, k]``: rows of the reference (the full reference, also when a mask was
    given), best first, -1 = none; for a sequence-matched query the ranks are distinct places
    (outside ``exclude`` of each other), for a single-frame one the ``k`` most similar frames.
    ``scores`` ``[Q, k]``: the sequence score (mean contrast-normalised similarity along the
    path), or the similarity for single-frame queries; ``similarities`` ``[Q, k]``: the cosine
    similarity of the query frame itself to each matched frame. ``margin`` ``[Q]``: best minus
    second-best *place*'s score (NaN without a second), in the score's unit for every row: a
    single frame is a path of one pair, its score the contrast-normalised similarity ``z`` and its
    second place the best candidate outside ``exclude`` of the best; after the re-rank, the best
    place's patch score minus the other place's; after the drive HMM, the best place's probability
    minus the other place's (``posterior`` ``[Q, k]``: each place's probability along the drive). ``ratio`` ``[Q]``: the query
    frame's descriptor distance to the best match over its distance to the second-best place
    (Lowe's ratio; lower is more distinct). ``speed`` ``[Q]``: relative speed of the best path
    (NaN for single frames). ``window`` ``[Q]``: frames the score was taken over (1 = single
    frame). ``sequence`` ``[Q]``: matched as a sequence. ``fallback`` ``[Q]``: why a row was
    matched frame by frame ("" for sequence rows; :data:`FALLBACK_REASONS`). ``info``: the
    settings used and what happened (``length_used``, ``sequence_queries``, ``single_queries``,
    ``fallback``: a summary, ``fallback_reasons``: rows per reason).
    """

    indices: I64
    scores: F64
    similarities: F32
    margin: F64
    speed: F64
    window: I64
    sequence: BoolArray
    ratio: F64 = field(default_factory=lambda: np.zeros(0))
    fallback: npt.NDArray[np.str_] = field(default_factory=lambda: np.zeros(0, dtype=str))
    info: dict[str, Any] = field(default_factory=dict)
    rerank: F64 | None = None
    posterior: F64 | None = None

    @property
    def confidence(self) -> F64:
        """Per-query confidence, one scale for every row: the margin of the best place over the
        second-best in score units (0 without a second place); -inf without a match."""
        found = self.indices[:, 0] >= 0
        m = np.where(np.isnan(self.margin), 0.0, self.margin)
        out: F64 = np.where(found, m, -np.inf).astype(np.float64)
        return out

    def take(self, rows: npt.ArrayLike) -> SequenceMatch:
        """The result of query ``rows`` (in that order), same info."""
        r = np.asarray(rows, dtype=np.int64)
        return SequenceMatch(self.indices[r], self.scores[r], self.similarities[r], self.margin[r], self.speed[r],
                             self.window[r], self.sequence[r], self.ratio[r], self.fallback[r], self.info,
                             None if self.rerank is None else self.rerank[r],
                             None if self.posterior is None else self.posterior[r])

    def top(self, k: int) -> SequenceMatch:
        """The ``k`` best places of every row (the others dropped)."""
        return replace(self, indices=self.indices[:, :k], scores=self.scores[:, :k],
                       similarities=self.similarities[:, :k],
                       rerank=None if self.rerank is None else self.rerank[:, :k],
                       posterior=None if self.posterior is None else self.posterior[:, :k])
