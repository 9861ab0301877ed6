"""Writers of trained results to files other tools read (PLY sequences, compact 4D caches)."""
