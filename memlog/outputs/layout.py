"""The Foxglove layout for memlog's annotated MCAPs, shipped with the package.

``foxglove_layout.json`` (beside this module) is a Foxglove layout (``configById``, the ``layout``
tree, ``globalVariables``, ``userNodes``, ``playbackConfig``) for the outputs of ``memlog score``
(``T/memlog/scores``, ``T/memlog/annotations``) and of ``memlog localize --annotate``
(``T/memlog/match``), where ``T`` is a camera topic of the input:

* an Image panel on ``T`` with ``T/memlog/annotations`` drawn over it (the dynamic-object boxes and
  the MS/SS/ES line);
* a Plot of ``T/memlog/scores`` ``.ms``, ``.ss``, ``.es``, ``.selected`` (1 = kept in the map) and
  the thresholds ``.thresholds.{mt,st,et}``; a State Transitions panel of ``.selected`` and
  ``.rejected_by``;
* a Table of ``.thresholds`` (the run's MT, ST, ET) and a Raw Messages panel of the whole score
  record (the full run config is the file's ``memlog_run`` metadata, which no panel shows);
* for an annotated query of ``memlog localize``: Plots of ``T/memlog/match``
  ``.matches[0].frame_index`` (the best map frame) and ``.confidence``, and a Raw Messages panel of
  the match (every candidate's map topic, frame index and similarity).

A panel whose topic the file does not have stays empty (the match panels on a scored log, the score
panels on an annotated query of an unscored log).

**Its camera** is :data:`LAYOUT_CAMERA`, the demo's (``fixtures/demo.mcap``). Every topic the layout
names is that camera or ``LAYOUT_CAMERA + "/memlog/..."``, so for another camera replace the text
``/camera/image/compressed`` everywhere in a copy of the file with that camera's topic (e.g.
``sed 's#/camera/image/compressed#/front/image_raw#g'``) and import the copy; the layout works for
every encoding family memlog writes (ROS 2, ROS 1, JSON, protobuf: the same field names).

**Opening it**: in Foxglove, open the MCAP, then *Layouts → Import from file…* and choose the file
:func:`layout_path` names (``python -c "from memlog.outputs.layout import layout_path;
print(layout_path())"``).
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["LAYOUT_CAMERA", "layout_path"]

#: The camera topic the shipped layout is written for (the demo log's compressed camera).
LAYOUT_CAMERA = "/camera/image/compressed"

_LAYOUT = Path(__file__).resolve().parent / "foxglove_layout.json"


def layout_path() -> Path:
    """The shipped Foxglove layout file (``memlog/outputs/foxglove_layout.json``, package data)."""
    return _LAYOUT
