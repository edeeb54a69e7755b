"""The drive matcher (:func:`match_tables`): a query log's descriptor table against a map's, as
``memlog localize`` and ``memlog evaluate`` run it: coordinates, runs, sequences, the patch re-rank and
the drive HMM."""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from memlog.descriptors.table import DescriptorTable
from memlog.matching.config import F32, F64, I64, SequenceConfig, SequenceMatch
from memlog.matching.coordinates import _topic_groups, drive_coordinates, drive_pace, drive_runs, reference_unit, resolve_coordinate, standing_rows, stop_runs, uses_stops
from memlog.matching.paths import _run_bounds
from memlog.matching.rerank import RERANK_PLACES, PairScores, _patch_plan, _ranked_by, rerank_by_patches
from memlog.matching.sequences import _median_step, match_sequences
from memlog.matching.drive_hmm import place_probabilities
from memlog.matching.ensemble import BELOW, ensemble_dims, leading, union

if TYPE_CHECKING:
    from memlog.descriptors.approx import IVFIndex

__all__ = ["match_tables"]

SPEED_STOP = 3  # a stop of this many standing frames ends the windows the re-rank's speeds are voted in


def match_tables(
    query: DescriptorTable,
    reference: DescriptorTable,
    config: SequenceConfig | None = None,
    *,
    k: int = 5,
    index: IVFIndex | None = None,
    nprobe: int | None = None,
    rerank: int | None = None,
    ref_mask: npt.ArrayLike | None = None,
    pair_cache: dict[str, PairScores] | None = None,
) -> SequenceMatch:
    """The drive matcher: :func:`match_sequences` for two descriptor tables (a query log and a
    map), what ``memlog localize``, ``memlog evaluate`` and the benchmarks all call. The
    coordinate is resolved (:func:`resolve_coordinate`), the query is cut into runs
    (:func:`drive_runs`) and put in drive order per topic; the map is cut into runs the same way
    (its topics, recording gaps and frames out of order), each run's coordinates far from the
    others' so no path crosses from one to the next; the reference frame spacing comes from the
    map's frame indices (so a sparse map's gaps are known). The patch re-rank scores each frame's
    places along the speed that windows not crossing a stop of the query vote (a stop of
    :data:`SPEED_STOP` standing frames or more; the places themselves come from the whole windows):
    a window across a stop votes a blend of the speeds before and after it. ``ref_mask``: the map is
    these rows of ``reference`` (returned rows are rows of the whole table). ``pair_cache``: kept across
    calls on two tables (evaluate's masks), each patch pair scored once. Results in query row order."""
    cfg = config or SequenceConfig()
    coordinate, note = resolve_coordinate(cfg.coordinate, query, reference)
    stops = uses_stops(cfg, coordinate)
    qc = drive_coordinates(query, coordinate, stops)
    labels, gap = drive_runs(query, cfg.max_gap_s)
    standing = standing_rows(query, labels) if stops else None
    # query rows topic by topic (a run never mixes topics), each in table order
    perm = np.concatenate(_topic_groups(query)) if len(query) else np.zeros(0, np.int64)
    rc = drive_coordinates(reference, coordinate, stops)
    unit = reference_unit(reference, rc)
    ref_runs, _gap = drive_runs(reference, cfg.max_gap_s)
    if len(rc) and ref_runs.max() > 0:  # several runs (cameras, recording gaps): far apart
        span = float(rc.max() - rc.min()) + 1.0
        rc = rc + ref_runs * 4.0 * span
    pace = drive_pace(query, reference) if coordinate == "frames" else 1.0
    query, why_not = _patch_plan(cfg, query, reference)
    places = max(k, RERANK_PLACES) if why_not is None else k
    map_rows = (np.flatnonzero(np.asarray(ref_mask, dtype=bool)) if ref_mask is not None
                else np.arange(len(reference), dtype=np.int64))
    # what every run shares (the whitening ensemble matches the drive once per member)
    q_desc, q_c, q_runs = query.descriptors[perm], qc[perm], labels[perm]
    q_standing = None if standing is None else standing[perm]
    # the runs the re-rank's speeds are voted in: cut after each stop (None: no stop that long)
    free_runs = None if q_standing is None else stop_runs(q_runs, q_standing, SPEED_STOP)
    pairs, spacing = None, 0.0
    if why_not is None:  # the re-rank's pair scores (each computed once) and the HMM's map spacing
        assert query.patches is not None and reference.patches is not None and reference.patch_pca is not None
        pairs = PairScores.kept_in(pair_cache, query.patches, perm, reference.patches)
        spacing = _median_step(np.sort(rc[map_rows]))

    def run(qd: F32, rd: F32, hmm: bool = True) -> SequenceMatch:
        """The descriptor stage, the patch re-rank and (``hmm``) the drive HMM on descriptors ``qd``, ``rd``."""
        def stage(runs: I64, n: int) -> SequenceMatch:
            return match_sequences(qd, q_c, index.db if index is not None else rd, rc, cfg, k=n, runs=runs,
                                   ref_unit=unit, coordinate=coordinate, index=index, nprobe=nprobe, rerank=rerank,
                                   standing=q_standing, ref_mask=None if index is not None else ref_mask, pace=pace)

        res = stage(q_runs, places)
        if pairs is None:
            return res
        assert reference.patch_pca is not None
        res, speeds = _speeds_between_stops(res, None if free_runs is None else stage(free_runs, 1))
        res = rerank_by_patches(res, qd, rd, pairs.q_patches, pairs.r_patches, q_c, rc, map_rows, q_runs, cfg,
                                places, unit, pairs=pairs)
        res.info["rerank"] = {"by": "patches", "places": places, "patch_pca": reference.patch_pca.sha256,
                              "speeds": speeds}
        if not (cfg.hmm and cfg.enabled):
            res.info["hmm"] = {"off": "turned off (--no-hmm)" if cfg.enabled else "single frames"}
        elif hmm:
            res = _along_drive(res, qd, rd, q_c, rc, q_runs, spacing, unit, cfg)
        return res

    dims, why_alone = _ensemble_plan(cfg, reference, why_not, index)
    res = run(q_desc, reference.descriptors, hmm=not dims)
    if dims:  # every member's re-ranked places, decided by one drive HMM
        members = [res] + [run(leading(q_desc, d), leading(reference.descriptors, d), hmm=False) for d in dims[1:]]
        res = _along_drive(union(members, q_desc, reference.descriptors), q_desc, reference.descriptors, q_c, rc,
                           q_runs, spacing, unit, cfg)
        res.info["ensemble"] = {"dims": dims}
    else:
        res.info["ensemble"] = {"off": why_alone}
    if why_not is None:
        res = res.top(k)
    else:
        res.info["rerank"] = {"off": why_not}
        res.info["hmm"] = {"off": "no re-rank: the drive HMM decides between re-ranked places"}
    inv = np.empty_like(perm)
    inv[perm] = np.arange(len(perm))
    res = res.take(inv)
    res.info["coordinate_note"] = note
    res.info["max_gap_s"] = gap
    res.info["stops"] = stops
    res.info["map_runs"] = int(ref_runs.max()) + 1 if len(ref_runs) else 0
    res.info.setdefault("standing_rows", 0)
    return res




def _speeds_between_stops(res: SequenceMatch, free: SequenceMatch | None) -> tuple[SequenceMatch, str]:
    """``res`` with each sequence row's speed the one ``free`` gives it (the descriptor stage on the
    query's runs cut after its stops; None: no stop that long) where that row is a sequence there
    too, and what the re-rank's speeds are."""
    if free is None:
        return res, "the windows' own"
    use = res.sequence & free.sequence
    return (replace(res, speed=np.where(use, free.speed, res.speed)),
            f"voted by windows cut at the query's stops ({SPEED_STOP}+ standing frames) for {int(use.sum())} rows")


def _along_drive(res: SequenceMatch, q_desc: F32, r_desc: F32, qc: F64, rc: F64, labels: I64, spacing: float,
                 unit: float, cfg: SequenceConfig) -> SequenceMatch:
    """``res`` (query rows in drive order, each with its re-ranked places) with every row's places
    ranked by their probability along the drive (:mod:`memlog.matching.drive_hmm`): the margin
    becomes the best place's probability minus the best other place's; a standing row takes its
    stop's first row's places."""
    assert res.rerank is not None
    score = np.where(res.indices >= 0, np.nan_to_num(res.rerank, nan=0.0), -np.inf)
    x = np.where(res.indices >= 0, rc[np.maximum(res.indices, 0)], 0.0)
    speeds = res.info.get("speeds")
    pace = float(res.info.get("pace") or 1.0)
    lo, hi = _run_bounds(labels, qc)
    post, owner = place_probabilities(score, x, qc, lo, hi, pace=pace, spacing=spacing,
                                      vmax=float(speeds[1]) if speeds else 3.0 * pace, causal=cfg.causal)
    res = res.take(owner)
    res.posterior = post[owner]
    res.info = {**res.info, "hmm": {"posterior": "filtered" if cfg.causal else "forward-backward",
                                    "standing_rows": int((owner != np.arange(len(owner))).sum())}}
    return _ranked_by(res, np.where(res.indices >= 0, res.posterior, -np.inf), q_desc, r_desc, rc,
                      cfg.exclude * unit)


def _ensemble_plan(cfg: SequenceConfig, reference: DescriptorTable, why_not: str | None,
                   index: IVFIndex | None) -> tuple[list[int], str | None]:
    """The whitened dimensions the drive is matched in (:mod:`memlog.matching.ensemble`; empty: once,
    as it is) and why not when it is matched once."""
    w = reference.whitening
    if not cfg.ensemble:
        return [], "turned off (--no-ensemble)"
    if why_not is not None or not (cfg.hmm and cfg.enabled):
        return [], "no drive HMM: it decides between the members' places"
    if w is None:
        return [], "the map is not whitened"
    if w.n_fit >= BELOW:
        return [], f"the map's whitening was fitted on {w.n_fit} frames (>= {BELOW}: a steady estimate)"
    if index is not None:
        return [], "approximate search: its index holds the whole whitening only"
    dims = ensemble_dims(w)
    if len(dims) < 2:
        return [], f"the map is whitened to {w.dim_out} dimensions: too few to cut"
    return dims, None
