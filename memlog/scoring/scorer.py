"""The staged scorer: staticity -> entropy -> memorability, cheapest first, with early exit.

:class:`Scorer` scores one decoded frame (``score``) or splits the work in two halves,
``cheap`` (resize, detector, staticity map, entropy map: OpenCV/numpy, releases the GIL) and
``finish`` (memorability CNN on onnxruntime), so a caller can run the cheap half of later
frames on one core while the CNN runs on the other (:meth:`Scorer.score_stream`).

Modes (``ScoreConfig.mode``):

* ``exact``: the paper's selections, fast. Exact sliding-histogram entropy, the detector once
  per frame, stages skipped once a frame fails, and the crop loop of the memorability stage
  stops as soon as MS >= MT is decided (MS is then recorded as a bound, ``ms_exact=False``).
* ``paper``: the literal pipeline (scikit-image entropy, every crop, every score) for reference.
* ``fast``: ``exact`` with an int8 surrogate of the memorability model in front: every crop is
  scored by the surrogate, and the exact model runs only on the crops needed to settle frames
  whose estimated MS is within the surrogate's measured error of MT (:class:`FastMemorability`).

``all_scores=True`` computes every score of every frame (for sweeps and reports).
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
import hashlib
from collections.abc import Hashable
from dataclasses import dataclass, field, replace
from functools import lru_cache
from typing import Any, TypeVar

import cv2
import numpy as np
import numpy.typing as npt

from memlog.errors import ScoringError
from memlog.models.resmem import FRAME, GRID
from memlog.scoring.config import ScoreConfig

__all__ = ["Scorer", "FrameScore", "SharedScore", "CheapStage", "EntropyBound", "resize_frame", "STAGES", "pixels_digest",
           "view_vector", "view_steps", "blank_views", "crops_needed"]

STAGES = ("staticity", "entropy", "memorability")
T = TypeVar("T")


def resize_frame(bgr: npt.NDArray[Any], size: int = FRAME) -> npt.NDArray[np.uint8]:
    """The spec's frame: BGR (grey replicated), ``cv2.resize`` to size x size, INTER_LINEAR."""
    if bgr.ndim == 2:
        bgr = cv2.cvtColor(bgr, cv2.COLOR_GRAY2BGR)
    if bgr.ndim != 3 or bgr.shape[2] != 3 or bgr.dtype != np.uint8:
        raise ScoringError(f"expected an HxWx3 uint8 BGR frame, got shape {bgr.shape} dtype {bgr.dtype}")
    return np.ascontiguousarray(cv2.resize(bgr, (size, size), interpolation=cv2.INTER_LINEAR))


def crops_needed(static_map: npt.NDArray[Any]) -> int:
    """The crops of non-zero weight (:func:`memlog.models.resmem.crop_weights`): what scoring MS
    fully runs. A map with no dynamic pixel gives every crop a positive weight (the weights are
    sums of non-negative terms), so that case needs no 1135 x 1135 product."""
    if bool(np.all(static_map)):
        return GRID * GRID
    from memlog.models.resmem import crop_weights

    return int(np.count_nonzero(crop_weights(static_map) > 0))


@lru_cache(maxsize=1)
def _all_static() -> npt.NDArray[np.float64]:
    """The static map of a frame without dynamic objects (every pixel 1), read-only; float64, as
    :func:`~memlog.scoring.entropy.entropy_score` multiplies with it (the same numbers as a uint8
    map of ones, without converting one per frame)."""
    s = np.ones((FRAME, FRAME), np.float64)
    s.setflags(write=False)
    return s


@dataclass
class EntropyBound:
    """The entropy half alone (no detector): ``es_static`` is the frame's ES were every pixel
    static, computed as the scorer computes ES for such a frame (so it *is* its ES when the
    detector finds no dynamic object). Masking only removes entropy (S <= 1) and SS <= 1, so it
    bounds the frame's ES and, with MS <= SS <= 1, its geometric score; staged selection runs the
    detector only where that bound can still win (:func:`memlog.selection.staged.detect_in_segment`)."""

    es_static: float
    height: int
    width: int
    timing_ms: dict[str, float] = field(default_factory=dict)


@dataclass
class CheapStage:
    """Result of the cheap half: staticity and entropy (maps kept only when asked)."""

    frame1135: npt.NDArray[np.uint8]
    height: int
    width: int
    static_map: npt.NDArray[Any]
    ss: float
    detections: list[Any]
    es: float | None = None
    entropy_map: npt.NDArray[Any] | None = None
    rejected_by: str | None = None
    timing_ms: dict[str, float] = field(default_factory=dict)


def _round6(v: float | None) -> float | None:
    return None if v is None else round(float(v), 6)


@dataclass
class FrameScore:
    """Scores of one frame (None where a stage was skipped)."""

    ms: float | None
    ss: float | None
    es: float | None
    selected: bool
    rejected_by: str | None
    memorability: npt.NDArray[np.float32] | None = None  # 5x5, NaN = not scored
    ms_low: float | None = None
    ms_high: float | None = None
    ms_exact: bool = True
    crops_scored: int = 0
    crops_surrogate: int = 0
    detections: list[Any] = field(default_factory=list)
    timing_ms: dict[str, float] = field(default_factory=dict)
    width: int = 0
    height: int = 0
    maps: dict[str, npt.NDArray[Any]] = field(default_factory=dict)
    shared_from: int | None = None  # frame index whose scores these are (a duplicate frame)
    crops_needed: int = 0  # crops of non-zero weight: what scoring MS fully runs (not in records)

    def to_json(self) -> dict[str, Any]:
        m = None
        if self.memorability is not None:
            m = [[None if not np.isfinite(v) else round(float(v), 6) for v in row] for row in self.memorability]
        r = _round6
        return {
            "ms": r(self.ms), "ms_low": r(self.ms_low), "ms_high": r(self.ms_high), "ms_exact": self.ms_exact,
            "ss": r(self.ss), "es": r(self.es), "memorability": m, "crops_scored": self.crops_scored,
            "crops_surrogate": self.crops_surrogate,
            "selected": self.selected, "rejected_by": self.rejected_by,
            "detections": len(self.detections),
            "timing_ms": {k: round(v, 3) for k, v in self.timing_ms.items()},
            "shared": self.shared_from is not None, "shared_from": self.shared_from,
        }


@dataclass(frozen=True)
class SharedScore:
    """The result for a frame that repeats the previous frame of its topic (pixel-identical; or,
    with ``duplicates="near"``, nearly so): not scored again, it carries frame ``index``'s scores."""

    index: int
    timing_ms: dict[str, float] = field(default_factory=dict)

    def apply(self, previous: FrameScore, index: int | None = None) -> FrameScore:
        """``previous``'s scores (those of frame ``index``, default :attr:`index`) as this frame's."""
        return replace(previous, shared_from=self.index if index is None else index, timing_ms=dict(self.timing_ms))


def view_vector(img: npt.NDArray[Any]) -> npt.NDArray[np.float64]:
    """A 32 x 16 grey thumbnail as a zero-mean unit vector (zero for a flat frame): what the
    near-duplicate test and the view-change measure of selection compare. A standing camera's
    consecutive frames differ by a cosine distance of at most 0.0002 (EuRoC before take-off, all
    188 pairs), a moving train's by a median 0.15 (Nordland)."""
    g = img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    v = cv2.resize(g, (32, 16), interpolation=cv2.INTER_AREA).astype(np.float64).ravel()
    v -= v.mean()
    n = float(np.linalg.norm(v))
    return v / n if n > 0 else v


def blank_views(view: npt.ArrayLike) -> npt.NDArray[np.bool_]:
    """Rows of ``view`` ([N, 512] view vectors) that are blank (a flat frame: zero vector)."""
    v = np.asarray(view, dtype=np.float64)
    return np.asarray(np.linalg.norm(v, axis=1) < 1e-6, dtype=bool)


def view_steps(view: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """How much the view changed from each row of ``view`` ([N, 512] view vectors, rows in drive
    order) to the next: the cosine distance to the predecessor (0 for the first row, 0 between two
    blank frames, 1 between a blank and a non-blank one; NaN where a vector is unknown)."""
    v = np.asarray(view, dtype=np.float64)
    out = np.zeros(len(v))
    if len(v) > 1:
        dots = np.einsum("ij,ij->i", v[1:], v[:-1])
        blank = blank_views(v)
        both = blank[1:] & blank[:-1]
        one = blank[1:] ^ blank[:-1]
        out[1:] = np.where(both, 0.0, np.where(one, 1.0, np.clip(1.0 - dots, 0.0, 2.0)))
    return out


def pixels_digest(img: npt.NDArray[Any]) -> bytes:
    """A digest of decoded pixels (shape, type and values): equal digests, identical frames."""
    h = hashlib.blake2b(digest_size=16)
    h.update(repr((img.shape, img.dtype.str)).encode())
    h.update(np.ascontiguousarray(img).tobytes())
    return h.digest()


class Scorer:
    """Scores frames with the three criteria of the paper. Models load on first use."""

    def __init__(
        self,
        config: ScoreConfig | None = None,
        *,
        memorability: Any = None,
        staticity: Any = None,
        memorability_path: Any = None,
    ) -> None:
        self.config = config or ScoreConfig()
        self._mem = memorability
        self._stat = staticity
        self._mem_path = memorability_path

    # -- models ---------------------------------------------------------------------
    @property
    def staticity(self) -> Any:
        if self._stat is None:
            from memlog.scoring.staticity import Staticity

            c = self.config
            self._stat = Staticity(conf=c.det_conf, min_area=c.det_min_area, dynamic=c.dynamic_classes,
                                   device=c.device)
        return self._stat

    @property
    def memorability(self) -> Any:
        if self._mem is None:
            from memlog.scoring.memorability import Memorability

            threads = self.config.threads or None
            exact = Memorability(self._mem_path, threads=threads, batch=self.config.crop_batch,
                                 device=self.config.device)
            from memlog.models.runtime import session_device

            if session_device(exact.session) == "cuda":
                exact.batch = 25  # a GPU runs a frame's 25 crops in one call as fast as a few
            if self.config.mode == "fast":
                from memlog.models.quantize import frame_fit, resmem_int8_bounds, resmem_int8_path
                from memlog.scoring.memorability import FastMemorability

                int8 = resmem_int8_path()
                eps, delta, bias = resmem_int8_bounds(int8)
                self._mem = FastMemorability(int8, exact, eps, delta, bias, refine=self.config.fast_refine,
                                             threads=threads, device=self.config.device, frame_fit=frame_fit())
            else:
                self._mem = exact
        return self._mem

    def load(self) -> "Scorer":
        """Load every model now (to fail early with a clear message)."""
        _ = self.staticity.net if hasattr(self.staticity, "net") else None
        _ = self.memorability
        return self

    def provenance(self) -> dict[str, Any]:
        """What scored the frames: sha256 of every model file used and the device each runs on
        (recorded in outputs). Loads the models; :class:`~memlog.errors.ModelError` when a hash
        cannot be read, so provenance is never silently empty."""
        from memlog.models import cache
        from memlog.models.detector import detector_info
        from memlog.models.fetch import sha256_file
        from memlog.models.runtime import session_device

        self.load()
        models: dict[str, str] = {}
        devices: dict[str, str] = {}
        mem = self.memorability
        exact = getattr(mem, "exact", mem)
        for name, model in (("resmem", exact), ("resmem-int8", getattr(mem, "surrogate", None))):
            if model is None or not hasattr(model, "path"):
                continue
            models[name] = cache.recorded_sha256(model.path) or sha256_file(model.path)
            devices[name] = session_device(model.session)
        net = getattr(self.staticity, "net", None)
        if net is not None:
            models["ssd-mobilenet-v2-coco"] = detector_info(hashes=True)["sha256"]["graph"]
            devices["ssd-mobilenet-v2-coco"] = getattr(net, "device", "cpu")
        return {"models": models, "devices": devices}

    # -- stages ---------------------------------------------------------------------
    def _entropy_map(self, gray: npt.NDArray[np.uint8]) -> npt.NDArray[np.float64]:
        """The entropy map E of the grey 1135 frame (scikit-image's in paper mode, memlog's exact
        sliding histograms otherwise: the same values)."""
        from memlog.scoring.entropy import entropy_map

        c = self.config
        if c.mode == "paper":
            from skimage.filters.rank import entropy as sk_entropy
            from skimage.morphology import disk

            return np.asarray(sk_entropy(gray, disk(c.entropy_radius)), np.float64)  # type: ignore[no-untyped-call]
        return entropy_map(gray, c.entropy_radius)

    def entropy_bound(self, bgr: npt.NDArray[Any]) -> EntropyBound:
        """Resize and entropy without the detector: the frame's ES were every pixel static
        (:class:`EntropyBound`; the SPEC's E of the grey 1135 x 1135 frame, masked by S = 1)."""
        from memlog.scoring.entropy import entropy_score

        t0 = time.perf_counter()
        h, w = bgr.shape[:2]
        f = resize_frame(bgr)
        t1 = time.perf_counter()
        gray: npt.NDArray[np.uint8] = np.asarray(cv2.cvtColor(f, cv2.COLOR_BGR2GRAY), np.uint8)
        es = entropy_score(self._entropy_map(gray), _all_static())
        t2 = time.perf_counter()
        return EntropyBound(float(es), h, w, {"resize": (t1 - t0) * 1e3, "entropy": (t2 - t1) * 1e3})

    def cheap(self, bgr: npt.NDArray[Any], keep_maps: bool | None = None, *,
              es_static: float | None = None) -> CheapStage:
        """Resize, staticity (detector once), entropy: everything but the CNN.

        ``es_static``: the frame's :attr:`EntropyBound.es_static`, computed before; when the
        detector finds no dynamic pixel it is the frame's ES (the same number, not recomputed),
        else the entropy map is computed again and masked."""
        from memlog.scoring.entropy import entropy_score

        c = self.config
        keep = c.maps if keep_maps is None else keep_maps
        timing: dict[str, float] = {}
        t0 = time.perf_counter()
        h, w = bgr.shape[:2]
        f = resize_frame(bgr)
        t1 = time.perf_counter()
        timing["resize"] = (t1 - t0) * 1e3
        s_map, ss, dets = self.staticity(f)
        t2 = time.perf_counter()
        timing["staticity"] = (t2 - t1) * 1e3
        out = CheapStage(f, h, w, s_map, float(ss), list(dets), timing_ms=timing)
        if ss < c.st:
            out.rejected_by = "staticity"
            if not c.all_scores and c.mode != "paper":
                return out
        if es_static is not None and not keep and bool(np.all(s_map)):
            es = es_static  # entropy_score(E, S) with S all ones: computed already
        else:
            gray: npt.NDArray[np.uint8] = np.asarray(cv2.cvtColor(f, cv2.COLOR_BGR2GRAY), np.uint8)
            emap = self._entropy_map(gray)
            es = entropy_score(emap, s_map)
            if keep:
                out.entropy_map = emap
        if c.normalize == "static":
            es = es / ss if ss > 0 else 0.0
        out.es = float(es)
        timing["entropy"] = (time.perf_counter() - t2) * 1e3
        if out.rejected_by is None and out.es < c.et:
            out.rejected_by = "entropy"
        return out

    def finish(self, cheap: CheapStage) -> FrameScore:
        """Memorability (when still needed) and the decision."""
        c = self.config
        timing = dict(cheap.timing_ms)
        res = FrameScore(ms=None, ss=cheap.ss, es=cheap.es, selected=False, rejected_by=cheap.rejected_by,
                         detections=cheap.detections, timing_ms=timing, width=cheap.width, height=cheap.height)
        res.crops_needed = crops_needed(cheap.static_map)
        need_m = cheap.rejected_by is None or c.all_scores or c.mode == "paper"
        if need_m:
            t0 = time.perf_counter()
            early = c.mode != "paper" and not c.all_scores
            thr = c.mt
            if c.normalize == "static":
                thr = c.mt * cheap.ss  # MS_static = MS_all / SS
            r = self.memorability(cheap.frame1135, cheap.static_map, threshold=thr if early else None)
            timing["memorability"] = (time.perf_counter() - t0) * 1e3
            scale = (1.0 / cheap.ss if cheap.ss > 0 else 0.0) if c.normalize == "static" else 1.0
            res.memorability = r.m
            res.crops_scored = r.n_scored
            res.crops_surrogate = r.n_surrogate
            res.ms_exact = bool(r.exact)
            res.ms_low, res.ms_high = r.ms_low * scale, r.ms_high * scale
            if r.ms is not None:  # exact value, or fast mode's estimate
                res.ms = r.ms * scale
            # else: the crop loop stopped early; MS is unknown, ms_low/ms_high bound it
            passed = r.passed if r.passed is not None else (res.ms is not None and res.ms >= c.mt)
            if res.rejected_by is None and not passed:
                res.rejected_by = "memorability"
            if c.maps:
                from memlog.scoring.memorability import memorability_map

                res.maps["memorability"] = memorability_map(np.where(np.isnan(r.m), 0.0, r.m))
        res.selected = res.rejected_by is None
        if c.maps:
            res.maps["staticity"] = cheap.static_map
            if cheap.entropy_map is not None:
                res.maps["entropy"] = cheap.entropy_map
        return res

    def score(self, bgr: npt.NDArray[Any]) -> FrameScore:
        """Score one decoded frame (BGR or grey, any size)."""
        return self.finish(self.cheap(bgr))

    def score_stream(
        self,
        items: Iterable[T],
        decode: Callable[[T], npt.NDArray[Any]],
        prefetch: int = 2,
        *,
        identity: Callable[[T], tuple[Hashable, int]] | None = None,
        seed: dict[Hashable, tuple[int, Any]] | None = None,
    ) -> Iterator[tuple[T, FrameScore | SharedScore | Exception]]:
        """Score a stream with the cheap half of later frames overlapping the CNN.

        ``decode`` turns an item into pixels (runs in the worker thread). Yields the item with
        its :class:`FrameScore`, or with the exception when decoding/scoring failed (the
        stream goes on). With ``identity`` (item -> (group, frame index), e.g. the topic) and
        ``config.duplicates`` not "off", a frame that repeats the previous frame of its group
        yields a :class:`SharedScore` instead of being scored again; ``seed`` gives, per group,
        the frame before the stream's first one (index, :meth:`duplicate_key` of its pixels).
        """
        share = identity is not None and self.config.duplicates != "off"
        last: dict[Hashable, tuple[int, Any]] = dict(seed or {})

        def cheap_of(item: T) -> CheapStage | SharedScore:
            t0 = time.perf_counter()
            img = decode(item)
            dt = (time.perf_counter() - t0) * 1e3
            if share and identity is not None:
                group, index = identity(item)
                key = self.duplicate_key(img)
                prev = last.get(group)
                if prev is not None and self.same_frame(prev[1], key):
                    last[group] = (prev[0], key)
                    return SharedScore(prev[0], {"decode": dt, "duplicate": (time.perf_counter() - t0) * 1e3 - dt})
                last[group] = (index, key)
            out = self.cheap(img)
            out.timing_ms = {"decode": dt, **out.timing_ms}
            return out

        pending: deque[tuple[T, Future[CheapStage | SharedScore]]] = deque()
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="memlog-cheap") as pool:
            def drain_one() -> tuple[T, FrameScore | SharedScore | Exception]:
                item, fut = pending.popleft()
                try:
                    res = fut.result()
                    return item, res if isinstance(res, SharedScore) else self.finish(res)
                except Exception as exc:  # one bad frame never stops the run
                    return item, exc

            for item in items:
                pending.append((item, pool.submit(cheap_of, item)))
                while len(pending) > prefetch:
                    yield drain_one()
            while pending:
                yield drain_one()

    def duplicate_key(self, img: npt.NDArray[Any]) -> Any:
        """What decides that two frames are the same: their pixel digest; with
        ``duplicates="near"`` (fast mode only) also their thumbnail descriptor."""
        if self.config.duplicates == "near":
            return (pixels_digest(img), view_vector(img))
        return pixels_digest(img)

    def same_frame(self, a: Any, b: Any) -> bool:
        """Whether frames with duplicate keys ``a`` and ``b`` share one scoring."""
        if self.config.duplicates == "near":
            if a[0] == b[0]:
                return True
            return float(1.0 - np.dot(a[1], b[1])) < self.config.near_distance
        return bool(a == b)
