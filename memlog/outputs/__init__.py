"""Every file memlog writes, one module each, all through the one atomic writer
(:mod:`memlog.io.atomic`): the annotated log, the map log, descriptor tables, match tables,
``results.json`` and the HTML report; memlog's channels in the input's encoding family
(:mod:`~memlog.outputs.channels`) and their definitions (:mod:`~memlog.outputs.schemas`)."""

__all__: list[str] = []
