"""Evaluation, in three layers: :mod:`~orbis2.eval.metrics` (the measures), :mod:`~orbis2.eval.protocols` (how
they are applied to models and data) and :mod:`~orbis2.eval.report` (tables and claims); beside them the records
the protocols write and the report reads (:mod:`~orbis2.eval.records`) and the figure writer both use
(:mod:`~orbis2.eval.figures`).
"""
