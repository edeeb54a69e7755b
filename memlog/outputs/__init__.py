"""Every file memlog writes, one module each, all through the one atomic writer
(:mod:`memlog.io.atomic`): the annotated log, the map log, descriptor tables, match tables,
``results.json`` and the HTML report; and the JSON Schemas of memlog's channels."""

__all__: list[str] = []
