"""The measures, independent of the pipeline: FVD, bootstrap statistics, odometry, ego-motion, the
inverse-dynamics instrument, and the linear probe heads with their mIoU and depth RMSE.

Nothing here imports :mod:`orbis2.eval.protocols` or :mod:`orbis2.eval.report`.
"""
