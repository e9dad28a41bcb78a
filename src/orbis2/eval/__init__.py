"""Evaluation: FVD and its chunked form, linear probes, steering odometry, speed."""
