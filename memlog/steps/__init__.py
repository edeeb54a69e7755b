"""The pipeline steps, one module each (hloc style), each a function with a typed config:

* :func:`memlog.steps.convert.convert` (:class:`~memlog.steps.convert.ConvertConfig`)
* :func:`memlog.steps.score.score` (:class:`~memlog.scoring.config.ScoreConfig`, a frame window)
* :func:`memlog.steps.map.make_map` (:class:`~memlog.steps.map.MapConfig`)
* :func:`memlog.steps.localize.localize` (:class:`~memlog.steps.localize.LocalizeConfig`)
* :func:`memlog.steps.evaluate.evaluate` (:class:`~memlog.steps.evaluate.EvaluateConfig`)
"""

__all__: list[str] = []
