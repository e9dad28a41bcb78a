"""How a measure is applied to models and data: rollouts scored by FVD, reference rows, steering, conditioning,
probes, speed, and `orbis2 evaluate`.

Built on :mod:`orbis2.eval.metrics` and the records; nothing here imports :mod:`orbis2.eval.report`.
"""
