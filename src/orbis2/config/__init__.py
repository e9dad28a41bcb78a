"""Typed, validated configuration read from ``params.yaml``, by concern.

- ``orbis2.config.params``: reading params.yaml (profiles, ``extends``, the strict
  check of every key) into a :class:`~orbis2.config.params.PipelineConfig`.
- ``orbis2.config.sections``: the dataclasses of the fixed sections (data, town,
  import, shards, assets, latents, evaluation).
- ``orbis2.config.training``: ``train`` (optimisation), the tokenizer and
  predictor sections, one per registry.yaml entry, and inverse_dynamics.

Types are checked by ``orbis2.typecheck``, the checker the model sizes use too.
"""
