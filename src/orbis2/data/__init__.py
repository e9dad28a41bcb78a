"""Data: the town dataset (rendered by `orbis2.sim`), imported videos, video I/O, the raw episode layout and shards."""
