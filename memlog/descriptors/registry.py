"""Named descriptor configurations (hloc style) and the factory that builds describers.

``DESCRIBERS[name]`` holds ``"class"`` (the implementation) and its constructor arguments;
:func:`make_describer` builds one from a name plus keyword overrides. Adding a descriptor: write
a :class:`~memlog.descriptors.base.Describer` subclass in its own module, add a named config
here and a branch in :func:`make_describer`.
"""

from __future__ import annotations

import copy
from typing import Any

from memlog.descriptors.base import Describer
from memlog.errors import DescriptorError

__all__ = ["DESCRIBERS", "make_describer"]


#: Named descriptor configurations. ``"class"`` picks the implementation, the other keys are
#: its constructor arguments (overridable in :func:`make_describer`). DINOv2 runs 8 images per
#: network pass: the same numbers as any other batch size, and faster per image on two cores than
#: 16 or 4 (docs/defaults.md).
DESCRIBERS: dict[str, dict[str, Any]] = {
    "thumbnail": {
        "class": "thumbnail",
        "width": 64,
        "height": 32,
        "patch": 8,
    },
    "dinov2-cls": {
        "class": "dinov2",
        "pooling": "cls",
        "resize": "stretch",
        "batch_size": 8,
    },
    "dinov2-gem": {
        "class": "dinov2",
        "pooling": "gem",
        "gem_p": 3.0,
        "resize": "stretch",
        "batch_size": 8,
    },
    # the mean of the final patch tokens: the best pooling on Stromovka's full map with sequences and
    # the re-rank, worse on its half map (benchmarks/descriptor_choices.py, docs/defaults.md)
    "dinov2-mean": {
        "class": "dinov2",
        "pooling": "mean",
        "resize": "stretch",
        "batch_size": 8,
    },
    # GeM over the patch tokens of a middle block (the 8th of 12): the best of blocks 6/8/10 x
    # cls/gem/mean on the Nordland slice (benchmarks/desc_table.py)
    "dinov2-gem-l7": {
        "class": "dinov2",
        "pooling": "gem",
        "gem_p": 3.0,
        "layer": 7,
        "resize": "stretch",
        "batch_size": 8,
    },
    # multi-scale: the whole frame plus its centred crop of 60 % (two network passes)
    "dinov2-gem-ms": {
        "class": "dinov2",
        "pooling": "gem",
        "gem_p": 3.0,
        "scales": (1.0, 0.6),
        "resize": "stretch",
        "batch_size": 8,
    },
}


def make_describer(name: str, **overrides: Any) -> Describer:
    """Build the describer registered as ``name`` in :data:`DESCRIBERS`, with ``overrides``.

    Raises :class:`DescriptorError` for an unknown name or parameter. A dinov2 describer raises
    :class:`~memlog.errors.ModelError` when its model has not been prepared.
    """
    if name not in DESCRIBERS:
        raise DescriptorError(f"unknown descriptor {name!r}; known: {', '.join(sorted(DESCRIBERS))}")
    conf = copy.deepcopy(DESCRIBERS[name])
    cls_name = conf.pop("class")
    conf.update(overrides)
    try:
        if cls_name == "thumbnail":
            from memlog.descriptors.thumbnail import ThumbnailDescriber

            return ThumbnailDescriber(kind=name, **conf)
        if cls_name == "dinov2":
            from memlog.descriptors.dinov2 import DinoV2Describer

            return DinoV2Describer(kind=name, **conf)
    except TypeError as exc:  # unexpected keyword
        raise DescriptorError(f"bad parameters for descriptor {name!r}: {exc}") from None
    raise DescriptorError(f"descriptor {name!r} names unknown implementation {cls_name!r}")
