"""The measures, independent of the pipeline: FVD, bootstrap statistics, odometry, ego-motion, the
inverse-dynamics instrument.

Nothing here imports :mod:`orbis2.eval.protocols` or :mod:`orbis2.eval.report`.
"""
