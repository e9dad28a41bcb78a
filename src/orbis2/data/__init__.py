"""Data: the embedded driving world, video I/O, the raw episode layout and shards."""
