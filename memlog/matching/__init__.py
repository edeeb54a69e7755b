"""The drive matcher: localize a drive against a map as sequences of frames, not frame by frame.

One module per job: :mod:`~memlog.matching.config` (settings and result), :mod:`~memlog.matching.coordinates`
(the drives' coordinates and runs), :mod:`~memlog.matching.paths` (path scoring),
:mod:`~memlog.matching.voting` (votes and places), :mod:`~memlog.matching.sequences` (sequences of
descriptor arrays), :mod:`~memlog.matching.rerank` (the patch re-rank), :mod:`~memlog.matching.drive_hmm`
(the drive HMM) and :mod:`~memlog.matching.matcher` (:func:`match_tables`, what ``memlog localize`` runs).

Both the map and the query are drives, so a query frame is matched together with its neighbours:
the frames ``t`` of a window around query frame ``i`` (``length`` frames before and after, or,
``causal``, the ``length`` frames before and ``i`` itself) are assumed to follow a path along
the reference drive, and the path whose frames are most similar to the window wins (SeqSLAM,
Milford & Wyeth 2012). What is matched is a *coordinate* along each drive (``coordinate``):

* ``frames``: the frame index on the topic (the map's rows carry their frame index in the
  reference drive, so a sparse map keeps the reference drive's numbering);
* ``time``: the header stamp, in seconds (a map recorded at another frame rate has the same
  speed 1);
* ``positions``: the distance travelled along the drive's positions, in metres (a stop adds
  nothing, so the speed is about 1 whatever the vehicle did);
* ``auto``: ``positions`` when both drives have positions for every frame, else ``frames``.

**The score of a path.** Every similarity is contrast-normalised per query frame:
``z = (s - mean) / std`` with the mean and standard deviation of the frame's similarities to a
fixed sample of :data:`STAT_SAMPLE` map frames spread evenly over the map (so no full row of
similarities is needed, and the value does not depend on which other queries are matched). A
path predicts a reference coordinate for each window frame, and each *map frame along the path*
is compared with the query frame(s) predicted nearest to it (all of them on a tie: a stop). On
a full map at the right speed that is every window frame against its own place; on a half or
quarter map (gaps: the map holds only the kept frames, with their frame indices in the reference
drive) each kept frame meets the query frame aligned with it, never the frames that fall in a gap
only because no kept frame is nearer (on Nordland a frame two places away is another view).
The measurements behind this and every default below: ``docs/defaults.md``. Predictions beyond the
map's ends meet nothing. The path's score is ``sum(z) / sqrt(pairs)``: standard normal when
nothing matches, whatever the number of pairs, so paths with fewer pairs do not win by noise
(the plain mean lost on half maps). Two path models (``path``):

* ``constant`` (SeqSLAM): a straight line, coordinate ``x + v (c_t - c_i)`` with the relative
  speed ``v`` (map coordinate per query coordinate) searched over ``speeds`` in steps of
  ``speed_step`` (default: the step that moves the window's far end by one reference frame).
  The default range is a third to three times the drives' *pace* (the speed of a query driven
  at the map's pace: 1 at one frame rate, the ratio of the frame intervals otherwise), with a
  *speed prior*: a path's score (and its vote) loses ``speed_prior`` per doubling or halving of
  its speed against the pace. There is no standing hypothesis (speed 0): stops are left out of
  both drives ("Stops" below), so a standing path could only fit noise;
* ``dp``: a monotone path found by dynamic programming on a grid of one reference frame, each
  step between consecutive window frames moving ``round(vmin d / u)`` to ``round(vmax d / u)``
  grid units (``d``: the query's coordinate step, ``u``: the reference's frame spacing), so the
  speed may change inside the window (a stop half-way through it). Each window frame is scored
  against the map frame nearest its grid position. Measured on the Nordland variants it loses to
  ``constant`` (its freedom fits wrong places too), so ``constant`` is the default.

**Any map size.** Only hypotheses supported by the single-frame search are considered: the top
``candidates`` map frames of every query frame (exact search, or an approximate FAISS index)
vote, for every speed, for the place they imply for the window's centre, weighted by how much
they stand out of that frame's next candidate (``z`` minus the ``z`` of candidate ``K + 1``);
votes for a centre beyond the map's ends are dropped. The :data:`EXACT_PLACES` best-voted places
(distinct places: non-maximum suppression with ``exclude``) compete for the best match: each is
scored exactly with the chosen path model at its voted speed and :data:`RESCORE_SPEEDS` steps
either side, with its centre refined in steps of half a reference frame within half the map's
spacing (a sparse map's place, or a query frame of a map at a lower frame rate, may lie between
map frames), and reported as the map frame nearest its centre. More places competing gave more
false maxima;
ranks beyond come from the next voted places. The cost per query does not depend on the map's
size beyond the candidate search.

**Confidence, one scale for every row.** The margin: the best place's score minus the second
best's, the second best being outside ``exclude`` reference frames of the best (a different
place, for ``exclude`` the truth window's half-width). A frame matched alone is a path of one
pair: its score is its ``z`` and its margin is taken over the best candidate of another place,
so sequence and single-frame rows rank on one scale.

**Stops.** A camera standing still (at a station, a junction, a red light) sees one place
for many frames. Along the frame index such a stop stretches one place over as many frames as it
lasted, and a window of frames around it covers little drive. With ``stops`` (the default), each
drive runs along its *moving index* in the ``frames`` coordinate
(:attr:`DescriptorTable.moving_index`: the frame index minus the frames spent standing; tables
without it keep the frame index) and along its moving time in the ``time`` coordinate (the time
spent standing left out); ``positions`` add nothing while standing anyway. A query frame that
stood still since its run's previous frame is not matched on its own: it takes the result of its
stop's first frame (``standing``; ``info["standing_rows"]``). ``docs/defaults.md``
(``benchmarks/matcher_defaults.py``) gives what this and the other defaults were measured on.

**Runs and the fallback.** Both drives are cut into runs (:func:`drive_runs`: recording gaps,
frames out of order, cameras); a map's runs lie far apart in coordinate, so no path crosses from
one to the next. A query is cut into runs of rows whose coordinates do not decrease
(and, for logs, whose stamps increase with gaps below a limit: :func:`drive_runs`); windows never
cross a run boundary and are cut at its ends. Offline, a run shorter than ``length + 1`` frames
(a single image, a log of unordered frames) is matched frame by frame; causal, a frame is matched
as a sequence once ``length`` frames of its run precede it (decided from the past alone), so the
first ``length`` frames of every run are single frames. A map spanning fewer reference frames
than the window, and a query that stood still throughout its run, are matched frame by frame
too. The result says so, row by row (``SequenceMatch.sequence``, ``SequenceMatch.fallback``: a
key of :data:`FALLBACK_REASONS`) and in total (``info["fallback"]``, ``info["fallback_reasons"]``).
``length = 0`` is single-frame matching.

**Batching.** Candidates come from :func:`memlog.descriptors.search.match` (independent of its
blocking), the statistics and the final scores are computed per query from its own window, and
the votes are summed in an order fixed by the query: matching the queries in blocks of any size
(``block``) gives identical results.
"""

from __future__ import annotations

from memlog.matching.config import (
    COORDINATES, FALLBACK_REASONS, PATHS, STAT_SAMPLE, Experimental, SequenceConfig, SequenceMatch,
)
from memlog.matching.coordinates import (
    drive_coordinates, drive_runs, has_positions, reference_unit, resolve_coordinate, standing_rows, uses_stops,
)
from memlog.matching.drive_hmm import place_probabilities
from memlog.matching.matcher import match_tables
from memlog.matching.rerank import RERANK_PLACES, rerank_by_patches
from memlog.matching.sequences import match_sequences

__all__ = [
    "SequenceConfig", "Experimental", "SequenceMatch", "match_sequences", "match_tables", "drive_coordinates",
    "drive_runs", "resolve_coordinate", "has_positions", "reference_unit", "standing_rows", "uses_stops",
    "rerank_by_patches", "place_probabilities", "COORDINATES", "PATHS", "STAT_SAMPLE", "FALLBACK_REASONS",
    "RERANK_PLACES",
]
