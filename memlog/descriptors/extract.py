"""Describe the frames of a log and package them as a :class:`DescriptorTable`.

Shared by ``memlog map`` (reference descriptors of the kept frames), ``memlog localize`` (query
descriptors) and ``memlog evaluate``: frames stream in batches, so memory stays bounded.
:class:`ReferenceDescribing` is the map's side: it describes every frame of the reference drive
while the map is written, fits the whitening on all of them (bounded memory) and keeps the
descriptors of the kept frames only.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator, Mapping, Sequence
from typing import Any

import numpy as np

from memlog.descriptors.base import Describer
from memlog.descriptors.patches import PatchPCA, PatchPCAFitter, PatchStore
from memlog.descriptors.table import DescriptorTable
from memlog.descriptors.whitening import WhitenedDescriber, Whitening, WhiteningFitter
from memlog.errors import ImageDecodeError
from memlog.io.base import FrameWindow, LogReader
from memlog.io.frame import Frame
from memlog.io.identity import log_identity
from memlog.io.open import open_log
from memlog.io.positions import MotionTrack, PositionTrack, read_tracks
from memlog.io.records import ReadReport
from memlog.progress import progress
from memlog.scoring.motion import STILL_DISTANCE, Stops, find_stops, frame_motion, moving_index, stop_rule, stops_record
from memlog.scoring.scorer import view_vector

__all__ = ["describe_frames", "build_table", "describe_log", "moving_indices", "ReferenceDescribing"]


def _batches(frames: Iterable[Frame], n: int) -> Iterator[list[Frame]]:
    batch: list[Frame] = []
    for f in frames:
        batch.append(f)
        if len(batch) >= n:
            yield batch
            batch = []
    if batch:
        yield batch


def describe_frames(
    frames: Iterable[Frame], describer: Describer, reader: LogReader | None = None, batch: int = 16,
    views: list[np.ndarray] | None = None, patches: list[np.ndarray] | None = None,
    patch_pca: PatchPCA | None = None,
) -> tuple[list[Frame], np.ndarray]:
    """Descriptors of ``frames`` ([N, dim] float32); frames that do not decode are reported
    through ``reader`` (when given) and left out. ``views``: receives each described frame's
    view vector (:func:`memlog.scoring.scorer.view_vector`), for where the drive stood still.
    ``patches``: receives, batch by batch, the described frames' pooled patch features when the
    describer gives them (float16; projected by ``patch_pca`` when given, else raw)."""
    kept: list[Frame] = []
    rows: list[np.ndarray] = []
    for group in _batches(frames, batch):
        imgs = []
        for f in group:
            try:
                imgs.append(f.decode_bgr())
                kept.append(f)
            except ImageDecodeError as exc:
                if reader is not None:
                    reader.decode_error(f, exc)
        if views is not None:
            views.extend(view_vector(img).astype(np.float32) for img in imgs)
        if imgs and patches is not None and describer.gives_patches:
            d, p = describer.describe_patches(imgs)
            rows.append(d)
            if p is not None:
                raw = p.astype(np.float16)  # what a cached table stores: projected alike either way
                patches.append(patch_pca.apply(raw) if patch_pca is not None else raw)
        elif imgs:
            rows.append(describer.describe(imgs))
    desc = np.concatenate(rows) if rows else np.zeros((0, describer.dim), np.float32)
    return kept, desc


def moving_indices(frames: Sequence[Frame], views: np.ndarray | Sequence[np.ndarray],
                   still_distance: float = STILL_DISTANCE,
                   motion: Sequence[MotionTrack] = ()) -> tuple[np.ndarray, dict[str, Any]]:
    """Each frame's index with its topic's stops left out
    (:func:`memlog.scoring.motion.moving_index`), and the record of how the stops were found
    (:func:`~memlog.scoring.motion.stops_record`, the table's ``extra["stops"]``): each topic's
    stops are :func:`~memlog.scoring.motion.find_stops`' from the log's ``motion``
    (:func:`memlog.io.positions.read_motion`) when it knows every frame of the topic, else from
    the frames' view vectors (``views``, one per frame) with ``still_distance``; each topic's frames
    in drive order, consecutive as far as they were read."""
    v = np.asarray(views, dtype=np.float64).reshape(len(frames), -1)
    index = np.array([f.index for f in frames], dtype=np.int64)
    t_ns = np.array([f.log_time_ns for f in frames], dtype=np.int64)
    topics = np.array([f.topic for f in frames], dtype=object)
    out = index.copy()
    found: dict[str, Stops] = {}
    for t in dict.fromkeys(topics.tolist()):
        rows = np.flatnonzero(topics == t)
        found[t] = find_stops(len(rows), v[rows], frame_motion(motion, t_ns[rows]), still_distance)
        out[rows] = moving_index(index[rows], found[t].still)
    return out, stops_record(still_distance, found)


def build_table(
    frames: list[Frame],
    descriptors: np.ndarray,
    describer: Describer,
    *,
    scores: Mapping[str, Mapping[int, Mapping[str, Any]]] | None = None,
    track: PositionTrack | None = None,
    extra: dict[str, Any] | None = None,
    whitening: Whitening | None = None,
    moving: np.ndarray | None = None,
    stops: Mapping[str, Any] | None = None,
    patches: np.ndarray | None = None,
    patch_pca: PatchPCA | None = None,
) -> DescriptorTable:
    """A DescriptorTable of described frames, with their scores and interpolated positions.
    With ``whitening``, ``descriptors`` are already whitened by it and the table carries it;
    ``moving``: the frames' :func:`moving_indices` (the table's ``moving_index``), ``stops`` how
    its stops were found (recorded as ``extra["stops"]``; default
    :func:`~memlog.scoring.motion.stop_rule`: by the images with the default ``still_distance``);
    ``patches``/``patch_pca``: the frames' patch features and the PCA that projected them."""
    def score(name: str) -> np.ndarray:
        if scores is None:
            return np.full(len(frames), np.nan)
        vals = []
        for f in frames:
            v = scores.get(f.topic, {}).get(f.index, {}).get(name)
            vals.append(np.nan if v is None else float(v))
        return np.asarray(vals, dtype=np.float64)

    positions: dict[str, np.ndarray] = {}
    if track is not None and frames:
        t = [f.log_time_ns for f in frames]
        if track.kind == "gnss":
            ll = track.latlon_at(t)
            assert ll is not None
            positions = {"lat": ll[:, 0], "lon": ll[:, 1], "alt": ll[:, 2]}
        else:
            xyz = track.at(t)
            positions = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}
    ex = dict(extra or {})
    if track is not None:
        ex["position_topic"] = track.topic
    if moving is not None:
        ex["stops"] = dict(stops) if stops is not None else stop_rule()
    return DescriptorTable(
        topic=[f.topic for f in frames],
        frame_index=np.array([f.index for f in frames], dtype=np.int64),
        log_time_ns=np.array([f.log_time_ns for f in frames], dtype=np.int64),
        stamp_ns=np.array([f.stamp_ns for f in frames], dtype=np.int64),
        descriptors=descriptors,
        meta=(describer if whitening is None else WhitenedDescriber(describer, whitening)).meta(),
        ms=score("ms"), ss=score("ss"), es=score("es"),
        positions=positions,
        extra=ex,
        whitening=whitening,
        moving_index=moving,
        patches=patches,
        patch_pca=patch_pca if patches is not None else None,
    )


def describe_log(
    log: str | os.PathLike[str],
    describer: Describer,
    window: FrameWindow | None = None,
    *,
    scores: Mapping[str, Mapping[int, Mapping[str, Any]]] | None = None,
    still_distance: float = STILL_DISTANCE,
    patches: bool = True,
    patch_pca: PatchPCA | None = None,
) -> tuple[DescriptorTable, ReadReport]:
    """Descriptors of the frames of ``window`` (default: the first camera topic, every frame),
    with positions when the log has them, and the read report (damage found); the moving index
    with stops found from the log's motion, else with ``still_distance`` from the images
    (:func:`moving_indices`). The table's ``extra`` records the log, its identity, the window and
    how stops were found. ``patches``: keep the frames' patch features when the describer gives
    them, projected by ``patch_pca`` (a map's) when given, else raw."""
    window = window or FrameWindow()
    with open_log(log) as reader:
        cams = reader.check_camera_topics(window.topics)
        if window.topics is None:
            cams = cams[:1]  # one camera per drive unless asked
        w = FrameWindow(tuple(cams), window.start_ns, window.end_ns, window.stride)
        track, motion = read_tracks(reader)
        frames = progress(reader.frames(w.topics, w.start_ns, w.end_ns, w.stride), total=reader.count_frames(w),
                          desc="describe", unit="frame")
        views: list[np.ndarray] = []
        pp: list[np.ndarray] | None = [] if patches and describer.gives_patches else None
        kept, desc = describe_frames(frames, describer, reader, views=views, patches=pp, patch_pca=patch_pca)
        extra = {"log": str(reader.path), "log_identity": log_identity(log), "window": w.to_dict()}
        moving, stops = moving_indices(kept, views, still_distance, motion)
        pat = np.concatenate(pp) if pp else None
        return build_table(kept, desc, describer, scores=scores, track=track, extra=extra,
                           moving=moving, stops=stops, patches=pat, patch_pca=patch_pca), reader.report


class ReferenceDescribing:
    """Describes reference frames in batches while a map is written (bounded memory).

    ``add(frame, keep)``: kept frames are described and stored (frames without their pixels); with
    ``fit_whitening``, the whitening and the patch PCA are fitted on the frames of ``fit_frames``
    (topic -> frame indices: the drive's moving frames, so every map of one drive shares one
    transform), each described once if it is not kept (its descriptor is not stored), or on the kept
    frames when ``fit_frames`` is None. ``whitening``: a transform fitted beforehand (e.g. with the
    distinctiveness pass) to apply instead of fitting one; ``known``: raw descriptors already
    computed, by ``(topic, frame index)``, used instead of describing again (``known_patches``: their
    raw pooled patch features). :meth:`result` returns the kept frames, their (whitened) descriptors
    and the transform (None without whitening). When the describer gives patch features
    (``patches``), the kept frames' are kept aside (:class:`~memlog.descriptors.patches.PatchStore`)
    and :meth:`patch_result` gives them projected by the PCA.
    """

    def __init__(self, describer: Describer, reader: LogReader, *, fit_whitening: bool = False,
                 fit_frames: Mapping[str, set[int]] | None = None,
                 whiten_dim: int | None = None, whitening: Whitening | None = None,
                 known: Mapping[tuple[str, int], np.ndarray] | None = None,
                 known_patches: Mapping[tuple[str, int], np.ndarray] | None = None,
                 patches: bool = True, batch: int = 16) -> None:
        self.describer, self.reader, self.batch = describer, reader, batch
        self.whitening = whitening
        self.whiten_dim = whiten_dim
        self.fitter = WhiteningFitter(describer.dim) if fit_whitening and whitening is None else None
        self.fit_frames = fit_frames
        self.known = known or {}
        self.known_patches = known_patches or {}
        self.patches = patches and describer.gives_patches
        self.store = PatchStore() if self.patches else None
        self.patch_fitter: PatchPCAFitter | None = None
        self.frames: list[Frame] = []
        self.rows: list[np.ndarray] = []
        self._pending: list[tuple[Frame, Any, bool, bool]] = []

    def fits_on(self, topic: str, index: int) -> bool:
        """Whether frame ``index`` of ``topic`` is one the whitening and the patch PCA are fitted on."""
        if self.fit_frames is None:
            return False
        return index in self.fit_frames.get(topic, ())

    def add(self, frame: Frame, keep: bool) -> None:
        fit = self.fits_on(frame.topic, frame.index)
        if not keep and not fit:
            return
        key = (frame.topic, frame.index)
        row = self.known.get(key)
        if row is not None and self.patches and key not in self.known_patches:
            row = None  # its patches are not known: describe it
        if row is None:
            try:
                img = frame.decode_bgr()
            except ImageDecodeError as exc:
                if keep:  # a frame that is not kept was reported by the scoring pass already
                    self.reader.decode_error(frame, exc)
                return
        self._pending.append((frame.stripped() if keep else frame, row if row is not None else img, keep, fit))
        if len(self._pending) >= self.batch:
            self.flush()

    def flush(self) -> None:
        if not self._pending:
            return
        todo = [k for k, p in enumerate(self._pending) if p[1].ndim != 1]
        desc = np.zeros((len(self._pending), self.describer.dim), np.float32)
        pooled: dict[int, np.ndarray] = {}
        if todo:
            imgs = [self._pending[k][1] for k in todo]
            d, p = self.describer.describe_patches(imgs) if self.patches else (self.describer.describe(imgs), None)
            desc[todo] = d
            if p is not None:
                pooled.update(zip(todo, p))
        for k, (f, v, _kp, _fit) in enumerate(self._pending):
            if v.ndim == 1:
                desc[k] = v
                if self.patches:
                    pooled[k] = self.known_patches[(f.topic, f.index)]
        keep = np.array([p[2] for p in self._pending], dtype=bool)
        fit = keep if self.fit_frames is None else np.array([p[3] for p in self._pending], dtype=bool)
        if self.fitter is not None:
            self.fitter.add(desc[fit])
        self.rows.append(desc[keep])
        if self.store is not None:
            # patches as stored (float16): the PCA is fitted on what it projects
            as_stored = {k: v.astype(np.float16) for k, v in pooled.items()}
            if fit.any():
                fitted = np.stack([as_stored[int(k)] for k in np.flatnonzero(fit)])
                if self.patch_fitter is None:
                    self.patch_fitter = PatchPCAFitter(int(fitted.shape[-1]))
                self.patch_fitter.add(fitted)
            if keep.any():
                self.store.add(np.stack([as_stored[int(k)] for k in np.flatnonzero(keep)]))
        self.frames.extend(p[0] for p in self._pending if p[2])
        self._pending.clear()

    def result(self, source: str = "") -> tuple[list[Frame], np.ndarray, Whitening | None]:
        self.flush()
        desc = np.concatenate(self.rows) if self.rows else np.zeros((0, self.describer.dim), np.float32)
        if self.fitter is not None:
            self.whitening = self.fitter.fit_or_none(self.whiten_dim, source=source)
        if self.whitening is not None:
            desc = self.whitening.apply(desc)
        return self.frames, desc, self.whitening

    def patch_result(self) -> tuple[np.ndarray | None, PatchPCA | None]:
        """The kept frames' patch features projected by the PCA fitted on the fit frames (module
        doc), and the PCA; (None, None) when the describer gives none or fewer than two patches were fitted."""
        self.flush()
        pca = self.patch_fitter.fit() if self.patch_fitter is not None else None
        if self.store is None or pca is None:
            return None, None
        try:
            return self.store.projected(pca), pca
        finally:
            self.store.close()


def drive_distinctiveness(
    reader: LogReader, topics: list[str], describer: Describer, *, whiten: bool, whiten_dim: int | None,
    config: Any = None, indices: Mapping[str, set[int]] | None = None,
    known: Mapping[tuple[str, int], np.ndarray] | None = None,
) -> tuple[dict[str, dict[int, float]], dict[tuple[str, int], np.ndarray], Whitening | None]:
    """Distinctiveness of every frame of ``topics`` (only those in ``indices[topic]`` when given:
    the frames the selection sees), computed on the describer's descriptors of the whole drive,
    whitened by a transform fitted on them when ``whiten``
    (:mod:`memlog.selection.distinctiveness`). Returns DS by topic and frame index, the raw
    descriptors by ``(topic, frame index)`` (so the map pass need not describe again) and the
    transform. ``known``: raw descriptors already computed (not described again)."""
    from memlog.selection.distinctiveness import distinctiveness

    raw: dict[tuple[str, int], np.ndarray] = {}
    per_topic: dict[str, tuple[list[int], np.ndarray]] = {}
    fitter = WhiteningFitter(describer.dim) if whiten else None
    for t in topics:
        have = {i: v for (tt, i), v in (known or {}).items() if tt == t}
        want = None if indices is None else set(indices.get(t, set()))
        if have and want is not None and want <= set(have):
            kept_idx = sorted(want)
            desc = np.stack([have[i] for i in kept_idx]).astype(np.float32) if kept_idx else \
                np.zeros((0, describer.dim), np.float32)
            per_topic[t] = (kept_idx, desc)
            raw.update({(t, i): desc[k] for k, i in enumerate(kept_idx)})
            if fitter is not None:
                fitter.add(desc)
            continue
        wanted = None if want is None else {t: want}
        total = reader.count_frames(FrameWindow((t,))) if wanted is None else len(want or ())
        frames = progress(reader.frames([t], indices=wanted), total=total, desc="describe", unit="frame")
        kept, desc = describe_frames(frames, describer, None)
        per_topic[t] = ([f.index for f in kept], desc)
        raw.update({(t, f.index): desc[k] for k, f in enumerate(kept)})
        if fitter is not None:
            fitter.add(desc)
    whitening = fitter.fit_or_none(whiten_dim, f"{reader.path} ({', '.join(topics)})") if fitter is not None else None
    ds: dict[str, dict[int, float]] = {}
    for t, (idx, desc) in per_topic.items():
        d = whitening.apply(desc) if whitening is not None else desc
        vals = distinctiveness(d, config) if len(idx) else np.zeros(0)
        ds[t] = {i: float(v) for i, v in zip(idx, vals)}
    return ds, raw, whitening
