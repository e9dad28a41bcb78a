"""Networks, one file per model with all of its blocks."""
